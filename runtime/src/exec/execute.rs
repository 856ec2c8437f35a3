//! The worker side of a task: keyed (when the coordinator could not), inputs read, operator run,
//! outputs checked and their blobs stored: a [`Ran`] task for the coordinator to commit.

use super::key::{decide, take_unreadable, Shared};
use super::task::{panic_message, Ended, Job, Keyed, Msg, Produced, Ran, Src};
use crate::digest::Digest;
use crate::operator::{Artifact, Blob, Made, Output, TaskContext};
use crate::record::{OutputRef, RecordInput, TaskRecord, INLINE_MAX};
use crate::store::{BlobError, Unread};
use anyhow::{anyhow, bail, Context, Result};
use crossbeam_channel::Sender;
use dist4d_graph::NodeId;
use std::sync::Arc;
use std::time::Instant;

/// Runs `job` on a thread of `scope`'s pool and reports how it ended on `tx`; a panic in the
/// stage is that task's failure.
pub(super) fn spawn_task<'s>(
    scope: &rayon::Scope<'s>,
    shared: &'s Shared<'_, '_>,
    tx: &Sender<Msg>,
    job: Job,
    waited: Option<usize>,
) {
    let tx = tx.clone();
    scope.spawn(move |_| {
        let (slot, task) = (job.slot, job.task);
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| shared.execute(job)))
            .unwrap_or_else(|panic| Err(anyhow!("the stage panicked: {}", panic_message(&panic))));
        let _ = tx.send(Msg::Task { slot, task, waited, result });
    });
}

impl Shared<'_, '_> {
    fn execute(&self, mut job: Job) -> Result<Ended> {
        let key = match job.key {
            Some(key) => key,
            None => match self.key_on_worker(&mut job)? {
                Keyed::Run(key) => key,
                Keyed::Cached(key, outputs) => return Ok(Ended::Cached(key, outputs)),
                Keyed::NotExecuted { deferred } => return Ok(Ended::NotExecuted { deferred }),
                Keyed::Unknown => unreachable!("decided with raw files hashed"),
            },
        };
        let t0 = Instant::now();
        let artifacts = match self.read_inputs(&job)? {
            Ok(artifacts) => artifacts,
            Err((port, lost)) => return Ok(Ended::LostInput { port, lost }),
        };
        let unread = self.unread_to_leave(job.node, &key);
        let (outs, nothing) = match self.run_operator(&job, &artifacts, &unread)? {
            Made::Outputs(outs) => {
                self.check_outputs(job.node, &outs, &unread)?;
                (outs, None)
            }
            Made::Nothing(why) => (Vec::new(), Some(why)),
        };
        let micros = t0.elapsed().as_micros() as u64;
        let produced = self.store_blobs(job.node, outs)?;
        let record = Box::new(self.record(&job, key, &produced, micros));
        Ok(Ended::Ran(Ran { key, produced, micros, record, nothing }))
    }

    /// Hashes the raw files the coordinator left and asks [`decide`] with them.
    fn key_on_worker(&self, job: &mut Job) -> Result<Keyed> {
        self.keys.hash_sources(&mut job.inputs);
        if let Some(e) = take_unreadable(&mut job.inputs) {
            return Err(e);
        }
        decide(self, job.node, &job.item, &job.inputs, job.may_execute, true)
    }

    /// The input artifacts' bytes; a blob found missing or corrupt is returned as such (the
    /// coordinator runs the task that made it again), any other problem is the task's failure.
    #[allow(clippy::type_complexity)]
    fn read_inputs(&self, job: &Job) -> Result<std::result::Result<Vec<Vec<Artifact>>, (String, BlobError)>> {
        let e = self.engine;
        let stage = e.pipeline.nodes[job.node].stage().expect("jobs are for stages");
        let mut artifacts: Vec<Vec<Artifact>> = Vec::with_capacity(job.inputs.len());
        for ((input, srcs), spec) in job.inputs.iter().zip(&job.srcs).zip(&stage.inputs) {
            let mut list = Vec::with_capacity(input.len());
            for (a, src) in input.iter().zip(srcs) {
                let bytes: Blob = match src {
                    Src::Mem(b) => b.clone(),
                    Src::Inline(b) => Arc::new(b.to_vec()),
                    Src::Cas(d) => match e.store.read_blob(d) {
                        Ok(bytes) => Arc::new(bytes),
                        Err(Unread::Lost(lost)) => return Ok(Err((spec.port.clone(), lost))),
                        Err(newer) => return Err(newer.into_error().context(format!("reading input `{}`", spec.port))),
                    },
                    Src::Source { port } => Arc::new(
                        e.dataset
                            .load_source(port, &a.item)
                            .with_context(|| format!("reading dataset.{port} for {}", e.dataset.path(&a.item)))?,
                    ),
                };
                list.push(Artifact { item: a.item, pos: a.pos(), bytes });
            }
            artifacts.push(list);
        }
        Ok(Ok(artifacts))
    }

