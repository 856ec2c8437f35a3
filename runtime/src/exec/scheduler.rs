//! The scheduler: admission of outer items (with their claims), the start of ready tasks on the
//! CPU threads or a resource's slots, back-pressure from the export writes, and what it does with
//! each message; the [`Book`] keeps the tasks.

use super::book::Book;
use super::claims::{Claims, CLAIM_POLL};
use super::execute::spawn_task;
use super::key::{Prepared, Shared};
use super::task::{Ended, Job, Keyed, Msg};
use super::{Engine, RunOptions};
use crate::operator::Operator;
use crate::plan::View;
use crate::runs::{Failure, RunStatus};
use anyhow::{anyhow, bail, Result};
use crossbeam_channel::{Receiver, RecvTimeoutError, Sender};
use std::cmp::Reverse;
use std::collections::VecDeque;
use std::sync::atomic::Ordering;
use std::time::Duration;

/// The thread pools' scopes a scheduler spawns on.
pub(super) struct Scopes<'r, 's> {
    /// CPU work.
    pub cpu: &'r rayon::Scope<'s>,
    /// Tasks that wait on an external resource (a model worker), a thread per slot.
    pub wait: &'r rayon::Scope<'s>,
    /// Export writes.
    pub export: &'r rayon::Scope<'s>,
}

/// What the scheduler owns besides the book: which outer items are still to admit, the threads
/// and resource slots in use, the export writes in flight, and whether the run is stopping.
pub(super) struct Scheduler<'s, 'e, 'a> {
    pub book: Book,
    engine: &'e Engine<'a>,
    opts: &'e RunOptions,
    view: View<'e>,
    shared: &'s Shared<'e, 'a>,
    tx: Sender<Msg>,
    /// Per node, why its operator cannot run in this run (its worker did not start).
    unavailable: Vec<Option<String>>,
    // Admission.
    outers: Vec<u32>,
    next_outer: usize,
    /// Outer items another process holds, with their sequence numbers: admitted once let go.
    held: VecDeque<(u32, u64)>,
    claims: Claims<'e>,
    /// The outer items whose tasks this run executes (all when `None`).
    executed: Option<Vec<u32>>,
    task_budget: usize,
    outer_budget: usize,
    // Threads and slots.
    classes: ResourceClasses,
    on_cpu: usize,
    max_on_cpu: usize,
    on_resources: usize,
    busy: Vec<usize>,
    parked: Vec<VecDeque<Job>>,
    // Back-pressure.
    exporting: usize,
    max_exporting: usize,
    pub stopping: Option<RunStatus>,
}

/// What the scheduler does next when no message is due.
enum Idle {
    /// Everything ended.
    Done,
    /// Only outer items that other processes hold are left: wait a moment, look again.
    Wait,
    /// Nothing runs but something is left to start: look again at once.
    Again,
    /// Something runs: wait for its message.
    Listen,
}

impl<'s, 'e, 'a> Scheduler<'s, 'e, 'a> {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn new(
        book: Book,
        shared: &'s Shared<'e, 'a>,
        opts: &'e RunOptions,
        view: View<'e>,
        outers: Vec<u32>,
        executed: Option<Vec<u32>>,
        unavailable: Vec<Option<String>>,
        tx: Sender<Msg>,
    ) -> Self {
        let engine = shared.engine;
        let jobs = opts.jobs.max(1);
        let classes = ResourceClasses::of(engine.operators);
        Scheduler {
            book,
            engine,
            opts,
            view,
            shared,
            tx,
            unavailable,
            outers,
            next_outer: 0,
            held: VecDeque::new(),
            claims: Claims::new(engine, engine.pipeline),
            executed,
            task_budget: 4096usize.max(opts.jobs * 256),
            // Outer items in flight at once: enough to keep every thread busy (the next item is
            // planned while the last tasks of one run), and no more, since each holds a claim that
            // other processes sharing the store would otherwise take.
            outer_budget: jobs + 1,
            on_cpu: 0,
            max_on_cpu: jobs * 2,
            on_resources: 0,
            busy: vec![0; classes.slots.len()],
            parked: classes.slots.iter().map(|_| VecDeque::new()).collect(),
            classes,
            exporting: 0,
            // Files written or waiting to be: past this, no task starts, so that a slow disk holds
            // back the tasks whose outputs would queue in memory (the tasks already running may
            // still add theirs: a soft bound).
            max_exporting: jobs * 4,
            stopping: None,
        }
    }

