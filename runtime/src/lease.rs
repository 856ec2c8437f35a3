//! Leases: who is using a store, told by files that a heartbeat keeps fresh, never by locks.
//!
//! `flock`/`fcntl` locks cannot say whether a process on another node is alive: Lustre mounted
//! with `localflock` keeps locks node-local (a live remote writer looks dead), and NFS lock
//! recovery can hand a live writer's lock to someone else. Snakemake and Nix users hit exactly
//! that on shared filesystems. So a process announces itself with a lease file
//! (`leases/<writer>.lease`) naming its host, boot, pid and that pid's start time, and a
//! heartbeat thread rewrites it every quarter of the lease timeout. A lease is live when:
//! - its holder is on this host (same host name and boot): its process is still running (the pid
//!   exists with the same start time). This is immediate, so a rerun after a kill on the same
//!   machine does not wait out a timeout;
//! - its holder is on another host: the file was rewritten less than the timeout ago. Ages are
//!   measured on the filesystem's clock (the mtime of our own lease, just rewritten, is "now"),
//!   so node clocks that disagree do not matter.
//!
//! The timeout is 60 s, or `DIST4D_LEASE_TIMEOUT` seconds.

use anyhow::{Context, Result};
use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::{Duration, SystemTime};

/// How long a lease on another host stays live without a heartbeat.
pub fn timeout() -> Duration {
    static T: OnceLock<Duration> = OnceLock::new();
    *T.get_or_init(|| {
        let secs = std::env::var("DIST4D_LEASE_TIMEOUT").ok().and_then(|s| s.trim().parse::<f64>().ok());
        Duration::from_secs_f64(secs.filter(|s| s.is_finite() && *s > 0.0).unwrap_or(60.0))
    })
}

/// The process a lease names.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Holder {
    pub host: String,
    pub boot: String,
    pub pid: u32,
    /// The pid's start time in clock ticks since boot (`/proc/<pid>/stat`, field 22): a pid
    /// reused by another process has another.
    pub start: u64,
    /// The store writer id of the holder (names its segments and temp files).
    pub writer: String,
}

impl Holder {
    /// This process, as writer `writer`.
    pub fn me(writer: &str) -> Holder {
        let pid = std::process::id();
        Holder { host: host_name(), boot: boot_id(), pid, start: pid_start(pid).unwrap_or(0), writer: writer.into() }
    }

    pub(crate) fn encode(&self) -> String {
        format!(
            "dist4d-lease 1\nhost {}\nboot {}\npid {}\nstart {}\nwriter {}\n",
            self.host, self.boot, self.pid, self.start, self.writer
        )
    }

    fn decode(text: &str) -> Option<Holder> {
        let mut lines = text.lines();
        if lines.next()? != "dist4d-lease 1" {
            return None;
        }
        let mut field = |name: &str| lines.next()?.strip_prefix(name)?.strip_prefix(' ').map(str::to_string);
        Some(Holder {
            host: field("host")?,
            boot: field("boot")?,
            pid: field("pid")?.parse().ok()?,
            start: field("start")?.parse().ok()?,
            writer: field("writer")?,
        })
    }

    /// `pid 1234 on node07`.
    pub fn describe(&self) -> String {
        format!("pid {} on {}", self.pid, self.host)
    }

    pub fn on_this_host(&self) -> bool {
        self.host == host_name() && self.boot == boot_id()
    }
}

/// What a lease file says of its holder.
#[derive(Debug, PartialEq, Eq)]
pub enum Liveness {
    Live(Holder),
    /// The holder is gone (killed, its node lost); `None` when the file could not be read as a
    /// lease (torn by a crash mid-write, or an older dist4d's) and is older than the timeout.
    Dead(Option<Holder>),
    /// No such lease.
    Gone,
}

