//! The engine: runs a pipeline's tasks over the dataset's items.
//!
//! One coordinator thread owns all task state ([`book::Book`]). The [`scheduler::Scheduler`]
//! admits the items of the outermost dimension lazily, one at a time (a task budget bounds how
//! many are in flight), and starts ready tasks: each is keyed ([`key`]) and, when every input
//! digest is known cheaply, decided there (cached, or not to run here); the rest go to a rayon
//! pool, where a worker keys what needs hashing with the same decision, reads its inputs, runs
//! the operator and stores its blobs ([`execute`]), and reports back on a crossbeam channel. The
//! coordinator commits every task that ended ([`commit`]: its key, outputs, exports and record)
//! and moves what waits on it. A task's life is in [`task`]. Ready tasks are taken in (outer
//! item, position along the ordered dimension, stage) order, so items stream through the stages:
//! an item can finish before later items start.
//!
//! An output that the run exports and no stage reads is not stored as a blob: its bytes go to the
//! output folder only ([`Keys::exporting_to`]). The record of a task with such outputs is written
//! once their files are in place, so that no record names bytes that are nowhere, whenever the
//! process is killed.

mod book;
mod claims;
mod commit;
mod execute;
mod key;
mod scheduler;
mod task;
#[cfg(test)]
mod tests;

use crate::digest::{Digest, DigestBuilder};
use crate::export::Exporter;
use crate::item::{ItemKey, ItemSpace};
use crate::keys::Keys;
use crate::operator::{Dataset, Identities, Operator};
use crate::plan::View;
use crate::progress::ProgressMode;
use crate::progress::{Counters, Reporter};
use crate::runs::{self, Failure, RunRecord, RunStatus, StageStats};
use crate::store::Store;
use anyhow::{bail, ensure, Context, Result};
use book::Book;
use crossbeam_channel::{unbounded, Receiver, Sender};
use dist4d_graph::Pipeline;
use key::Shared;
use scheduler::{Scheduler, Scopes};
use std::collections::{BinaryHeap, HashMap};
use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;
use task::Msg;

/// How to run.
#[derive(Clone)]
pub struct RunOptions {
    /// Worker threads.
    pub jobs: usize,
    /// Stop at the first failing task.
    pub fail_fast: bool,
    /// Only these items of the outermost dimension (by label); all when `None`.
    pub outer_items: Option<Vec<String>>,
    /// Only the first N items along the pipeline's ordered dimension ([`Pipeline::ordered_dim`])
    /// under each of its prefixes.
    pub limit: Option<u32>,
    /// Only shard `i` of `n` of the (selected) outer items ([`shard_outer`]).
    pub shard: Option<(u32, u32)>,
    /// Only the tasks of these outer items (by label) are executed; the other items' tasks are
    /// taken from the cache or, when not there, counted as missing. All
    /// are executed when `None`. What a merge job after a cluster array uses: it retries the
    /// items that failed and collects what the array made, without redoing a lost shard.
    pub execute_only: Option<Vec<String>>,
    /// Tasks of operators served by an external resource (model workers) are not executed,
    /// only taken from the cache (counted as missing otherwise): the CPU array of a cluster
    /// submission leaves them to a GPU array that runs after it.
    pub defer_resources: bool,
    /// The group of runs this run belongs to (the shards and merge of one cluster submission),
    /// recorded in its run record.
    pub group: Option<String>,
    /// Where exported files go; nothing is exported when `None`.
    pub out_dir: Option<PathBuf>,
    /// Set (by a Ctrl-C handler) to stop cleanly: running tasks finish, nothing new starts.
    pub cancel: Arc<AtomicBool>,
    pub progress: ProgressMode,
    /// The `--set` overrides the pipeline was loaded with, kept in the run record.
    pub sets: Vec<String>,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            jobs: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
            fail_fast: false,
            outer_items: None,
            limit: None,
            shard: None,
            execute_only: None,
            defer_resources: false,
            group: None,
            out_dir: None,
            cancel: Arc::new(AtomicBool::new(false)),
            progress: ProgressMode::Off,
            sets: Vec::new(),
        }
    }
}

/// A pipeline bound to its dataset and operators, ready to run against a store.
pub struct Engine<'a> {
    pub pipeline: &'a Pipeline,
    pub dataset: &'a dyn Dataset,
    /// One operator per node (None for sources).
    pub operators: &'a [Option<Box<dyn Operator>>],
    pub store: &'a Store,
}

