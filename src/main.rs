//! The `dist4d` command line: argument parsing and wiring only.

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use dist4d_graph::{load_file, Pipeline};
use dist4d_runtime::{exec::Engine, Access, ProgressMode, RunOptions, RunStatus, Store};
use dist4d_stages::Registry;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::Arc;

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

#[derive(Parser)]
#[command(
    name = "dist4d",
    version,
    about = "Declared, reproducible, incremental data pipelines for 4D driving-scene generation"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Args, Clone)]
struct PipelineArgs {
    /// The pipeline file (RON).
    pipeline: PathBuf,
    /// Override a param or dataset field: `stage.param=value`, `dataset.root=PATH` (repeatable).
    #[arg(long = "set", value_name = "TARGET.FIELD=VALUE")]
    sets: Vec<String>,
    /// The store (cache) directory [default: .dist4d/ beside the pipeline file].
    #[arg(long)]
    cache: Option<PathBuf>,
    /// Only these scenes, by name (comma-separated).
    #[arg(long, value_delimiter = ',')]
    scenes: Option<Vec<String>>,
    /// Only the first N frames of each scene.
    #[arg(long, value_name = "N")]
    limit: Option<u32>,
    /// Only shard I of N of the scenes (0 <= I < N; scenes dealt to shards by size, the same on
    /// every machine): run the N shards at once, anywhere, against one shared --cache.
    #[arg(long, value_name = "I/N", value_parser = parse_shard)]
    shard: Option<(u32, u32)>,
}

impl PipelineArgs {
    /// `--cache`, or `.dist4d/` beside the pipeline file.
    fn cache_dir(&self) -> PathBuf {
        self.cache.clone().unwrap_or_else(|| beside(&self.pipeline, ".dist4d"))
    }

    /// `--out` when given, else `out/<pipeline name>/` beside the pipeline file.
    fn out_dir(&self, out: Option<PathBuf>, pipeline: &Pipeline) -> PathBuf {
        out.unwrap_or_else(|| beside(&self.pipeline, &format!("out/{}", pipeline.name)))
    }
}

/// `I/N` with 0 <= I < N.
fn parse_shard(s: &str) -> std::result::Result<(u32, u32), String> {
    let (i, n) = s.split_once('/').ok_or_else(|| format!("`{s}` is not I/N (e.g. 0/4)"))?;
    let (i, n): (u32, u32) = (
        i.trim().parse().map_err(|_| format!("`{i}` in `{s}` is not a number"))?,
        n.trim().parse().map_err(|_| format!("`{n}` in `{s}` is not a number"))?,
    );
    if n == 0 || i >= n {
        return Err(format!("shard `{s}`: I must be 0 to N - 1 and N at least 1"));
    }
    Ok((i, n))
}

