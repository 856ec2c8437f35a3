//! The `dist4d` command line: argument parsing (`cli`) and dispatch to one module per command
//! (`commands`); `execute` runs a pipeline for the commands that do, `slurm` writes job scripts.

use anyhow::Result;
use clap::Parser;
use cli::{Cli, Command};
use dist4d_stages::Registry;
use std::process::ExitCode;

mod cli;
mod commands;
mod execute;
mod load;
mod slurm;

// Stages allocate and free image-sized buffers (a 1600x900 f32 map is 5.8 MB) many times a
// second; glibc hands each one back to the kernel and faults it in again, which cost as much
// system time as the stages' own work. mimalloc keeps them.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// mimalloc's `mi_option_purge_delay`: its place in mimalloc 3's `mi_option_e` (the Rust bindings
/// name no constant for it; a test below checks the place by its default).
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// mimalloc 3 still gives freed memory back to the kernel a second after it is freed: a run's
/// per-task buffers were faulted in and zeroed again ~50 000 times for 48 images (8% of its CPU).
/// Never purging keeps them for the next task; peak memory is the same (the buffers of the tasks
/// in flight), and a process ends with its run. `MIMALLOC_PURGE_DELAY` in the environment wins.
fn keep_freed_memory() {
    // SAFETY: plain reads and writes of mimalloc's option table; an option set in the environment
    // (read at load) is left alone by `set_default`. A mimalloc whose option at that place does not
    // hold the documented default of 1000 ms is not the one this was written for: left alone too.
    unsafe {
        if libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY) == 1000 {
            libmimalloc_sys::mi_option_set_default(MI_OPTION_PURGE_DELAY, -1);
        }
    }
}

fn main() -> ExitCode {
    keep_freed_memory();
    // Whichever way main ends (a return, an error, a panic unwinding), no model worker outlives
    // it: the pools end theirs, and this ends any left (docs/security.md, "Signals").
    let _workers = dist4d_runtime::worker::KillWorkersOnDrop;
    let cli = Cli::parse();
    if matches!(cli.command, Command::Runs { .. } | Command::Graph { .. } | Command::Check { .. }) {
        // Commands that only print and start no worker end quietly when their reader goes
        // (`dist4d runs --json | head`), as Unix tools do, instead of panicking on the closed
        // pipe. Not for the others: a worker's closed stdin must stay an error, not a signal.
        // SAFETY: setting a signal's disposition to the default has no memory effects.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    match dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(1)
        }
    }
}

/// Runs the command; its exit code, or the error `main` prints.
fn dispatch(cli: Cli) -> Result<ExitCode> {
    let registry = Registry::default();
    match cli.command {
        Command::Check { p } => commands::check::run(&registry, &p),
        Command::Graph { p } => commands::graph::run(&registry, &p),
        Command::Explain { p, out } => commands::explain::run(&registry, &p, out),
        Command::Eval { p, jobs, out, progress } => commands::eval::run(&registry, &p, jobs, out, &progress),
        Command::Run { p, jobs, fail_fast, out, progress, group, defer_workers } => {
            commands::run::run(&registry, &p, jobs, fail_fast, out, &progress, group, defer_workers)
        }
        Command::Slurm { p, out, submit } => commands::slurm::run(&registry, &p, out, &submit),
        Command::Merge { p, out, group, shards, gpu_shards, no_retry, jobs, progress } => {
            commands::merge::run(&registry, &p, out, &group, shards, gpu_shards, no_retry, jobs, &progress)
        }
        Command::Runs { cache, json } => commands::runs::run(cache, json),
        Command::Demo { dir, keyframes, width, height, progress } => {
            commands::demo::run(&dir, keyframes, width, height, &progress)
        }
        Command::Synth(args) => commands::synth::run(args),
        Command::Occ3dAnnotations { out, val } => commands::occ3d_annotations::run(out, val),
        Command::Export12Hz { root, version, out, drop_lone_tracks } => {
            commands::export_12hz::run(root, version, out, drop_lone_tracks)
        }
        Command::ExportInfos { root, version, out, path_prefix, max_sweeps, split } => {
            commands::export_infos::run(root, version, out, path_prefix, max_sweeps, split)
        }
        Command::Depthroot { out } => commands::depthroot::run(out),
        Command::Verify { out, store, cache } => commands::verify::run(out, store, cache),
        Command::Gc { cache, keep_runs, max_size, dry_run } => commands::gc::run(cache, keep_runs, max_size, dry_run),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_purge_delay_option_is_where_keep_freed_memory_sets_it() {
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
            return;
        }
        // SAFETY: reads of mimalloc's option table.
        let (delay, next) = unsafe {
            (
                libmimalloc_sys::mi_option_get(super::MI_OPTION_PURGE_DELAY),
                libmimalloc_sys::mi_option_get(super::MI_OPTION_PURGE_DELAY + 1),
            )
        };
        // mimalloc 3's defaults: purge_delay 1000 ms, then use_numa_nodes 0.
        assert_eq!((delay, next), (1000, 0), "mimalloc's option numbering changed: update MI_OPTION_PURGE_DELAY");
        super::keep_freed_memory();
        assert_eq!(unsafe { libmimalloc_sys::mi_option_get(super::MI_OPTION_PURGE_DELAY) }, -1);
    }
}
