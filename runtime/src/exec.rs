//! The scheduler: runs a pipeline's tasks over the dataset's items.
//!
//! One coordinator thread owns all task state. It plans the items of the outermost dimension
//! lazily, one at a time (a task budget bounds how many are in flight), resolves cache hits itself
//! when every input digest is known cheaply (through [`crate::keys`]), and sends the rest to a
//! rayon pool. Workers compute what needs reading (raw-file digests, input blobs), run the
//! operator, store outputs and the task record, and report back on a crossbeam channel. Ready
//! tasks are taken in (outer item, position along the second dimension, stage) order, so items
//! stream through the stages: an item can finish before later items start.
//!
//! An output that the run exports and no stage reads is not stored as a blob: its bytes go to the
//! output folder only ([`Keys::exporting_to`]). The record of a task with such outputs is appended
//! once their files are in place, so that no record names bytes that are nowhere, whenever the
//! process is killed.

use crate::digest::{Digest, DigestBuilder};
use crate::export::{ExportJob, Exporter, FileStat};
use crate::item::{ItemKey, ItemSpace};
use crate::keys::{Decision, Input, Keys, Unknown};
use crate::lease::{Claim, Holder};
use crate::operator::{Artifact, Blob, Dataset, Identities, NotApplicable, Operator, Output, TaskContext};
use crate::plan::{plan_outer, InputSrc, OuterPlan, View};
use crate::progress::{Counters, ProgressMode, Reporter};
use crate::record::{OutputRef, RecordInput, TaskRecord, INLINE_MAX};
use crate::runs::{self, Failure, RunRecord, RunStatus, StageStats};
use crate::store::{BlobError, Store};
use anyhow::{anyhow, bail, ensure, Context, Result};
use crossbeam_channel::{unbounded, Receiver, RecvTimeoutError, Sender};
use dist4d_graph::{NodeId, NodeKind, Pipeline};
use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap, VecDeque};
use std::io::Write;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How to run.
#[derive(Clone)]
pub struct RunOptions {
    /// Worker threads.
    pub jobs: usize,
    /// Stop at the first failing task.
    pub fail_fast: bool,
    /// Only these items of the outermost dimension (by label); all when `None`.
    pub outer_items: Option<Vec<String>>,
    /// Only the first N items along the second dimension under each outer item.
    pub second_dim_limit: Option<u32>,
    /// Only shard `i` of `n` of the (selected) outer items ([`shard_outer`]).
    pub shard: Option<(u32, u32)>,
    /// Only the tasks of these outer items (by label) are executed; the other items' tasks are
    /// taken from the cache or, when not there, counted as missing (see [`NotExecuted`]). All
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
            second_dim_limit: None,
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
/// `second_dim_limit`, as [`Engine::run`] deals them), for commands that take item names.
pub fn shard_labels(
    space: &dyn ItemSpace,
    dims: usize,
    dim_name: &str,
    names: Option<&[String]>,
    second_dim_limit: Option<u32>,
    shard: (u32, u32),
) -> Result<Vec<String>> {
    ensure!(shard.1 >= 1 && shard.0 < shard.1, "shard {}/{}: the shard is 0 to n - 1 of n", shard.0, shard.1);
    let view = View { space, second_dim_limit };
    let outers = select_outer(space, dim_name, names)?;
    Ok(shard_outer(&view, &outers, dims, shard).into_iter().map(|o| space.label(&ItemKey::new(&[o]))).collect())
}

/// A task that a run with [`RunOptions::execute_only`] did not execute: it is not cached, and
/// its outer item is not among those the run executes.
#[derive(Debug)]
pub struct NotExecuted {
    /// Left by request to a later run ([`RunOptions::defer_resources`]): counted as deferred,
    /// not missing.
    deferred: bool,
}

impl std::fmt::Display for NotExecuted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.deferred {
            true => write!(f, "served by a model worker, which this run leaves to a later one"),
            false => write!(f, "not cached, and this run executes none of its item's tasks"),
        }
    }
}

/// How [`Coord::skip_all`] counts the tasks it skips.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Skip {
    /// An input failed.
    Failed,
    /// An input was not executed ([`NotExecuted`]).
    Missing,
    /// An input was left to a later run.
    Deferred,
}

impl std::error::Error for NotExecuted {}

/// What a run did.
pub struct RunSummary {
    pub record: RunRecord,
}

/// An output as the coordinator holds it: the reference, plus the bytes while readers need them.
#[derive(Clone)]
struct Produced {
    r: OutputRef,
    mem: Option<Blob>,
    /// Made by this run and kept only in the output folder: its task's record waits for its files.
    only_in_folder: bool,
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum State {
    Waiting,
    Running,
    Done,
    Failed,
    Skipped,
}

struct OuterRun {
    plan: OuterPlan,
    seq: u64,
    state: Vec<State>,
    waiting: Vec<u32>,
    /// Per task and output port, the tasks that still have to read it: a port's bytes are kept
    /// in memory until its last reader has them (per port, not per task: a scene-wide index that
    /// reads one small port of every task must not keep their images in memory until it runs).
    readers_left: Vec<Vec<u32>>,
    outputs: Vec<Option<Arc<Vec<Produced>>>>,
    open: usize,
    /// Export writes of this outer item still running: it stays active until they end, so that
    /// a task whose blob turns out corrupt when exported can still be run again.
    exports_pending: usize,
    /// Finished tasks being run again because a blob of theirs was found missing or corrupt, with
    /// the tasks waiting for the new output (they failed reading the old one).
    redoing: HashMap<u32, Vec<u32>>,
    /// How often each task was run again (bounded by [`MAX_REDO`]).
    redone: HashMap<u32, u32>,
    /// This process's claim on the outer item, released when it closes (see [`Claims`]).
    claim: Option<Claim>,
    /// Whether its tasks may be executed ([`RunOptions::execute_only`]).
    may_execute: bool,
}

impl OuterRun {
    fn closed(&self) -> bool {
        self.open == 0 && self.exports_pending == 0 && self.redoing.is_empty()
    }
}

/// How often a run looks again at the outer items other processes hold.
const CLAIM_POLL: Duration = Duration::from_millis(200);

/// Claims on outer items, so that processes sharing a store share the work instead of each
/// doing all of it: a process runs an outer item only while it holds the item's claim (a file
/// under the store's `leases/claims/`, see [`crate::lease::Claim`]); an item another live
/// process holds waits, and once let go it is admitted and finds its tasks cached. The claim's
/// name is the pipeline's digest with the item's label: processes running different pipelines
/// (or params) do not wait for each other.
struct Claims<'e> {
    store: &'e Store,
    space: &'e dyn ItemSpace,
    pipeline: String,
    dim: String,
    said: std::collections::HashSet<u32>,
    last_poll: Instant,
}

