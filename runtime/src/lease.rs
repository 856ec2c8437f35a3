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
    /// The holder's own lease timeout (ms): it renews every quarter of it, so it is judged by
    /// it, whatever the judge's own setting.
    pub timeout_ms: u64,
}

impl Holder {
    /// This process, as writer `writer`.
    pub fn me(writer: &str) -> Holder {
        let pid = std::process::id();
        Holder {
            host: host_name(),
            boot: boot_id(),
            pid,
            start: pid_start(pid).unwrap_or(0),
            writer: writer.into(),
            timeout_ms: timeout().as_millis() as u64,
        }
    }

    pub(crate) fn encode(&self) -> String {
        format!(
            "dist4d-lease 1\nhost {}\nboot {}\npid {}\nstart {}\nwriter {}\ntimeout_ms {}\n",
            self.host, self.boot, self.pid, self.start, self.writer, self.timeout_ms
        )
    }

    fn decode(text: &str) -> Option<Holder> {
        let mut lines = text.lines();
        if lines.next()? != "dist4d-lease 1" {
            return None;
        }
        let mut field = |name: &str| lines.next()?.strip_prefix(name)?.strip_prefix(' ').map(str::to_string);
        let (host, boot, pid, start, writer) = (
            field("host")?,
            field("boot")?,
            field("pid")?.parse().ok()?,
            field("start")?.parse().ok()?,
            field("writer")?,
        );
        // A lease written whole ends with its newline (a torn one is not believed).
        if !text.ends_with('\n') {
            return None;
        }
        let timeout_ms = field("timeout_ms").and_then(|t| t.parse().ok()).unwrap_or(timeout().as_millis() as u64);
        Some(Holder { host, boot, pid, start, writer, timeout_ms })
    }

    fn timeout(&self) -> Duration {
        Duration::from_millis(self.timeout_ms.max(1))
    }

    /// Whether its process still runs (on this host): its pid exists with the same start time.
    /// Where `/proc` hides other users' processes (`hidepid`), `kill(pid, 0)` answers: refused
    /// (EPERM) means it exists.
    fn process_alive(&self) -> bool {
        if let Some(start) = pid_start(self.pid) {
            return self.start == 0 || start == self.start;
        }
        // SAFETY: signal 0 only checks that the process exists and may be signalled.
        let r = unsafe { libc::kill(self.pid as libc::pid_t, 0) };
        r == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
    }

    /// Stand-in for a lease being written right now (unreadable yet): live.
    fn unknown() -> Holder {
        Holder { host: "?".into(), boot: String::new(), pid: 0, start: 0, writer: String::new(), timeout_ms: 0 }
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
    match read_holder(path, now) {
        Err(decided) => decided,
        Ok((h, _)) if h.on_this_host() => {
            if h.process_alive() {
                Liveness::Live(h)
            } else {
                Liveness::Dead(Some(h))
            }
        }
        Ok((h, age)) if age < h.timeout() => Liveness::Live(h),
        Ok((h, _)) => Liveness::Dead(Some(h)),
    }
}

/// The holder a lease or claim file names, with the file's age; `Err` with the verdict when the
/// file alone decides: gone; unreadable (permissions, an I/O error: nothing says its holder is
/// gone, so live); torn or being written (live while younger than the timeout, else dead).
fn read_holder(path: &Path, now: SystemTime) -> std::result::Result<(Holder, Duration), Liveness> {
    // Opened first, then stat'ed through the handle: on NFS, opening revalidates a file's
    // attributes, where a path stat may answer from a cache up to a minute old, and a live
    // heartbeat would look stale.
    let mut file = match File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(Liveness::Gone),
        Err(_) => return Err(Liveness::Live(Holder::unknown())),
    };
    let Ok(meta) = file.metadata() else { return Err(Liveness::Live(Holder::unknown())) };
    let age = meta.modified().ok().and_then(|m| now.duration_since(m).ok()).unwrap_or_default();
    let mut text = String::new();
    match std::io::Read::read_to_string(&mut file, &mut text).ok().and_then(|_| Holder::decode(&text)) {
        Some(h) => Ok((h, age)),
        None if age < timeout() => Err(Liveness::Live(Holder::unknown())),
        None => Err(Liveness::Dead(None)),
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
    body: String,
    stop: Option<crossbeam_channel::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// Set when the heartbeat found the lease removed, or could not renew it for longer than
    /// the timeout (the process was stopped, the filesystem stalled): other processes may have
    /// judged it dead and taken over its work, so it must not go on writing as if they had not.
    lost: std::sync::Arc<std::sync::atomic::AtomicBool>,
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
        Ok(Some(Lease::renewed(path.to_path_buf(), body, timeout() / 4)))
    }

