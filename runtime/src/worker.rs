//! External workers: long-lived subprocesses (a GPU model in Python, or anything else) that
//! serve requests over newline-delimited JSON on stdin/stdout, logging on stderr. The protocol
//! mirrors Bazel's persistent workers (a request names its inputs by path and digest, the reply
//! names its outputs) and LSP's lifecycle (a handshake first, `shutdown` last):
//!
//! - worker -> engine, first line: `{"type": "hello", "protocol": 1, "name": "..", "version": "..",
//!   "weights_digest": "..", "ops": ["complete_depth"], "max_batch": 4}`; its name, version and
//!   weights digest are what task keys hold, so a new model version reruns exactly its stage.
//! - engine -> worker: `{"type": "request", "id": 7, "op": "..", "item": "s0/003/cam2", "inputs": [{"name": "image",
//!   "path": "..", "digest": ".."}], "params": {..}, "out_dir": ".."}`; the worker writes its
//!   outputs into `out_dir` and replies `{"type": "reply", "id": 7, "status": "ok", "outputs":
//!   [{"name": "depth", "path": ".."}]}`, or `"status": "error"` / `"retryable"` with a `message`.
//! - `{"type": "ping", "id": 8}` -> `{"type": "pong", "id": 8}`; `{"type": "cancel", "id": 7}`
//!   when request 7 missed its deadline (a worker that replies to it within a grace is kept, one
//!   that does not is killed); `{"type": "shutdown"}`, after which the worker exits.
//!
//! This module is one worker process: starting it (in its own process group, so a deadline kills
//! the model and everything it spawned), the handshake, calls with deadlines, and the tail of its
//! stderr for error chains. Nothing here knows what the worker computes.

use anyhow::{anyhow, bail, Context, Result};
use crossbeam_channel::{Receiver, RecvTimeoutError};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::process::CommandExt;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The protocol version this engine speaks.
pub const PROTOCOL: u32 = 1;

/// How long a dead worker's stderr is read on before its error is reported.
const STDERR_GRACE: Duration = Duration::from_millis(500);

/// Lines of a worker's stderr kept for error messages.
const STDERR_TAIL: usize = 20;

/// After a missed deadline, how long a worker has to answer the `cancel` of its pending requests
/// (at most the deadline itself) before it is killed.
const CANCEL_GRACE: Duration = Duration::from_secs(5);

/// How to start a worker.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct WorkerCommand {
    pub program: String,
    pub args: Vec<String>,
}

impl std::fmt::Display for WorkerCommand {
    /// The program and its first argument (`python3 workers/fill_completer.py`): an interpreter
    /// alone does not say which worker it runs.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.args.first() {
            Some(a) => write!(f, "{} {a}", self.program),
            None => write!(f, "{}", self.program),
        }
    }
}

/// What a worker says of itself when it starts.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hello {
    pub protocol: u32,
    pub name: String,
    pub version: String,
    #[serde(default)]
    pub weights_digest: String,
    pub ops: Vec<String>,
    #[serde(default = "one")]
    pub max_batch: u32,
}

fn one() -> u32 {
    1
}

/// One input or output file of a request.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileRef {
    pub name: String,
    pub path: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub digest: Option<String>,
}

/// A request, as the engine sends it (the `id` is the worker's own).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Request {
    pub op: String,
    /// The item's label (`scene/frame/camera`), for the worker's logs and messages.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub item: String,
    pub inputs: Vec<FileRef>,
    pub params: serde_json::Value,
    pub out_dir: String,
}

/// How a request ended, as the worker says.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    Ok,
    /// This item cannot be done (its inputs are bad for the model): fail the item.
    Error,
    /// Worth another try (out of GPU memory, a transient fault).
    Retryable,
}

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Reply {
    pub status: Status,
    #[serde(default)]
    pub outputs: Vec<FileRef>,
    #[serde(default)]
    pub message: String,
}

/// Why a call did not give a reply.
#[derive(Debug)]
pub enum CallError {
    /// No reply within the deadline, nor to the `cancel` after it: the worker's process group was
    /// killed.
    Timeout(Duration),
    /// No reply within the deadline; the worker answered the `cancel` after it, so it is alive
    /// and keeps its loaded model.
    Cancelled(Duration),
    /// The worker exited (or closed stdout) before replying.
    Died(String),
    /// It wrote something that is not the protocol.
    Malformed(String),
}

impl std::fmt::Display for CallError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CallError::Timeout(d) => write!(f, "no reply within {:.1} s: the worker was killed", d.as_secs_f64()),
            CallError::Cancelled(d) => {
                write!(f, "no reply within {:.1} s: cancelled (the worker stopped the request)", d.as_secs_f64())
            }
            CallError::Died(why) => write!(f, "the worker died: {why}"),
            CallError::Malformed(why) => write!(
                f,
                "the worker broke the protocol: {why} (a worker writes only protocol lines to stdout; its logs go to stderr)"
            ),
        }
    }
}

