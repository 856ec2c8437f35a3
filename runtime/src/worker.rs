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
//!
//! What holds whatever the worker does: every wait has a bound (a reply, a write to its stdin, its
//! exit after a kill); a worker whose stdout ends is dead, even if its process lives on; a line
//! longer than [`MAX_LINE`] is a protocol error, read no further; a reply to a request that was
//! never sent is one too; and no worker's process group outlives the engine (`groups`).

mod groups;
mod lines;
mod write;

pub use groups::{kill_all_workers, KillWorkersOnDrop};

use anyhow::{anyhow, bail, Context, Result};
use crossbeam_channel::{Receiver, RecvTimeoutError};
use groups::{kill_group, WORKERS};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::io::BufReader;
use std::os::unix::process::CommandExt;
use std::process::{Child, ChildStdin, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The protocol version this engine speaks.
pub const PROTOCOL: u32 = 1;

/// The longest line a worker may write to stdout (a reply names files, it does not hold them):
/// a longer one is a protocol error, and no more of it than this is ever held in memory.
pub const MAX_LINE: usize = 16 << 20;

/// How much of each line of a worker's stderr is kept for error messages (the rest is read and
/// dropped, with a note of how much).
const STDERR_LINE_KEPT: usize = 4096;

/// How long a dead worker's stderr is read on before its error is reported.
const STDERR_GRACE: Duration = Duration::from_millis(500);

/// Lines of a worker's stderr kept for error messages.
const STDERR_TAIL: usize = 20;

/// Lines read from a worker's stdout and not yet taken by a call: a worker that writes while no
/// call listens is held back by its pipe, not buffered without end.
const LINES_QUEUED: usize = 16;

/// When a worker's stdout ends, how long it has to exit on its own (a crash closes stdout as it
/// exits) before it is taken for one that closed stdout and lives on, and killed.
const EXIT_GRACE: Duration = Duration::from_millis(200);

/// How long the engine waits to reap a worker it killed: a process in uninterruptible sleep (a
/// GPU driver, a hung network filesystem) dies only when that ends, and is reaped by a thread.
const REAP_WAIT: Duration = Duration::from_secs(2);

/// Ids of requests given up on (cancelled) that are remembered: a late reply to one of them is
/// skipped, a reply to any other id that is not the call's is a protocol error.
const GIVEN_UP_KEPT: usize = 1024;

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
    /// Not the protocol: why.
    Bad(String),
    Closed,
}

/// Why a write to the worker failed.
enum SendError {
    /// It did not read it before the deadline.
    Late,
    /// It could not be written (the worker is gone, or the message is not JSON).
    Failed(CallError),
}

/// A running worker process.
pub struct Worker {
    pub hello: Hello,
    command: WorkerCommand,
    child: Child,
    /// Set once the child is reaped (or handed to a thread that reaps it): its pid, and so its
    /// process group id, may then be another process's.
    reaped: bool,
    stdin: ChildStdin,
    lines: Receiver<Line>,
    stderr: Arc<Mutex<VecDeque<String>>>,
    /// Disconnected when the stderr reader has read to the end.
    stderr_read: Receiver<()>,
    next_id: u64,
    /// Requests cancelled by earlier calls, the latest last (at most `GIVEN_UP_KEPT`).
    given_up: VecDeque<u64>,
    /// Whether the process was asked to stop ([`Worker::stop_when`]): a call then ends as its
    /// deadline would, at once, instead of waiting up to the deadline.
    stop: Option<fn() -> bool>,
}

/// How often a call waiting on a worker looks whether the process was asked to stop.
const STOP_POLL: Duration = Duration::from_millis(200);

