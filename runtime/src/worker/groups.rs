//! The process groups of the workers alive in this process, so that every way out of it ends
//! them. A worker runs in a group of its own (the model and whatever it started), and nothing
//! ends a process group when its parent exits: a worker left behind keeps its GPU memory and
//! runs on. `Worker` removes its group from here once it has killed and reaped it; what is
//! still here when the process leaves (a second signal calls `std::process::exit`, which runs no
//! `Drop`; the end of `main`) is killed by [`kill_all_workers`].

use std::collections::BTreeSet;
use std::process::{Child, Command};
use std::sync::{Mutex, MutexGuard};

/// A set of live process groups, closed once they have all been killed.
pub struct Groups {
    state: Mutex<State>,
}

struct State {
    live: BTreeSet<libc::pid_t>,
    /// Set by [`Groups::kill_all`]: the process is on its way out, so no worker starts.
    closed: bool,
}

/// The workers of this process.
pub(crate) static WORKERS: Groups = Groups::new();

/// Kills the process group of every worker this process started and has not reaped: for the
/// ways out of the process that skip `Worker`'s `Drop` (call it before `std::process::exit`, and
/// at the end of `main`). No worker starts after it.
pub fn kill_all_workers() {
    WORKERS.kill_all();
}

/// Calls [`kill_all_workers`] when dropped: held by `main`, it ends the workers whichever way
/// `main` ends (a return, an error, a panic unwinding).
pub struct KillWorkersOnDrop;

impl Drop for KillWorkersOnDrop {
    fn drop(&mut self) {
        kill_all_workers();
    }
}

impl Groups {
    pub const fn new() -> Groups {
        Groups { state: Mutex::new(State { live: BTreeSet::new(), closed: false }) }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic elsewhere while holding the lock leaves a set that is still right.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Spawns `command` (which must make the child a process group leader) and adds its group,
    /// under the lock: a [`Groups::kill_all`] at the same time kills it or comes first and
    /// refuses it, so no worker slips between the two.
    pub fn spawn(&self, command: &mut Command) -> std::io::Result<Child> {
        let mut s = self.lock();
        if s.closed {
            return Err(std::io::Error::other("the engine is exiting: no worker starts"));
        }
        let child = command.spawn()?;
        s.live.insert(child.id() as libc::pid_t);
        Ok(child)
    }

    /// Forgets the group of a worker that has been killed and reaped.
    pub fn remove(&self, pgid: libc::pid_t) {
        self.lock().live.remove(&pgid);
    }

    /// Sends SIGKILL to every live group, and closes the set.
    pub fn kill_all(&self) {
        let mut s = self.lock();
        s.closed = true;
        for &pgid in &s.live {
            kill_group(pgid);
        }
    }
}

/// SIGKILL to process group `pgid`.
pub fn kill_group(pgid: libc::pid_t) {
    // SAFETY: kill(2) with a negative pid signals a process group; it has no memory effects. The
    // groups signalled are those of workers not yet reaped, whose ids cannot have been reused.
    unsafe {
        libc::kill(-pgid, libc::SIGKILL);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::process::CommandExt;

    #[test]
    fn kill_all_ends_every_group_and_refuses_new_ones() {
        let groups = Groups::new();
        let mut children: Vec<Child> =
            (0..2).map(|_| groups.spawn(Command::new("sleep").arg("30").process_group(0)).unwrap()).collect();
        groups.kill_all();
        for c in &mut children {
            use std::os::unix::process::ExitStatusExt;
            assert_eq!(c.wait().unwrap().signal(), Some(libc::SIGKILL));
        }
        let err = groups.spawn(Command::new("sleep").arg("30").process_group(0)).unwrap_err();
        assert!(err.to_string().contains("exiting"), "{err}");
    }
}