/// Digest of everything about a pipeline that affects its results.
pub fn pipeline_digest(p: &Pipeline) -> Digest {
    let mut b = DigestBuilder::new("dist4d-pipeline-v1");
    b.str(&p.dataset.kind).str(&p.dataset.config.canonical);
    for &n in &p.order {
        let node = &p.nodes[n];
        b.str(&node.name).u64(node.grain as u64);
        if let Some(s) = node.stage() {
            b.str(&s.kind).u64(s.version as u64).str(&s.params.canonical);
            if s.every != 1 {
                b.str("every").u64(s.every as u64);
            }
            for i in &s.inputs {
                b.str(&i.port).str(&p.nodes[i.from].name).u64(i.from_port as u64).str(&format!("{:?}", i.selector));
            }
        }
    }
    for e in &p.exports {
        b.str(&p.nodes[e.node].name).u64(e.port as u64).str(&e.template);
    }
    b.finish()
}

/// Indices of the items of the outermost dimension (named `dim`) selected by label (all when
/// `names` is `None`).
pub fn select_outer(space: &dyn ItemSpace, dim: &str, names: Option<&[String]>) -> Result<Vec<u32>> {
    let n = space.count(&ItemKey::new(&[]));
    let Some(names) = names else { return Ok((0..n).collect()) };
    let labels: Vec<String> = (0..n).map(|i| space.label(&ItemKey::new(&[i]))).collect();
    let mut out = Vec::new();
    for name in names {
        match labels.iter().position(|l| l == name) {
            Some(i) => out.push(i as u32),
            None => {
                let some: Vec<&str> = labels.iter().take(8).map(|s| s.as_str()).collect();
                bail!(
                    "the dataset has no {dim} `{name}` (it has {n}: {}{})",
                    some.join(", "),
                    if n > 8 { ", ..." } else { "" }
                );
            }
        }
    }
    out.sort();
    out.dedup();
    Ok(out)
}

/// Shard `i` of `n` of the outer items `outers`: the items are dealt, largest first (by their
/// number of items at `depth`, a measure of their tasks; ties by index), each to the shard with
/// the fewest items so far (ties to the lower shard), so shards are balanced and the split is the
/// same on every machine. Returned in index order.
pub fn shard_outer(view: &View, outers: &[u32], depth: usize, (i, n): (u32, u32)) -> Vec<u32> {
    let n = n.max(1) as usize;
    let mut sized: Vec<(u64, u32)> =
        outers.iter().map(|&o| (count_items(view, ItemKey::new(&[o]), depth), o)).collect();
    sized.sort_by_key(|&(size, o)| (std::cmp::Reverse(size), o));
    let mut load = vec![0u64; n];
    let mut mine = Vec::new();
    for (size, o) in sized {
        let s = (0..n).min_by_key(|&s| (load[s], s)).unwrap_or(0);
        load[s] += size.max(1);
        if s == i as usize {
            mine.push(o);
        }
    }
    mine.sort();
    mine
}

/// The labels of the outer items shard `shard` of a run holds (selected by `names`, seen through
/// `limit`, as [`Engine::run`] deals them), for commands that take item names.
pub fn shard_labels(
    p: &Pipeline,
    space: &dyn ItemSpace,
    names: Option<&[String]>,
    limit: Option<u32>,
    shard: (u32, u32),
) -> Result<Vec<String>> {
    ensure!(shard.1 >= 1 && shard.0 < shard.1, "shard {}/{}: the shard is 0 to n - 1 of n", shard.0, shard.1);
    let view = View::limited(p, space, limit)?;
    let outers = select_outer(space, &p.dims[0].name, names)?;
    let labels = shard_outer(&view, &outers, p.dims.len(), shard).into_iter();
    Ok(labels.map(|o| space.label(&ItemKey::new(&[o]))).collect())
}

/// What a run did.
pub struct RunSummary {
    pub record: RunRecord,
}

/// A run recorded as running and not yet ended: what [`Engine::run`] records if the run stops on
/// an error (a full disk) instead of leaving it "running", which `dist4d runs` would then show as
/// killed.
struct Unfinished {
    record: RunRecord,
    started: Instant,
    counters: Arc<Counters>,
}