impl<'e> Claims<'e> {
    fn new(engine: &'e Engine, p: &Pipeline) -> Claims<'e> {
        Claims {
            store: engine.store,
            space: engine.dataset,
            pipeline: pipeline_digest(p).hex(),
            dim: p.dims[0].name.clone(),
            said: Default::default(),
            last_poll: Instant::now(),
        }
    }

    fn take(&mut self, outer: u32) -> Result<std::result::Result<Claim, Holder>> {
        let label = self.space.label(&ItemKey::new(&[outer]));
        let name = DigestBuilder::new("dist4d-claim").str(&self.pipeline).str(&label).finish().hex();
        self.store.claim(&name[..32])
    }

    /// Says that the run waits for another process (for the first few items: with many
    /// processes on one store, collisions are many and each one is ordinary).
    fn waiting_for(&mut self, outer: u32, holder: &Holder) {
        if self.said.len() == 3 && self.said.insert(outer) {
            eprintln!("(and more: items other processes are running are waited for, silently from now on)");
        }
        if self.said.len() < 3 && self.said.insert(outer) {
            let label = self.space.label(&ItemKey::new(&[outer]));
            eprintln!(
                "{} `{label}` is being run by another process sharing the store ({}); this run takes its results when it ends",
                self.dim,
                holder.describe()
            );
        }
    }

    fn poll_due(&mut self) -> bool {
        let due = self.last_poll.elapsed() >= CLAIM_POLL;
        if due {
            self.last_poll = Instant::now();
        }
        due
    }
}

/// How often one task is run again in one run to replace a missing or corrupt blob: a store
/// that keeps losing blobs (a failing disk) must not make a run loop.
const MAX_REDO: u32 = 2;

/// Where a worker finds the bytes of one input artifact.
enum Src {
    Mem(Blob),
    Inline(Arc<[u8]>),
    Cas(Digest),
    Source { port: String },
}

struct Job {
    slot: u32,
    task: u32,
    node: usize,
    item: ItemKey,
    /// Known when the coordinator could compute it without hashing raw files.
    key: Option<Digest>,
    inputs: Vec<Vec<Input>>,
    /// Where the bytes of each input are, in the shape of `inputs`.
    srcs: Vec<Vec<Src>>,
    /// False: only a cache hit is taken ([`RunOptions::execute_only`]).
    may_execute: bool,
}

/// A ready task, as the coordinator found it.
enum Prepared {
    Cached(Digest, Vec<OutputRef>),
    Job(Job),
}

enum Outcome {
    Cached(Digest, Vec<OutputRef>),
    /// Key, outputs, microseconds, and the task record when it waits for exports to be appended
    /// (outputs kept only in the output folder); `None` when the worker appended it.
    Executed(Digest, Vec<Produced>, u64, Option<Box<TaskRecord>>),
}

impl Outcome {
    /// How many outputs the task made (none: it had nothing to make).
    fn outputs(&self) -> usize {
        match self {
            Outcome::Cached(_, outs) => outs.len(),
            Outcome::Executed(_, produced, ..) => produced.len(),
        }
    }
}

enum Msg {
    Task {
        slot: u32,
        task: u32,
        /// The resource class whose slot the task held, if any.
        waited: Option<usize>,
        result: Result<Outcome>,
    },
    /// An export job ended; `awaiting` is the id of the task record waiting for it, if any.
    Exported { slot: u32, task: u32, rel: String, result: Result<FileStat>, awaiting: Option<u64> },
}

/// The record of an executed task whose outputs are kept only in the output folder, waiting for
/// their files to be written before it is appended.
struct Awaiting {
    /// None once an export of it failed: its bytes are not all anywhere, so no record.
    record: Option<Box<TaskRecord>>,
    files_left: usize,
}

/// Heap entry: lower sorts first (earlier outer item, earlier position along the second dimension,
/// earlier stage).
type ReadyEntry = Reverse<(u64, u32, u32, u32, u32)>;

/// A run recorded as running and not yet ended: what [`Engine::run`] records if the run stops on
/// an error (a full disk) instead of leaving it "running", which `dist4d runs` would then show as
/// killed.
struct Unfinished {
    record: RunRecord,
    started: Instant,
    counters: Arc<Counters>,
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

    fn run_recorded(&self, opts: &RunOptions, unfinished: &mut Option<Unfinished>) -> Result<RunSummary> {
        let started = Instant::now();
        let started_unix = runs::now_secs();
        let p = self.pipeline;
        // Millisecond prefix: ids of runs started in the same second still sort in start order.
        let millis =
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis()).unwrap_or(0);
        let run_id = format!("{millis:013}-{}", self.store.writer_id());
        let view = View { space: self.dataset, second_dim_limit: opts.second_dim_limit };
        let mut outers = select_outer(self.dataset, &p.dims[0].name, opts.outer_items.as_deref())?;
        if let Some((i, n)) = opts.shard {
            ensure!(n >= 1 && i < n, "shard {i}/{n}: the shard is 0 to n - 1 of n");
            outers = shard_outer(&view, &outers, p.dims.len(), (i, n));
        }

