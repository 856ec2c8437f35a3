//! Running a loaded pipeline for `run`, `eval`, `demo` and `merge`: the run options, the stop on
//! signals, the memory warning, the per-stage table and what the exit code says.

use crate::cli::PipelineArgs;
use crate::load::{load, refuse_dataset_root};
use anyhow::{Context, Result};
use dist4d_graph::Pipeline;
use dist4d_runtime::{exec::Engine, Access, ProgressMode, RunOptions, RunStatus, Store};
use dist4d_stages::Registry;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::Arc;

/// `run` and `eval`: loads the pipeline, checks it with `usable` (exit 2 when that fails), runs
/// it, returns it with its output folder and exit code (or the exit code of a pipeline that did
/// not load or was not usable).
pub fn run_pipeline(
    registry: &Registry,
    p: &PipelineArgs,
    usable: fn(&Pipeline) -> Result<()>,
    jobs: Option<usize>,
    fail_fast: bool,
    out: Option<PathBuf>,
    progress: &str,
    tweak: impl FnOnce(&mut RunOptions),
) -> Result<Result<(Pipeline, PathBuf, ExitCode), ExitCode>> {
    let pipeline = match load(p, registry)? {
        Ok(x) => x,
        Err(code) => return Ok(Err(code)),
    };
    if let Err(e) = usable(&pipeline) {
        eprintln!("error: {e:#}");
        return Ok(Err(ExitCode::from(2)));
    }
    if let Some(code) = refuse_dataset_root(p, registry, &pipeline) {
        return Ok(Err(code));
    }
    let (cache, out_dir) = (p.cache_dir(), p.out_dir(out, &pipeline));
    let mut opts = RunOptions {
        fail_fast,
        outer_items: p.scenes.clone(),
        limit: p.limit,
        shard: p.shard,
        out_dir: Some(out_dir.clone()),
        progress: progress_mode(progress),
        sets: p.sets.clone(),
        ..Default::default()
    };
    if let Some(j) = jobs {
        opts.jobs = j;
    }
    tweak(&mut opts);
    let (code, _) = execute(registry, &pipeline, &cache, &out_dir, opts)?;
    Ok(Ok((pipeline, out_dir, code)))
}