    /// How many threads the pool for tasks waiting on resources needs.
    pub(super) fn resource_threads(&self) -> usize {
        self.classes.slots.iter().sum::<usize>().clamp(1, 256)
    }

    /// Runs until every admitted task and export has ended (or the run stops).
    pub(super) fn drive(&mut self, scopes: &Scopes<'_, 's>, rx: &Receiver<Msg>) -> Result<()> {
        loop {
            self.check_stop();
            self.admit()?;
            self.admit_let_go()?;
            self.sync_released()?;
            self.start_ready(scopes)?;
            match self.idle() {
                Idle::Done => return Ok(()),
                Idle::Wait => {
                    std::thread::sleep(CLAIM_POLL);
                    continue;
                }
                Idle::Again => continue,
                Idle::Listen => {}
            }
            match rx.recv_timeout(Duration::from_millis(200)) {
                Ok(msg) => self.on_message(msg, scopes)?,
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => bail!("the worker pool stopped unexpectedly"),
            }
            self.stop_on_failure();
        }
    }

    /// Stops on a cancel request, or when this process's lease was lost.
    fn check_stop(&mut self) {
        if self.stopping.is_none() && self.opts.cancel.load(Ordering::Relaxed) {
            self.stopping = Some(RunStatus::Interrupted);
        }
        if self.stopping.is_none() && self.engine.store.lease_lost() {
            // Others judged this process dead and may be redoing its items: it stops rather than
            // race them. What it finished is in the store.
            self.book.failures.push(Failure {
                stage: "-".into(),
                item: "-".into(),
                error:
                    "this process's lease in the store was lost (it was stopped or its filesystem stalled for \
                        longer than the lease timeout, and other processes judged it dead): it stopped; rerun to finish"
                        .into(),
            });
            self.stopping = Some(RunStatus::Stopped);
        }
    }

    fn stop_on_failure(&mut self) {
        if self.opts.fail_fast && !self.book.failures.is_empty() {
            self.stopping.get_or_insert(RunStatus::Stopped);
        }
    }

    fn has_room(&self) -> bool {
        self.book.has_room(self.task_budget, self.outer_budget)
    }

    fn may_execute(&self, outer: u32) -> bool {
        self.executed.as_ref().is_none_or(|v| v.binary_search(&outer).is_ok())
    }

    /// Admits outer items while there is room; one that another process is running waits, and
    /// is admitted (its tasks then cached) when it lets go.
    fn admit(&mut self) -> Result<()> {
        while self.stopping.is_none() && self.next_outer < self.outers.len() && self.has_room() {
            let (o, seq) = (self.outers[self.next_outer], self.next_outer as u64);
            self.next_outer += 1;
            match self.claims.take(o)? {
                Ok(claim) => self.admit_claimed(o, seq, claim)?,
                Err(holder) => {
                    self.claims.waiting_for(o, &holder);
                    self.held.push_back((o, seq));
                }
            }
        }
        Ok(())
    }

    /// Admits the held outer items whose holders let go (looked at every [`CLAIM_POLL`]).
    fn admit_let_go(&mut self) -> Result<()> {
        if self.stopping.is_some() || self.held.is_empty() || !self.has_room() || !self.claims.poll_due() {
            return Ok(());
        }
        // All the claims of a process that just died free up at once.
        for _ in 0..self.held.len() {
            if !self.has_room() {
                break;
            }
            let (o, seq) = self.held.pop_front().expect("counted");
            match self.claims.take(o)? {
                Ok(claim) => self.admit_claimed(o, seq, claim)?,
                Err(_) => self.held.push_back((o, seq)),
            }
        }
        Ok(())
    }

    fn admit_claimed(&mut self, o: u32, seq: u64, claim: crate::lease::Claim) -> Result<()> {
        // Another process may have run the item and let it go since this one opened the store:
        // its records are read first (a refresh with nothing new costs a listing and a stat per
        // segment).
        self.engine.store.refresh()?;
        let may_execute = self.may_execute(o);
        self.book.admit(self.engine.pipeline, &self.view, o, seq, Some(claim), may_execute);
        Ok(())
    }