    /// Renews `path` with `body` every `every` (a quarter of the timeout) until dropped.
    fn renewed(path: PathBuf, body: String, every: Duration) -> Lease {
        let (stop, stopped) = crossbeam_channel::bounded::<()>(0);
        let lost = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (p, b, l) = (path.clone(), body.clone(), lost.clone());
        let thread = std::thread::Builder::new()
            .name("dist4d-lease".into())
            .spawn(move || {
                let mut renewed = std::time::Instant::now();
                while let Err(crossbeam_channel::RecvTimeoutError::Timeout) = stopped.recv_timeout(every) {
                    if renewed.elapsed() > timeout() || !renew(&p, &b) {
                        l.store(true, std::sync::atomic::Ordering::SeqCst);
                        return;
                    }
                    renewed = std::time::Instant::now();
                }
            })
            .ok();
        Lease { path, body, stop: Some(stop), thread, lost }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether the lease was lost (see the field).
    pub fn lost(&self) -> bool {
        self.lost.load(std::sync::atomic::Ordering::SeqCst)
    }
}

/// Rewrites a lease's bytes in place (the write moves its mtime, on the filesystem's clock).
/// False when it is gone: another process judged us dead and removed it (it is not recreated:
/// see [`Lease::lost`]).
fn renew(path: &Path, body: &str) -> bool {
    match OpenOptions::new().write(true).open(path) {
        Ok(f) => {
            if let Err(e) = f.write_all_at(body.as_bytes(), 0) {
                eprintln!("warning: cannot renew lease {}: {e}", path.display());
            }
            true
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
        Err(e) => {
            eprintln!("warning: cannot renew lease {}: {e}", path.display());
            true
        }
    }
}

/// Removes the file at `path` if it still holds `body` (a file another process put there
/// since is not ours to remove).
fn remove_if_ours(path: &Path, body: &str) {
    if fs::read_to_string(path).is_ok_and(|t| t == body) {
        let _ = fs::remove_file(path);
    }
}

/// Runs `take` holding `<path>.takeover`, an exclusive side file, so that of several processes
/// that found the same dead holder, one takes over and the others see its new claim. `None`
/// when another process is taking over now (the caller treats the item as held). A side file
/// older than the timeout was left by a taker that died: it is removed.
fn taking_over<T>(path: &Path, now: SystemTime, take: impl FnOnce() -> T) -> Option<T> {
    let guard =
        path.with_extension(format!("{}.takeover", path.extension().and_then(|e| e.to_str()).unwrap_or_default()));
    match OpenOptions::new().write(true).create_new(true).open(&guard) {
        Ok(_) => {
            let t = take();
            let _ = fs::remove_file(&guard);
            Some(t)
        }
        Err(_) => {
            let age = fs::metadata(&guard).and_then(|m| m.modified()).ok().and_then(|m| now.duration_since(m).ok());
            if age.is_some_and(|a| a > timeout()) {
                let _ = fs::remove_file(&guard);
            }
            None
        }
    }
}

impl Drop for Lease {
    fn drop(&mut self) {
        drop(self.stop.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        remove_if_ours(&self.path, &self.body);
    }
}

/// Takes the lease at `path`, taking it over from a dead holder. `Err(holder)` (as a plain
/// value in `Ok`) when a live process holds it, or another is taking it over right now.
pub fn acquire(path: &Path, me: &Holder, now: impl Fn() -> SystemTime) -> Result<std::result::Result<Lease, Holder>> {
    for _ in 0..8 {
        if let Some(lease) = Lease::create(path, me)? {
            return Ok(Ok(lease));
        }
        match judge(path, now()) {
            Liveness::Live(h) => return Ok(Err(h)),
            Liveness::Dead(_) => {
                // Judged again under the side file: another taker may have replaced it since.
                let taken = taking_over(path, now(), || match judge(path, now()) {
                    Liveness::Live(h) => Ok(Err(h)),
                    _ => {
                        let _ = fs::remove_file(path);
                        Lease::create(path, me).map(|l| l.ok_or_else(Holder::unknown))
                    }
                });
                match taken {
                    Some(r) => return r,
                    None => return Ok(Err(Holder::unknown())),
                }
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
    body: String,
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
        let create = || -> Result<Option<Claim>> {
            match OpenOptions::new().write(true).create_new(true).open(path) {
                Ok(mut f) => {
                    let body = me.encode();
                    f.write_all(body.as_bytes()).with_context(|| format!("writing {}", path.display()))?;
                    Ok(Some(Claim { path: path.to_path_buf(), body }))
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(None),
                Err(e) => Err(e).with_context(|| format!("creating claim {}", path.display())),
            }
        };
        for _ in 0..8 {
            if let Some(claim) = create()? {
                return Ok(Ok(claim));
            }
            match Claim::judge(path, leases, now) {
                Liveness::Live(h) => return Ok(Err(h)),
                Liveness::Dead(_) => {
                    // Of several processes that found the holder dead, one takes over (under a
                    // side file) and judges again first; the others find its claim live.
                    let taken = taking_over(path, now, || match Claim::judge(path, leases, now) {
                        Liveness::Live(h) => Ok(Err(h)),
                        _ => {
                            let _ = fs::remove_file(path);
                            create().map(|c| c.ok_or_else(Holder::unknown))
                        }
                    });
                    return taken.unwrap_or(Ok(Err(Holder::unknown())));
                }
                Liveness::Gone => {}
            }
        }
        anyhow::bail!("cannot take claim {}: it keeps changing hands", path.display())
    }

    /// A claim is live while its holder's writer lease is.
    pub fn judge(path: &Path, leases: &Path, now: SystemTime) -> Liveness {
        match read_holder(path, now) {
            Err(decided) => decided,
            Ok((h, _)) => match judge(&leases.join(format!("{}.lease", h.writer)), now) {
                Liveness::Live(_) => Liveness::Live(h),
                _ => Liveness::Dead(Some(h)),
            },
        }
    }
}

impl Drop for Claim {
    fn drop(&mut self) {
        remove_if_ours(&self.path, &self.body);
    }
}

/// Whether `path` is on a filesystem that other machines share (NFS, Lustre, GPFS, BeeGFS,
/// CephFS, SMB): there, a client's view of a directory may lag another node's changes by its
/// attribute and directory caches (up to a minute by default on NFS).
pub fn network_filesystem(path: &Path) -> bool {
    use std::os::unix::ffi::OsStrExt;
    let Ok(c) = std::ffi::CString::new(path.as_os_str().as_bytes()) else { return false };
    // SAFETY: a valid C string and a zeroed statfs the call fills.
    let mut st: libc::statfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::statfs(c.as_ptr(), &mut st) } != 0 {
        return false;
    }
    const NETWORK: [i64; 8] = [
        0x6969,      // NFS
        0x0BD0_0BD0, // Lustre
        0x4750_4653, // GPFS
        0x1983_0326, // BeeGFS
        0x00C3_6400, // CephFS
        0xFF53_4D42, // CIFS
        0xFE53_4D42, // SMB2
        0x6573_5546, // FUSE (sshfs and the like)
    ];
    NETWORK.contains(&(st.f_type as i64))
}

/// This machine's host name.
pub fn host_name() -> String {
    static H: OnceLock<String> = OnceLock::new();
    H.get_or_init(|| fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default().trim().to_string()).clone()
}

/// This boot of this machine, and this process's PID namespace: two containers that share a
/// host name but not their PIDs are two hosts here (their pids mean nothing to each other).
fn boot_id() -> String {
    static B: OnceLock<String> = OnceLock::new();
    B.get_or_init(|| {
        let boot = fs::read_to_string("/proc/sys/kernel/random/boot_id").unwrap_or_default();
        let pidns = fs::read_link("/proc/self/ns/pid").map(|p| p.display().to_string()).unwrap_or_default();
        format!("{}/{}", boot.trim(), pidns.trim_start_matches("pid:").trim_matches(|c| c == '[' || c == ']'))
    })
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
    fn a_lease_removed_by_others_is_lost_not_recreated() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.lease");
        let body = Holder::me("w").encode();
        fs::write(&path, &body).unwrap();
        let lease = Lease::renewed(path.clone(), body, Duration::from_millis(20));
        std::thread::sleep(Duration::from_millis(60));
        assert!(!lease.lost());
        fs::remove_file(&path).unwrap(); // judged dead by another process
        let t0 = std::time::Instant::now();
        while !lease.lost() {
            assert!(t0.elapsed() < Duration::from_secs(5), "never noticed");
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(!path.exists(), "not recreated: others may have taken over its work");
    }

    #[test]
    fn of_two_takers_of_a_dead_claim_one_gets_it_and_a_holder_removes_only_its_own_file() {
        let dir = tempfile::tempdir().unwrap();
        let (leases, path) = (dir.path().join("leases"), dir.path().join("leases/claims/x.claim"));
        fs::create_dir_all(path.parent().unwrap()).unwrap();
        let dead = Holder { writer: "gone".into(), ..Holder::me("gone") };
        fs::write(&path, dead.encode()).unwrap(); // its writer lease does not exist: dead
                                                  // Another process is taking it over right now (its side file is there): held.
        let side = dir.path().join("leases/claims/x.claim.takeover");
        fs::write(&side, b"").unwrap();
        let (b, c) = (Holder::me("writer-b"), Holder::me("writer-c"));
        let _b_lease = Lease::create(&leases.join("writer-b.lease"), &b).unwrap().unwrap();
        let _c_lease = Lease::create(&leases.join("writer-c.lease"), &c).unwrap().unwrap();
        assert!(Claim::take(&path, &leases, &b, SystemTime::now()).unwrap().is_err());
        fs::remove_file(&side).unwrap();
        let claim = Claim::take(&path, &leases, &b, SystemTime::now()).unwrap().expect("taken over");
        assert!(!side.exists(), "the side file goes with the takeover");
        assert_eq!(Claim::take(&path, &leases, &c, SystemTime::now()).unwrap().err(), Some(b.clone()));
        // Its file replaced meanwhile (it was judged dead and taken over): drop leaves that alone.
        fs::write(&path, c.encode()).unwrap();
        drop(claim);
        assert_eq!(fs::read_to_string(&path).unwrap(), c.encode());
        // A side file left by a taker that died goes once older than the timeout.
        fs::write(&side, b"").unwrap();
        let later = SystemTime::now() + timeout() * 2;
        assert!(taking_over(&path, later, || ()).is_none());
        assert!(!side.exists());
    }

    #[test]
    fn a_holder_is_judged_by_its_own_timeout() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("remote.lease");
        let patient =
            Holder { host: "elsewhere".into(), timeout_ms: timeout().as_millis() as u64 * 10, ..Holder::me("p") };
        fs::write(&path, patient.encode()).unwrap();
        let written = fs::metadata(&path).unwrap().modified().unwrap();
        assert!(matches!(judge(&path, written + timeout() * 2), Liveness::Live(_)), "it renews every 10 x ours / 4");
        assert!(matches!(judge(&path, written + timeout() * 11), Liveness::Dead(_)));
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
