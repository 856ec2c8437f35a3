//! Stopping long computations when the process is asked to stop (SIGINT, SIGTERM, SIGHUP).
//!
//! A task of MultiViewStereo with hundreds of planes, an exact occupancy reference at 0.1 m or a
//! depth completion of a large image runs for minutes; a run that waits for its running tasks to
//! end before it stops would ignore SIGTERM (Slurm's, systemd's) for that long. So long loops call
//! [`check`] at their cancellation points (once per plane, row block or iteration: microseconds
//! apart, never in an inner pixel loop), which returns an error once [`request`] was called; the
//! runtime counts a task that ends so while the run is stopping as not executed, and nothing of it
//! is stored.
//!
//! The flag is process-wide: the signal arrives for the process, and stages call [`check`] from
//! pure functions deep inside crates that know nothing of a run (the synthetic world's renderer).

use std::sync::atomic::{AtomicBool, Ordering};

static REQUESTED: AtomicBool = AtomicBool::new(false);

/// Asks every running computation to stop at its next cancellation point.
pub fn request() {
    REQUESTED.store(true, Ordering::SeqCst);
}

/// Whether a stop was requested.
pub fn requested() -> bool {
    REQUESTED.load(Ordering::Relaxed)
}

/// A cancellation point: an error once a stop was requested.
pub fn check() -> Result<(), Stopped> {
    if requested() {
        Err(Stopped)
    } else {
        Ok(())
    }
}

/// The error of a computation stopped at a cancellation point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stopped;

impl std::fmt::Display for Stopped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("stopped: the process was asked to stop")
    }
}

impl std::error::Error for Stopped {}