        let mut exporter = match &opts.out_dir {
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
        let keys = match &exporter {
            Some(x) => Keys::new(p, self.dataset, self.store).with_identities(&identities).exporting_to(x.folder()),
            None => Keys::new(p, self.dataset, self.store).with_identities(&identities),
        };
        // Canonical params are stored as blobs so that explain can show what changed.
        for n in p.stage_order() {
            let text = &p.nodes[n].stage().unwrap().params.canonical;
            self.store.put_blob(&keys.params(n), text.as_bytes())?;
        }

        let stage_nodes: Vec<usize> = p.stage_order().collect();
        let mut rank = vec![0u32; p.nodes.len()];
        for (i, &n) in p.order.iter().enumerate() {
            rank[n] = i as u32;
        }
        let counters = Arc::new(Counters::new(stage_nodes.iter().map(|&n| p.nodes[n].name.clone()).collect()));
        let counter_of: Vec<usize> = {
            let mut v = vec![usize::MAX; p.nodes.len()];
            for (i, &n) in stage_nodes.iter().enumerate() {
                v[n] = i;
            }
            v
        };
        // Expected totals, corrected as outer items are planned.
        for (i, &n) in stage_nodes.iter().enumerate() {
            let mut total = 0u64;
            for &s in &outers {
                total += count_items(&view, ItemKey::new(&[s]), p.nodes[n].grain);
            }
            counters.total[i].store(total, Ordering::Relaxed);
        }
        let stats: Vec<StageStats> = stage_nodes
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
        *unfinished = Some(Unfinished { record: provisional.clone(), started, counters: counters.clone() });
        let reporter = Reporter::start(counters.clone(), opts.progress);

        let keys_tmp = self.store.temp_path();
        let keys_out = std::io::BufWriter::new(
            std::fs::File::create(&keys_tmp).with_context(|| format!("creating {}", keys_tmp.display()))?,
        );

        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(opts.jobs.max(1))
            .thread_name(|i| format!("dist4d-worker-{i}"))
            .build()?;
        // Tasks of operators that wait on an external resource (a model worker on a GPU) run on
        // threads of their own, as many at once as the resource takes, so that waiting for a
        // model does not hold the CPU threads the other stages need.
        let classes = ResourceClasses::of(self.operators);
        let wait_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(classes.slots.iter().sum::<usize>().clamp(1, 256))
            .thread_name(|i| format!("dist4d-wait-{i}"))
            .build()?;
        // Exported files are written on threads of their own: a large file goes to the device
        // directly (`direct_io`) and its thread waits for it, which should not idle a CPU thread.
        // (A task's blobs are still written by the task's thread: its record must not be
        // appended before them. The largest, a compressed depth map, takes ~1 ms of the device.)
        let export_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(opts.jobs.clamp(1, 8))
            .thread_name(|i| format!("dist4d-export-{i}"))
            .build()?;
        // Files written or waiting to be: past this, no task starts, so that a slow disk holds
        // back the tasks whose outputs would queue in memory (the tasks already running may still
        // add theirs: a soft bound).
        let max_exporting = opts.jobs.max(1) * 4;
        let (tx, rx): (Sender<Msg>, Receiver<Msg>) = unbounded();
        let max_inflight = opts.jobs.max(1) * 2;
        let task_budget = 4096usize.max(opts.jobs * 256);
        // Outer items in flight at once: enough to keep every thread busy (the next item is
        // planned while the last tasks of one run), and no more, since each holds a claim that
        // other processes sharing the store would otherwise take.
        let outer_budget = opts.jobs.max(1) + 1;
        let mut c = Coord {
            active: Vec::new(),
            ready: BinaryHeap::new(),
            stats,
            counters: counters.clone(),
            counter_of,
            failures: Vec::new(),
            keys_out,
            exporter: exporter.take(),
            rank,
            live_tasks: 0,
            export_jobs: Vec::new(),
            awaiting: HashMap::new(),
            next_awaiting: 0,
            released: Vec::new(),
            stop: opts.cancel.clone(),
        };
        let deferred = self.operators.iter().map(|op| op.as_deref().is_some_and(deferred_node)).collect();
        let nothing = Mutex::new(vec![None; p.nodes.len()]);
        let ctx = Ctx { engine: self, keys: &keys, deferred, nothing };
        let mut next_outer = 0usize;
        let mut inflight = 0usize;
        let mut exporting = 0usize;
        let mut busy = vec![0usize; classes.slots.len()];
        let mut parked: Vec<VecDeque<Job>> = classes.slots.iter().map(|_| VecDeque::new()).collect();
        let mut waiting = 0usize;
        let mut stopping: Option<RunStatus> = None;
        let mut claims = Claims::new(self, p);
        let executed_outers: Option<Vec<u32>> = match &opts.execute_only {
            Some(names) => Some(select_outer(self.dataset, &p.dims[0].name, Some(names))?),
            None => None,
        };
        let may_execute = |o: u32| executed_outers.as_ref().is_none_or(|v| v.binary_search(&o).is_ok());
        let mut deferred: VecDeque<(u32, u64)> = VecDeque::new();

        // The scopes guarantee every spawned job has ended before they return, even on an error.
        export_pool.in_place_scope(|export_scope| -> Result<()> {
            wait_pool.in_place_scope(|wait_scope| -> Result<()> {
                pool.in_place_scope(|scope| -> Result<()> {
                    loop {
                        if stopping.is_none() && opts.cancel.load(Ordering::Relaxed) {
                            stopping = Some(RunStatus::Interrupted);
                        }
                        if stopping.is_none() && self.store.lease_lost() {
                            // Others judged this process dead and may be redoing its items: it
                            // stops rather than race them. What it finished is in the store.
                            c.failures.push(Failure {
                                stage: "-".into(),
                                item: "-".into(),
                                error: "this process's lease in the store was lost (it was stopped or its filesystem \
                                    stalled for longer than the lease timeout, and other processes judged it dead): \
                                    it stopped; rerun to finish"
                                    .into(),
                            });
                            stopping = Some(RunStatus::Stopped);
                        }
                        // Admit outer items while there is room; one that another process is
                        // running waits, and is admitted (its tasks then cached) when it lets go.
                        while stopping.is_none() && next_outer < outers.len() && c.has_room(task_budget, outer_budget) {
                            let o = outers[next_outer];
                            match claims.take(o)? {
                                Ok(claim) => {
                                    // Another process may have run the item and let it go since this
                                    // one opened the store: its records are read first (a refresh
                                    // with nothing new costs a listing and a stat per segment).
                                    self.store.refresh()?;
                                    c.admit(p, &view, o, next_outer as u64, &stage_nodes, Some(claim), may_execute(o))
                                }
                                Err(holder) => {
                                    claims.waiting_for(o, &holder);
                                    deferred.push_back((o, next_outer as u64));
                                }
                            }
                            next_outer += 1;
                        }
                        if stopping.is_none()
                            && !deferred.is_empty()
                            && c.has_room(task_budget, outer_budget)
                            && claims.poll_due()
                        {
                            for _ in 0..deferred.len() {
                                // All the claims of a process that just died free up at once.
                                if !c.has_room(task_budget, outer_budget) {
                                    break;
                                }
                                let (o, seq) = deferred.pop_front().expect("counted");
                                match claims.take(o)? {
                                    Ok(claim) => {
                                        self.store.refresh()?;
                                        c.admit(p, &view, o, seq, &stage_nodes, Some(claim), may_execute(o));
                                    }
                                    Err(_) => deferred.push_back((o, seq)),
                                }
                            }
                        }
                        // Released claims: the records of their items go to the server first, so
                        // that a process on another node that takes the item over finds them.
                        if !c.released.is_empty() {
                            self.store.sync_records()?;
                            c.released.clear();
                        }

                        // Start ready tasks: cache hits complete here, the rest go to the pools.
                        while stopping.is_none() && inflight < max_inflight && exporting < max_exporting {
                            let Some(Reverse((_, _, _, slot, task))) = c.ready.pop() else { break };
                            let run = c.active[slot as usize].as_ref().unwrap();
                            let node = run.plan.tasks[task as usize].node as usize;
                            if let Some(why) = &unavailable[node] {
                                c.finish(self, slot, task, Err(anyhow!("{why}")))?;
                                continue;
                            }
                            match ctx.prepare(run, slot, task) {
                                Err(e) => c.finish(self, slot, task, Err(e))?,
                                Ok(Prepared::Cached(key, outs)) => {
                                    c.finish(self, slot, task, Ok(Outcome::Cached(key, outs)))?
                                }
                                Ok(Prepared::Job(job)) => {
                                    c.active[slot as usize].as_mut().unwrap().state[task as usize] = State::Running;
                                    match classes.of_node[job.node] {
                                        None => {
                                            inflight += 1;
                                            spawn_task(scope, &ctx, &tx, job, None);
                                        }
                                        Some(k) if busy[k] < classes.slots[k] => {
                                            busy[k] += 1;
                                            waiting += 1;
                                            spawn_task(wait_scope, &ctx, &tx, job, Some(k));
                                        }
                                        Some(k) => parked[k].push_back(job),
                                    }
                                }
                            }
                            if opts.fail_fast && !c.failures.is_empty() {
                                stopping.get_or_insert(RunStatus::Stopped);
                            }
                            exporting += c.spawn_exports(export_scope, &tx);
                        }

                        let outers_left = stopping.is_none() && (next_outer < outers.len() || !deferred.is_empty());
                        let ready_left = stopping.is_none() && !c.ready.is_empty();
                        if inflight == 0 && waiting == 0 && exporting == 0 && !outers_left && !ready_left {
                            return Ok(());
                        }
                        if inflight == 0 && waiting == 0 && exporting == 0 {
                            if !ready_left && next_outer == outers.len() {
                                // Only items other processes hold are left.
                                std::thread::sleep(CLAIM_POLL);
                            }
                            continue;
                        }
                        match rx.recv_timeout(Duration::from_millis(200)) {
                            Ok(Msg::Task { slot, task, waited, result }) => {
                                match waited {
                                    None => inflight -= 1,
                                    Some(k) => {
                                        waiting -= 1;
                                        busy[k] -= 1;
                                        if let Some(job) = parked[k].pop_front().filter(|_| stopping.is_none()) {
                                            busy[k] += 1;
                                            waiting += 1;
                                            spawn_task(wait_scope, &ctx, &tx, job, Some(k));
                                        }
                                    }
                                }
                                c.finish(self, slot, task, result)?;
                                exporting += c.spawn_exports(export_scope, &tx);
                            }
                            Ok(Msg::Exported { slot, task, rel, result, awaiting }) => {
                                exporting -= 1;
                                c.exported(self, slot, task, &rel, result, awaiting);
                            }
                            Err(RecvTimeoutError::Timeout) => {}
                            Err(RecvTimeoutError::Disconnected) => bail!("the worker pool stopped unexpectedly"),
                        }
                        if opts.fail_fast && !c.failures.is_empty() {
                            stopping.get_or_insert(RunStatus::Stopped);
                        }
                    }
                })
            })
        })?;
        drop(export_pool);
        drop(wait_pool);
        drop(pool);
        drop(reporter);
        let Coord { mut stats, failures, mut keys_out, exporter, awaiting, counter_of, .. } = c;
        debug_assert!(awaiting.is_empty(), "every export job has ended");
        for (i, s) in stats.iter_mut().enumerate() {
            s.total = counters.total[i].load(Ordering::Relaxed);
        }
        let nothing = ctx.nothing.into_inner().unwrap_or_else(|e| e.into_inner());
        for (node, why) in nothing.into_iter().enumerate() {
            if let (Some(why), Some(&ci)) = (why, counter_of.get(node)) {
                stats[ci].nothing = Some(why);
            }
        }

        // The output folder first (its files, then its manifest), then the store: after a power
        // loss, a record made durable names exported files that are too. The key layer lets go
        // of the folder first, so that its manifest is not copied.
        drop(keys);
        let exported = match exporter {
            Some(e) => e.finish()?,
            None => 0,
        };
        self.store.sync()?;
        keys_out.flush().with_context(|| format!("writing {}", keys_tmp.display()))?;
        drop(keys_out);
        std::fs::rename(&keys_tmp, runs::keys_path(self.store, &run_id))
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
        Ok(RunSummary { record })
    }