/// What a run sets up before its first task ([`Engine::begin`]).
struct Begun<'e> {
    started: Instant,
    view: View<'e>,
    outers: Vec<u32>,
    /// The outer items whose tasks the run executes (all when `None`).
    executed: Option<Vec<u32>>,
    keys: Keys<'e>,
    exporter: Option<Exporter>,
    /// Per node, why its operator cannot run (its worker did not start).
    unavailable: Vec<Option<String>>,
    /// Per node, whether its tasks are left to a later run ([`RunOptions::defer_resources`]).
    deferred: Vec<bool>,
    counters: Arc<Counters>,
    counter_of: Vec<usize>,
    stats: Vec<StageStats>,
    provisional: RunRecord,
    keys_tmp: PathBuf,
    keys_out: std::io::BufWriter<std::fs::File>,
}

impl<'a> Engine<'a> {
    pub fn run(&self, opts: &RunOptions) -> Result<RunSummary> {
        let mut unfinished = None;
        let result = self.run_recorded(opts, &mut unfinished);
        if let (Err(e), Some(u)) = (&result, unfinished) {
            self.record_stop(opts, u, e);
        }
        result
    }

    /// A run stopped by an error: its temp files go first (on a full disk, they may be what
    /// leaves room for the record), then it is recorded as failed with the error. Best effort:
    /// the error itself is what the caller reports.
    fn record_stop(&self, opts: &RunOptions, u: Unfinished, e: &anyhow::Error) {
        let out_tmp: Vec<PathBuf> = opts.out_dir.iter().map(|d| d.join(crate::export::TMP)).collect();
        self.store.remove_own_temp_files(&out_tmp);
        let mut stages = u.record.stages.clone();
        for (i, s) in stages.iter_mut().enumerate() {
            s.failed = u.counters.failed.get(i).map_or(0, |f| f.load(Ordering::Relaxed));
        }
        let record = RunRecord {
            seconds: u.started.elapsed().as_secs_f64(),
            status: RunStatus::Failed,
            stages,
            failures: vec![Failure { stage: "-".into(), item: "-".into(), error: format!("the run stopped: {e:#}") }],
            ..u.record
        };
        // A full disk may have no room for a new file even now: the record it started then
        // takes the update in place.
        if let Err(w) = runs::write_run(self.store, &record).or_else(|_| runs::overwrite_run(self.store, &record)) {
            eprintln!("warning: the run's record could not be updated ({w:#}): `dist4d runs` will show it as killed");
        }
    }

    /// The run's life: begun (recorded as running), driven by the scheduler, ended (recorded).
    fn run_recorded(&self, opts: &RunOptions, unfinished: &mut Option<Unfinished>) -> Result<RunSummary> {
        let begun = self.begin(opts)?;
        *unfinished = Some(Unfinished {
            record: begun.provisional.clone(),
            started: begun.started,
            counters: begun.counters.clone(),
        });
        let reporter = Reporter::start(begun.counters.clone(), opts.progress);
        let Begun { started, view, outers, executed, keys, exporter, unavailable, deferred, .. } = begun;
        let book = Book {
            active: Vec::new(),
            ready: BinaryHeap::new(),
            stats: begun.stats,
            counters: begun.counters.clone(),
            counter_of: begun.counter_of,
            failures: Vec::new(),
            keys_out: begun.keys_out,
            exporter,
            rank: rank_of(self.pipeline),
            ordered_dim: self.pipeline.ordered_dim(),
            live_tasks: 0,
            export_jobs: Vec::new(),
            awaiting: HashMap::new(),
            next_awaiting: 0,
            released: Vec::new(),
            nothing: vec![None; self.pipeline.nodes.len()],
            stop: opts.cancel.clone(),
        };
        let shared = Shared { engine: self, keys: &keys, deferred };
        let (book, stopping) = self.drive(opts, &shared, book, view, outers, executed, unavailable)?;
        drop(reporter);
        drop(shared);
        // The key layer lets go of the output folder first, so that its manifest is not copied.
        drop(keys);
        let record = self.end(book, stopping, &begun.counters, started, begun.provisional, &begun.keys_tmp)?;
        Ok(RunSummary { record })
    }