    /// Released claims: the records of their items go to the server first, so that a process on
    /// another node that takes the item over finds them.
    fn sync_released(&mut self) -> Result<()> {
        if !self.book.released.is_empty() {
            self.engine.store.sync_records()?;
            self.book.released.clear();
        }
        Ok(())
    }

    /// Starts ready tasks while threads and the export queue have room: those the cache decides
    /// end here, the rest go to the CPU threads or a resource's slots.
    fn start_ready(&mut self, scopes: &Scopes<'_, 's>) -> Result<()> {
        while self.stopping.is_none() && self.on_cpu < self.max_on_cpu && self.exporting < self.max_exporting {
            let Some(Reverse((_, _, _, slot, task))) = self.book.ready.pop() else { break };
            let run = self.book.active[slot as usize].as_ref().expect("an active slot");
            let node = run.plan.tasks[task as usize].node as usize;
            if let Some(why) = &self.unavailable[node] {
                let err = anyhow!("{why}");
                self.book.finish(self.engine, slot, task, Err(err))?;
                continue;
            }
            match self.shared.prepare(run, slot, task) {
                Err(e) => self.book.finish(self.engine, slot, task, Err(e))?,
                Ok(Prepared::Decided(keyed)) => self.book.finish(self.engine, slot, task, Ok(decided(keyed)))?,
                Ok(Prepared::Job(job)) => self.start(job, scopes),
            }
            self.stop_on_failure();
            self.exporting += self.book.spawn_exports(scopes.export, &self.tx);
        }
        Ok(())
    }

    /// Hands a job to a CPU thread, or to its resource's slot (parked while they are all busy).
    fn start(&mut self, job: Job, scopes: &Scopes<'_, 's>) {
        let run = self.book.active[job.slot as usize].as_mut().expect("an active slot");
        run.state[job.task as usize] = super::task::State::Running;
        match self.classes.of_node[job.node] {
            None => {
                self.on_cpu += 1;
                spawn_task(scopes.cpu, self.shared, &self.tx, job, None);
            }
            Some(k) if self.busy[k] < self.classes.slots[k] => {
                self.busy[k] += 1;
                self.on_resources += 1;
                spawn_task(scopes.wait, self.shared, &self.tx, job, Some(k));
            }
            Some(k) => self.parked[k].push_back(job),
        }
    }

    fn idle(&self) -> Idle {
        let stopping = self.stopping.is_some();
        let outers_left = !stopping && (self.next_outer < self.outers.len() || !self.held.is_empty());
        let ready_left = !stopping && !self.book.ready.is_empty();
        let running = self.on_cpu > 0 || self.on_resources > 0 || self.exporting > 0;
        match (running, outers_left || ready_left) {
            (true, _) => Idle::Listen,
            (false, false) => Idle::Done,
            // Only items other processes hold are left.
            (false, true) if !ready_left && self.next_outer == self.outers.len() => Idle::Wait,
            (false, true) => Idle::Again,
        }
    }

    fn on_message(&mut self, msg: Msg, scopes: &Scopes<'_, 's>) -> Result<()> {
        match msg {
            Msg::Task { slot, task, waited, result } => {
                match waited {
                    None => self.on_cpu -= 1,
                    Some(k) => {
                        self.on_resources -= 1;
                        self.busy[k] -= 1;
                        if let Some(job) = self.parked[k].pop_front().filter(|_| self.stopping.is_none()) {
                            self.busy[k] += 1;
                            self.on_resources += 1;
                            spawn_task(scopes.wait, self.shared, &self.tx, job, Some(k));
                        }
                    }
                }
                self.book.finish(self.engine, slot, task, result)?;
                self.exporting += self.book.spawn_exports(scopes.export, &self.tx);
            }
            Msg::Exported { slot, task, rel, result, awaiting } => {
                self.exporting -= 1;
                self.book.exported(self.engine, slot, task, &rel, result, awaiting);
            }
        }
        Ok(())
    }
}

/// How a task the cache decided on the coordinator ended.
fn decided(keyed: Keyed) -> Ended {
    match keyed {
        Keyed::Cached(key, outputs) => Ended::Cached(key, outputs),
        Keyed::NotExecuted { deferred } => Ended::NotExecuted { deferred },
        Keyed::Run(_) | Keyed::Unknown => unreachable!("a task to run is a job"),
    }
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