    /// Worker side: key the task if the coordinator could not (hashing raw files), check the
    /// cache, else run it and store its outputs and record.
    fn execute(&self, mut job: Job, keys: &Keys, nothing: &Mutex<Vec<Option<(String, String)>>>) -> Result<Outcome> {
        let node = &self.pipeline.nodes[job.node];
        let stage = node.stage().expect("jobs are for stages");
        let label = self.dataset.path(&job.item);
        let key = match job.key {
            Some(k) => k,
            None => {
                keys.hash_sources(&mut job.inputs);
                if let Some(e) = take_unreadable(&mut job.inputs) {
                    return Err(e);
                }
                match keys.decide(job.node, &job.item, &job.inputs, true) {
                    Decision::Cached { key, outputs } => return Ok(Outcome::Cached(key, outputs)),
                    Decision::Run { .. } if !job.may_execute => return Err(NotExecuted { deferred: false }.into()),
                    Decision::Run { key, .. } => key,
                    Decision::Unknown => bail!("{}", self.unknown_inputs(&job)),
                }
            }
        };
        let t0 = Instant::now();
        let mut artifacts: Vec<Vec<Artifact>> = Vec::with_capacity(job.inputs.len());
        for ((input, srcs), spec) in job.inputs.iter().zip(&job.srcs).zip(&stage.inputs) {
            let mut list = Vec::with_capacity(input.len());
            for (a, src) in input.iter().zip(srcs) {
                let bytes: Blob = match src {
                    Src::Mem(b) => b.clone(),
                    Src::Inline(b) => Arc::new(b.to_vec()),
                    Src::Cas(d) => {
                        Arc::new(self.store.get_blob(d).with_context(|| format!("reading input `{}`", spec.port))?)
                    }
                    Src::Source { port } => Arc::new(
                        self.dataset
                            .load_source(port, &a.item)
                            .with_context(|| format!("reading dataset.{port} for {}", self.dataset.path(&a.item)))?,
                    ),
                };
                list.push(Artifact { item: a.item, pos: a.pos(), bytes });
            }
            artifacts.push(list);
        }
        let unread = self.unread_to_leave(keys, job.node, &key);
        let ctx = TaskContext { item: job.item, seed: keys.seed(job.node, &job.item), label: &label, unread: &unread };
        let outs = match self.operators[job.node]
            .as_ref()
            .ok_or_else(|| anyhow!("no operator for stage `{}`", node.name))?
            .run(&ctx, &artifacts)
        {
            Ok(outs) => outs,
            // Recorded with no outputs, like a task that made them (see NotApplicable); the
            // first reason per stage is kept for the run to say.
            Err(e) if e.downcast_ref::<NotApplicable>().is_some() => {
                if let Some(NotApplicable(reason)) = e.downcast_ref::<NotApplicable>() {
                    let mut first = nothing.lock().unwrap_or_else(|e| e.into_inner());
                    if let Some(slot) = first.get_mut(job.node) {
                        if slot.as_ref().is_none_or(|(_, item)| label.as_str() < item.as_str()) {
                            *slot = Some((reason.clone(), label.clone()));
                        }
                    }
                }
                Vec::new()
            }
            Err(e) => return Err(e.context(format!("{} ({})", node.name, stage.kind))),
        };
        if !outs.is_empty() && outs.len() != node.outputs.len() {
            bail!(
                "stage `{}` ({}) returned {} outputs, its kind declares {}; nothing was stored",
                node.name,
                stage.kind,
                outs.len(),
                node.outputs.len()
            );
        }
        // Before anything enters the cache: a mistyped output would fail only in a reader downstream.
        for (out, port) in outs.iter().zip(&node.outputs) {
            if out.ty != port.ty {
                bail!(
                    "stage `{}` ({}) returned a {} for output `{}`, which is declared {}; nothing was stored",
                    node.name,
                    stage.kind,
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
                "stage `{}` ({}) did not make output `{}`, which this run reads; nothing was stored",
                node.name,
                stage.kind,
                node.outputs[port].name
            );
        }
        let micros = t0.elapsed().as_micros() as u64;
        let mut produced = Vec::with_capacity(outs.len());
        for (port, Output { bytes, .. }) in outs.into_iter().enumerate() {
            let Some(bytes) = bytes else {
                produced.push(Produced { r: OutputRef::unmade(), mem: None, only_in_folder: false });
                continue;
            };
            let digest = Digest::of(&bytes);
            let size = bytes.len() as u64;
            // Its bytes go to the output folder only (the exporter writes them from memory).
            let only_in_folder = keys.only_in_folder(job.node, port, size);
            let inline = if bytes.len() <= INLINE_MAX {
                Some(Arc::<[u8]>::from(bytes.as_slice()))
            } else {
                if !only_in_folder {
                    self.store.put_blob(&digest, &bytes)?;
                }
                None
            };
            let r = OutputRef { digest, size, inline };
            produced.push(Produced { r, mem: Some(Arc::new(bytes)), only_in_folder });
        }
        let record = TaskRecord {
            key,
            stage: node.name.clone(),
            item: job.item,
            kind: stage.kind.clone(),
            version: stage.version,
            params: keys.params(job.node),
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
        };
        if produced.iter().any(|p| p.only_in_folder) {
            return Ok(Outcome::Executed(key, produced, micros, Some(Box::new(record))));
        }
        self.store.append_record(&record)?;
        Ok(Outcome::Executed(key, produced, micros, None))
    }

    /// The output ports of `node` its task under `key` may leave unmade: those nothing of the run
    /// reads, except those an earlier record of the key made and still has the bytes of. A record
    /// replaces the one before it, so without this two pipelines (or two stages of one) reading
    /// different ports of one task would each find the other's record short and run it again,
    /// every run; this way a task's records only gain outputs.
    fn unread_to_leave(&self, keys: &Keys, node: NodeId, key: &Digest) -> Vec<String> {
        let unread = keys.unread(node);
        let Some(old) = (!unread.is_empty()).then(|| self.store.lookup(key)).flatten() else {
            return unread.to_vec();
        };
        let outputs = &self.pipeline.nodes[node].outputs;
        let had = |name: &String| {
            let port = outputs.iter().position(|o| &o.name == name);
            port.and_then(|p| old.outputs.get(p))
                .is_some_and(|o| !o.is_unmade() && (o.inline.is_some() || self.store.has_blob(&o.digest)))
        };
        unread.iter().filter(|name| !had(name)).cloned().collect()
    }

    /// Which inputs of a job still have no digest after hashing, for the error.
    fn unknown_inputs(&self, job: &Job) -> String {
        let stage = self.pipeline.nodes[job.node].stage().expect("jobs are for stages");
        let mut missing = Vec::new();
        for (input, spec) in job.inputs.iter().zip(&stage.inputs) {
            for a in input.iter().filter(|a| a.digest.is_err()) {
                let from = match a.src {
                    InputSrc::Task { task, .. } => format!("upstream task {task}"),
                    InputSrc::Source { node, .. } => self.pipeline.nodes[node as usize].name.clone(),
                };
                missing.push(format!("input `{}` ({from} for {})", spec.port, self.dataset.path(&a.item)));
            }
        }
        format!("no digest for {}", missing.join(", "))
    }
}

/// The coordinator's state: only the coordinator thread touches it.
struct Coord {
    active: Vec<Option<OuterRun>>,
    ready: BinaryHeap<ReadyEntry>,
    stats: Vec<StageStats>,
    counters: Arc<Counters>,
    counter_of: Vec<usize>,
    failures: Vec<Failure>,
    keys_out: std::io::BufWriter<std::fs::File>,
    exporter: Option<Exporter>,
    rank: Vec<u32>,
    live_tasks: usize,
    /// Export writes decided by `finish` (with the task's slot and index, and the id of the record
    /// awaiting it), to be spawned by the loop.
    export_jobs: Vec<(ExportJob, u32, u32, Option<u64>)>,
    /// Task records waiting for their exports, by id.
    awaiting: HashMap<u64, Awaiting>,
    next_awaiting: u64,
    /// Claims of outer items that closed, to be let go once their records are synced.
    released: Vec<Claim>,
    /// Set when the run is asked to stop ([`RunOptions::cancel`]): a task that ends in an error
    /// then was most likely cut short at one of its cancellation points, so it is counted as not
    /// executed, not as a failure (a rerun runs it again either way: failures are not cached).
    stop: Arc<AtomicBool>,
}

impl Coord {
    /// Whether another outer item may be admitted.
    fn has_room(&self, task_budget: usize, outer_budget: usize) -> bool {
        self.live_tasks < task_budget && self.active.iter().filter(|a| a.is_some()).count() < outer_budget
    }

