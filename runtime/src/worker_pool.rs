//! A pool of one kind of worker ([`crate::worker`]): at most `max_workers` processes, started when
//! a call needs one and kept for the next; a worker that dies or misses a deadline is replaced,
//! with a growing pause between starts; a call is tried again (on a fresh worker) after a crash,
//! a deadline or a `retryable` reply, a bounded number of times. The pool knows nothing of what
//! the workers compute.
//!
//! Batching: calls made at the same time (from the threads of a stage's resource class) wait in
//! one queue; whichever caller gets a worker takes its own request and the oldest others, up to
//! the worker's `max_batch`, sends them as one batch and hands each caller its reply. A batch
//! that crashed its worker is tried again one request at a time, so that one bad item does not
//! use up the tries of the items batched with it.

use crate::worker::{CallError, Hello, Reply, Request, Status, Worker, WorkerCommand};
use anyhow::{anyhow, bail, Result};
use std::collections::{HashMap, VecDeque};
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// How a pool treats its workers.
#[derive(Clone, Debug)]
pub struct PoolOptions {
    /// Worker processes at most (a GPU holds one or two models).
    pub max_workers: usize,
    /// Time to the worker's hello.
    pub startup: Duration,
    /// Time to a request's reply (to a batch's last reply).
    pub deadline: Duration,
    /// Tries of one call in all (the first included).
    pub tries: u32,
    /// Pause before the first restart after a failure, doubled for each one after.
    pub backoff: Duration,
    /// A worker idle this long is pinged before it is given work, and replaced if it does not
    /// answer (a process wedged between items).
    pub ping_after: Duration,
    /// Whether the process was asked to stop: calls then end at once (as at their deadline),
    /// and nothing is tried again or restarted.
    pub stop: Option<fn() -> bool>,
}

impl Default for PoolOptions {
    fn default() -> Self {
        PoolOptions {
            max_workers: 1,
            startup: Duration::from_secs(120),
            deadline: Duration::from_secs(600),
            tries: 3,
            backoff: Duration::from_millis(100),
            ping_after: Duration::from_secs(30),
            stop: None,
        }
    }
}

/// Items in a row whose every try crashed or missed its deadline, after which a pool gives up on
/// its worker for the rest of the run.
pub const GIVE_UP_AFTER_ITEMS: u32 = 3;

/// "once", "2 times".
fn times(n: u32) -> String {
    if n == 1 {
        "once".into()
    } else {
        format!("{n} times")
    }
}

/// One call waiting for, or in, a batch.
struct Ticket {
    request: Request,
    /// Tries made.
    tries: u32,
    /// Why the last try failed.
    last: String,
    /// Never batched with others again (it was in a batch that crashed its worker).
    alone: bool,
    /// Set when the call has its answer.
    result: Option<Result<Reply>>,
}

struct State {
    /// Idle workers, with when they became idle.
    idle: Vec<(Worker, Instant)>,
    /// Workers started and not yet returned or dropped.
    live: usize,
    /// Failures in a row (reset by a success): the restart pause grows with them.
    failures: u32,
    /// The last hello (a new worker must say the same: its identity is in the task keys).
    hello: Option<Hello>,
    /// Calls waiting for a worker, oldest first.
    queue: VecDeque<u64>,
    tickets: HashMap<u64, Ticket>,
    next_ticket: u64,
    /// Set when a worker broke the protocol: the model's code writes to stdout, and every worker
    /// started will, so the calls after it fail at once with why instead of restarting it.
    broken: Option<String>,
    /// Items in a row, since the last reply `ok`, whose every try crashed or timed out; at
    /// [`GIVE_UP_AFTER_ITEMS`] the pool stops starting the worker ([`State::given_up`]).
    failed_in_row: u32,
    /// Why the pool gave up on the worker: a worker that dies on every request would otherwise
    /// cost each remaining item its tries, and the restart pause (up to 30 s) each try.
    given_up: Option<String>,
    /// Requests sent in batches of more than one, and workers started (for tests and
    /// benchmarks).
    batched: u64,
    starts: u64,
}

