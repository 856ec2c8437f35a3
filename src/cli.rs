//! The command line's arguments (clap): the commands, their options and help texts, and the
//! parsers of `--shard`, `--jobs` and `--max-size`.

use crate::slurm;
use clap::{Args, Parser, Subcommand};
use dist4d_graph::Pipeline;
use std::path::{Path, PathBuf};

#[derive(Parser)]
#[command(
    name = "dist4d",
    version,
    about = "Declared, reproducible, incremental data pipelines for 4D driving-scene generation"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Args, Clone)]
pub struct PipelineArgs {
    /// The pipeline file (RON).
    pub pipeline: PathBuf,
    /// Override a param or dataset field: `stage.param=value`, `dataset.root=PATH` (repeatable).
    #[arg(long = "set", value_name = "TARGET.FIELD=VALUE")]
    pub sets: Vec<String>,
    /// The store (cache) directory [default: .dist4d/ beside the pipeline file].
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Only these scenes, by name (comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub scenes: Option<Vec<String>>,
    /// Only the first N frames of each scene.
    #[arg(long, value_name = "N")]
    pub limit: Option<u32>,
    /// Only shard I of N of the scenes (0 <= I < N; scenes dealt to shards by size, the same on
    /// every machine): run the N shards at once, anywhere, against one shared --cache.
    #[arg(long, value_name = "I/N", value_parser = parse_shard)]
    pub shard: Option<(u32, u32)>,
}

impl PipelineArgs {
    /// `--cache`, or `.dist4d/` beside the pipeline file.
    pub fn cache_dir(&self) -> PathBuf {
        self.cache.clone().unwrap_or_else(|| beside(&self.pipeline, ".dist4d"))
    }

    /// `--out` when given, else `out/<pipeline name>/` beside the pipeline file.
    pub fn out_dir(&self, out: Option<PathBuf>, pipeline: &Pipeline) -> PathBuf {
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
pub enum Command {
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
    Synth(SynthArgs),
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

/// `rel` beside the pipeline file (in its folder; `.` for a bare file name).
fn beside(pipeline: &Path, rel: &str) -> PathBuf {
    pipeline.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new(".")).join(rel)
}

/// The arguments of `dist4d synth`.
#[derive(clap::Args, Debug)]
pub struct SynthArgs {
    /// The dataset folder to create (must not exist, or hold the same synthetic dataset).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long, default_value_t = 1)]
    pub scenes: u32,
    /// Keyframes (2 Hz samples) per scene.
    #[arg(long, default_value_t = 40)]
    pub keyframes: u32,
    #[arg(long, default_value_t = 1600)]
    pub width: u32,
    #[arg(long, default_value_t = 900)]
    pub height: u32,
    /// Also write the 12 Hz camera sweeps between keyframes.
    #[arg(long)]
    pub camera_sweeps: bool,
    /// Write LiDAR keyframes only (no 20 Hz sweeps in between).
    #[arg(long)]
    pub no_lidar_sweeps: bool,
    /// Skip the ground-truth depth and semantic images.
    #[arg(long)]
    pub no_ground_truth: bool,
}