    /// Plans an outer item and queues its tasks that have no upstream tasks.
    #[allow(clippy::too_many_arguments)]
    fn admit(
        &mut self,
        p: &Pipeline,
        view: &View,
        outer: u32,
        seq: u64,
        stage_nodes: &[usize],
        claim: Option<Claim>,
        may_execute: bool,
    ) {
        let plan = plan_outer(p, view, outer);
        // Tasks that could not be planned (offsets past the end of a dimension) leave the totals.
        for (i, &n) in stage_nodes.iter().enumerate() {
            let expected = count_items(view, ItemKey::new(&[outer]), p.nodes[n].grain);
            let planned = plan.tasks.iter().filter(|t| t.node as usize == n).count() as u64;
            self.counters.total[i].fetch_sub(expected - planned, Ordering::Relaxed);
        }
        let n = plan.tasks.len();
        if n == 0 {
            return;
        }
        self.live_tasks += n;
        let slot = match self.active.iter().position(|a| a.is_none()) {
            Some(s) => s,
            None => {
                self.active.push(None);
                self.active.len() - 1
            }
        };
        let run = OuterRun {
            seq,
            state: vec![State::Waiting; n],
            waiting: plan.tasks.iter().map(|t| t.upstream).collect(),
            readers_left: readers_per_port(&plan, p),
            outputs: vec![None; n],
            open: n,
            exports_pending: 0,
            redoing: HashMap::new(),
            redone: HashMap::new(),
            claim,
            may_execute,
            plan,
        };
        for (t, task) in run.plan.tasks.iter().enumerate() {
            if task.upstream == 0 {
                self.ready.push(entry(&run, slot as u32, t as u32, &self.rank));
            }
        }
        self.active[slot] = Some(run);
    }