#[derive(Subcommand)]
enum Command {
    /// Run a pipeline: only tasks whose inputs, params or stage version changed are executed.
    ///
    /// Rerunning the same command after a crash or Ctrl-C continues where it stopped. Exit code: 0 when
    /// every task finished, 1 when some failed (listed at the end), 2 for a bad pipeline, 130 when interrupted.
    ///
    /// Example: dist4d run pipelines/lidar_depth.ron --set dataset.root=/data/nuscenes --jobs 8
    Run {
        #[command(flatten)]
        p: PipelineArgs,
        /// Worker threads, 1 to 1024 [default: the number of cores].
        #[arg(long, short, value_parser = parse_jobs)]
        jobs: Option<usize>,
        /// Stop at the first failing task.
        #[arg(long)]
        fail_fast: bool,
        /// Where exported files go [default: out/<pipeline name>/ beside the pipeline file].
        #[arg(long)]
        out: Option<PathBuf>,
        /// Progress: auto (bars on a terminal, lines otherwise), lines, off.
        #[arg(long, default_value = "auto")]
        progress: String,
        /// Record the run as part of group NAME: the shards and merge of one cluster submission
        /// show as one run in `dist4d runs` (the job scripts of `dist4d slurm` set it).
        #[arg(long, value_name = "NAME")]
        group: Option<String>,
        /// Leave the stages served by model workers to a later run: their tasks are taken from
        /// the cache or left missing (the CPU array of `dist4d slurm --gres`).
        #[arg(long)]
        defer_workers: bool,
    },
    /// Submit a pipeline to Slurm: one job array over the scenes that have work left (shard i of
    /// N per array task, all against the shared --cache), and a merge job after it.
    ///
    /// Plans on this node: scenes whose tasks are all cached get no shard. Writes the job scripts
    /// and logs into <cache>/slurm/<group>/ (put the store on the shared filesystem). With --gres,
    /// the stages served by model workers go to a second array on GPU nodes, after the first.
    /// The merge job reads what the shards recorded in the store, retries items that failed,
    /// and writes the index and run report; rerun the same command to submit what is still
    /// missing. See docs/cluster.md.
    ///
    /// Example: dist4d slurm pipelines/curation.ron --cache /shared/d4/store --out /shared/d4/out --shards 64 --array-limit 16 --partition cpu --sbatch=--time=4:00:00
    Slurm {
        #[command(flatten)]
        p: PipelineArgs,
        /// Where exported files go [default: out/<pipeline name>/ beside the pipeline file].
        #[arg(long)]
        out: Option<PathBuf>,
        #[command(flatten)]
        submit: slurm::Submit,
    },
    /// The merge job of a `dist4d slurm` submission: reads what the group's shards recorded,
    /// retries the scenes with failed items, collects everything else from the cache (a lost
    /// shard's missing work is reported, not redone here), and writes the index and run record.
    ///
    /// Exit code 0 when every task is done, 1 when some failed or are missing.
    Merge {
        #[command(flatten)]
        p: PipelineArgs,
        /// Where exported files go [default: out/<pipeline name>/ beside the pipeline file].
        #[arg(long)]
        out: Option<PathBuf>,
        /// The group of the submission.
        #[arg(long)]
        group: String,
        /// Tasks of its CPU array.
        #[arg(long)]
        shards: u32,
        /// Tasks of its GPU array, if it had one.
        #[arg(long)]
        gpu_shards: Option<u32>,
        /// List the failed items instead of retrying them.
        #[arg(long)]
        no_retry: bool,
        /// Worker threads [default: the number of cores].
        #[arg(long, short, value_parser = parse_jobs)]
        jobs: Option<usize>,
        #[arg(long, default_value = "lines")]
        progress: String,
    },
    /// Run a pipeline (cached tasks are not redone) and tabulate the scores of its EvalDepth
    /// stages: Abs Rel, Sq Rel, RMSE, RMSE log, delta < 1.25^k and the bad-pixel rates (relative
    /// error > 10%, > 25%), raw and median-scaled, per camera and averaged over cameras, for each
    /// reference (gt, gt_above_lidar, gt_moving, lidar, lidar_multi, holdout); against the dense ground truth
    /// also sky IoU, sky given a structure depth, structure given the sky depth and the iBims-1
    /// depth-boundary accuracy and completeness (px).
    ///
    /// Example: dist4d eval pipelines/curation.ron --set aggregate.holdout=0.2
    Eval {
        #[command(flatten)]
        p: PipelineArgs,
        /// Worker threads, 1 to 1024 [default: the number of cores].
        #[arg(long, short, value_parser = parse_jobs)]
        jobs: Option<usize>,
        /// Where exported files go [default: out/<pipeline name>/ beside the pipeline file].
        #[arg(long)]
        out: Option<PathBuf>,
        /// Progress: auto (bars on a terminal, lines otherwise), lines, off. On by default, as for
        /// `run`: an eval runs the pipeline, often for minutes.
        #[arg(long, default_value = "auto")]
        progress: String,
    },
    /// Check a pipeline file without running it: every problem, with file:line:column.
    ///
    /// Example: dist4d check pipelines/lidar_depth.ron --set project.min_depth=2
    Check {
        #[command(flatten)]
        p: PipelineArgs,
    },
    /// Say, per stage, how many tasks are cached, will run or failed, and why each would run.
    ///
    /// Outputs that are exported and read by no stage are kept in the output folder only, so
    /// whether their tasks are cached depends on the folder a run would export to: give the
    /// same --out as the run.
    ///
    /// Example: dist4d explain pipelines/lidar_depth.ron --set project.min_depth=2
    Explain {
        #[command(flatten)]
        p: PipelineArgs,
        /// The output folder of the run to explain [default: out/<pipeline name>/ beside the pipeline file].
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Print the stage DAG as Graphviz DOT.
    ///
    /// Example: dist4d graph pipelines/lidar_depth.ron | dot -Tsvg > dag.svg
    Graph {
        #[command(flatten)]
        p: PipelineArgs,
    },
    /// List the runs recorded in a store: when, pipeline, status, counts, dataset, output folder
    /// and --set values.
    ///
    /// Example: dist4d runs --cache pipelines/.dist4d --json
    Runs {
        /// The store directory [default: pipelines/.dist4d, the store of `dist4d run
        /// pipelines/x.ron`, else .dist4d].
        #[arg(long)]
        cache: Option<PathBuf>,
        /// Print the run records as JSON (newest last).
        #[arg(long)]
        json: bool,
    },
    /// Synthesize a nuScenes-format dataset of a procedural street, with exact ground truth.
    ///
    /// Deterministic per seed. Writes v1.0-mini/ tables, samples/, sweeps/, lidarseg/, maps/ and
    /// groundtruth/ (dense depth EXR and semantic PNG per camera image). Example:
    /// dist4d synth --out data/synth --keyframes 10 --width 800 --height 450
    Synth {
        /// The dataset folder to create (must not exist, or hold the same synthetic dataset).
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long, default_value_t = 1)]
        scenes: u32,
        /// Keyframes (2 Hz samples) per scene.
        #[arg(long, default_value_t = 40)]
        keyframes: u32,
        #[arg(long, default_value_t = 1600)]
        width: u32,
        #[arg(long, default_value_t = 900)]
        height: u32,
        /// Also write the 12 Hz camera sweeps between keyframes.
        #[arg(long)]
        camera_sweeps: bool,
        /// Write LiDAR keyframes only (no 20 Hz sweeps in between).
        #[arg(long)]
        no_lidar_sweeps: bool,
        /// Skip the ground-truth depth and semantic images.
        #[arg(long)]
        no_ground_truth: bool,
    },
    /// Write the 12 Hz nuScenes tables ASAP's users load: every round of the surround cameras a
    /// `sample`, with its images, its LiDAR sweep and boxes interpolated to its time.
    ///
    /// Writes ROOT/interp_12Hz_<split>/ (load it with the devkit: NuScenes(version='interp_12Hz_mini',
    /// dataroot=ROOT)) beside the version's tables, which it leaves as they are; an existing folder
    /// is replaced whole. See docs/datasets.md, "The 12 Hz tables". Example:
    /// dist4d export-12hz --root /data/nuscenes --version v1.0-trainval
    #[command(name = "export-12hz")]
    Export12Hz {
        /// The nuScenes root (holding v1.0-*/, samples/, sweeps/).
        #[arg(long)]
        root: PathBuf,
        /// The table folder to read.
        #[arg(long, default_value = "v1.0-mini")]
        version: String,
        /// Where the tables go [default: ROOT/interp_12Hz_<split>, e.g. interp_12Hz_mini].
        #[arg(long)]
        out: Option<PathBuf>,
        /// Leave out the boxes of a track annotated on only one of the keyframes around a sample
        /// (ASAP's rule) instead of extrapolating them with their velocity for up to half an interval.
        #[arg(long)]
        drop_lone_tracks: bool,
    },
    /// Write the info pickles nuScenes-based generators train on (MagicDrive, MagicDriveDiT,
    /// UniScene, DiST-4D), as MagicDrive-V2's converter writes them, for every split of the version.
    ///
    /// v1.0-* gives nuscenes_infos_{train,val}.pkl; interp_12Hz_* (the folder export-12hz writes,
    /// or ASAP's) gives nuscenes_interp_12Hz_infos_{train,val}_with_bid.pkl. Each file is written
    /// whole or not at all. See docs/interop.md. Example:
    /// dist4d export-infos --root /data/nuscenes --version interp_12Hz_trainval --out data/nuscenes_mmdet3d-12Hz
    #[command(name = "export-infos")]
    ExportInfos {
        /// The nuScenes root (holding the version's table folder).
        #[arg(long)]
        root: PathBuf,
        /// The table folder: v1.0-trainval, v1.0-mini, v1.0-test, interp_12Hz_trainval, interp_12Hz_mini, ...
        #[arg(long)]
        version: String,
        /// Where the pickles go [default: ROOT, as the converter writes].
        #[arg(long)]
        out: Option<PathBuf>,
        /// What lidar_path and data_path start with: the converter's --root-path as typed, which the
        /// training code opens relative to its working directory.
        #[arg(long, default_value = "./data/nuscenes")]
        path_prefix: String,
        /// LiDAR sweeps per info [default: 10 for v1.0-*, 0 at 12 Hz, as MagicDrive-V2's scripts run].
        #[arg(long)]
        max_sweeps: Option<usize>,
        /// Write only this split (train, val or test); repeat for several [default: every split].
        #[arg(long)]
        split: Vec<String>,
    },
    /// Index the DiST-4D depth files an export wrote (pipelines/dist4d_layout.ron) in
    /// OUT/nus_sampletoken2depthroot.json: sample token -> its folder, for DiST-4D's loaders.
    ///
    /// Run it after every run (or every shard) into OUT; it lists exactly the samples that have
    /// <folder>/<CAMERA>/refined_depth.npz. See docs/interop.md. Example:
    /// dist4d depthroot pipelines/out/dist4d_layout
    #[command(name = "depthroot")]
    Depthroot {
        /// The export folder (the pipeline's --out).
        out: PathBuf,
    },
    /// Merge the per-scene parts of Occ3D's annotations.json that `pipelines/occupancy.ron`
    /// exports (OUT/occ3d/scenes/<scene>.json) into OUT/annotations.json, with the splits.
    ///
    /// Example: dist4d occ3d-annotations pipelines/out/occupancy --val scene-0103,scene-0916
    #[command(name = "occ3d-annotations")]
    Occ3dAnnotations {
        /// The occupancy pipeline's output folder.
        out: PathBuf,
        /// The scenes of the validation split (comma-separated); the others are training scenes.
        #[arg(long, value_delimiter = ',')]
        val: Vec<String>,
    },
    /// The built-in default: synthesize a small dataset (if not there yet) and run the shipped
    /// pipeline on it, then say where everything is.
    ///
    /// Example: dist4d demo --dir demo
    Demo {
        /// Where the data, the pipeline, the cache and the outputs go.
        #[arg(long, default_value = "demo")]
        dir: PathBuf,
        #[arg(long, default_value_t = 6)]
        keyframes: u32,
        #[arg(long, default_value_t = 800)]
        width: u32,
        #[arg(long, default_value_t = 450)]
        height: u32,
        /// Progress: auto, lines, off.
        #[arg(long, default_value = "auto")]
        progress: String,
    },
    /// Check every exported file of an output folder against what dist4d wrote there, or (with
    /// --store) every blob and record of a store.
    ///
    /// Hashes each file the folder's manifest lists. Exit code 0 when all are intact, 1 when some
    /// are modified or missing (a rerun of the pipeline rewrites them). With --store, reads every
    /// task record and hashes every blob of the store named by --cache, writing nothing: exit code
    /// 1 when something is damaged or was written by a newer dist4d. Examples: dist4d verify
    /// out/curation; dist4d verify --store --cache pipelines/.dist4d
    Verify {
        /// The output folder (a run's --out).
        #[arg(required_unless_present = "store")]
        out: Option<PathBuf>,
        /// Check the store (--cache) instead: every blob against its digest, every record's checksum.
        #[arg(long)]
        store: bool,
        /// The store directory, with --store [default: pipelines/.dist4d, the store of `dist4d run
        /// pipelines/x.ron`, else .dist4d].
        #[arg(long, requires = "store")]
        cache: Option<PathBuf>,
    },
    /// Remove cached records and blobs that the last N runs did not use.
    ///
    /// Needs the store alone (no run in progress), except with --dry-run, which only reads it.
    /// Example: dist4d gc --cache pipelines/.dist4d --keep-runs 3 --max-size 50G
    Gc {
        /// The store directory [default: pipelines/.dist4d, the store of `dist4d run
        /// pipelines/x.ron`, else .dist4d].
        #[arg(long)]
        cache: Option<PathBuf>,
        /// Keep what the newest N runs used.
        #[arg(long, default_value_t = 5)]
        keep_runs: usize,
        /// Keep at most this many bytes of blobs (suffixes K, M, G), dropping older runs first.
        #[arg(long, value_parser = parse_size)]
        max_size: Option<u64>,
        /// Say what would be removed, and remove nothing (works on a store it cannot write).
        #[arg(long)]
        dry_run: bool,
    },
}