pub struct WorkerPool {
    command: WorkerCommand,
    options: PoolOptions,
    state: Mutex<State>,
    changed: Condvar,
}

impl WorkerPool {
    pub fn new(command: WorkerCommand, options: PoolOptions) -> WorkerPool {
        WorkerPool {
            command,
            options,
            state: Mutex::new(State {
                idle: Vec::new(),
                live: 0,
                failures: 0,
                hello: None,
                queue: VecDeque::new(),
                tickets: HashMap::new(),
                next_ticket: 0,
                broken: None,
                failed_in_row: 0,
                given_up: None,
                batched: 0,
                starts: 0,
            }),
            changed: Condvar::new(),
        }
    }

    /// The workers' hello (starting one if none ran yet): name, version and weights digest are
    /// what a task key holds of a worker.
    pub fn hello(&self) -> Result<Hello> {
        let mut s = self.lock()?;
        if let Some(h) = s.hello.clone() {
            return Ok(h);
        }
        while s.idle.is_empty() && s.live >= self.options.max_workers {
            s = self.wait(s)?;
            if let Some(h) = s.hello.clone() {
                return Ok(h);
            }
        }
        let (w, s) = self.take(s)?;
        let h = w.hello.clone();
        self.give_back(s, w);
        Ok(h)
    }

    /// The hello of a worker that started, without starting one.
    pub fn known_hello(&self) -> Option<Hello> {
        self.state.lock().ok()?.hello.clone()
    }