    fn spawn_exports<'s>(&mut self, scope: &rayon::Scope<'s>, tx: &Sender<Msg>) -> usize {
        let n = self.export_jobs.len();
        for (job, slot, task, awaiting) in self.export_jobs.drain(..) {
            let tx = tx.clone();
            scope.spawn(move |_| {
                let rel = job.rel.clone();
                // A panic is this file's failure, reported like an error: the loop counts every
                // export job it spawned back in, and would wait forever for one that never is.
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| job.write()))
                    .unwrap_or_else(|panic| Err(anyhow!("writing the file panicked: {}", panic_message(&panic))));
                let _ = tx.send(Msg::Exported { slot, task, rel, result, awaiting });
            });
        }
        n
    }

    /// A task ended (cached, executed or failed): record it and release what waited on it.
    fn finish(&mut self, e: &Engine, slot: u32, task: u32, result: Result<Outcome>) -> Result<()> {
        let t = task as usize;
        if let Err(err) = &result {
            if let Some(blob) = BlobError::find(err) {
                if self.heal(slot, t, blob.digest) {
                    return Ok(());
                }
            }
        }
        let run = self.active[slot as usize].as_mut().unwrap();
        if let Some(waiters) = run.redoing.remove(&task) {
            return self.finish_redo(e, slot, t, waiters, result);
        }
        let node = run.plan.tasks[t].node as usize;
        let ci = self.counter_of[node];
        match result {
            Ok(outcome) => {
                // A task with nothing to make counts as that, not as executed or cached.
                let nothing = outcome.outputs() == 0 && !e.pipeline.nodes[node].outputs.is_empty();
                match &outcome {
                    Outcome::Cached(..) if !nothing => self.stats[ci].cached += 1,
                    Outcome::Executed(_, _, micros, _) => {
                        self.stats[ci].executed += !nothing as u64;
                        self.stats[ci].seconds += *micros as f64 / 1e6;
                    }
                    Outcome::Cached(..) => {}
                }
                self.counters.done[ci].fetch_add(1, Ordering::Relaxed);
                self.complete(e, slot, t, outcome)?;
                if nothing {
                    self.stats[ci].not_applicable += 1;
                    self.pass_over(e, slot, t);
                } else {
                    let dependents = run_of(&self.active, slot).plan.tasks[t].dependents.clone();
                    self.release(slot, &dependents);
                }
            }
            Err(err) if err.downcast_ref::<NotExecuted>().is_some() || self.stop.load(Ordering::Relaxed) => {
                let how = match err.downcast_ref::<NotExecuted>() {
                    Some(NotExecuted { deferred: true }) => Skip::Deferred,
                    _ => Skip::Missing,
                };
                run.state[t] = State::Skipped;
                let dependents: Vec<usize> = run.plan.tasks[t].dependents.iter().map(|&d| d as usize).collect();
                self.count_skipped(ci, how);
                self.skip_all(slot, dependents, how);
            }
            Err(err) => {
                self.stats[ci].failed += 1;
                self.counters.failed[ci].fetch_add(1, Ordering::Relaxed);
                run.state[t] = State::Failed;
                self.failures.push(Failure {
                    stage: e.pipeline.nodes[node].name.clone(),
                    item: e.dataset.path(&run.plan.tasks[t].item),
                    error: format!("{err:#}"),
                });
                let dependents: Vec<usize> = run.plan.tasks[t].dependents.iter().map(|&d| d as usize).collect();
                self.skip_all(slot, dependents, Skip::Failed);
            }
        }
        let run = self.active[slot as usize].as_mut().unwrap();
        release_inputs(run, t);
        run.open -= 1;
        self.live_tasks -= 1;
        self.close_if_done(slot);
        Ok(())
    }

    /// Records a finished task's key and keeps its outputs (first run or run again alike).
    fn complete(&mut self, e: &Engine, slot: u32, t: usize, outcome: Outcome) -> Result<()> {
        let (key, produced, record) = match outcome {
            Outcome::Cached(key, outs) => {
                (key, outs.into_iter().map(|r| Produced { r, mem: None, only_in_folder: false }).collect(), None)
            }
            Outcome::Executed(key, produced, _, record) => (key, produced, record),
        };
        self.keys_out.write_all(&key.0).context("writing the run's task keys")?;
        self.store_outputs(e, slot, t, produced, record);
        Ok(())
    }

    /// One input of each of `tasks` is now there: those that wait for nothing more are ready.
    fn release(&mut self, slot: u32, tasks: &[u32]) {
        let run = self.active[slot as usize].as_mut().unwrap();
        for &d in tasks {
            let d = d as usize;
            run.waiting[d] -= 1;
            if run.waiting[d] == 0 && run.state[d] == State::Waiting {
                self.ready.push(entry(run, slot, d as u32, &self.rank));
            }
        }
    }

    /// Task `t` had nothing to make: its outputs leave the inputs of the tasks that read them,
    /// which then go on without them, or, when that leaves one of their inputs with nothing,
    /// have nothing to make either (and so on downstream).
    fn pass_over(&mut self, e: &Engine, slot: u32, t: usize) {
        let mut stack = vec![t];
        while let Some(u) = stack.pop() {
            let run = self.active[slot as usize].as_mut().unwrap();
            let dependents = run.plan.tasks[u].dependents.clone();
            for d in dependents {
                let d = d as usize;
                if run.state[d] != State::Waiting {
                    continue;
                }
                if run.plan.drop_upstream(d as u32, u as u32) {
                    run.state[d] = State::Skipped;
                    // Nothing to make: what an earlier run exported for it goes.
                    let (node, item) = (run.plan.tasks[d].node as usize, run.plan.tasks[d].item);
                    if let Some(exporter) = self.exporter.as_mut() {
                        for x in e.pipeline.exports.iter().filter(|x| x.node == node) {
                            exporter.remove_stale(x, &item, e.dataset);
                        }
                    }
                    let dn = self.counter_of[run.plan.tasks[d].node as usize];
                    self.stats[dn].not_applicable += 1;
                    self.counters.done[dn].fetch_add(1, Ordering::Relaxed);
                    release_inputs(run, d);
                    run.open -= 1;
                    self.live_tasks -= 1;
                    stack.push(d);
                } else {
                    run.waiting[d] -= 1;
                    if run.waiting[d] == 0 {
                        self.ready.push(entry(run, slot, d as u32, &self.rank));
                    }
                }
            }
        }
    }

    /// Frees the slot of an outer item whose tasks, exports and reruns have all ended.
    fn close_if_done(&mut self, slot: u32) {
        if run_of(&self.active, slot).closed() {
            if let Some(claim) = self.active[slot as usize].take().and_then(|r| r.claim) {
                self.released.push(claim);
            }
        }
    }

    /// Marks the tasks of `stack` and everything downstream of them that still waits as skipped:
    /// an input of theirs failed.
    /// `how` says why, and so how they count (see [`Skip`]).
    fn skip_all(&mut self, slot: u32, mut stack: Vec<usize>, how: Skip) {
        while let Some(d) = stack.pop() {
            let run = self.active[slot as usize].as_mut().unwrap();
            if run.state[d] != State::Waiting {
                continue;
            }
            run.state[d] = State::Skipped;
            let dn = self.counter_of[run.plan.tasks[d].node as usize];
            self.count_skipped(dn, how);
            let run = self.active[slot as usize].as_mut().unwrap();
            release_inputs(run, d);
            run.open -= 1;
            self.live_tasks -= 1;
            stack.extend(run.plan.tasks[d].dependents.iter().map(|&x| x as usize));
        }
    }

    /// Counts a task of stage counter `ci` that does not run, as `how` says.
    fn count_skipped(&mut self, ci: usize, how: Skip) {
        match how {
            Skip::Failed => {
                self.stats[ci].skipped += 1;
                self.counters.failed[ci].fetch_add(1, Ordering::Relaxed);
            }
            Skip::Missing => {
                self.stats[ci].missing += 1;
                self.counters.missing[ci].fetch_add(1, Ordering::Relaxed);
            }
            Skip::Deferred => {
                self.stats[ci].deferred += 1;
                self.counters.missing[ci].fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Keeps a finished task's outputs for its readers and plans their exports. `record`, of a
    /// task just executed whose outputs are kept only in the output folder, is appended once the
    /// files of those outputs are in place (at once when they already are), and never when one
    /// of them cannot be written.
    fn store_outputs(
        &mut self,
        e: &Engine,
        slot: u32,
        t: usize,
        produced: Vec<Produced>,
        record: Option<Box<TaskRecord>>,
    ) {
        let p = e.pipeline;
        let run = self.active[slot as usize].as_mut().unwrap();
        run.state[t] = State::Done;
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
            Some(a) if a.files_left > 0 => {
                self.awaiting.insert(id, a);
                self.next_awaiting += 1;
            }
            Some(Awaiting { record: Some(record), .. }) => self.append(e, &record),
            _ => {}
        }
    }

    /// Appends the record of a task whose exports are in place; failing to is the task's failure.
    fn append(&mut self, e: &Engine, record: &TaskRecord) {
        if let Err(err) = e.store.append_record(record) {
            self.failures.push(Failure {
                stage: record.stage.clone(),
                item: e.dataset.path(&record.item),
                error: format!("recording the finished task in the store: {err:#}"),
            });
        }
    }

    /// A blob that finished task `u` produced is missing or corrupt, found by its reader `t`:
    /// runs `u` again and makes `t` wait for it. False when no task of the outer item made that blob,
    /// or `u` was already run again [`MAX_REDO`] times.
    fn heal(&mut self, slot: u32, t: usize, digest: Digest) -> bool {
        let run = self.active[slot as usize].as_ref().unwrap();
        let made_it = |u: usize, port: usize| {
            run.outputs[u].as_ref().and_then(|o| o.get(port)).is_some_and(|o| o.r.digest == digest)
        };
        let producer = run.plan.tasks[t].inputs.iter().flatten().find_map(|src| match *src {
            InputSrc::Task { task: u, port, .. } if made_it(u as usize, port as usize) => Some(u as usize),
            _ => None,
        });
        let Some(u) = producer else { return false };
        if !self.redo(slot, u) {
            return false;
        }
        let run = self.active[slot as usize].as_mut().unwrap();
        run.state[t] = State::Waiting;
        run.waiting[t] = 1;
        run.redoing.get_mut(&(u as u32)).expect("redo registered it").push(t as u32);
        true
    }

    /// Queues finished task `u` to run again (once, however many readers ask); false when it
    /// was already run again [`MAX_REDO`] times.
    fn redo(&mut self, slot: u32, u: usize) -> bool {
        let run = self.active[slot as usize].as_mut().unwrap();
        if run.redoing.contains_key(&(u as u32)) {
            return true;
        }
        let n = run.redone.entry(u as u32).or_default();
        if run.state[u] != State::Done || *n >= MAX_REDO {
            return false;
        }
        *n += 1;
        run.state[u] = State::Waiting;
        run.redoing.insert(u as u32, Vec::new());
        self.ready.push(entry(run, slot, u as u32, &self.rank));
        let ci = self.counter_of[run.plan.tasks[u].node as usize];
        self.stats[ci].recomputed += 1;
        true
    }

    /// A task run again to replace a lost blob ended: its waiters go on with the new output, or
    /// fail with it.
    fn finish_redo(
        &mut self,
        e: &Engine,
        slot: u32,
        t: usize,
        waiters: Vec<u32>,
        result: Result<Outcome>,
    ) -> Result<()> {
        match result {
            Ok(outcome) => {
                self.complete(e, slot, t, outcome)?;
                self.release(slot, &waiters);
            }
            // Its item is not one this run executes (a merge): the lost output is missing.
            Err(err) if err.downcast_ref::<NotExecuted>().is_some() => {
                let run = self.active[slot as usize].as_mut().unwrap();
                run.state[t] = State::Skipped;
                let ci = self.counter_of[run.plan.tasks[t].node as usize];
                self.count_skipped(ci, Skip::Missing);
                self.skip_all(slot, waiters.into_iter().map(|w| w as usize).collect(), Skip::Missing);
            }
            Err(err) => {
                let run = self.active[slot as usize].as_mut().unwrap();
                run.state[t] = State::Failed;
                let node = run.plan.tasks[t].node as usize;
                self.failures.push(Failure {
                    stage: e.pipeline.nodes[node].name.clone(),
                    item: e.dataset.path(&run.plan.tasks[t].item),
                    error: format!("run again to replace a lost cache blob, it failed: {err:#}"),
                });
                self.skip_all(slot, waiters.into_iter().map(|w| w as usize).collect(), Skip::Failed);
            }
        }
        self.close_if_done(slot);
        Ok(())
    }

    /// An export write ended. A blob found missing or corrupt makes its task run again (which
    /// exports it anew); any other failure is the item's.
    fn exported(
        &mut self,
        e: &Engine,
        slot: u32,
        task: u32,
        rel: &str,
        result: Result<FileStat>,
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
                    self.append(e, &record);
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
                let healed = BlobError::find(&err).is_some() && self.redo(slot, t);
                if !healed {
                    self.failures.push(Failure { stage, item, error: format!("{err:#}") });
                }
            }
        }
        self.close_if_done(slot);
    }
}