fn parse_size(s: &str) -> Result<u64, String> {
    let s = s.trim();
    let (num, mult) = match s.chars().last() {
        Some('K' | 'k') => (&s[..s.len() - 1], 1u64 << 10),
        Some('M' | 'm') => (&s[..s.len() - 1], 1 << 20),
        Some('G' | 'g') => (&s[..s.len() - 1], 1 << 30),
        Some('T' | 't') => (&s[..s.len() - 1], 1 << 40),
        _ => (s, 1),
    };
    num.trim()
        .parse::<f64>()
        .map(|n| (n * mult as f64) as u64)
        .map_err(|_| format!("`{s}` is not a size like 500M or 20G"))
}

/// Most worker threads `--jobs` takes: beyond the hardware threads of the largest machines,
/// where more threads only add stacks and contention (10,000 took 94 s and 2.7 GB to start).
const MAX_JOBS: usize = 1024;

/// `--jobs`: a thread count in 1..=MAX_JOBS (0 used to mean 1 without saying so).
fn parse_jobs(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("at least 1 worker thread is needed".into()),
        Ok(n) if n <= MAX_JOBS => Ok(n),
        Ok(n) => Err(format!("{n} worker threads is over the limit of {MAX_JOBS}")),
        Err(_) => Err(format!("`{s}` is not a thread count (1 to {MAX_JOBS})")),
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
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(1)
        }
    }
}

