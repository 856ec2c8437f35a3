//! Committing a task that ended (cached or ran), and its exports: the one place a task's key and
//! record are written.

use super::book::{strip_unread, Awaiting, Book};
use super::task::{panic_message, Ended, Msg, Produced, State};
use super::Engine;
use crate::export::{ExportError, FileStat};
use crate::record::TaskRecord;
use crate::runs::Failure;
use anyhow::{anyhow, Context, Result};
use crossbeam_channel::Sender;
use std::io::Write;
use std::sync::Arc;

impl Book {
    /// Commits task `t` (first run or run again alike): writes its key to the run's list, keeps
    /// its outputs for its readers, plans its exports, and writes its record (of a task that ran)
    /// now or, when its outputs are kept only in the output folder, once their files are in
    /// place, and never when one of them cannot be written.
    pub(super) fn commit(&mut self, e: &Engine, slot: u32, t: usize, ended: Ended) -> Result<()> {
        let (key, produced, record) = match ended {
            Ended::Cached(key, outs) => {
                (key, outs.into_iter().map(|r| Produced { r, mem: None, only_in_folder: false }).collect(), None)
            }
            Ended::Ran(ran) => (ran.key, ran.produced, Some(ran.record)),
            Ended::NotExecuted { .. } | Ended::LostInput { .. } => unreachable!("only a task that ended is committed"),
        };
        self.keys_out.write_all(&key.0).context("writing the run's task keys")?;
        let p = e.pipeline;
        let run = self.active[slot as usize].as_mut().unwrap();
        run.state[t] = State::Committed;
        let node = run.plan.tasks[t].node as usize;
        let item = run.plan.tasks[t].item;
        let id = self.next_awaiting;
        let mut awaiting = record.map(|record| Awaiting { record: Some(record), files_left: 0 });
        if let Some(exporter) = self.exporter.as_mut() {
            for x in p.exports.iter().filter(|x| x.node == node) {
                // A task with nothing to make (no outputs) has nothing to export, and what an
                // earlier run exported for it goes.
                let Some(out) = produced.get(x.port) else {
                    exporter.remove_stale(x, &item, e.dataset);
                    continue;
                };
                let names = (p.nodes[node].name.as_str(), p.nodes[node].outputs[x.port].name.as_str());
                let waiting = awaiting.as_mut().filter(|_| out.only_in_folder);
                match exporter.plan(x, names, &item, e.dataset, &out.r, out.mem.clone(), e.store) {
                    Ok(Some(job)) => {
                        run.exports_pending += 1;
                        let by = waiting.map(|a| {
                            a.files_left += 1;
                            id
                        });
                        self.export_jobs.push((job, slot, t as u32, by));
                    }
                    Ok(None) => {}
                    Err(err) => {
                        if let Some(a) = waiting {
                            a.record = None;
                        }
                        self.failures.push(Failure {
                            stage: p.nodes[node].name.clone(),
                            item: e.dataset.path(&item),
                            error: format!("{err:#}"),
                        })
                    }
                }
            }
        }
        let produced = Arc::new(produced);
        run.outputs[t] = Some(strip_unread(&produced, &run.readers_left[t]));
        match awaiting {
            // Files left only for outputs kept only in the folder: the record waits for them.
            Some(a) if a.files_left > 0 => {
                self.awaiting.insert(id, a);
                self.next_awaiting += 1;
            }
            Some(Awaiting { record: Some(record), .. }) => self.write_record(e, &record),
            _ => {}
        }
        Ok(())
    }

    /// Writes the record of a task that ran; failing to is the task's failure.
    fn write_record(&mut self, e: &Engine, record: &TaskRecord) {
        if let Err(err) = e.store.append_record(record) {
            self.failures.push(Failure {
                stage: record.stage.clone(),
                item: e.dataset.path(&record.item),
                error: format!("recording the finished task in the store: {err:#}"),
            });
        }
    }

    /// Starts the export writes `commit` planned, on `scope`; returns how many.
    pub(super) fn spawn_exports<'s>(&mut self, scope: &rayon::Scope<'s>, tx: &Sender<Msg>) -> usize {
        let n = self.export_jobs.len();
        for (job, slot, task, awaiting) in self.export_jobs.drain(..) {
            let tx = tx.clone();
            scope.spawn(move |_| {
                let rel = job.rel.clone();
                // A panic is this file's failure, reported like an error: the scheduler counts
                // every export job it spawned back in, and would wait forever for one that never is.
                let result =
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| job.write())).unwrap_or_else(|panic| {
                        Err(ExportError::Failed(anyhow!("writing the file panicked: {}", panic_message(&panic))))
                    });
                let _ = tx.send(Msg::Exported { slot, task, rel, result, awaiting });
            });
        }
        n
    }

    /// An export write ended. A blob found missing or corrupt makes its task run again (which
    /// exports it anew); any other failure is the item's.
    pub(super) fn exported(
        &mut self,
        e: &Engine,
        slot: u32,
        task: u32,
        rel: &str,
        result: std::result::Result<FileStat, ExportError>,
        awaiting: Option<u64>,
    ) {
        if let Some(id) = awaiting {
            let a = self.awaiting.get_mut(&id).expect("a record awaits each of its export jobs");
            if result.is_err() {
                a.record = None;
            }
            a.files_left -= 1;
            if a.files_left == 0 {
                if let Some(record) = self.awaiting.remove(&id).and_then(|a| a.record) {
                    self.write_record(e, &record);
                }
            }
        }
        let t = task as usize;
        let run = self.active[slot as usize].as_mut().unwrap();
        run.exports_pending -= 1;
        let (stage, item) = {
            let node = run.plan.tasks[t].node as usize;
            (e.pipeline.nodes[node].name.clone(), e.dataset.path(&run.plan.tasks[t].item))
        };
        match result {
            Ok(stat) => {
                if let Some(x) = self.exporter.as_mut() {
                    x.job_done(rel, Some(stat));
                }
            }
            Err(err) => {
                if let Some(x) = self.exporter.as_mut() {
                    x.job_done(rel, None);
                }
                let healed = matches!(err, ExportError::LostBlob(_)) && self.redo(slot, t);
                if !healed {
                    self.failures.push(Failure { stage, item, error: err.to_string() });
                }
            }
        }
        self.close_if_done(slot);
    }
}