struct Ctx<'e, 'a> {
    engine: &'e Engine<'a>,
    keys: &'e Keys<'e>,
    /// Per node: its tasks are only taken from the cache ([`RunOptions::defer_resources`]).
    deferred: Vec<bool>,
    /// Per node: the reason its first task (by item label, so the same at any thread count) with
    /// nothing to make gave, and that item ([`StageStats::nothing`]).
    nothing: Mutex<Vec<Option<(String, String)>>>,
}

impl Ctx<'_, '_> {
    /// Resolves a ready task's inputs without hashing raw files, and decides through the key
    /// layer whether it is cached; otherwise makes the job a worker runs.
    fn prepare(&self, run: &OuterRun, slot: u32, task: u32) -> Result<Prepared> {
        let p = self.engine.pipeline;
        let t = &run.plan.tasks[task as usize];
        let node = t.node as usize;
        // Its worker is not started here, so its key (which holds the worker's identity) is not known.
        if self.deferred[node] {
            return Err(NotExecuted { deferred: true }.into());
        }
        let may_execute = run.may_execute;
        let output = |u: u32, port: u16| run.outputs[u as usize].as_ref().map(|o| &o[port as usize]);
        let mut inputs = self.keys.resolve(&run.plan, task, |u, port| output(u, port).map(|o| o.r.digest), false);
        if let Some(e) = take_unreadable(&mut inputs) {
            return Err(e);
        }
        // Without hashing: a raw file, or an exported file whose stat changed, is for the worker.
        let key = match self.keys.decide(node, &t.item, &inputs, false) {
            Decision::Cached { key, outputs } => return Ok(Prepared::Cached(key, outputs)),
            Decision::Run { .. } if !may_execute => return Err(NotExecuted { deferred: false }.into()),
            Decision::Run { key, .. } => Some(key),
            Decision::Unknown => None,
        };
        let srcs = t
            .inputs
            .iter()
            .map(|srcs| {
                srcs.iter()
                    .map(|src| match *src {
                        InputSrc::Task { task: u, port, .. } => {
                            let o = output(u, port).expect("upstream finished before its dependents are ready");
                            match (&o.mem, &o.r.inline) {
                                (Some(m), _) => Src::Mem(m.clone()),
                                (None, Some(b)) => Src::Inline(b.clone()),
                                (None, None) => Src::Cas(o.r.digest),
                            }
                        }
                        InputSrc::Source { node: sn, .. } => match &p.nodes[sn as usize].kind {
                            NodeKind::Source { port } => Src::Source { port: port.clone() },
                            NodeKind::Stage(_) => unreachable!("source inputs come from source nodes"),
                        },
                    })
                    .collect()
            })
            .collect();
        Ok(Prepared::Job(Job { slot, task, node, item: t.item, key, inputs, srcs, may_execute }))
    }
}