/// Reads the worker's stdout into `tx`, a line at a time, each at most [`MAX_LINE`] bytes: a
/// longer one is reported and ends the reading (the stream is out of step from there on).
fn read_stdout(stdout: std::process::ChildStdout, tx: crossbeam_channel::Sender<Line>) {
    let mut r = BufReader::new(stdout);
    let mut buf = Vec::new();
    loop {
        buf.clear();
        let end = lines::read_line(&mut r, &mut buf, MAX_LINE).unwrap_or(lines::End::Eof);
        let start = |buf: &[u8]| String::from_utf8_lossy(&buf[..buf.len().min(200)]).into_owned();
        if end == lines::End::TooLong {
            let why = format!("a line longer than {} MiB (MAX_LINE), starting `{}`", MAX_LINE >> 20, start(&buf));
            let _ = tx.send(Line::Bad(why));
            return;
        }
        if !buf.trim_ascii().is_empty() {
            let msg = match serde_json::from_slice(&buf) {
                Ok(v) => Line::Json(v),
                Err(_) => Line::Bad(format!("not JSON: {}", start(&buf))),
            };
            if tx.send(msg).is_err() {
                return;
            }
        }
        if end == lines::End::Eof {
            let _ = tx.send(Line::Closed);
            return;
        }
    }
}

/// Keeps the last [`STDERR_TAIL`] lines of the worker's stderr in `tail`, each cut to
/// [`STDERR_LINE_KEPT`] bytes.
fn read_stderr(stderr: std::process::ChildStderr, tail: &Mutex<VecDeque<String>>) {
    let mut r = BufReader::new(stderr);
    loop {
        let mut buf = Vec::new();
        let mut end = lines::read_line(&mut r, &mut buf, STDERR_LINE_KEPT).unwrap_or(lines::End::Eof);
        let mut line = String::from_utf8_lossy(&buf).into_owned();
        if end == lines::End::TooLong {
            let (cut, after) = lines::skip_line(&mut r).unwrap_or((0, lines::End::Eof));
            line.push_str(&format!(" [and {cut} more bytes]"));
            end = after;
        }
        if !(end == lines::End::Eof && line.is_empty()) {
            if let Ok(mut t) = tail.lock() {
                if t.len() == STDERR_TAIL {
                    t.pop_front();
                }
                t.push_back(line);
            }
        }
        if end == lines::End::Eof {
            return;
        }
    }
}

impl Worker {
    /// Starts `command` and waits up to `startup` for its hello.
    pub fn start(command: &WorkerCommand, startup: Duration) -> Result<Worker> {
        let what = || format!("worker `{command}`");
        let mut child = WORKERS
            .spawn(
                Command::new(&command.program)
                    .args(&command.args)
                    .stdin(Stdio::piped())
                    .stdout(Stdio::piped())
                    .stderr(Stdio::piped())
                    // Its own process group: a deadline kills the model and whatever it started.
                    .process_group(0),
            )
            .with_context(|| format!("starting {}", what()))?;
        // Taken before anything can fail, so that a failure below drops a `Worker` that ends it.
        let pipes = (child.stdin.take(), child.stdout.take(), child.stderr.take());
        let (Some(stdin), Some(stdout), Some(stderr_pipe)) = pipes else {
            kill_group(child.id() as libc::pid_t);
            let _ = child.wait();
            WORKERS.remove(child.id() as libc::pid_t);
            bail!("{}: its stdin, stdout or stderr is not a pipe", what());
        };
        let (tx, lines) = crossbeam_channel::bounded(LINES_QUEUED);
        std::thread::spawn(move || read_stdout(stdout, tx));
        let stderr = Arc::new(Mutex::new(VecDeque::new()));
        let tail = stderr.clone();
        let (read_to_end, stderr_read) = crossbeam_channel::bounded::<()>(0);
        std::thread::spawn(move || {
            // Dropped at the end of the stream: a dead worker's last words are in the tail then.
            let _read_to_end = read_to_end;
            read_stderr(stderr_pipe, &tail);
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
            reaped: false,
            stdin,
            lines,
            stderr,
            stderr_read,
            next_id: 1,
            given_up: VecDeque::new(),
            stop: None,
        };
        if let Err(e) = write::set_nonblocking(&worker.stdin) {
            worker.kill();
            bail!("{}: making its stdin non-blocking: {e}", what());
        }
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
            Ok(Line::Bad(why)) => Err(CallError::Malformed(why)),
            Ok(Line::Closed) | Err(RecvTimeoutError::Disconnected) => Err(self.stdout_closed()),
            Err(RecvTimeoutError::Timeout) => Err(CallError::Timeout(wait)),
        }
    }