/// Judges the lease at `path`; `now` is the filesystem's current time (see [`fs_now`]).
pub fn judge(path: &Path, now: SystemTime) -> Liveness {
    // Opened first, then stat'ed through the handle: on NFS, opening revalidates a file's
    // attributes, where a path stat may answer from a cache up to a minute old, and a live
    // heartbeat would look stale.
    let Ok(mut file) = File::open(path) else { return Liveness::Gone };
    let Ok(meta) = file.metadata() else { return Liveness::Gone };
    let age = meta.modified().ok().and_then(|m| now.duration_since(m).ok()).unwrap_or_default();
    let mut text = String::new();
    let holder = std::io::Read::read_to_string(&mut file, &mut text).ok().and_then(|_| Holder::decode(&text));
    match holder {
        Some(h) if h.on_this_host() => {
            if pid_start(h.pid).is_some_and(|s| s == h.start) {
                Liveness::Live(h)
            } else {
                Liveness::Dead(Some(h))
            }
        }
        Some(h) if age < timeout() => Liveness::Live(h),
        Some(h) => Liveness::Dead(Some(h)),
        // Unreadable: being written right now, or torn. Only old enough is it dead.
        None if age < timeout() => {
            Liveness::Live(Holder { host: "?".into(), boot: String::new(), pid: 0, start: 0, writer: String::new() })
        }
        None => Liveness::Dead(None),
    }
}

/// The current time on the clock of the filesystem holding `probe` (a file this process may
/// rewrite: its own lease): it is touched and its mtime read back. Falls back to this host's
/// clock.
pub fn fs_now(probe: &Path) -> SystemTime {
    let touched = OpenOptions::new().write(true).open(probe).and_then(|f| {
        let mut b = [0u8; 1];
        f.read_at(&mut b, 0)?;
        f.write_at(&b, 0)?;
        f.metadata()?.modified()
    });
    touched.unwrap_or_else(|_| SystemTime::now())
}