/// For a command that reads the pipeline's data: a root that does not exist or holds another
/// kind's data is, like a bad pipeline, a problem of the command line (exit 2), found before
/// anything runs. (`check` only notes a missing root: the data may live on the cluster.)
fn refuse_dataset_root(args: &PipelineArgs, registry: &Registry, pipeline: &Pipeline) -> Option<ExitCode> {
    let problem = registry.dataset_root_problem(pipeline)?;
    eprintln!("error: {}: {problem}", args.pipeline.display());
    Some(ExitCode::from(2))
}

/// Loads and checks a pipeline; a bad one prints every problem and exits 2.
fn load(args: &PipelineArgs, registry: &Registry) -> Result<Result<Pipeline, ExitCode>> {
    let cwd = std::env::current_dir()?;
    Ok(match load_file(&args.pipeline, &args.sets, &cwd, registry) {
        Ok(p) => Ok(p),
        Err(e) => {
            eprint!("{}", e.render());
            Err(ExitCode::from(2))
        }
    })
}

/// Writes a synthetic dataset (or finds it already there) and says so.
fn synthesize(config: &dist4d_synth::SynthConfig, out: &Path) -> Result<()> {
    match dist4d_synth::write_dataset(config, out, &|m| eprintln!("synth: {m}"))? {
        None => println!("{}: the synthetic dataset is already there", out.display()),
        Some(s) => println!(
            "{}: {} scenes, {} samples, {} LiDAR sweeps, {} camera images, {} annotations in {:.1}s",
            out.display(),
            s.scenes,
            s.samples,
            s.lidar_sweeps,
            s.camera_images,
            s.annotations,
            s.seconds
        ),
    }
    Ok(())
}