    /// The error of a worker whose stdout ended: it cannot answer any more, so it is dead to
    /// the engine whether or not its process lives on. A crash closes stdout as the process
    /// exits; one still running after `EXIT_GRACE` closed it and lives on (waiting on it would
    /// wait for ever). Either way its process group is killed, with whatever it started.
    fn stdout_closed(&mut self) -> CallError {
        let exited = self.exits_within(EXIT_GRACE);
        let status = self.end();
        let why = match status {
            Some(s) if exited => s.to_string(),
            None if exited => "it exited (its status is unknown)".into(),
            _ => "it closed its stdout and kept running, so it was killed with its process group".into(),
        };
        self.died(why)
    }

    /// Writes `msg` to the worker's stdin, giving up at `by`.
    fn send(&mut self, msg: &serde_json::Value, by: Instant) -> std::result::Result<(), SendError> {
        let mut line = serde_json::to_vec(msg).map_err(|e| SendError::Failed(CallError::Malformed(e.to_string())))?;
        line.push(b'\n');
        match write::write_all_by(&mut self.stdin, &line, by) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => Err(SendError::Late),
            Err(e) => Err(SendError::Failed(self.died(format!("writing to it: {e}")))),
        }
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
    /// Ends calls early, as their deadline would (a `cancel`, then the kill), once `stop` says
    /// the process was asked to stop: a run stopping on SIGTERM must not wait out a deadline of
    /// minutes.
    pub fn stop_when(&mut self, stop: Option<fn() -> bool>) {
        self.stop = stop;
    }

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
        let mut until = Instant::now() + deadline;
        let sent = match msgs.len() {
            0 => return Ok(Vec::new()),
            1 => self.send(&msgs[0], until),
            _ => self.send(&serde_json::json!({"type": "batch", "requests": msgs}), until),
        };
        self.sent(sent, deadline)?;
        let mut replies: Vec<Option<Reply>> = vec![None; requests.len()];
        let mut left = requests.len();
        let mut cancelled = false;
        while left > 0 {
            // Waits in slices while a stop may come, so that it is seen within STOP_POLL.
            let slice_end = match self.stop {
                Some(_) if !cancelled => until.min(Instant::now() + STOP_POLL),
                _ => until,
            };
            let v = match self.next_line(slice_end) {
                Ok(v) => v,
                Err(CallError::Timeout(_)) if Instant::now() < until => {
                    if self.stop.is_some_and(|stop| stop()) {
                        // Asked to stop: the deadline is now (cancel, then kill).
                        until = Instant::now();
                    }
                    continue;
                }
                Err(CallError::Timeout(_)) if !cancelled => {
                    // Ask the worker to stop what is pending: one that answers keeps its process
                    // (a GPU model takes minutes to load); one that does not is killed.
                    cancelled = true;
                    until = Instant::now() + CANCEL_GRACE.min(deadline);
                    let pending: Vec<u64> =
                        (0..replies.len()).filter(|&i| replies[i].is_none()).map(|i| first + i as u64).collect();
                    for id in pending {
                        // Replies to it after this call are late, not a breach of the protocol.
                        self.give_up(id);
                        let sent = self.send(&serde_json::json!({"type": "cancel", "id": id}), until);
                        self.sent(sent, deadline)?;
                    }
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
                    let Some(id) = v["id"].as_u64() else {
                        return Err(CallError::Malformed(format!("a reply without a request id: {v}")));
                    };
                    let Some(i) = id.checked_sub(first).map(|i| i as usize).filter(|&i| i < replies.len()) else {
                        // A late reply to a request given up on is not this call's; any other
                        // (an id never sent, a second reply to an answered one) is a worker out
                        // of step, which no wait would mend.
                        if self.given_up.contains(&id) {
                            continue;
                        }
                        let last = first + requests.len() as u64 - 1;
                        return Err(CallError::Malformed(if id >= self.next_id {
                            format!("a reply to request {id}, which was never sent (this call's are {first} to {last}): {v}")
                        } else {
                            format!("a reply to request {id}, which is neither this call's ({first} to {last}) nor a cancelled one: {v}")
                        }));
                    };
                    if replies[i].is_some() {
                        // The first reply to a request stands; a second one is late if the
                        // request was cancelled, and a worker out of step if not.
                        if self.given_up.contains(&id) {
                            continue;
                        }
                        return Err(CallError::Malformed(format!("a second reply to request {id}: {v}")));
                    }
                    let reply = serde_json::from_value(v.clone())
                        .map_err(|e| CallError::Malformed(format!("a reply ({e}): {v}")))?;
                    replies[i] = Some(reply);
                    left -= 1;
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

    /// The end of a `send` of a call with `deadline`: a worker that did not take the message in
    /// time is killed, as one that did not answer it.
    fn sent(
        &mut self,
        sent: std::result::Result<(), SendError>,
        deadline: Duration,
    ) -> std::result::Result<(), CallError> {
        match sent {
            Ok(()) => Ok(()),
            Err(SendError::Late) => {
                self.kill();
                Err(CallError::Timeout(deadline))
            }
            Err(SendError::Failed(e)) => Err(e),
        }
    }

    /// Remembers that request `id` was given up on, forgetting the oldest beyond `GIVEN_UP_KEPT`.
    fn give_up(&mut self, id: u64) {
        if self.given_up.len() == GIVEN_UP_KEPT {
            self.given_up.pop_front();
        }
        self.given_up.push_back(id);
    }

    /// Whether the worker answers a ping within `timeout` (pongs to earlier pings and late
    /// replies to requests given up on are passed over; anything else is a no).
    pub fn ping(&mut self, timeout: Duration) -> bool {
        let id = self.next_id;
        self.next_id += 1;
        let until = Instant::now() + timeout;
        if self.send(&serde_json::json!({"type": "ping", "id": id}), until).is_err() {
            return false;
        }
        loop {
            match self.next_line(until) {
                Ok(v) if v["type"] == "pong" && v["id"] == id => return true,
                Ok(v) if v["type"] == "pong" => continue,
                Ok(v) if v["type"] == "reply" && v["id"].as_u64().is_some_and(|r| self.given_up.contains(&r)) => {
                    continue
                }
                Ok(_) | Err(_) => return false,
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

    /// Asks the worker to exit, and kills it if it does not within `grace`. Either way what it
    /// started in its process group is killed too: a worker's helpers do not outlive it.
    pub fn shutdown(mut self, grace: Duration) {
        let until = Instant::now() + grace;
        if self.send(&serde_json::json!({"type": "shutdown"}), until).is_ok() {
            self.exits_within(grace);
        }
        self.kill();
    }

    /// Whether the worker exits within `wait` (it is left unreaped: its pid, and so its process
    /// group's id, stays reserved until [`Worker::end`]).
    fn exits_within(&self, wait: Duration) -> bool {
        let until = Instant::now() + wait;
        loop {
            if self.reaped || self.exited() {
                return true;
            }
            if Instant::now() >= until {
                return false;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Whether the worker has exited, without reaping it.
    fn exited(&self) -> bool {
        // SAFETY: waitid(2) on our own child, into a zeroed siginfo_t that lives across the call;
        // WNOWAIT leaves the child to be reaped by `Child::wait`.
        unsafe {
            let mut info: libc::siginfo_t = std::mem::zeroed();
            let r = libc::waitid(
                libc::P_PID,
                self.child.id() as libc::id_t,
                &mut info,
                libc::WEXITED | libc::WNOHANG | libc::WNOWAIT,
            );
            r == 0 && info.si_pid() != 0
        }
    }

    /// Kills the worker's process group and reaps it.
    pub fn kill(&mut self) {
        self.end();
    }

    /// Kills the worker's process group (SIGKILL, which no worker can ignore; sent before the
    /// worker is reaped, so the group's id is still its own) and reaps the worker, waiting at
    /// most `REAP_WAIT`: its exit status, if it was reaped now. One that takes longer to die is
    /// reaped by a thread of its own, and stays in the registry of live groups until then.
    fn end(&mut self) -> Option<ExitStatus> {
        if self.reaped {
            return None;
        }
        let pid = self.child.id() as libc::pid_t;
        kill_group(pid);
        self.reaped = true;
        let until = Instant::now() + REAP_WAIT;
        loop {
            match self.child.try_wait() {
                Ok(Some(status)) => {
                    WORKERS.remove(pid);
                    return Some(status);
                }
                Ok(None) if Instant::now() < until => std::thread::sleep(Duration::from_millis(5)),
                Ok(None) => break,
                Err(_) => {
                    WORKERS.remove(pid);
                    return None;
                }
            }
        }
        std::thread::spawn(move || {
            let mut status = 0;
            // SAFETY: waitpid(2) on our own child, which nothing else reaps (`reaped` is set).
            unsafe { libc::waitpid(pid, &mut status, 0) };
            WORKERS.remove(pid);
        });
        None
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        self.end();
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

    /// The live processes (not zombies) of process group `pgid`, from /proc.
    fn alive_in_group(pgid: u32) -> Vec<u32> {
        let mut alive = Vec::new();
        for entry in std::fs::read_dir("/proc").unwrap().flatten() {
            let Some(pid) = entry.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else { continue };
            let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else { continue };
            // `pid (comm) state ppid pgrp ...`: the command may hold spaces and parentheses.
            let fields: Vec<&str> = stat[stat.rfind(')').unwrap() + 1..].split_whitespace().collect();
            if fields[0] != "Z" && fields[2] == pgid.to_string() {
                alive.push(pid);
            }
        }
        alive
    }

    /// What is left of process group `pgid` after up to 2 s: SIGKILL is certain, but a process
    /// the engine did not reap itself (what the worker started) dies when it is next scheduled.
    fn left_of_group(pgid: u32) -> Vec<u32> {
        let t = Instant::now();
        while !alive_in_group(pgid).is_empty() && t.elapsed() < Duration::from_secs(2) {
            std::thread::sleep(Duration::from_millis(10));
        }
        alive_in_group(pgid)
    }

    /// A file name in the temporary directory for a test worker's `--pid-file`.
    fn pid_file(test: &str) -> std::path::PathBuf {
        let p = std::env::temp_dir().join(format!("dist4d-worker-test-{}-{test}", std::process::id()));
        let _ = std::fs::remove_file(&p);
        p
    }

    /// The worker pids a `--pid-file` lists (the first of each line).
    fn workers_in(pid_file: &std::path::Path) -> Vec<u32> {
        let text = std::fs::read_to_string(pid_file).unwrap();
        text.lines().map(|l| l.split_whitespace().next().unwrap().parse().unwrap()).collect()
    }

    #[test]
    fn a_worker_that_closes_its_stdout_and_lives_on_is_dead_at_once_and_its_group_killed() {
        let pids = pid_file("close-stdout");
        let args = ["--pid-file", pids.to_str().unwrap()];
        let mut w = Worker::start(&reference("protocol_test_worker.py", &args), Duration::from_secs(10)).unwrap();
        let t = Instant::now();
        let err = w.call(&request("close-stdout"), Duration::from_secs(20)).unwrap_err();
        assert!(matches!(err, CallError::Died(_)) && err.to_string().contains("closed its stdout"), "{err}");
        assert!(t.elapsed() < Duration::from_secs(3), "long before the deadline: {:?}", t.elapsed());
        let group = workers_in(&pids)[0];
        assert_eq!(left_of_group(group), Vec::<u32>::new(), "the worker and the `sleep` it started are gone");
        // Before its hello, likewise.
        let t = Instant::now();
        let args = ["--close-stdout-at-start", "--pid-file", pids.to_str().unwrap()];
        let err = Worker::start(&reference("protocol_test_worker.py", &args), Duration::from_secs(20)).err().unwrap();
        assert!(format!("{err:#}").contains("closed its stdout"), "{err:#}");
        assert!(t.elapsed() < Duration::from_secs(3), "long before the startup limit: {:?}", t.elapsed());
        assert_eq!(left_of_group(workers_in(&pids)[1]), Vec::<u32>::new());
        let _ = std::fs::remove_file(&pids);
    }

    #[test]
    fn a_reply_to_a_request_never_sent_is_a_protocol_error_at_once_and_a_late_one_to_a_cancelled_request_is_not() {
        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        let t = Instant::now();
        let err = w.call(&request("unknown-id"), Duration::from_secs(10)).unwrap_err();
        assert!(matches!(err, CallError::Malformed(_)) && err.to_string().contains("never sent"), "{err}");
        assert!(t.elapsed() < Duration::from_secs(2), "at once, not at the deadline: {:?}", t.elapsed());
        // A second reply to a request answered already is one too, found by the next call.
        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        assert_eq!(w.call(&request("twice"), Duration::from_secs(5)).unwrap().status, Status::Ok);
        let err = w.call(&request("a"), Duration::from_secs(10)).unwrap_err();
        assert!(matches!(err, CallError::Malformed(_)) && err.to_string().contains("reply to request 1"), "{err}");
        // A worker that answers a cancel and then the cancelled request too: the late reply is
        // skipped by the next call.
        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        let err = w.call(&request("slow-late:30"), Duration::from_millis(300)).unwrap_err();
        assert!(matches!(err, CallError::Cancelled(_)), "{err}");
        assert_eq!(w.call(&request("after"), Duration::from_secs(5)).unwrap().outputs[0].path, "after");
    }

    #[test]
    fn a_stdout_line_over_the_bound_is_a_protocol_error_and_stderr_lines_are_cut() {
        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        let t = Instant::now();
        // 100 MB without a newline, and then nothing: the bound ends the call, not the deadline.
        let err = w.call(&request("long-line:100000000"), Duration::from_secs(20)).unwrap_err();
        assert!(matches!(err, CallError::Malformed(_)) && err.to_string().contains("16 MiB"), "{err}");
        assert!(t.elapsed() < Duration::from_secs(10), "{:?}", t.elapsed());
        // 50 MB on stderr without a newline, then a crash: the tail keeps the crash, and a cut line.
        let mut w = Worker::start(&reference("protocol_test_worker.py", &[]), Duration::from_secs(10)).unwrap();
        let err = w.call(&request("long-stderr:50000000"), Duration::from_secs(20)).unwrap_err();
        assert!(matches!(err, CallError::Died(_)), "{err}");
        let tail = w.stderr_tail();
        assert!(tail.contains("asked to crash after a long line"), "{}", &tail[tail.len().saturating_sub(300)..]);
        assert!(tail.len() < 64 * 1024, "a stderr tail of {} bytes", tail.len());
    }

    #[test]
    fn a_request_to_a_worker_that_does_not_read_stdin_ends_at_the_deadline() {
        let mut w =
            Worker::start(&reference("protocol_test_worker.py", &["--no-read"]), Duration::from_secs(10)).unwrap();
        // Larger than a pipe's buffer: writing it blocks until the worker reads.
        let mut big = request("a");
        big.params = serde_json::json!({"pad": "x".repeat(4 << 20)});
        let t = Instant::now();
        let err = w.call(&big, Duration::from_millis(500)).unwrap_err();
        assert!(matches!(err, CallError::Timeout(_)), "{err}");
        assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());
        assert_eq!(left_of_group(w.child.id()), Vec::<u32>::new());
    }
}