    fn run_operator(&self, job: &Job, artifacts: &[Vec<Artifact>], unread: &[String]) -> Result<Made<Vec<Output>>> {
        let e = self.engine;
        let node = &e.pipeline.nodes[job.node];
        let stage = node.stage().expect("jobs are for stages");
        let label = e.dataset.path(&job.item);
        let ctx = TaskContext { item: job.item, seed: self.keys.seed(job.node, &job.item), label: &label, unread };
        e.operators[job.node]
            .as_ref()
            .ok_or_else(|| anyhow!("no operator for stage `{}`", node.name))?
            .run(&ctx, artifacts)
            .map_err(|err| err.context(format!("{} ({})", node.name, stage.kind)))
    }

    /// Fails the task, before anything enters the cache, when its outputs are not the ones its
    /// kind declares: a mistyped or missing output would otherwise fail only in a reader downstream.
    fn check_outputs(&self, node: NodeId, outs: &[Output], unread: &[String]) -> Result<()> {
        let node = &self.engine.pipeline.nodes[node];
        let kind = &node.stage().expect("jobs are for stages").kind;
        if outs.len() != node.outputs.len() {
            bail!(
                "stage `{}` ({kind}) returned {} outputs, its kind declares {}; nothing was stored",
                node.name,
                outs.len(),
                node.outputs.len()
            );
        }
        for (out, port) in outs.iter().zip(&node.outputs) {
            if out.ty != port.ty {
                bail!(
                    "stage `{}` ({kind}) returned a {} for output `{}`, which is declared {}; nothing was stored",
                    node.name,
                    out.ty,
                    port.name,
                    port.ty
                );
            }
        }
        if let Some(port) =
            (0..outs.len()).find(|&p| outs[p].bytes.is_none() && !unread.contains(&node.outputs[p].name))
        {
            bail!(
                "stage `{}` ({kind}) did not make output `{}`, which this run reads; nothing was stored",
                node.name,
                node.outputs[port].name
            );
        }
        Ok(())
    }

    /// Stores the blobs of the outputs that go to the store (small ones are inlined in the record;
    /// those kept only in the output folder are written there by the exporter, from memory).
    fn store_blobs(&self, node: NodeId, outs: Vec<Output>) -> Result<Vec<Produced>> {
        let mut produced = Vec::with_capacity(outs.len());
        for (port, Output { bytes, .. }) in outs.into_iter().enumerate() {
            let Some(bytes) = bytes else {
                produced.push(Produced { r: OutputRef::unmade(), mem: None, only_in_folder: false });
                continue;
            };
            let digest = Digest::of(&bytes);
            let size = bytes.len() as u64;
            let only_in_folder = self.keys.only_in_folder(node, port, size);
            let inline = if bytes.len() <= INLINE_MAX {
                Some(Arc::<[u8]>::from(bytes.as_slice()))
            } else {
                if !only_in_folder {
                    self.engine.store.put_blob(&digest, &bytes)?;
                }
                None
            };
            let r = OutputRef { digest, size, inline };
            produced.push(Produced { r, mem: Some(Arc::new(bytes)), only_in_folder });
        }
        Ok(produced)
    }

    /// The record of a task that ran (written by the coordinator's commit).
    fn record(&self, job: &Job, key: Digest, produced: &[Produced], micros: u64) -> TaskRecord {
        let node = &self.engine.pipeline.nodes[job.node];
        let stage = node.stage().expect("jobs are for stages");
        TaskRecord {
            key,
            stage: node.name.clone(),
            item: job.item,
            kind: stage.kind.clone(),
            version: stage.version,
            params: self.keys.params(job.node),
            inputs: stage
                .inputs
                .iter()
                .zip(&job.inputs)
                .map(|(spec, got)| RecordInput {
                    port: spec.port.clone(),
                    digests: got.iter().map(|a| a.digest.as_ref().copied().unwrap_or_default()).collect(),
                })
                .collect(),
            outputs: produced.iter().map(|p| p.r.clone()).collect(),
            finished_ms: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_millis() as u64)
                .unwrap_or(0),
            micros,
        }
    }

    /// The output ports of `node` its task under `key` may leave unmade: those nothing of the run
    /// reads, except those an earlier record of the key made and still has the bytes of. A record
    /// replaces the one before it, so without this two pipelines (or two stages of one) reading
    /// different ports of one task would each find the other's record short and run it again,
    /// every run; this way a task's records only gain outputs.
    fn unread_to_leave(&self, node: NodeId, key: &Digest) -> Vec<String> {
        let store = self.engine.store;
        let unread = self.keys.unread(node);
        let Some(old) = (!unread.is_empty()).then(|| store.lookup(key)).flatten() else {
            return unread.to_vec();
        };
        let outputs = &self.engine.pipeline.nodes[node].outputs;
        let had = |name: &String| {
            let port = outputs.iter().position(|o| &o.name == name);
            port.and_then(|p| old.outputs.get(p))
                .is_some_and(|o| !o.is_unmade() && (o.inline.is_some() || store.has_blob(&o.digest)))
        };
        unread.iter().filter(|name| !had(name)).cloned().collect()
    }
}