/// `--progress`: `auto` is bars on a terminal and lines otherwise, every `DIST4D_PROGRESS_SECS`
/// (10 s) in both `auto` and `lines`.
pub fn progress_mode(name: &str) -> ProgressMode {
    use std::io::IsTerminal;
    let lines =
        || ProgressMode::Lines(std::env::var("DIST4D_PROGRESS_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(10));
    match name {
        "off" => ProgressMode::Off,
        "lines" => lines(),
        _ if std::io::stderr().is_terminal() => ProgressMode::Auto,
        _ => lines(),
    }
}

/// Runs a loaded pipeline and prints the per-stage table; the exit code says how it ended.
pub fn execute(
    registry: &Registry,
    pipeline: &Pipeline,
    cache: &Path,
    out_dir: &Path,
    opts: RunOptions,
) -> Result<(ExitCode, dist4d_runtime::RunRecord)> {
    let dataset = registry.open_dataset(pipeline)?;
    let ops = registry.operators(pipeline)?;
    if let Some(warning) = memory_warning(pipeline, &ops, opts.jobs, machine_memory()) {
        eprintln!("{warning}");
    }
    let store = Store::open(cache, Access::Shared).with_context(|| format!("opening the store {}", cache.display()))?;
    let stopped_by = stop_on_signals(opts.cancel.clone())?;
    let engine = Engine { pipeline, dataset: dataset.as_ref(), operators: &ops, store: &store };
    let rec = engine.run(&opts)?.record;
    println!(
        "{:<16} {:<18} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9}",
        "stage", "kind", "total", "executed", "cached", "failed", "skipped", "n/a", "seconds"
    );
    for s in &rec.stages {
        println!(
            "{:<16} {:<18} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9.2}",
            s.stage, s.kind, s.total, s.executed, s.cached, s.failed, s.skipped, s.not_applicable, s.seconds
        );
    }
    // Once per stage, why it made nothing for some items: an output that is just missing, or a
    // stage that made nothing at all, would otherwise go unexplained.
    for line in dist4d_runtime::nothing::lines(pipeline, &rec.stages) {
        println!("{line}");
    }
    // Tasks an interrupted run never started are in no counter: what is left of the totals.
    let not_started: u64 = rec
        .stages
        .iter()
        .map(|s| {
            s.total.saturating_sub(
                s.executed + s.cached + s.failed + s.skipped + s.not_applicable + s.missing + s.deferred,
            )
        })
        .sum();
    if rec.status == RunStatus::Interrupted && rec.missing() + not_started > 0 {
        println!(
            "stopped: {} tasks were cut short or not started; rerun the same command to finish (nothing of them was stored)",
            rec.missing() + not_started
        );
    } else if rec.missing() > 0 {
        println!(
            "missing: {} tasks neither cached nor executed (a merge collects what the shards made; the next `dist4d slurm` submits the rest)",
            rec.missing()
        );
    }
    if rec.deferred() > 0 {
        println!(
            "deferred: {} tasks of the stages served by model workers, and what reads them, are left to a later run (--defer-workers; the GPU array makes them)",
            rec.deferred()
        );
    }
    let recomputed: u64 = rec.stages.iter().map(|s| s.recomputed).sum();
    if recomputed > 0 {
        eprintln!(
            "note: finished tasks were run again {recomputed} times because the store had lost or corrupted their outputs"
        );
    }
    for f in &rec.failures {
        // Item names come from the dataset: control characters are shown, not sent to the terminal.
        eprintln!("failed: {} {}: {}", f.stage, printable(&f.item), printable(&f.error));
    }
    println!(
        "run {} {:?} in {:.2}s: {} executed, {} cached, {} failed; {} files in {}",
        rec.id,
        rec.status,
        rec.seconds,
        rec.executed(),
        rec.cached(),
        rec.failures.len(),
        rec.exported,
        out_dir.display()
    );
    let code = match rec.status {
        RunStatus::Complete => ExitCode::SUCCESS,
        // 128 + the signal, as a shell reports a process that the signal ended.
        RunStatus::Interrupted => ExitCode::from(128 + stopped_by.load(Ordering::SeqCst).clamp(1, 127) as u8),
        RunStatus::Failed | RunStatus::Stopped | RunStatus::Incomplete | RunStatus::Running => ExitCode::from(1),
    };
    Ok((code, rec))
}

/// `s` with control characters escaped (`\u{1b}`), line breaks of multi-line errors kept.
pub fn printable(s: &str) -> String {
    s.chars()
        .map(|c| if c.is_control() && c != '\n' { c.escape_default().to_string() } else { c.to_string() })
        .collect()
}

/// A warning when `jobs` tasks of the stage with the largest bounded peak (see
/// `Operator::peak_memory`) could together need more than `memory` bytes: each task keeps to its
/// budget, but `--jobs` of them run at once.
fn memory_warning(
    pipeline: &Pipeline,
    ops: &[Option<Box<dyn dist4d_runtime::Operator>>],
    jobs: usize,
    memory: Option<u64>,
) -> Option<String> {
    let memory = memory?;
    let (node, peak) =
        ops.iter().enumerate().filter_map(|(n, op)| Some((n, op.as_ref()?.peak_memory()?))).max_by_key(|(_, p)| *p)?;
    let need = peak.saturating_mul(jobs as u64);
    let gib = |b: u64| format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64);
    (need > memory).then(|| {
        format!(
            "warning: --jobs {jobs} x {} per task of stage `{}` = {}, more than this machine's {} of memory: a run \
             whose tasks of that stage meet at their peak would be killed by the kernel; lower --jobs to {}",
            gib(peak),
            pipeline.nodes[node].name,
            gib(need),
            gib(memory),
            (memory / peak).max(1)
        )
    })
}

/// The machine's memory (MemTotal of /proc/meminfo), if it can be read.
fn machine_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let kib: u64 =
        text.lines().find_map(|l| l.strip_prefix("MemTotal:"))?.trim().trim_end_matches("kB").trim().parse().ok()?;
    Some(kib * 1024)
}

/// Stops a run cleanly on SIGINT (Ctrl-C), SIGTERM (what Slurm, systemd and `kill` send before
/// SIGKILL) and SIGHUP (its terminal closed): nothing new starts, running tasks stop at their next
/// cancellation point (`dist4d_types::cancel`) or finish, the run record is written. A second
/// signal leaves at once, which is safe too (every file is written whole or not at all), and
/// kills the model workers' process groups first. Returns
/// the number of the signal that stopped the run (SIGINT until one arrives).
fn stop_on_signals(cancel: Arc<AtomicBool>) -> Result<Arc<AtomicI32>> {
    use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
    let stopped_by = Arc::new(AtomicI32::new(SIGINT));
    let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM, SIGHUP])
        .context("listening for SIGINT, SIGTERM and SIGHUP")?;
    let by = stopped_by.clone();
    std::thread::Builder::new().name("dist4d-signals".into()).spawn(move || {
        for signal in signals.forever() {
            if cancel.swap(true, Ordering::SeqCst) {
                // `exit` runs no Drop: the workers' process groups are killed here, or they
                // would run on (and hold their GPU) after dist4d is gone.
                dist4d_runtime::worker::kill_all_workers();
                std::process::exit(128 + signal);
            }
            by.store(signal, Ordering::SeqCst);
            // Long tasks stop at their next cancellation point instead of running to their end.
            dist4d_types::cancel::request();
            let name = if signal == SIGTERM {
                "SIGTERM"
            } else if signal == SIGHUP {
                "SIGHUP"
            } else {
                "Ctrl-C"
            };
            eprintln!(
                "\nstopping on {name}: running tasks stop at their next cancellation point, nothing new starts (signal \
                 again to quit at once)"
            );
        }
    })?;
    Ok(stopped_by)
}