/// `--progress`: `auto` is bars on a terminal and lines otherwise, every `DIST4D_PROGRESS_SECS`
/// (10 s) in both `auto` and `lines`.
fn progress_mode(name: &str) -> ProgressMode {
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
fn execute(
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
fn printable(s: &str) -> String {
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

/// The shipped pipeline the demo runs, built into the binary so the demo works from anywhere.
const DEMO_PIPELINE: &str = include_str!("../pipelines/curation.ron");

/// `dist4d demo`: synthesize a small dataset (once), write the shipped pipeline beside it as it
/// ships (its `root: "../data/nuscenes"` finds the data in the same layout as in the repository),
/// run it with the default store and output folder, and print its scores.
fn demo(dir: &Path, keyframes: u32, width: u32, height: u32, progress: &str) -> Result<ExitCode> {
    let data = dir.join("data/nuscenes");
    let config = dist4d_synth::SynthConfig { keyframes, width, height, ..Default::default() };
    synthesize(&config, &data)?;
    let pipeline_file = dir.join("pipelines/curation.ron");
    if std::fs::read_to_string(&pipeline_file).ok().as_deref() != Some(DEMO_PIPELINE) {
        std::fs::create_dir_all(dir.join("pipelines"))?;
        std::fs::write(&pipeline_file, DEMO_PIPELINE)
            .with_context(|| format!("writing {}", pipeline_file.display()))?;
    }
    let registry = Registry::default();
    let args = PipelineArgs {
        pipeline: pipeline_file.clone(),
        sets: vec![],
        cache: None,
        scenes: None,
        limit: None,
        shard: None,
    };
    let (pipeline, out_dir, code) =
        match run_pipeline(&registry, &args, |_| Ok(()), None, false, None, progress, |_| ())? {
            Ok(x) => x,
            Err(code) => return Ok(code),
        };
    print!("{}", dist4d_stages::eval::report::tables(&pipeline, &out_dir)?);
    println!();
    println!("demo outputs:");
    println!("  synthetic nuScenes dataset   {}", data.display());
    println!("  its ground truth             {}", data.join("groundtruth").display());
    println!("  dense depth per camera       {}", out_dir.display());
    println!("  e.g. open                    {}", out_dir.join("synth-0000/sheets/001.png").display());
    println!("  rerun or edit the pipeline   dist4d run {}", pipeline_file.display());
    Ok(code)
}

/// `run` and `eval`: loads the pipeline, checks it with `usable` (exit 2 when that fails), runs
/// it, returns it with its output folder and exit code (or the exit code of a pipeline that did
/// not load or was not usable).
fn run_pipeline(
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

/// `dist4d slurm`: plans on this node, then writes and submits the job scripts.
fn slurm_submit(
    registry: &Registry,
    p: &PipelineArgs,
    out: Option<PathBuf>,
    submit: &slurm::Submit,
) -> Result<ExitCode> {
    if p.shard.is_some() {
        anyhow::bail!("--shard is for `dist4d run`; `dist4d slurm` makes the shards (--shards N)");
    }
    let pipeline = match load(p, registry)? {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    if let Some(code) = refuse_dataset_root(p, registry, &pipeline) {
        return Ok(code);
    }
    let (cache, out_dir) = (p.cache_dir(), p.out_dir(out, &pipeline));
    let pending = {
        let dataset = registry.open_dataset(&pipeline)?;
        let ops = registry.operators(&pipeline)?;
        let store =
            Store::open(&cache, Access::Shared).with_context(|| format!("opening the store {}", cache.display()))?;
        let engine = Engine { pipeline: &pipeline, dataset: dataset.as_ref(), operators: &ops, store: &store };
        let (_, per_outer) =
            dist4d_runtime::explain::explain_per_outer(&engine, p.scenes.as_deref(), p.limit, Some(&out_dir), false)?;
        let label = |o: u32| dataset.label(&dist4d_runtime::ItemKey::new(&[o]));
        slurm::Pending {
            scenes: per_outer.iter().filter(|(_, n)| *n > 0).map(|&(o, _)| label(o)).collect(),
            tasks: per_outer.iter().map(|(_, n)| n).sum(),
            all_scenes: per_outer.len(),
            has_workers: ops.iter().flatten().any(|op| op.resource().is_some()),
        }
    };
    let dim = &pipeline.dims[0].name;
    if pending.scenes.is_empty() {
        println!(
            "nothing to submit: every task of the {} {dim}{} is cached (`dist4d explain` says what a run would do)",
            pending.all_scenes,
            if pending.all_scenes == 1 { "" } else { "s" }
        );
        return Ok(ExitCode::SUCCESS);
    }
    let group = slurm::group_name(&pipeline.name);
    let bin = std::env::current_exe().context("finding the dist4d executable")?;
    let target = slurm::Target {
        pipeline: p.pipeline.clone(),
        sets: p.sets.clone(),
        cache: cache.clone(),
        out: out_dir,
        scenes: p.scenes.clone(),
        limit: p.limit,
    };
    let jobs = slurm::jobs(&target, submit, &pending, &group, &bin)?;
    let dir = slurm::job_dir(&cache, &group)?;
    // An earlier submission whose merge has not written its report is still queued or running
    // (or its merge was cancelled): submitting again would do its work twice.
    for earlier in slurm::unmerged_groups(&cache, &pipeline.name) {
        eprintln!(
            "warning: group {earlier} (submitted earlier) has no merge report yet: if its jobs are still queued or \
             running (squeue), this submission repeats their scenes; scancel one of the two"
        );
    }
    println!(
        "{} of {} {dim}s have work left ({} tasks): group {group}",
        pending.scenes.len(),
        pending.all_scenes,
        pending.tasks
    );
    if submit.dry_run {
        let ids: Vec<String> = jobs.iter().map(|j| format!("<{} job id>", j.name)).collect();
        println!("--dry-run: nothing written or submitted; without it, these scripts are written and submitted as:");
        for job in &jobs {
            let script = dir.join(format!("{}.sh", job.name));
            let args: Vec<String> =
                slurm::sbatch_args(job, &ids, &script).iter().map(|a| slurm::shell_word(a)).collect();
            println!("\n# sbatch {}", args.join(" "));
            print!("{}", job.script);
        }
        return Ok(ExitCode::SUCCESS);
    }
    let ids = slurm::submit(&jobs, &dir)?;
    for (job, id) in jobs.iter().zip(&ids) {
        println!(
            "submitted {} as job {id}{}",
            job.name,
            job.array.as_ref().map(|a| format!(" (array {a})")).unwrap_or_default()
        );
    }
    println!(
        "scripts and logs: {}
follow with: dist4d runs --cache {}",
        dir.display(),
        cache.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// `dist4d merge`: the last job of a submission.
#[allow(clippy::too_many_arguments)]
fn slurm_merge(
    registry: &Registry,
    p: &PipelineArgs,
    out: Option<PathBuf>,
    group: &str,
    shards: u32,
    gpu_shards: Option<u32>,
    no_retry: bool,
    jobs: Option<usize>,
    progress: &str,
) -> Result<ExitCode> {
    let pipeline = match load(p, registry)? {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    let (cache, out_dir) = (p.cache_dir(), p.out_dir(out, &pipeline));
    let runs = dist4d_runtime::runs::list_runs(&cache.join("runs"))?;
    let arrays: Vec<u32> = std::iter::once(shards).chain(gpu_shards).collect();
    let report = slurm::shards_report(&runs, group, &arrays);
    println!("group {group}:");
    for line in report.lines() {
        println!("  {line}");
    }
    let retry = if no_retry { Vec::new() } else { report.failed_scenes.clone() };
    if !retry.is_empty() {
        println!("retrying the {} scene(s) with failed items: {}", retry.len(), retry.join(", "));
    }
    let mut opts = RunOptions {
        outer_items: p.scenes.clone(),
        limit: p.limit,
        out_dir: Some(out_dir.clone()),
        progress: progress_mode(progress),
        execute_only: Some(retry.clone()),
        group: Some(group.to_string()),
        ..Default::default()
    };
    if let Some(j) = jobs {
        opts.jobs = j;
    }
    let (code, rec) = execute(registry, &pipeline, &cache, &out_dir, opts)?;
    // The group's report, beside its scripts and logs.
    let report_path = slurm::job_dir(&cache, group)?.join("report.json");
    let json = serde_json::json!({
        "group": group,
        "pipeline": pipeline.name,
        "shards": report.shards.iter().map(|s| s.to_json()).collect::<Vec<_>>(),
        "executed_by_shards": report.shards.iter().map(|s| s.executed).sum::<u64>(),
        "retried": retry,
        "merge_run": rec.id,
        "status": rec.status,
        "executed_by_merge": rec.executed(),
        "cached": rec.cached(),
        "missing": rec.missing(),
        "failures": rec.failures,
        "out_dir": out_dir.display().to_string(),
    });
    let tmp = report_path.with_extension("json.tmp");
    std::fs::create_dir_all(report_path.parent().unwrap_or(Path::new(".")))
        .and_then(|_| std::fs::write(&tmp, serde_json::to_vec_pretty(&json).unwrap_or_default()))
        .and_then(|_| std::fs::rename(&tmp, &report_path))
        .with_context(|| format!("writing the group report {}", report_path.display()))?;
    println!("report: {}", report_path.display());
    if !rec.failures.is_empty() {
        println!(
            "{} task(s) failed{}: see the errors above. The same input fails the same way: fix it, or leave its {} out \
             (--scenes); rerunning `dist4d slurm` retries them.",
            rec.failures.len(),
            if retry.is_empty() { "" } else { " (in the merge's retry too)" },
            pipeline.dims[0].name
        );
    }
    if rec.missing() > 0 {
        println!(
            "{} tasks are missing ({} shard(s) did not finish): rerun the same `dist4d slurm` command; only the {}s with missing work become shards",
            rec.missing(),
            report.unfinished(),
            pipeline.dims[0].name
        );
    }
    Ok(code)
}

/// What tells runs of one pipeline apart in `dist4d runs`: `  dataset NuScenes /data  out DIR  --set a=1`.
fn run_inputs(r: &dist4d_runtime::RunRecord) -> String {
    let mut s = String::new();
    if let Some(d) = r.dataset_label() {
        s += &format!("  dataset {}", printable(&d));
    }
    if let Some(out) = &r.out_dir {
        s += &format!("  out {}", printable(out));
    }
    for set in &r.sets {
        s += &format!("  --set {}", printable(set));
    }
    s
}

/// The store `dist4d runs`, `gc` and `verify --store` read without --cache: the one `dist4d run pipelines/x.ron` uses
/// (`.dist4d/` beside the pipeline files), else `.dist4d/` here, whichever has runs first.
fn default_store() -> PathBuf {
    let candidates = [PathBuf::from("pipelines/.dist4d"), PathBuf::from(".dist4d")];
    let has_runs = |c: &PathBuf| c.join("runs").is_dir();
    candidates.iter().find(|c| has_runs(c)).unwrap_or(&candidates[0]).clone()
}

/// The store a command that only works on an existing store (gc, verify --store) was given, or
/// [`default_store`] (said on stderr); a folder that does not exist is an error, not a new store.
fn existing_store(cache: Option<PathBuf>) -> Result<PathBuf> {
    let cache = cache.unwrap_or_else(|| {
        let found = default_store();
        eprintln!("store: {} (--cache for another)", found.display());
        found
    });
    anyhow::ensure!(cache.is_dir(), "there is no store at {} (--cache names it)", cache.display());
    Ok(cache)
}

fn beside(pipeline: &Path, rel: &str) -> PathBuf {
    pipeline.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).join(rel)
}

fn run(cli: Cli) -> Result<ExitCode> {
    let registry = Registry::default();
    match cli.command {
        Command::Check { p } => {
            let pipeline = match load(&p, &registry)? {
                Ok(x) => x,
                Err(code) => return Ok(code),
            };
            // The data may live on another machine (checked here, run on the cluster): a root
            // that is not here is a note; one that holds another kind's data is an error.
            match registry.dataset_root_problem(&pipeline) {
                Some(missing @ dist4d_datasets::registry::RootProblem::Missing(_)) => {
                    eprintln!("note: {missing}; `run` needs it")
                }
                Some(other) => {
                    eprintln!("error: {}: {other}", p.pipeline.display());
                    return Ok(ExitCode::from(2));
                }
                None => {}
            }
            let stages = pipeline.stage_order().count();
            println!(
                "{}: ok ({} stages, {} dataset ports, {} exports)",
                p.pipeline.display(),
                stages,
                pipeline.nodes.len() - stages,
                pipeline.exports.len()
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Graph { p } => {
            let pipeline = match load(&p, &registry)? {
                Ok(x) => x,
                Err(code) => return Ok(code),
            };
            print!("{}", pipeline.to_dot());
            Ok(ExitCode::SUCCESS)
        }
        Command::Explain { p, out } => {
            let pipeline = match load(&p, &registry)? {
                Ok(x) => x,
                Err(code) => return Ok(code),
            };
            if let Some(code) = refuse_dataset_root(&p, &registry, &pipeline) {
                return Ok(code);
            }
            let dataset = registry.open_dataset(&pipeline)?;
            let ops = registry.operators(&pipeline)?;
            // Explain only reads: no lease, nothing written (it works on a read-only store).
            let store = Store::open(&p.cache_dir(), Access::ReadOnly)?;
            let engine = Engine { pipeline: &pipeline, dataset: dataset.as_ref(), operators: &ops, store: &store };
            let out_dir = p.out_dir(out, &pipeline);
            // The scenes a run with the same --shard would take.
            let scenes = match p.shard {
                Some(shard) => Some(dist4d_runtime::exec::shard_labels(
                    &pipeline,
                    dataset.as_ref(),
                    p.scenes.as_deref(),
                    p.limit,
                    shard,
                )?),
                None => p.scenes.clone(),
            };
            let report = dist4d_runtime::explain::explain(&engine, scenes.as_deref(), p.limit, Some(&out_dir))?;
            for s in &report {
                let failed = if s.failed_last_run > 0 {
                    format!(", {} failed last run", s.failed_last_run)
                } else {
                    String::new()
                };
                let nothing = if s.not_applicable > 0 {
                    format!(", {} with nothing to make", s.not_applicable)
                } else {
                    String::new()
                };
                println!("{} ({}): {} cached, {} will run{failed}{nothing}", s.stage, s.kind, s.cached, s.will_run);
                for (reason, (n, example)) in &s.reasons {
                    println!("    {n} x {reason}  (e.g. {example})");
                }
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Eval { p, jobs, out, progress } => {
            // A pipeline that cannot be reported on fails before its run, not after.
            let reportable = |p: &Pipeline| dist4d_stages::eval::report::scored_stages(p).map(|_| ());
            let (pipeline, out_dir, code) =
                match run_pipeline(&registry, &p, reportable, jobs, false, out, &progress, |_| ())? {
                    Ok(x) => x,
                    Err(code) => return Ok(code),
                };
            // A stopped run has not exported every score: say how it ended, not what is missing.
            if code == ExitCode::SUCCESS || code == ExitCode::from(1) {
                print!("{}", dist4d_stages::eval::report::tables(&pipeline, &out_dir)?);
            }
            Ok(code)
        }
        Command::Run { p, jobs, fail_fast, out, progress, group, defer_workers } => {
            let tweak = |o: &mut RunOptions| {
                o.group = group;
                o.defer_resources = defer_workers;
            };
            Ok(run_pipeline(&registry, &p, |_| Ok(()), jobs, fail_fast, out, &progress, tweak)?
                .map_or_else(|code| code, |(_, _, code)| code))
        }
        Command::Slurm { p, out, submit } => slurm_submit(&registry, &p, out, &submit),
        Command::Merge { p, out, group, shards, gpu_shards, no_retry, jobs, progress } => {
            slurm_merge(&registry, &p, out, &group, shards, gpu_shards, no_retry, jobs, &progress)
        }
        Command::Runs { cache, json } => {
            let cache = match cache {
                Some(c) => c,
                None => {
                    let found = default_store();
                    eprintln!("store: {} (--cache for another)", found.display());
                    found
                }
            };
            let runs = dist4d_runtime::runs::list_runs(&cache.join("runs"))?;
            if json {
                println!("{}", serde_json::to_string_pretty(&runs)?);
                return Ok(ExitCode::SUCCESS);
            }
            if runs.is_empty() {
                println!("no runs recorded in {}", cache.display());
            }
            for group in dist4d_runtime::runs::grouped(&runs) {
                let first = group[0];
                let sum = |f: fn(&dist4d_runtime::RunRecord) -> u64| group.iter().map(|r| f(r)).sum::<u64>();
                // A group's time is from its first start to its last end (its jobs overlap).
                let end = group.iter().map(|r| r.started as f64 + r.seconds).fold(0.0, f64::max);
                let shards = group.iter().filter(|r| r.shard.is_some()).count();
                let merged = group.len() > shards;
                // Shards expected: the largest split the group's shards name (a GPU array's is smaller).
                let expected = group.iter().filter_map(|r| r.shard).map(|(_, n)| n as usize).max().unwrap_or(0);
                let (id, what) = match &first.group {
                    Some(g) if merged => (g.clone(), format!(" ({shards} shard runs + merge)")),
                    Some(g) => (g.clone(), format!(" ({shards} of {expected} shards recorded, no merge yet)")),
                    None => (first.id.clone(), String::new()),
                };
                // What the group's last run found is what the group left: its merge sees the
                // shards' work as cached, so cached counts what was there before the group.
                let last = group[group.len() - 1];
                let executed = sum(|r| r.executed());
                let missing = if last.missing() > 0 { format!(", {} missing", last.missing()) } else { String::new() };
                println!(
                    "{}  {}  {:<14} {}  {} executed, {} cached, {} failed{missing}, {:.1}s{what}{}",
                    dist4d_runtime::runs::format_utc(first.started),
                    id,
                    first.pipeline,
                    // A group whose merge has not run is not done, whatever its shards said; a run
                    // recorded as running is running, or was killed before it could say so.
                    match dist4d_runtime::runs::running_or_killed(&cache, last) {
                        _ if first.group.is_some() && !merged => "Pending".to_string(),
                        Some("running") => "Running".to_string(),
                        Some(_) => "Killed".to_string(),
                        None => format!("{:?}", dist4d_runtime::runs::group_status(&group)),
                    },
                    executed,
                    if group.len() > 1 {
                        (last.cached() + last.executed()).saturating_sub(executed)
                    } else {
                        last.cached()
                    },
                    last.failed(),
                    end - first.started as f64,
                    run_inputs(first)
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Demo { dir, keyframes, width, height, progress } => demo(&dir, keyframes, width, height, &progress),
        Command::Synth {
            out,
            seed,
            scenes,
            keyframes,
            width,
            height,
            camera_sweeps,
            no_lidar_sweeps,
            no_ground_truth,
        } => {
            let config = dist4d_synth::SynthConfig {
                seed,
                scenes,
                keyframes,
                width,
                height,
                camera_sweeps,
                lidar_sweeps: !no_lidar_sweeps,
                ground_truth: !no_ground_truth,
                ..Default::default()
            };
            synthesize(&config, &out)?;
            Ok(ExitCode::SUCCESS)
        }
        Command::Occ3dAnnotations { out, val } => {
            let dir = out.join("occ3d/scenes");
            let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
                .with_context(|| {
                    format!("reading {} (run pipelines/occupancy.ron into {} first)", dir.display(), out.display())
                })?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "json"))
                .collect();
            files.sort();
            let mut parts = Vec::new();
            for f in &files {
                let text = std::fs::read(f).with_context(|| format!("reading {}", f.display()))?;
                parts.push(serde_json::from_slice(&text).with_context(|| format!("{} is not JSON", f.display()))?);
            }
            anyhow::ensure!(!parts.is_empty(), "{} holds no scene's part", dir.display());
            let merged = dist4d_stages::occupancy::annotations::merge(&parts, &val)?;
            let target = out.join("annotations.json");
            let tmp = out.join(".annotations.json.tmp");
            std::fs::write(&tmp, serde_json::to_vec(&merged)?).with_context(|| format!("writing {}", tmp.display()))?;
            std::fs::rename(&tmp, &target).with_context(|| format!("writing {}", target.display()))?;
            let frames: usize = merged["scene_infos"]
                .as_object()
                .map_or(0, |s| s.values().filter_map(|v| v.as_object()).map(|f| f.len()).sum());
            println!(
                "{}: {} scene(s) ({} train, {} val), {frames} frames",
                target.display(),
                parts.len(),
                merged["train_split"].as_array().map_or(0, Vec::len),
                merged["val_split"].as_array().map_or(0, Vec::len)
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Export12Hz { root, version, out, drop_lone_tracks } => {
            use dist4d_datasets::nuscenes::{interp12hz, LoneTracks, NuScenesConfig};
            let config = NuScenesConfig {
                root: root.to_string_lossy().into_owned(),
                version: version.clone(),
                lone_tracks: if drop_lone_tracks { LoneTracks::Drop } else { LoneTracks::Extrapolate },
                ..Default::default()
            };
            let out = out.unwrap_or_else(|| interp12hz::default_folder(&root, &version));
            let r = interp12hz::write_interp_12hz(&config, &out)?;
            for w in &r.warnings {
                eprintln!("warning: {w}");
            }
            println!(
                "{}: {} scene(s), {} samples ({} keyframes, {} camera rounds between), {} interpolated annotations ({} extrapolated)",
                out.display(),
                r.scenes,
                r.samples,
                r.keyframes,
                r.samples - r.keyframes,
                r.annotations,
                r.extrapolated
            );
            for line in interp12hz::how_to_load(&root, &out) {
                println!("{line}");
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::ExportInfos { root, version, out, path_prefix, max_sweeps, split } => {
            use dist4d_datasets::nuscenes::infos::{write_infos, InfosOptions};
            let out = out.unwrap_or_else(|| root.clone());
            let r = write_infos(&InfosOptions { root, version, out, path_prefix, max_sweeps, splits: split })?;
            for w in &r.warnings {
                eprintln!("warning: {w}");
            }
            for f in &r.files {
                println!(
                    "{}: {} {} samples of {} scene(s), {} in scene_tokens",
                    f.path.display(),
                    f.samples,
                    f.split,
                    f.scenes,
                    f.scene_lists
                );
            }
            Ok(ExitCode::SUCCESS)
        }
        Command::Depthroot { out } => {
            let r = dist4d_stages::output::depthroot::write_depthroot(&out)?;
            println!(
                "{}: {} samples ({} depth files)",
                out.join(dist4d_stages::output::depthroot::INDEX).display(),
                r.samples,
                r.files
            );
            Ok(ExitCode::SUCCESS)
        }
        Command::Verify { out, store, cache } => {
            let mut code = ExitCode::SUCCESS;
            if store {
                code = verify_store(&existing_store(cache)?)?;
            }
            let Some(out) = out else { return Ok(code) };
            let r = dist4d_runtime::export::verify(&out)?;
            for rel in &r.modified {
                println!("modified: {rel}");
            }
            for rel in &r.missing {
                println!("missing:  {rel}");
            }
            let owner = r.owner.as_deref().unwrap_or("?");
            println!(
                "{}: {} files intact, {} modified, {} missing (exports of pipeline `{owner}`)",
                out.display(),
                r.ok,
                r.modified.len(),
                r.missing.len()
            );
            if r.modified.is_empty() && r.missing.is_empty() {
                return Ok(code);
            }
            println!("rerun pipeline `{owner}` with the same --out to rewrite them");
            Ok(ExitCode::from(1))
        }
        Command::Gc { cache, keep_runs, max_size, dry_run } => {
            let cache = existing_store(cache)?;
            let r = dist4d_runtime::gc::gc(&cache, keep_runs, max_size, dry_run)?;
            println!(
                "{}kept {} runs, {} records, {} blobs ({} bytes); {} {} runs, {} records, {} blobs ({} bytes)",
                if dry_run { "--dry-run, nothing removed: would have " } else { "" },
                r.runs_kept,
                r.records_kept,
                r.blobs_kept,
                r.bytes_kept,
                if dry_run { "would remove" } else { "removed" },
                r.runs_dropped,
                r.records_dropped,
                r.blobs_dropped,
                r.bytes_freed
            );
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// `dist4d verify --store`: prints what is wrong, then a summary; exit code 1 unless all is sound.
fn verify_store(cache: &Path) -> Result<ExitCode> {
    let r = dist4d_runtime::verify::verify_store(cache)?;
    for line in &r.damaged {
        println!("damaged:  {line}");
    }
    for line in &r.unreadable {
        println!("unreadable: {line}");
    }
    for line in &r.notes {
        println!("note:     {line}");
    }
    println!(
        "{}: {} records in {} segments, {} fingerprints, {} blobs ({} bytes), {} run records checked; {} damaged, {} unreadable",
        cache.display(),
        r.records,
        r.segments,
        r.fingerprints,
        r.blobs,
        r.blob_bytes,
        r.runs,
        r.damaged.len(),
        r.unreadable.len()
    );
    if r.sound() {
        return Ok(ExitCode::SUCCESS);
    }
    if !r.damaged.is_empty() {
        println!("runs recompute what damaged blobs and records held (rerun the pipelines that use them)");
    }
    Ok(ExitCode::from(1))
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