/// A lease this process holds: written at once, renewed by a heartbeat thread, removed on drop.
pub struct Lease {
    path: PathBuf,
    stop: Option<crossbeam_channel::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Lease {
    /// Takes the lease at `path`, which must not exist (`create_new`: on NFSv3+ and Lustre an
    /// exclusive create is atomic). `Ok(None)` when it exists.
    pub fn create(path: &Path, holder: &Holder) -> Result<Option<Lease>> {
        if let Some(dir) = path.parent() {
            fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        let mut f = match OpenOptions::new().write(true).create_new(true).open(path) {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => return Ok(None),
            Err(e) => return Err(e).with_context(|| format!("creating lease {}", path.display())),
        };
        let body = holder.encode();
        f.write_all(body.as_bytes()).with_context(|| format!("writing lease {}", path.display()))?;
        Ok(Some(Lease::renewed(path.to_path_buf(), body)))
    }

    /// Renews `path` with `body` every quarter timeout until dropped.
    fn renewed(path: PathBuf, body: String) -> Lease {
        let (stop, stopped) = crossbeam_channel::bounded::<()>(0);
        let every = timeout() / 4;
        let p = path.clone();
        let thread = std::thread::Builder::new()
            .name("dist4d-lease".into())
            .spawn(move || {
                while let Err(crossbeam_channel::RecvTimeoutError::Timeout) = stopped.recv_timeout(every) {
                    renew(&p, &body);
                }
            })
            .ok();
        Lease { path, stop: Some(stop), thread }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Rewrites a lease's bytes in place (the write moves its mtime, on the filesystem's clock);
/// recreates it if someone removed it, judging us dead.
fn renew(path: &Path, body: &str) {
    let done = match OpenOptions::new().write(true).open(path) {
        Ok(f) => f.write_all_at(body.as_bytes(), 0),
        Err(_) => File::create(path).and_then(|mut f| f.write_all(body.as_bytes())),
    };
    if let Err(e) = done {
        eprintln!("warning: cannot renew lease {}: {e}", path.display());
    }
}

impl Drop for Lease {
    fn drop(&mut self) {
        drop(self.stop.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        let _ = fs::remove_file(&self.path);
    }
}

/// Takes the lease at `path`, taking it over from a dead holder. `Err(holder)` (as a plain
/// value in `Ok`) when a live process holds it.
pub fn acquire(path: &Path, me: &Holder, now: impl Fn() -> SystemTime) -> Result<std::result::Result<Lease, Holder>> {
    for _ in 0..8 {
        if let Some(lease) = Lease::create(path, me)? {
            return Ok(Ok(lease));
        }
        match judge(path, now()) {
            Liveness::Live(h) => return Ok(Err(h)),
            // Another taker may remove and recreate at the same moment; the exclusive create
            // above then lets one of us in, and the other finds a live holder.
            Liveness::Dead(_) => {
                let _ = fs::remove_file(path);
            }
            Liveness::Gone => {}
        }
    }
    anyhow::bail!("cannot take lease {}: it keeps changing hands", path.display())
}

/// A claim on an item of work: a file naming its holder, live while the holder's writer lease
/// is (so claims need no heartbeat of their own), removed when dropped.
pub struct Claim {
    path: PathBuf,
}

impl Claim {
    /// Takes the claim at `path`, taking it over from a dead holder; `Ok(Err(holder))` when a
    /// live process holds it. Writer leases are in `leases`.
    pub fn take(
        path: &Path,
        leases: &Path,
        me: &Holder,
        now: SystemTime,
    ) -> Result<std::result::Result<Claim, Holder>> {
        if let Some(dir) = path.parent() {
            fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        for _ in 0..8 {
            match OpenOptions::new().write(true).create_new(true).open(path) {
                Ok(mut f) => {
                    f.write_all(me.encode().as_bytes()).with_context(|| format!("writing {}", path.display()))?;
                    return Ok(Ok(Claim { path: path.to_path_buf() }));
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(e).with_context(|| format!("creating claim {}", path.display())),
            }
            match Claim::judge(path, leases, now) {
                Liveness::Live(h) => return Ok(Err(h)),
                Liveness::Dead(_) => {
                    let _ = fs::remove_file(path);
                }
                Liveness::Gone => {}
            }
        }
        anyhow::bail!("cannot take claim {}: it keeps changing hands", path.display())
    }

    /// A claim is live while its holder's writer lease is.
    pub fn judge(path: &Path, leases: &Path, now: SystemTime) -> Liveness {
        let Ok(meta) = fs::metadata(path) else { return Liveness::Gone };
        match fs::read_to_string(path).ok().and_then(|t| Holder::decode(&t)) {
            Some(h) => match judge(&leases.join(format!("{}.lease", h.writer)), now) {
                Liveness::Live(_) => Liveness::Live(h),
                _ => Liveness::Dead(Some(h)),
            },
            None => {
                let age = meta.modified().ok().and_then(|m| now.duration_since(m).ok()).unwrap_or_default();
                if age < timeout() {
                    Liveness::Live(Holder {
                        host: "?".into(),
                        boot: String::new(),
                        pid: 0,
                        start: 0,
                        writer: String::new(),
                    })
                } else {
                    Liveness::Dead(None)
                }
            }
        }
    }
}

impl Drop for Claim {
    fn drop(&mut self) {
        let _ = fs::remove_file(&self.path);
    }
}

/// This machine's host name.
pub fn host_name() -> String {
    static H: OnceLock<String> = OnceLock::new();
    H.get_or_init(|| fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default().trim().to_string()).clone()
}

fn boot_id() -> String {
    static B: OnceLock<String> = OnceLock::new();
    B.get_or_init(|| fs::read_to_string("/proc/sys/kernel/random/boot_id").unwrap_or_default().trim().to_string())
        .clone()
}

/// The start time of process `pid` (clock ticks since boot), if it is running.
fn pid_start(pid: u32) -> Option<u64> {
    let stat = fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) is in parentheses and may hold spaces; fields count after it.
    let rest = &stat[stat.rfind(')')? + 1..];
    let state = rest.split_whitespace().next()?;
    if state == "Z" || state == "X" {
        return None; // a zombie has exited: only its exit status is left
    }
    rest.split_whitespace().nth(19)?.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lease_is_live_while_held_and_gone_after() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.lease");
        let me = Holder::me("w1");
        let lease = Lease::create(&path, &me).unwrap().unwrap();
        assert!(Lease::create(&path, &me).unwrap().is_none(), "exclusive");
        assert_eq!(judge(&path, SystemTime::now()), Liveness::Live(me.clone()));
        drop(lease);
        assert_eq!(judge(&path, SystemTime::now()), Liveness::Gone);
    }

    #[test]
    fn a_killed_holder_on_this_host_is_dead_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.lease");
        let mut child = std::process::Command::new("sleep").arg("30").spawn().unwrap();
        let holder = Holder { pid: child.id(), start: pid_start(child.id()).unwrap(), ..Holder::me("w2") };
        fs::write(&path, holder.encode()).unwrap();
        assert!(matches!(judge(&path, SystemTime::now()), Liveness::Live(_)));
        child.kill().unwrap();
        child.wait().unwrap();
        assert_eq!(judge(&path, SystemTime::now()), Liveness::Dead(Some(holder.clone())));
        // And a pid reused by another process is not the holder.
        let reused = Holder { pid: std::process::id(), start: 1, ..holder };
        fs::write(&path, reused.encode()).unwrap();
        assert!(matches!(judge(&path, SystemTime::now()), Liveness::Dead(_)));
        let me = Holder::me("w3");
        let taken = acquire(&path, &me, SystemTime::now).unwrap().expect("taken over from the dead");
        assert_eq!(judge(taken.path(), SystemTime::now()), Liveness::Live(me));
    }

    #[test]
    fn a_holder_on_another_host_is_live_until_its_heartbeat_is_older_than_the_timeout() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("remote.lease");
        let remote = Holder { host: "node-elsewhere".into(), ..Holder::me("w4") };
        fs::write(&path, remote.encode()).unwrap();
        let written = fs::metadata(&path).unwrap().modified().unwrap();
        assert_eq!(judge(&path, written + timeout() / 2), Liveness::Live(remote.clone()));
        assert_eq!(judge(&path, written + timeout() * 2), Liveness::Dead(Some(remote.clone())));
        let me = Holder::me("w5");
        assert!(acquire(&path, &me, || written).unwrap().is_err(), "live: not taken");
        assert!(acquire(&path, &me, || written + timeout() * 2).unwrap().is_ok(), "dead: taken over");
    }

    #[test]
    fn a_torn_lease_is_live_until_old() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("torn.lease");
        fs::write(&path, b"dist4d-lease 1\nhost ").unwrap();
        let written = fs::metadata(&path).unwrap().modified().unwrap();
        assert!(matches!(judge(&path, written), Liveness::Live(_)));
        assert_eq!(judge(&path, written + timeout() * 2), Liveness::Dead(None));
    }

    #[test]
    fn a_claim_lives_and_dies_with_its_holders_writer_lease() {
        let dir = tempfile::tempdir().unwrap();
        let (leases, path) = (dir.path().join("leases"), dir.path().join("leases/claims/x.claim"));
        let a = Holder::me("writer-a");
        let a_lease = Lease::create(&leases.join("writer-a.lease"), &a).unwrap().unwrap();
        let claim = Claim::take(&path, &leases, &a, SystemTime::now()).unwrap().unwrap();
        let b = Holder::me("writer-b");
        assert_eq!(Claim::take(&path, &leases, &b, SystemTime::now()).unwrap().err(), Some(a.clone()));
        drop(claim);
        let again = Claim::take(&path, &leases, &a, SystemTime::now()).unwrap().unwrap();
        // Its holder ends without releasing it (killed): the claim is taken over.
        std::mem::forget(again);
        drop(a_lease);
        assert!(matches!(Claim::judge(&path, &leases, SystemTime::now()), Liveness::Dead(Some(_))));
        let taken = Claim::take(&path, &leases, &b, SystemTime::now()).unwrap().expect("taken over");
        assert_eq!(fs::read_to_string(&path).unwrap(), b.encode());
        drop(taken);
        assert!(!path.exists());
    }

    #[test]
    fn the_filesystem_clock_is_read_from_a_touched_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("probe");
        fs::write(&path, b"x").unwrap();
        let old = SystemTime::UNIX_EPOCH + Duration::from_secs(1_000_000);
        File::options().write(true).open(&path).unwrap().set_modified(old).unwrap();
        let now = fs_now(&path);
        assert!(now > old + Duration::from_secs(1_000_000), "the probe's mtime moved to now");
        assert_eq!(fs::read(&path).unwrap(), b"x", "its bytes are unchanged");
    }
}