/// Runs `job` on a thread of `scope`'s pool and reports its outcome on `tx`; a panic in the
/// stage is that task's failure.
fn spawn_task<'s>(scope: &rayon::Scope<'s>, ctx: &'s Ctx<'_, '_>, tx: &Sender<Msg>, job: Job, waited: Option<usize>) {
    let tx = tx.clone();
    scope.spawn(move |_| {
        let (slot, task) = (job.slot, job.task);
        let result =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| ctx.engine.execute(job, ctx.keys, &ctx.nothing)))
                .unwrap_or_else(|panic| Err(anyhow!("the stage panicked: {}", panic_message(&panic))));
        let _ = tx.send(Msg::Task { slot, task, waited, result });
    });
}

/// The external resources a pipeline's operators wait on ([`crate::operator::Resource`]): one
/// class per resource name, with its slots, and each node's class.
struct ResourceClasses {
    slots: Vec<usize>,
    of_node: Vec<Option<usize>>,
}

impl ResourceClasses {
    fn of(operators: &[Option<Box<dyn Operator>>]) -> ResourceClasses {
        let mut names: Vec<String> = Vec::new();
        let mut slots = Vec::new();
        let of_node = operators
            .iter()
            .map(|op| {
                let r = op.as_ref()?.resource()?;
                Some(match names.iter().position(|n| *n == r.name) {
                    Some(k) => k,
                    None => {
                        names.push(r.name);
                        slots.push(r.slots.max(1));
                        names.len() - 1
                    }
                })
            })
            .collect();
        ResourceClasses { slots, of_node }
    }
}

/// The error of the first input whose dataset source could not be fingerprinted, if any.
fn take_unreadable(inputs: &mut [Vec<Input>]) -> Option<anyhow::Error> {
    for input in inputs.iter_mut().flatten() {
        if matches!(input.digest, Err(Unknown::Unreadable(_))) {
            if let Err(Unknown::Unreadable(e)) = std::mem::replace(&mut input.digest, Err(Unknown::Unhashed)) {
                return Some(e);
            }
        }
    }
    None
}

fn entry(run: &OuterRun, slot: u32, task: u32, rank: &[u32]) -> ReadyEntry {
    let t = &run.plan.tasks[task as usize];
    // Items without a second coordinate (per outer item) come after those with one.
    let second = if t.item.depth >= 2 { t.item.idx[1] } else { u32::MAX };
    Reverse((run.seq, second, rank[t.node as usize], slot, task))
}

/// A task no longer needs its inputs: upstream outputs nobody else will read drop their bytes.
fn release_inputs(run: &mut OuterRun, t: usize) {
    let mut seen: Vec<(u32, u16)> = Vec::new();
    for srcs in &run.plan.tasks[t].inputs {
        for src in srcs {
            if let InputSrc::Task { task: u, port, .. } = *src {
                if seen.contains(&(u, port)) {
                    continue;
                }
                seen.push((u, port));
                let (u, port) = (u as usize, port as usize);
                let Some(left) = run.readers_left[u].get_mut(port) else { continue };
                *left = left.saturating_sub(1);
                if *left == 0 {
                    if let Some(o) = &run.outputs[u] {
                        run.outputs[u] = Some(strip_unread(o, &run.readers_left[u]));
                    }
                }
            }
        }
    }
}

/// Per task of `plan` and output port, how many tasks read it.
fn readers_per_port(plan: &OuterPlan, p: &Pipeline) -> Vec<Vec<u32>> {
    let mut readers: Vec<Vec<u32>> =
        plan.tasks.iter().map(|t| vec![0; p.nodes[t.node as usize].outputs.len()]).collect();
    let mut seen: Vec<(u32, u16)> = Vec::new();
    for t in &plan.tasks {
        seen.clear();
        for src in t.inputs.iter().flatten() {
            if let InputSrc::Task { task: u, port, .. } = *src {
                if !seen.contains(&(u, port)) {
                    seen.push((u, port));
                    if let Some(n) = readers[u as usize].get_mut(port as usize) {
                        *n += 1;
                    }
                }
            }
        }
    }
    readers
}

/// The outputs with the in-memory bytes of every port no task still has to read dropped (they
/// are in the store, or in the output folder for the exports).
fn strip_unread(p: &Arc<Vec<Produced>>, readers_left: &[u32]) -> Arc<Vec<Produced>> {
    if p.iter().enumerate().all(|(i, x)| x.mem.is_none() || readers_left.get(i).is_some_and(|&n| n > 0)) {
        return p.clone();
    }
    Arc::new(
        p.iter()
            .enumerate()
            .map(|(i, x)| {
                if readers_left.get(i).is_some_and(|&n| n > 0) {
                    x.clone()
                } else {
                    Produced { mem: None, ..x.clone() }
                }
            })
            .collect(),
    )
}

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

fn panic_message(p: &Box<dyn std::any::Any + Send>) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}

/// The active outer item in `slot` (the coordinator only asks for slots it holds).
fn run_of(active: &[Option<OuterRun>], slot: u32) -> &OuterRun {
    active[slot as usize].as_ref().expect("an active slot")
}
