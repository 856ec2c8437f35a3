//! The coordinator's book of tasks: per active outer item, each task's [`State`], what it waits
//! for and what it made; how a task that ended moves the tasks downstream of it.

use super::task::{Ended, Produced, State};
use super::Engine;
use crate::digest::Digest;
use crate::export::{ExportJob, Exporter};
use crate::item::ItemKey;
use crate::lease::Claim;
use crate::plan::{plan_outer, InputSrc, OuterPlan, View};
use crate::progress::Counters;
use crate::runs::{Failure, StageStats};
use anyhow::{anyhow, Result};
use dist4d_graph::Pipeline;
use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// How often one task is run again in one run to replace a missing or corrupt blob: a store
/// that keeps losing blobs (a failing disk) must not make a run loop.
const MAX_REDO: u32 = 2;

/// How [`Book::skip_all`] counts the tasks it skips.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Skip {
    /// An input failed.
    Failed,
    /// An input was not executed ([`Ended::NotExecuted`]).
    Missing,
    /// An input was left to a later run.
    Deferred,
}

/// Heap entry: lower sorts first (earlier outer item, earlier position along the pipeline's
/// ordered dimension, earlier stage).
pub(super) type ReadyEntry = Reverse<(u64, u32, u32, u32, u32)>;

/// One outer item being run.
pub(super) struct OuterRun {
    pub plan: OuterPlan,
    pub seq: u64,
    pub state: Vec<State>,
    /// Per task, how many upstream tasks it still waits for.
    pub waiting: Vec<u32>,
    /// Per task and output port, the tasks that still have to read it: a port's bytes are kept
    /// in memory until its last reader has them (per port, not per task: a scene-wide index that
    /// reads one small port of every task must not keep their images in memory until it runs).
    pub readers_left: Vec<Vec<u32>>,
    pub outputs: Vec<Option<Arc<Vec<Produced>>>>,
    pub open: usize,
    /// Export writes of this outer item still running: it stays active until they end, so that
    /// a task whose blob turns out corrupt when exported can still be run again.
    pub exports_pending: usize,
    /// Finished tasks being run again because a blob of theirs was found missing or corrupt, with
    /// the tasks waiting for the new output (they failed reading the old one).
    pub redoing: HashMap<u32, Vec<u32>>,
    /// How often each task was run again (bounded by [`MAX_REDO`]).
    pub redone: HashMap<u32, u32>,
    /// This process's claim on the outer item, released when it closes (see [`super::claims`]).
    pub claim: Option<Claim>,
    /// Whether its tasks may be executed ([`super::RunOptions::execute_only`]).
    pub may_execute: bool,
}

impl OuterRun {
    fn closed(&self) -> bool {
        self.open == 0 && self.exports_pending == 0 && self.redoing.is_empty()
    }
}

/// The record of a task that ran and whose outputs are kept only in the output folder, waiting
/// for their files to be written before it is written.
pub(super) struct Awaiting {
    /// None once an export of it failed: its bytes are not all anywhere, so no record.
    pub record: Option<Box<crate::record::TaskRecord>>,
    pub files_left: usize,
}

/// The coordinator's state: only the coordinator thread touches it.
pub(super) struct Book {
    pub active: Vec<Option<OuterRun>>,
    pub ready: BinaryHeap<ReadyEntry>,
    pub stats: Vec<StageStats>,
    pub counters: Arc<Counters>,
    pub counter_of: Vec<usize>,
    pub failures: Vec<Failure>,
    pub keys_out: std::io::BufWriter<std::fs::File>,
    pub exporter: Option<Exporter>,
    /// Per node, its position in the pipeline's order.
    pub rank: Vec<u32>,
    /// The pipeline's ordered dimension (as an item depth), by which ready tasks are taken.
    pub ordered_dim: Option<usize>,
    pub live_tasks: usize,
    /// Export writes decided by `commit` (with the task's slot and index, and the id of the record
    /// awaiting it), to be spawned by the scheduler.
    pub export_jobs: Vec<(ExportJob, u32, u32, Option<u64>)>,
    /// Task records waiting for their exports, by id.
    pub awaiting: HashMap<u64, Awaiting>,
    pub next_awaiting: u64,
    /// Claims of outer items that closed, to be let go once their records are synced.
    pub released: Vec<Claim>,
    /// Per node: the reason its first task (by item label, so the same at any thread count) with
    /// nothing to make gave, and that item ([`StageStats::nothing`]).
    pub nothing: Vec<Option<(String, String)>>,
    /// Set when the run is asked to stop ([`super::RunOptions::cancel`]): a task that ends in an
    /// error then was most likely cut short at one of its cancellation points, so it is counted as
    /// not executed, not as a failure (a rerun runs it again either way: failures are not cached).
    pub stop: Arc<AtomicBool>,
}

impl Book {
    /// Whether another outer item may be admitted.
    pub(super) fn has_room(&self, task_budget: usize, outer_budget: usize) -> bool {
        self.live_tasks < task_budget && self.active.iter().filter(|a| a.is_some()).count() < outer_budget
    }