    fn lock(&self) -> Result<MutexGuard<'_, State>> {
        self.state.lock().map_err(|_| anyhow!("worker pool poisoned"))
    }

    fn wait<'g>(&self, s: MutexGuard<'g, State>) -> Result<MutexGuard<'g, State>> {
        self.changed.wait(s).map_err(|_| anyhow!("worker pool poisoned"))
    }

    /// An idle worker (pinged first if it has been idle long), or a new one; the caller checked
    /// that one of these is possible. The lock is given up while a worker starts or is pinged.
    fn take<'g>(&'g self, mut s: MutexGuard<'g, State>) -> Result<(Worker, MutexGuard<'g, State>)> {
        while let Some((mut w, since)) = s.idle.pop() {
            if since.elapsed() < self.options.ping_after {
                return Ok((w, s));
            }
            drop(s);
            let alive = w.ping(self.options.deadline.min(Duration::from_secs(5)));
            s = self.lock()?;
            if alive {
                return Ok((w, s));
            }
            drop(w);
            s.live -= 1;
        }
        s.live += 1;
        s.starts += 1;
        let pause = (s.failures > 0).then(|| self.options.backoff * 2u32.saturating_pow(s.failures - 1));
        drop(s);
        if let Some(p) = pause.filter(|_| !self.stopping()) {
            std::thread::sleep(p.min(Duration::from_secs(30)));
        }
        let started = if self.stopping() {
            Err(anyhow!("stopped: the process was asked to stop, so worker `{}` is not started", self.command))
        } else {
            Worker::start(&self.command, self.options.startup).map(|mut w| {
                w.stop_when(self.options.stop);
                w
            })
        };
        let mut s = self.lock()?;
        let w = match started {
            Ok(w) => w,
            Err(e) => {
                s.live -= 1;
                s.failures += 1;
                self.changed.notify_all();
                return Err(e);
            }
        };
        let id = |h: &Hello| (h.name.clone(), h.version.clone(), h.weights_digest.clone());
        if let Some(h) = s.hello.clone().filter(|h| id(h) != id(&w.hello)) {
            s.live -= 1;
            self.changed.notify_all();
            bail!(
                "worker `{}` restarted as {} {} (weights {}), not {} {} (weights {}): its results would not match their task keys",
                self.command,
                w.hello.name,
                w.hello.version,
                w.hello.weights_digest,
                h.name,
                h.version,
                h.weights_digest
            );
        }
        s.hello = Some(w.hello.clone());
        Ok((w, s))
    }

    fn give_back(&self, mut s: MutexGuard<'_, State>, w: Worker) {
        s.idle.push((w, Instant::now()));
        drop(s);
        self.changed.notify_all();
    }

    /// Runs `request` on a worker, batched with other calls waiting at the same time: a reply
    /// `ok` is returned; `error` is this item's failure; a crash, a missed deadline or
    /// `retryable` are tried again on a fresh worker, `tries` times in all. Errors carry the
    /// worker's stderr tail.
    pub fn call(&self, request: &Request) -> Result<Reply> {
        let mut s = self.lock()?;
        if let Some(why) = &s.broken {
            bail!(
                "worker `{}` broke the protocol earlier in this run, so it is not started again: {why}",
                self.command
            );
        }
        if let Some(why) = &s.given_up {
            return Err(self.gave_up(why));
        }
        let id = s.next_ticket;
        s.next_ticket += 1;
        s.tickets
            .insert(id, Ticket { request: request.clone(), tries: 0, last: String::new(), alone: false, result: None });
        s.queue.push_back(id);
        loop {
            if s.tickets[&id].result.is_some() {
                let t = s.tickets.remove(&id).expect("this call's ticket");
                return t.result.expect("checked above");
            }
            let queued = s.queue.contains(&id);
            // Calls that waited while the pool gave up on the worker do not start it again.
            if let Some(why) = s.given_up.clone().filter(|_| queued) {
                s.queue.retain(|t| *t != id);
                s.tickets.remove(&id);
                return Err(self.gave_up(&why));
            }
            if queued && (!s.idle.is_empty() || s.live < self.options.max_workers) {
                s = self.lead(s, id)?;
            } else {
                s = self.wait(s)?;
            }
        }
    }

    /// Takes a worker and a batch (`own` first, then the oldest waiting calls up to the worker's
    /// `max_batch`), runs it and settles every call in it.
    fn lead<'g>(&'g self, mut s: MutexGuard<'g, State>, own: u64) -> Result<MutexGuard<'g, State>> {
        s.queue.retain(|t| *t != own);
        let mut batch = vec![own];
        let max = s.hello.as_ref().map_or(1, |h| h.max_batch.max(1)) as usize;
        if !s.tickets[&own].alone {
            let mut i = 0;
            while batch.len() < max && i < s.queue.len() {
                let t = s.queue[i];
                if s.tickets[&t].alone {
                    i += 1;
                } else {
                    s.queue.remove(i);
                    batch.push(t);
                }
            }
        }
        let (mut w, s2) = match self.take(s) {
            Ok(x) => x,
            Err(e) => {
                // No worker: every call of the batch fails with why.
                let mut s = self.lock()?;
                let why = format!("{e:#}");
                for t in &batch {
                    s.tickets.get_mut(t).expect("a batched ticket").result = Some(Err(anyhow!("{why}")));
                }
                self.changed.notify_all();
                return Ok(s);
            }
        };
        s = s2;
        let requests: Vec<Request> = batch.iter().map(|t| s.tickets[t].request.clone()).collect();
        if batch.len() > 1 {
            s.batched += batch.len() as u64;
        }
        drop(s);
        let refs: Vec<&Request> = requests.iter().collect();
        let answer = w.call_batch(&refs, self.options.deadline);
        let mut s = self.lock()?;
        let program = &self.command;
        let tries = self.options.tries.max(1);
        match answer {
            Ok(replies) => {
                let mut ok = false;
                for (t, reply) in batch.iter().zip(replies) {
                    let ticket = s.tickets.get_mut(t).expect("a batched ticket");
                    ticket.tries += 1;
                    match reply.status {
                        Status::Ok => {
                            ok = true;
                            ticket.result = Some(Ok(reply));
                        }
                        Status::Error => {
                            let tail = w.stderr_tail();
                            ticket.result =
                                Some(Err(anyhow!("worker `{program}` could not do it: {}{tail}", reply.message)));
                        }
                        Status::Retryable => {
                            ticket.last = format!("try {}: retryable: {}", ticket.tries, reply.message);
                            if ticket.tries >= tries || self.stopping() {
                                ticket.result =
                                    Some(Err(anyhow!("worker `{program}` failed {}: {}", times(tries), ticket.last)));
                            } else {
                                s.queue.push_front(*t);
                            }
                        }
                    }
                }
                if ok {
                    s.failures = 0;
                    s.failed_in_row = 0;
                }
                self.give_back(s, w);
                self.lock()
            }
            Err(e) => {
                let tail = w.stderr_tail();
                if matches!(e, CallError::Cancelled(_)) {
                    // Alive and answering: it keeps its model for the next request.
                    s.idle.push((w, Instant::now()));
                } else {
                    drop(w);
                    s.live -= 1;
                }
                s.failures += 1;
                let malformed = matches!(e, CallError::Malformed(_));
                if malformed {
                    s.broken = Some(format!("{e}{tail}"));
                }
                for t in batch.iter().rev() {
                    let ticket = s.tickets.get_mut(t).expect("a batched ticket");
                    ticket.tries += 1;
                    ticket.alone |= batch.len() > 1;
                    ticket.last = format!("try {}: {e}{tail}", ticket.tries);
                    if malformed {
                        ticket.result = Some(Err(anyhow!("worker `{program}`: {e}{tail}")));
                    } else if ticket.tries >= tries || self.stopping() {
                        ticket.result =
                            Some(Err(anyhow!("worker `{program}` failed {}: {}", times(tries), ticket.last)));
                        s.failed_in_row += 1;
                        if s.failed_in_row >= GIVE_UP_AFTER_ITEMS && s.given_up.is_none() {
                            s.given_up = Some(format!("the last: {}", s.tickets[t].last));
                        }
                    } else {
                        s.queue.push_front(*t);
                    }
                }
                self.changed.notify_all();
                Ok(s)
            }
        }
    }

    /// The error of a call made after the pool gave up on its worker ([`State::given_up`]).
    fn gave_up(&self, why: &str) -> anyhow::Error {
        anyhow!(
            "worker `{}` failed every try of {GIVE_UP_AFTER_ITEMS} items in a row earlier in this run, so it is not \
             started again (fix it and rerun: these items are not cached): {why}",
            self.command
        )
    }

    /// Whether the process was asked to stop ([`PoolOptions::stop`]).
    fn stopping(&self) -> bool {
        self.options.stop.is_some_and(|stop| stop())
    }

    /// Shuts every idle worker down.
    pub fn shutdown(&self) {
        let idle = self.state.lock().map(|mut s| std::mem::take(&mut s.idle)).unwrap_or_default();
        for (w, _) in idle {
            w.shutdown(Duration::from_secs(5));
        }
    }
}

