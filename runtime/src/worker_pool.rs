//! A pool of one kind of worker ([`crate::worker`]): at most `max_workers` processes, started when
//! a call needs one and kept for the next; a worker that dies or misses a deadline is replaced,
//! with a growing pause between starts; a call is tried again (on a fresh worker) after a crash,
//! a deadline or a `retryable` reply, a bounded number of times. The pool knows nothing of what
//! the workers compute.

use crate::worker::{CallError, Hello, Reply, Request, Status, Worker, WorkerCommand};
use anyhow::{anyhow, bail, Result};
use std::sync::{Condvar, Mutex};
use std::time::Duration;

/// How a pool treats its workers.
#[derive(Clone, Debug)]
pub struct PoolOptions {
    /// Worker processes at most (a GPU holds one or two models).
    pub max_workers: usize,
    /// Time to the worker's hello.
    pub startup: Duration,
    /// Time to a request's reply.
    pub deadline: Duration,
    /// Tries of one call in all (the first included).
    pub tries: u32,
    /// Pause before the first restart after a failure, doubled for each one after.
    pub backoff: Duration,
}

impl Default for PoolOptions {
    fn default() -> Self {
        PoolOptions {
            max_workers: 1,
            startup: Duration::from_secs(120),
            deadline: Duration::from_secs(600),
            tries: 3,
            backoff: Duration::from_millis(100),
        }
    }
}

struct State {
    idle: Vec<Worker>,
    /// Workers started and not yet returned or dropped.
    live: usize,
    /// Failures in a row (reset by a success): the restart pause grows with them.
    failures: u32,
    /// The last hello (a new worker must say the same: its identity is in the task keys).
    hello: Option<Hello>,
}

pub struct WorkerPool {
    command: WorkerCommand,
    options: PoolOptions,
    state: Mutex<State>,
    freed: Condvar,
}

impl WorkerPool {
    pub fn new(command: WorkerCommand, options: PoolOptions) -> WorkerPool {
        WorkerPool {
            command,
            options,
            state: Mutex::new(State { idle: Vec::new(), live: 0, failures: 0, hello: None }),
            freed: Condvar::new(),
        }
    }

    /// The workers' hello (starting one if none ran yet): name, version and weights digest are
    /// what a task key holds of a worker.
    pub fn hello(&self) -> Result<Hello> {
        if let Some(h) = self.lock()?.hello.clone() {
            return Ok(h);
        }
        let w = self.take()?;
        let h = w.hello.clone();
        self.give_back(w);
        Ok(h)
    }

    fn lock(&self) -> Result<std::sync::MutexGuard<'_, State>> {
        self.state.lock().map_err(|_| anyhow!("worker pool poisoned"))
    }

    /// An idle worker, a new one when fewer than `max_workers` live, or the next one freed.
    fn take(&self) -> Result<Worker> {
        let mut s = self.lock()?;
        loop {
            if let Some(w) = s.idle.pop() {
                return Ok(w);
            }
            if s.live < self.options.max_workers {
                s.live += 1;
                let pause = (s.failures > 0).then(|| self.options.backoff * 2u32.saturating_pow(s.failures - 1));
                drop(s);
                if let Some(p) = pause {
                    std::thread::sleep(p.min(Duration::from_secs(30)));
                }
                return match Worker::start(&self.command, self.options.startup) {
                    Ok(w) => {
                        let mut s = self.lock()?;
                        let id = |h: &Hello| (h.name.clone(), h.version.clone(), h.weights_digest.clone());
                        if let Some(h) = s.hello.clone().filter(|h| id(h) != id(&w.hello)) {
                            s.live -= 1;
                            drop(s);
                            self.freed.notify_one();
                            bail!(
                                "worker `{}` restarted as {} {} (weights {}), not {} {} (weights {}): its results would not match their task keys",
                                self.command.program,
                                w.hello.name,
                                w.hello.version,
                                w.hello.weights_digest,
                                h.name,
                                h.version,
                                h.weights_digest
                            );
                        }
                        s.hello = Some(w.hello.clone());
                        Ok(w)
                    }
                    Err(e) => {
                        let mut s = self.lock()?;
                        s.live -= 1;
                        s.failures += 1;
                        self.freed.notify_one();
                        Err(e)
                    }
                };
            }
            s = self.freed.wait(s).map_err(|_| anyhow!("worker pool poisoned"))?;
        }
    }

    fn give_back(&self, w: Worker) {
        if let Ok(mut s) = self.state.lock() {
            s.idle.push(w);
        }
        self.freed.notify_one();
    }

    /// A worker that failed: it is gone, and the next start waits a little longer.
    fn lose(&self, w: Worker) {
        drop(w);
        if let Ok(mut s) = self.state.lock() {
            s.live -= 1;
            s.failures += 1;
        }
        self.freed.notify_one();
    }

    /// Runs `request` on a worker: a reply `ok` is returned; `error` is this item's failure; a
    /// crash, a missed deadline or `retryable` are tried again on a fresh worker, `tries` times in
    /// all. Errors carry the worker's stderr tail.
    pub fn call(&self, request: &Request) -> Result<Reply> {
        let mut last = String::new();
        for attempt in 1..=self.options.tries.max(1) {
            let mut w = self.take()?;
            match w.call(request, self.options.deadline) {
                Ok(reply) if reply.status == Status::Ok => {
                    if let Ok(mut s) = self.state.lock() {
                        s.failures = 0;
                    }
                    self.give_back(w);
                    return Ok(reply);
                }
                Ok(reply) if reply.status == Status::Error => {
                    let tail = w.stderr_tail();
                    self.give_back(w);
                    bail!("worker `{}` could not do it: {}{tail}", self.command.program, reply.message);
                }
                Ok(reply) => {
                    last = format!("try {attempt}: retryable: {}", reply.message);
                    self.give_back(w);
                }
                Err(e @ CallError::Malformed(_)) => {
                    let tail = w.stderr_tail();
                    self.lose(w);
                    bail!("worker `{}`: {e}{tail}", self.command.program);
                }
                Err(e) => {
                    last = format!("try {attempt}: {e}{}", w.stderr_tail());
                    self.lose(w);
                }
            }
        }
        bail!("worker `{}` failed {} times: {last}", self.command.program, self.options.tries.max(1))
    }

    /// Shuts every idle worker down.
    pub fn shutdown(&self) {
        let idle = self.state.lock().map(|mut s| std::mem::take(&mut s.idle)).unwrap_or_default();
        for w in idle {
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
        assert!(err.contains("broke the protocol"), "{err}");
        assert_eq!(pool.call(&request("c")).unwrap().outputs[0].path, "c");
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
}