impl std::error::Error for CallError {}

/// A line from the worker's stdout, or its end.
enum Line {
    Json(serde_json::Value),
    Bad(String),
    Closed,
}

/// A running worker process.
pub struct Worker {
    pub hello: Hello,
    command: WorkerCommand,
    child: Child,
    stdin: ChildStdin,
    lines: Receiver<Line>,
    stderr: Arc<Mutex<VecDeque<String>>>,
    /// Disconnected when the stderr reader has read to the end.
    stderr_read: Receiver<()>,
    next_id: u64,
}

impl Worker {
    /// Starts `command` and waits up to `startup` for its hello.
    pub fn start(command: &WorkerCommand, startup: Duration) -> Result<Worker> {
        let what = || format!("worker `{command}`");
        let mut child = Command::new(&command.program)
            .args(&command.args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            // Its own process group: a deadline kills the model and whatever it started.
            .process_group(0)
            .spawn()
            .with_context(|| format!("starting {}", what()))?;
        let stdin = child.stdin.take().context("the worker has no stdin")?;
        let stdout = child.stdout.take().context("the worker has no stdout")?;
        let stderr_pipe = child.stderr.take().context("the worker has no stderr")?;
        let (tx, lines) = crossbeam_channel::unbounded();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if line.trim().is_empty() {
                    continue;
                }
                let msg = match serde_json::from_str(&line) {
                    Ok(v) => Line::Json(v),
                    Err(_) => Line::Bad(line.chars().take(200).collect()),
                };
                if tx.send(msg).is_err() {
                    return;
                }
            }
            let _ = tx.send(Line::Closed);
        });
        let stderr = Arc::new(Mutex::new(VecDeque::new()));
        let tail = stderr.clone();
        let (read_to_end, stderr_read) = crossbeam_channel::bounded::<()>(0);
        std::thread::spawn(move || {
            // Dropped at the end of the stream: a dead worker's last words are in the tail then.
            let _read_to_end = read_to_end;
            for line in BufReader::new(stderr_pipe).lines() {
                let Ok(line) = line else { break };
                if let Ok(mut t) = tail.lock() {
                    if t.len() == STDERR_TAIL {
                        t.pop_front();
                    }
                    t.push_back(line);
                }
            }
        });
        let mut worker = Worker {
            hello: Hello {
                protocol: 0,
                name: String::new(),
                version: String::new(),
                weights_digest: String::new(),
                ops: vec![],
                max_batch: 1,
            },
            command: command.clone(),
            child,
            stdin,
            lines,
            stderr,
            stderr_read,
            next_id: 1,
        };
        let hello = match worker.next_line(Instant::now() + startup) {
            Ok(v) if v["type"] == "hello" => serde_json::from_value::<Hello>(v.clone())
                .map_err(|e| anyhow!("{}: its hello is malformed ({e}): {v}", what()))?,
            Ok(v) => {
                worker.kill();
                bail!("{}: its first line must be a hello, found {v}{}", what(), worker.stderr_tail())
            }
            Err(e) => {
                worker.kill();
                bail!("{} did not start: {e}{}", what(), worker.stderr_tail())
            }
        };
        if hello.protocol != PROTOCOL {
            worker.kill();
            bail!("{} speaks protocol {}, this engine {PROTOCOL}", what(), hello.protocol);
        }
        worker.hello = hello;
        Ok(worker)
    }

    /// The next JSON line before `deadline`.
    fn next_line(&mut self, deadline: Instant) -> std::result::Result<serde_json::Value, CallError> {
        let wait = deadline.saturating_duration_since(Instant::now());
        match self.lines.recv_timeout(wait) {
            Ok(Line::Json(v)) => Ok(v),
            Ok(Line::Bad(line)) => Err(CallError::Malformed(format!("not JSON: {line}"))),
            Ok(Line::Closed) | Err(RecvTimeoutError::Disconnected) => {
                let status = self.child.wait().map(|s| s.to_string()).unwrap_or_else(|e| e.to_string());
                Err(self.died(status))
            }
            Err(RecvTimeoutError::Timeout) => Err(CallError::Timeout(wait)),
        }
    }

    fn send(&mut self, msg: &serde_json::Value) -> std::result::Result<(), CallError> {
        let mut line = serde_json::to_vec(msg).map_err(|e| CallError::Malformed(e.to_string()))?;
        line.push(b'\n');
        let written = self.stdin.write_all(&line).and_then(|_| self.stdin.flush());
        written.map_err(|e| self.died(format!("writing to it: {e}")))
    }

    /// The error of a worker found dead. What it wrote to stderr before dying (often why) may
    /// still be in the pipe, and error messages are made from the tail: so the reader is first
    /// let finish, for at most `STDERR_GRACE` (a process the worker started may hold the pipe).
    fn died(&self, why: String) -> CallError {
        let _ = self.stderr_read.recv_timeout(STDERR_GRACE);
        CallError::Died(why)
    }

    /// Sends `request` and waits up to `deadline` for its reply. A timeout kills the worker (its
    /// whole process group): a model stuck on one item must not hold the others.
    pub fn call(&mut self, request: &Request, deadline: Duration) -> std::result::Result<Reply, CallError> {
        Ok(self.call_batch(&[request], deadline)?.remove(0))
    }

    /// Sends `requests` as one batch (a GPU model runs them as one tensor batch) and waits up to
    /// `deadline` for all their replies, which come back in the order of `requests`. One request
    /// goes as a plain `request`; more as `{"type": "batch", "requests": [..]}`, each with its
    /// own id, answered by one `reply` line per id in any order. At most the hello's `max_batch`.
    pub fn call_batch(
        &mut self,
        requests: &[&Request],
        deadline: Duration,
    ) -> std::result::Result<Vec<Reply>, CallError> {
        let first = self.next_id;
        self.next_id += requests.len() as u64;
        let mut msgs = Vec::with_capacity(requests.len());
        for (i, r) in requests.iter().enumerate() {
            let mut msg = serde_json::to_value(r).map_err(|e| CallError::Malformed(e.to_string()))?;
            msg["type"] = "request".into();
            msg["id"] = (first + i as u64).into();
            msgs.push(msg);
        }
        match msgs.len() {
            0 => return Ok(Vec::new()),
            1 => self.send(&msgs[0])?,
            _ => self.send(&serde_json::json!({"type": "batch", "requests": msgs}))?,
        }
        let mut until = Instant::now() + deadline;
        let mut replies: Vec<Option<Reply>> = vec![None; requests.len()];
        let mut left = requests.len();
        let mut cancelled = false;
        while left > 0 {
            let v = match self.next_line(until) {
                Ok(v) => v,
                Err(CallError::Timeout(_)) if !cancelled => {
                    // Ask the worker to stop what is pending: one that answers keeps its process
                    // (a GPU model takes minutes to load); one that does not is killed.
                    for (i, r) in replies.iter().enumerate() {
                        if r.is_none() {
                            self.send(&serde_json::json!({"type": "cancel", "id": first + i as u64}))?;
                        }
                    }
                    cancelled = true;
                    until = Instant::now() + CANCEL_GRACE.min(deadline);
                    continue;
                }
                Err(CallError::Timeout(_)) => {
                    self.kill();
                    return Err(CallError::Timeout(deadline));
                }
                Err(e) => return Err(e),
            };
            match v["type"].as_str() {
                Some("reply") => {
                    // A late reply to a request given up on is not this call's.
                    let Some(i) = v["id"].as_u64().and_then(|id| id.checked_sub(first)).map(|i| i as usize) else {
                        continue;
                    };
                    if i >= replies.len() {
                        continue;
                    }
                    let reply = serde_json::from_value(v.clone())
                        .map_err(|e| CallError::Malformed(format!("a reply ({e}): {v}")))?;
                    if replies[i].replace(reply).is_none() {
                        left -= 1;
                    }
                }
                Some("pong") => continue,
                _ => return Err(CallError::Malformed(format!("expected a reply, found {v}"))),
            }
        }
        let replies: Vec<Reply> = replies.into_iter().map(|r| r.expect("every reply arrived")).collect();
        // Replies that made it within the grace are as good as any; a cancelled one is not.
        if cancelled && replies.iter().any(|r| r.status != Status::Ok) {
            return Err(CallError::Cancelled(deadline));
        }
        Ok(replies)
    }

    /// Whether the worker answers a ping within `timeout`.
    pub fn ping(&mut self, timeout: Duration) -> bool {
        let id = self.next_id;
        self.next_id += 1;
        if self.send(&serde_json::json!({"type": "ping", "id": id})).is_err() {
            return false;
        }
        let until = Instant::now() + timeout;
        loop {
            match self.next_line(until) {
                Ok(v) if v["type"] == "pong" && v["id"] == id => return true,
                Ok(_) => continue,
                Err(_) => return false,
            }
        }
    }

    /// The last lines the worker wrote to stderr, as a suffix for an error message.
    pub fn stderr_tail(&self) -> String {
        let lines: Vec<String> = self.stderr.lock().map(|t| t.iter().cloned().collect()).unwrap_or_default();
        if lines.is_empty() {
            String::new()
        } else {
            format!("\n  worker stderr (last lines):\n    {}", lines.join("\n    "))
        }
    }

    pub fn command(&self) -> &WorkerCommand {
        &self.command
    }

    /// Asks the worker to exit, and kills it if it does not within `grace`.
    pub fn shutdown(mut self, grace: Duration) {
        let _ = self.send(&serde_json::json!({"type": "shutdown"}));
        let until = Instant::now() + grace;
        while Instant::now() < until {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        self.kill();
    }

    /// Kills the worker's process group and reaps it.
    pub fn kill(&mut self) {
        let pid = self.child.id() as libc::pid_t;
        // SAFETY: kill(2) with a negative pid signals the process group we created in `start`
        // (its id is the child's pid); it has no memory effects.
        unsafe {
            libc::kill(-pid, libc::SIGKILL);
        }
        let _ = self.child.wait();
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            self.kill();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A reference worker of `workers/` run with the system's Python.
    fn reference(name: &str, args: &[&str]) -> WorkerCommand {
        let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../workers").join(name);
        let mut all = vec![script.display().to_string()];
        all.extend(args.iter().map(|s| s.to_string()));
        WorkerCommand { program: "python3".into(), args: all }
    }

    fn request(text: &str) -> Request {
        Request {
            item: String::new(),
            op: "echo".into(),
            inputs: vec![FileRef { name: "x".into(), path: text.into(), digest: None }],
            params: serde_json::json!({}),
            out_dir: "/tmp".into(),
        }
    }

    #[test]
    fn a_worker_says_hello_answers_requests_and_pings_and_shuts_down() {
        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        assert_eq!(
            (w.hello.name.as_str(), w.hello.protocol, w.hello.ops.clone()),
            ("protocol-test", 1, vec!["echo".to_string()])
        );
        for i in 0..3 {
            let reply = w.call(&request(&format!("item{i}")), Duration::from_secs(5)).unwrap();
            assert_eq!(reply.status, Status::Ok);
            assert_eq!(reply.outputs[0].path, format!("item{i}"));
        }
        assert!(w.ping(Duration::from_secs(5)));
        w.shutdown(Duration::from_secs(5));
    }

    #[test]
    fn a_hanging_worker_is_killed_at_the_deadline_and_a_crash_or_garbage_is_reported() {
        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        let t = Instant::now();
        let err = w.call(&request("hang"), Duration::from_millis(300)).unwrap_err();
        assert!(matches!(err, CallError::Timeout(_)), "{err}");
        assert!(t.elapsed() < Duration::from_secs(3));
        assert!(!w.ping(Duration::from_millis(200)), "killed");

        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        let err = w.call(&request("crash"), Duration::from_secs(5)).unwrap_err();
        assert!(matches!(err, CallError::Died(_)), "{err}");
        assert!(w.stderr_tail().contains("asked to crash"), "{}", w.stderr_tail());

        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        let err = w.call(&request("garbage"), Duration::from_secs(5)).unwrap_err();
        assert!(matches!(err, CallError::Malformed(_)), "{err}");

        let reply = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10))
            .unwrap()
            .call(&request("bad item"), Duration::from_secs(5))
            .unwrap();
        assert_eq!((reply.status, reply.message.as_str()), (Status::Error, "cannot do `bad item`"));
    }

    #[test]
    fn a_worker_that_answers_the_cancel_after_a_missed_deadline_is_kept_alive() {
        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        let err = w.call(&request("slow:30"), Duration::from_millis(300)).unwrap_err();
        assert!(matches!(err, CallError::Cancelled(_)), "{err}");
        assert!(w.ping(Duration::from_secs(2)), "the worker stopped the request and goes on");
        let reply = w.call(&request("after"), Duration::from_secs(5)).unwrap();
        assert_eq!(reply.outputs[0].path, "after");
    }

    #[test]
    fn a_worker_that_dies_at_start_or_speaks_another_protocol_is_refused_with_its_stderr() {
        let err = Worker::start(&reference("protocol_test_worker.py", &["--die-at-start"]), Duration::from_secs(10))
            .err()
            .unwrap();
        let msg = format!("{err:#}");
        assert!(msg.contains("did not start") && msg.contains("no model here"), "{msg}");
        let err = Worker::start(&reference("protocol_test_worker.py", &["--protocol", "9"]), Duration::from_secs(10))
            .err()
            .unwrap();
        assert!(format!("{err:#}").contains("speaks protocol 9"), "{err:#}");
        let err = Worker::start(
            &WorkerCommand { program: "/nonexistent/worker".into(), args: vec![] },
            Duration::from_secs(1),
        )
        .err()
        .unwrap();
        assert!(format!("{err:#}").contains("starting worker `/nonexistent/worker`"), "{err:#}");
    }
}