    /// Sets a run up: the outer items it takes, its output folder, its key layer (with the
    /// operators' identities), its counters, and its record, written at once as running.
    fn begin(&self, opts: &RunOptions) -> Result<Begun<'a>> {
        let started = Instant::now();
        let started_unix = runs::now_secs();
        let p = self.pipeline;
        // Millisecond prefix: ids of runs started in the same second still sort in start order.
        let millis =
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis()).unwrap_or(0);
        let run_id = format!("{millis:013}-{}", self.store.writer_id());
        let view = View::limited(p, self.dataset, opts.limit)?;
        let mut outers = select_outer(self.dataset, &p.dims[0].name, opts.outer_items.as_deref())?;
        if let Some((i, n)) = opts.shard {
            ensure!(n >= 1 && i < n, "shard {i}/{n}: the shard is 0 to n - 1 of n");
            outers = shard_outer(&view, &outers, p.dims.len(), (i, n));
        }
        let executed = match &opts.execute_only {
            Some(names) => Some(select_outer(self.dataset, &p.dims[0].name, Some(names))?),
            None => None,
        };
        let exporter = match &opts.out_dir {
            Some(dir) if !p.exports.is_empty() => {
                let stages: Vec<&str> = p.stage_order().map(|n| p.nodes[n].name.as_str()).collect();
                Some(Exporter::open(dir, self.store, &p.name, &stages, &p.dims, opts.shard)?)
            }
            _ => None,
        };
        let names: Vec<String> = p.nodes.iter().map(|n| n.name.clone()).collect();
        // A run that leaves the worker stages to another (a GPU array) does not start their workers.
        let deferred_node = |op: &dyn Operator| opts.defer_resources && op.resource().is_some();
        let Identities { ids: identities, unavailable } = Identities::of_except(self.operators, &names, deferred_node);
        let deferred = self.operators.iter().map(|op| op.as_deref().is_some_and(deferred_node)).collect();
        let keys = match &exporter {
            Some(x) => Keys::new(p, self.dataset, self.store).with_identities(&identities).exporting_to(x.folder()),
            None => Keys::new(p, self.dataset, self.store).with_identities(&identities),
        };
        // Canonical params are stored as blobs so that explain can show what changed.
        for n in p.stage_order() {
            let text = &p.nodes[n].stage().unwrap().params.canonical;
            self.store.put_blob(&keys.params(n), text.as_bytes())?;
        }
        let (counters, counter_of, stats) = self.counters(&view, &outers);
        // Recorded at once as running, so that `dist4d runs` (and a cluster's merge job) sees a
        // run in progress, and one killed before it could record its end (its writer's lease
        // dead) as killed.
        let provisional = RunRecord {
            id: run_id.clone(),
            pipeline: p.name.clone(),
            pipeline_path: p.path.display().to_string(),
            pipeline_digest: pipeline_digest(p).hex(),
            started: started_unix,
            seconds: 0.0,
            status: RunStatus::Running,
            jobs: opts.jobs,
            stages: stats.clone(),
            failures: Vec::new(),
            exported: 0,
            out_dir: opts.out_dir.as_ref().map(|d| d.display().to_string()),
            group: opts.group.clone(),
            shard: opts.shard,
            writer: Some(self.store.writer_id().to_string()),
            dataset: Some(runs::dataset_identity(p)),
            sets: opts.sets.clone(),
        };
        runs::write_run(self.store, &provisional)?;
        let keys_tmp = self.store.temp_path();
        let keys_out = std::io::BufWriter::new(
            std::fs::File::create(&keys_tmp).with_context(|| format!("creating {}", keys_tmp.display()))?,
        );
        Ok(Begun {
            started,
            view,
            outers,
            executed,
            keys,
            exporter,
            unavailable,
            deferred,
            counters,
            counter_of,
            stats,
            provisional,
            keys_tmp,
            keys_out,
        })
    }

    /// Per stage: its progress counters (with the expected totals, corrected as outer items are
    /// planned), the counter of each node, and its run statistics.
    fn counters(&self, view: &View, outers: &[u32]) -> (Arc<Counters>, Vec<usize>, Vec<StageStats>) {
        let p = self.pipeline;
        let stage_nodes: Vec<usize> = p.stage_order().collect();
        let counters = Arc::new(Counters::new(stage_nodes.iter().map(|&n| p.nodes[n].name.clone()).collect()));
        let mut counter_of = vec![usize::MAX; p.nodes.len()];
        for (i, &n) in stage_nodes.iter().enumerate() {
            counter_of[n] = i;
            let total: u64 = outers.iter().map(|&s| count_items(view, ItemKey::new(&[s]), p.nodes[n].grain)).sum();
            counters.total[i].store(total, Ordering::Relaxed);
        }
        let stats = stage_nodes
            .iter()
            .map(|&n| {
                let node = &p.nodes[n];
                StageStats {
                    stage: node.name.clone(),
                    kind: node.stage().unwrap().kind.clone(),
                    grain: p.grain_name(node.grain).into(),
                    ..Default::default()
                }
            })
            .collect();
        (counters, counter_of, stats)
    }

    /// Runs the scheduler on its thread pools until every task and export has ended or the run
    /// stops; returns the book and why it stopped, if it did.
    #[allow(clippy::too_many_arguments)]
    fn drive(
        &self,
        opts: &RunOptions,
        shared: &Shared<'_, 'a>,
        book: Book,
        view: View,
        outers: Vec<u32>,
        executed: Option<Vec<u32>>,
        unavailable: Vec<Option<String>>,
    ) -> Result<(Book, Option<RunStatus>)> {
        let (tx, rx): (Sender<Msg>, Receiver<Msg>) = unbounded();
        let mut scheduler = Scheduler::new(book, shared, opts, view, outers, executed, unavailable, tx);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(opts.jobs.max(1))
            .thread_name(|i| format!("dist4d-worker-{i}"))
            .build()?;
        // Tasks of operators that wait on an external resource (a model worker on a GPU) run on
        // threads of their own, as many at once as the resource takes, so that waiting for a
        // model does not hold the CPU threads the other stages need.
        let wait_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(scheduler.resource_threads())
            .thread_name(|i| format!("dist4d-wait-{i}"))
            .build()?;
        // Exported files are written on threads of their own: a large file goes to the device
        // directly (`direct_io`) and its thread waits for it, which should not idle a CPU thread.
        // (A task's blobs are still written by the task's thread: its record must not be
        // written before them. The largest, a compressed depth map, takes ~1 ms of the device.)
        let export_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(opts.jobs.clamp(1, 8))
            .thread_name(|i| format!("dist4d-export-{i}"))
            .build()?;
        // The scopes guarantee every spawned job has ended before they return, even on an error.
        export_pool.in_place_scope(|export| {
            wait_pool
                .in_place_scope(|wait| pool.in_place_scope(|cpu| scheduler.drive(&Scopes { cpu, wait, export }, &rx)))
        })?;
        Ok((scheduler.book, scheduler.stopping))
    }

    /// Ends a run: the output folder first (its files, then its manifest), then the store: after
    /// a power loss, a record made durable names exported files that are too. Then the run's task
    /// keys and its record, with its status.
    fn end(
        &self,
        book: Book,
        stopping: Option<RunStatus>,
        counters: &Counters,
        started: Instant,
        provisional: RunRecord,
        keys_tmp: &std::path::Path,
    ) -> Result<RunRecord> {
        let Book { mut stats, failures, mut keys_out, exporter, awaiting, counter_of, nothing, .. } = book;
        debug_assert!(awaiting.is_empty(), "every export job has ended");
        for (i, s) in stats.iter_mut().enumerate() {
            s.total = counters.total[i].load(Ordering::Relaxed);
        }
        for (node, why) in nothing.into_iter().enumerate() {
            if let (Some(why), Some(&ci)) = (why, counter_of.get(node)) {
                stats[ci].nothing = Some(why);
            }
        }
        let exported = match exporter {
            Some(e) => e.finish()?,
            None => 0,
        };
        self.store.sync()?;
        keys_out.flush().with_context(|| format!("writing {}", keys_tmp.display()))?;
        drop(keys_out);
        std::fs::rename(keys_tmp, runs::keys_path(self.store, &provisional.id))
            .with_context(|| "saving the run's task keys")?;
        let status = match stopping {
            Some(s) => s,
            None if !failures.is_empty() => RunStatus::Failed,
            None if stats.iter().any(|s| s.missing > 0) => RunStatus::Incomplete,
            None => RunStatus::Complete,
        };
        let record = RunRecord {
            seconds: started.elapsed().as_secs_f64(),
            status,
            stages: stats,
            failures,
            exported,
            ..provisional
        };
        runs::write_run(self.store, &record)?;
        Ok(record)
    }
}

/// Per node, its position in the pipeline's order (ready tasks of one item go in that order).
fn rank_of(p: &Pipeline) -> Vec<u32> {
    let mut rank = vec![0u32; p.nodes.len()];
    for (i, &n) in p.order.iter().enumerate() {
        rank[n] = i as u32;
    }
    rank
}

/// How many items of depth `depth` are under `prefix`.
fn count_items(view: &View, prefix: ItemKey, depth: usize) -> u64 {
    if prefix.depth as usize >= depth {
        return 1;
    }
    let n = view.count(&prefix);
    if prefix.depth as usize + 1 == depth {
        return n as u64;
    }
    (0..n).map(|i| count_items(view, prefix.child(i), depth)).sum()
}