impl Drop for WorkerPool {
    fn drop(&mut self) {
        self.shutdown();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::worker::FileRef;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;
    use std::time::Instant;

    fn command(args: &[&str]) -> WorkerCommand {
        let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../workers/protocol_test_worker.py");
        let mut all = vec![script.display().to_string()];
        all.extend(args.iter().map(|s| s.to_string()));
        WorkerCommand { program: "python3".into(), args: all }
    }

    fn request(what: &str) -> Request {
        Request {
            item: String::new(),
            op: "echo".into(),
            inputs: vec![FileRef { name: "x".into(), path: what.into(), digest: None }],
            params: serde_json::json!({}),
            out_dir: "/tmp".into(),
        }
    }

    fn quick() -> PoolOptions {
        PoolOptions {
            deadline: Duration::from_millis(500),
            backoff: Duration::from_millis(10),
            ..PoolOptions::default()
        }
    }

    #[test]
    fn a_worker_that_dies_on_every_request_is_given_up_after_three_items() {
        // Each try fails at once, but the restart pause doubles up to 30 s: 96 items of such a
        // worker took over an hour. After three items whose every try failed, the rest fail at once.
        let pool = WorkerPool::new(command(&["--every", "close-stdout"]), PoolOptions { tries: 2, ..quick() });
        for i in 0..GIVE_UP_AFTER_ITEMS {
            let err = format!("{:#}", pool.call(&request(&format!("item{i}"))).unwrap_err());
            assert!(err.contains("failed 2 times") && err.contains("closed its stdout"), "{err}");
        }
        let starts = pool.state.lock().unwrap().starts;
        let t = Instant::now();
        let err = format!("{:#}", pool.call(&request("next")).unwrap_err());
        assert!(t.elapsed() < Duration::from_millis(100), "at once");
        assert!(err.contains("failed every try of 3 items in a row") && err.contains("closed its stdout"), "{err}");
        assert_eq!(pool.state.lock().unwrap().starts, starts, "not started again");
    }

    #[test]
    fn a_crash_or_a_hang_fails_that_item_after_its_tries_and_the_next_item_gets_a_fresh_worker() {
        let pool = WorkerPool::new(command(&[]), quick());
        assert_eq!(pool.call(&request("a")).unwrap().outputs[0].path, "a");
        let err = format!("{:#}", pool.call(&request("crash")).unwrap_err());
        assert!(err.contains("failed 3 times") && err.contains("asked to crash"), "{err}");
        let t = Instant::now();
        let err = format!("{:#}", pool.call(&request("hang")).unwrap_err());
        assert!(err.contains("no reply within"), "{err}");
        assert!(t.elapsed() < Duration::from_secs(5), "three deadlines of 0.5 s and short pauses");
        // The pool goes on with a new worker.
        assert_eq!(pool.call(&request("b")).unwrap().outputs[0].path, "b");
        let err = format!("{:#}", pool.call(&request("bad item")).unwrap_err());
        assert!(err.contains("could not do it: cannot do `bad item`"), "{err}");
        let err = format!("{:#}", pool.call(&request("garbage")).unwrap_err());
        assert!(err.contains("broke the protocol") && err.contains("logs go to stderr"), "{err}");
        // A worker that writes junk to stdout will again: the pool stops starting it.
        let t = Instant::now();
        let err = format!("{:#}", pool.call(&request("c")).unwrap_err());
        assert!(err.contains("broke the protocol earlier in this run"), "{err}");
        assert!(t.elapsed() < Duration::from_millis(100), "at once, no restart");
    }

    #[test]
    fn at_most_max_workers_run_and_they_are_kept_between_calls() {
        let pool = Arc::new(WorkerPool::new(command(&[]), PoolOptions { max_workers: 2, ..quick() }));
        let done = Arc::new(AtomicUsize::new(0));
        let threads: Vec<_> = (0..4)
            .map(|i| {
                let (pool, done) = (pool.clone(), done.clone());
                std::thread::spawn(move || {
                    for j in 0..5 {
                        let what = format!("{i}-{j}");
                        assert_eq!(pool.call(&request(&what)).unwrap().outputs[0].path, what);
                        done.fetch_add(1, Ordering::Relaxed);
                    }
                })
            })
            .collect();
        for t in threads {
            t.join().unwrap();
        }
        assert_eq!(done.load(Ordering::Relaxed), 20);
        let s = pool.state.lock().unwrap();
        assert!(s.live <= 2 && s.idle.len() == s.live, "live {}, idle {}", s.live, s.idle.len());
        assert_eq!(s.hello.as_ref().map(|h| h.name.as_str()), Some("protocol-test"));
    }

    #[test]
    fn a_worker_that_cannot_start_fails_the_call_with_why() {
        let pool = WorkerPool::new(command(&["--die-at-start"]), quick());
        let err = format!("{:#}", pool.call(&request("a")).unwrap_err());
        assert!(err.contains("did not start") && err.contains("no model here"), "{err}");
        assert!(pool.hello().is_err());
    }

    /// Runs `what`s from one thread each, at the same time; their results in order.
    fn call_together(pool: &Arc<WorkerPool>, whats: &[&str]) -> Vec<Result<String>> {
        let threads: Vec<_> = whats
            .iter()
            .map(|w| {
                let (pool, w) = (pool.clone(), w.to_string());
                std::thread::spawn(move || pool.call(&request(&w)).map(|r| r.outputs[0].path.clone()))
            })
            .collect();
        threads.into_iter().map(|t| t.join().unwrap()).collect()
    }

    #[test]
    fn calls_made_together_go_in_batches_up_to_the_workers_max_and_each_gets_its_own_reply() {
        let pool = Arc::new(WorkerPool::new(command(&["--max-batch", "3"]), quick()));
        pool.hello().unwrap();
        // The first call holds the one worker for a while, so the others queue up behind it.
        let whats = ["sleep:0.3", "a", "b", "c", "d", "e", "f"];
        let results = call_together(&pool, &whats);
        for (w, r) in whats.iter().zip(&results) {
            assert_eq!(r.as_ref().unwrap(), w);
        }
        let batched = pool.state.lock().unwrap().batched;
        assert!(batched >= 3, "the six waiting calls went in batches: {batched} batched");
        // The worker asserts that no batch is larger than 3: it would have crashed.
        assert_eq!(pool.state.lock().unwrap().failures, 0);
    }

    #[test]
    fn a_batch_that_crashes_its_worker_is_retried_one_by_one_so_only_the_bad_item_fails() {
        let pool = Arc::new(WorkerPool::new(command(&["--max-batch", "4"]), quick()));
        pool.hello().unwrap();
        let whats = ["sleep:0.3", "a", "crash", "b", "c"];
        let results = call_together(&pool, &whats);
        for (w, r) in whats.iter().zip(&results) {
            match *w {
                "crash" => {
                    let err = format!("{:#}", r.as_ref().unwrap_err());
                    assert!(err.contains("failed 3 times") && err.contains("asked to crash"), "{err}");
                }
                _ => assert_eq!(r.as_ref().unwrap(), w),
            }
        }
        assert!(pool.state.lock().unwrap().batched > 0, "the crash was in a batch");
    }

    #[test]
    fn a_worker_idle_past_ping_after_is_pinged_kept_when_it_answers_and_replaced_when_not() {
        for (args, starts) in [(&[][..], 1), (&["--no-pong"][..], 2)] {
            let pool = WorkerPool::new(command(args), PoolOptions { ping_after: Duration::ZERO, ..quick() });
            assert_eq!(pool.call(&request("a")).unwrap().outputs[0].path, "a");
            assert_eq!(pool.call(&request("b")).unwrap().outputs[0].path, "b");
            let s = pool.state.lock().unwrap();
            assert_eq!((s.live, s.starts), (1, starts), "{args:?}");
        }
    }

    #[test]
    fn a_request_cancelled_at_its_deadline_is_retried_on_the_same_worker_which_keeps_its_model() {
        let pool = WorkerPool::new(command(&[]), PoolOptions { tries: 2, ..quick() });
        let err = format!("{:#}", pool.call(&request("slow:30")).unwrap_err());
        assert!(err.contains("failed 2 times") && err.contains("cancelled"), "{err}");
        assert_eq!(pool.call(&request("a")).unwrap().outputs[0].path, "a");
        let s = pool.state.lock().unwrap();
        assert_eq!((s.live, s.starts), (1, 1), "one worker, never restarted");
    }
}