    /// Plans an outer item and queues its tasks that have no upstream tasks.
    pub(super) fn admit(
        &mut self,
        p: &Pipeline,
        view: &View,
        outer: u32,
        seq: u64,
        claim: Option<Claim>,
        may_execute: bool,
    ) {
        let plan = plan_outer(p, view, outer);
        // Tasks that could not be planned (offsets past the end of a dimension) leave the totals.
        for n in p.stage_order() {
            let expected = super::count_items(view, ItemKey::new(&[outer]), p.nodes[n].grain);
            let planned = plan.tasks.iter().filter(|t| t.node as usize == n).count() as u64;
            self.counters.total[self.counter_of[n]].fetch_sub(expected - planned, Ordering::Relaxed);
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
            state: vec![State::Planned; n],
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
                self.ready.push(self.entry(&run, slot as u32, t as u32));
            }
        }
        self.active[slot] = Some(run);
    }

    /// The ready-queue entry of a task: tasks stream through the stages in (outer item, position
    /// along the ordered dimension, stage) order, so an item can finish before later items start.
    fn entry(&self, run: &OuterRun, slot: u32, task: u32) -> ReadyEntry {
        let t = &run.plan.tasks[task as usize];
        // Items without a coordinate along it (per outer item) come after those with one.
        let along = match self.ordered_dim {
            Some(d) if (t.item.depth as usize) > d => t.item.idx[d],
            _ => u32::MAX,
        };
        Reverse((run.seq, along, self.rank[t.node as usize], slot, task))
    }

    /// A task ended (cached, ran, not executed or failed): commit it and move what waited on it.
    pub(super) fn finish(&mut self, e: &Engine, slot: u32, task: u32, result: Result<Ended>) -> Result<()> {
        let t = task as usize;
        if let Ok(Ended::LostInput { lost, .. }) = &result {
            if self.heal(slot, t, lost.digest) {
                return Ok(());
            }
        }
        let result = match result {
            Ok(Ended::LostInput { port, lost }) => Err(anyhow!(lost).context(format!("reading input `{port}`"))),
            r => r,
        };
        let run = self.active[slot as usize].as_mut().unwrap();
        if let Some(waiters) = run.redoing.remove(&task) {
            return self.finish_redo(e, slot, t, waiters, result);
        }
        let node = run.plan.tasks[t].node as usize;
        let ci = self.counter_of[node];
        let stopping = self.stop.load(Ordering::Relaxed);
        match result {
            Ok(Ended::NotExecuted { deferred }) => {
                self.skip_task(slot, t, if deferred { Skip::Deferred } else { Skip::Missing })
            }
            Err(_) if stopping => self.skip_task(slot, t, Skip::Missing),
            Ok(ended) => {
                // A task with nothing to make counts as that, not as executed or cached.
                let nothing = ended.made_nothing() && !e.pipeline.nodes[node].outputs.is_empty();
                match &ended {
                    Ended::Cached(..) if !nothing => self.stats[ci].cached += 1,
                    Ended::Ran(ran) => {
                        self.stats[ci].executed += !nothing as u64;
                        self.stats[ci].seconds += ran.micros as f64 / 1e6;
                        if let Some(why) = &ran.nothing {
                            let item = run_of(&self.active, slot).plan.tasks[t].item;
                            self.keep_first_reason(e, node, why, &item);
                        }
                    }
                    _ => {}
                }
                self.counters.done[ci].fetch_add(1, Ordering::Relaxed);
                self.commit(e, slot, t, ended)?;
                if nothing {
                    self.stats[ci].not_applicable += 1;
                    self.pass_over(e, slot, t);
                } else {
                    let dependents = run_of(&self.active, slot).plan.tasks[t].dependents.clone();
                    self.release(slot, &dependents);
                }
            }
            Err(err) => {
                self.stats[ci].failed += 1;
                self.counters.failed[ci].fetch_add(1, Ordering::Relaxed);
                let run = self.active[slot as usize].as_mut().unwrap();
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

    /// Task `t` did not run ([`Skip`] says why): it and everything downstream are skipped.
    fn skip_task(&mut self, slot: u32, t: usize, how: Skip) {
        let run = self.active[slot as usize].as_mut().unwrap();
        run.state[t] = State::Skipped;
        let ci = self.counter_of[run.plan.tasks[t].node as usize];
        let dependents: Vec<usize> = run.plan.tasks[t].dependents.iter().map(|&d| d as usize).collect();
        self.count_skipped(ci, how);
        self.skip_all(slot, dependents, how);
    }

    /// Keeps the reason a task of `node` gave for having nothing to make if its item's label
    /// sorts first, so that the run says the same whatever order its threads ran in.
    fn keep_first_reason(&mut self, e: &Engine, node: usize, why: &str, item: &ItemKey) {
        let label = e.dataset.path(item);
        if let Some(slot) = self.nothing.get_mut(node) {
            if slot.as_ref().is_none_or(|(_, first)| label.as_str() < first.as_str()) {
                *slot = Some((why.to_string(), label));
            }
        }
    }

    /// One input of each of `tasks` is now there: those that wait for nothing more are ready.
    pub(super) fn release(&mut self, slot: u32, tasks: &[u32]) {
        for &d in tasks {
            let d = d as usize;
            let run = self.active[slot as usize].as_mut().unwrap();
            run.waiting[d] -= 1;
            if run.waiting[d] == 0 && run.state[d] == State::Planned {
                let entry = self.entry(run_of(&self.active, slot), slot, d as u32);
                self.ready.push(entry);
            }
        }
    }

    /// Task `t` had nothing to make: its outputs leave the inputs of the tasks that read them,
    /// which then go on without them, or, when that leaves one of their inputs with nothing,
    /// have nothing to make either (and so on downstream).
    fn pass_over(&mut self, e: &Engine, slot: u32, t: usize) {
        let mut stack = vec![t];
        while let Some(u) = stack.pop() {
            let dependents = run_of(&self.active, slot).plan.tasks[u].dependents.clone();
            for d in dependents {
                let d = d as usize;
                let run = self.active[slot as usize].as_mut().unwrap();
                if run.state[d] != State::Planned {
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
                    let dn = self.counter_of[node];
                    self.stats[dn].not_applicable += 1;
                    self.counters.done[dn].fetch_add(1, Ordering::Relaxed);
                    release_inputs(run, d);
                    run.open -= 1;
                    self.live_tasks -= 1;
                    stack.push(d);
                } else {
                    run.waiting[d] -= 1;
                    if run.waiting[d] == 0 {
                        let entry = self.entry(run_of(&self.active, slot), slot, d as u32);
                        self.ready.push(entry);
                    }
                }
            }
        }
    }

    /// Frees the slot of an outer item whose tasks, exports and reruns have all ended.
    pub(super) fn close_if_done(&mut self, slot: u32) {
        if run_of(&self.active, slot).closed() {
            if let Some(claim) = self.active[slot as usize].take().and_then(|r| r.claim) {
                self.released.push(claim);
            }
        }
    }

    /// Marks the tasks of `stack` and everything downstream of them that still waits as skipped;
    /// `how` says why, and so how they count (see [`Skip`]).
    fn skip_all(&mut self, slot: u32, mut stack: Vec<usize>, how: Skip) {
        while let Some(d) = stack.pop() {
            let run = self.active[slot as usize].as_mut().unwrap();
            if run.state[d] != State::Planned {
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

    /// A blob that finished task `u` produced is missing or corrupt, found by its reader `t`:
    /// runs `u` again and makes `t` wait for it. False when no task of the outer item made that blob,
    /// or `u` was already run again [`MAX_REDO`] times.
    fn heal(&mut self, slot: u32, t: usize, digest: Digest) -> bool {
        let run = run_of(&self.active, slot);
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
        run.state[t] = State::Planned;
        run.waiting[t] = 1;
        run.redoing.get_mut(&(u as u32)).expect("redo registered it").push(t as u32);
        true
    }

    /// Queues finished task `u` to run again (once, however many readers ask); false when it
    /// was already run again [`MAX_REDO`] times.
    pub(super) fn redo(&mut self, slot: u32, u: usize) -> bool {
        let run = self.active[slot as usize].as_mut().unwrap();
        if run.redoing.contains_key(&(u as u32)) {
            return true;
        }
        let n = run.redone.entry(u as u32).or_default();
        if run.state[u] != State::Committed || *n >= MAX_REDO {
            return false;
        }
        *n += 1;
        run.state[u] = State::Planned;
        run.redoing.insert(u as u32, Vec::new());
        let ci = self.counter_of[run.plan.tasks[u].node as usize];
        let entry = self.entry(run_of(&self.active, slot), slot, u as u32);
        self.ready.push(entry);
        self.stats[ci].recomputed += 1;
        true
    }

    /// A task run again to replace a lost blob ended: its waiters go on with the new output, or
    /// fail with it.
    fn finish_redo(&mut self, e: &Engine, slot: u32, t: usize, waiters: Vec<u32>, result: Result<Ended>) -> Result<()> {
        let run = self.active[slot as usize].as_mut().unwrap();
        let node = run.plan.tasks[t].node as usize;
        match result {
            // Its item is not one this run executes (a merge): the lost output is missing.
            Ok(Ended::NotExecuted { .. }) => {
                run.state[t] = State::Skipped;
                self.count_skipped(self.counter_of[node], Skip::Missing);
                self.skip_all(slot, waiters.into_iter().map(|w| w as usize).collect(), Skip::Missing);
            }
            Ok(ended) => {
                self.commit(e, slot, t, ended)?;
                self.release(slot, &waiters);
            }
            Err(err) => {
                run.state[t] = State::Failed;
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
pub(super) fn strip_unread(p: &Arc<Vec<Produced>>, readers_left: &[u32]) -> Arc<Vec<Produced>> {
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

/// The active outer item in `slot` (the coordinator only asks for slots it holds).
pub(super) fn run_of(active: &[Option<OuterRun>], slot: u32) -> &OuterRun {
    active[slot as usize].as_ref().expect("an active slot")
}
