//! `dist4d slurm` and `dist4d merge`: a pipeline as Slurm job arrays against a shared store.
//!
//! The submitting node plans (explain, per scene): only scenes with work left become shards.
//! It writes the job scripts into the store (`<store>/slurm/<group>/`), where every node sees
//! them and their logs, and submits with `sbatch`: one array whose task i runs
//! `dist4d run --shard i/N --group G` over those scenes, optionally a GPU array for the stages
//! served by model workers, and a merge job that depends on them (`afterany`, so it runs
//! whatever became of them). The merge job reads what the shards recorded in the store (not
//! `sacct`: accounting is often off), retries the items that failed, collects the rest from
//! the cache without redoing a lost shard's work, and writes the index and the run record.
//! Slurm is the cluster manager: nothing here watches or restarts jobs.

use anyhow::{bail, Context, Result};
use dist4d_runtime::runs::{RunRecord, RunStatus};
use std::path::{Path, PathBuf};

/// What a job runs on: the arguments of the `dist4d` command that named it.
pub struct Target {
    pub pipeline: PathBuf,
    pub sets: Vec<String>,
    pub cache: PathBuf,
    pub out: PathBuf,
    pub scenes: Option<Vec<String>>,
    pub limit: Option<u32>,
}

impl Target {
    /// `PIPELINE --cache C --out O [--set ...] [--limit N]`, paths made absolute (a job starts
    /// in another directory, maybe on another node). Scenes are given by the caller.
    fn args(&self) -> Result<Vec<String>> {
        let abs = |p: &Path| -> Result<String> {
            let p = if p.is_absolute() { p.to_path_buf() } else { std::env::current_dir()?.join(p) };
            Ok(p.display().to_string())
        };
        let mut a = vec![abs(&self.pipeline)?, "--cache".into(), abs(&self.cache)?, "--out".into(), abs(&self.out)?];
        for s in &self.sets {
            a.extend(["--set".into(), s.clone()]);
        }
        if let Some(n) = self.limit {
            a.extend(["--limit".into(), n.to_string()]);
        }
        Ok(a)
    }
}

/// How to submit (the options of `dist4d slurm`).
#[derive(clap::Args)]
pub struct Submit {
    /// Array tasks (at most one per scene with work left).
    #[arg(long, default_value_t = 8)]
    pub shards: u32,
    /// Array tasks running at once (--array=0-N%K), so the controller is not flooded.
    #[arg(long, value_name = "K")]
    pub array_limit: Option<u32>,
    #[arg(long)]
    pub partition: Option<String>,
    /// CPUs per array task; each shard runs that many threads.
    #[arg(long, default_value_t = 4)]
    pub cpus_per_task: u32,
    /// An extra sbatch option for every job (repeatable), e.g. --sbatch=--time=4:00:00 --sbatch=--account=ad.
    #[arg(long, value_name = "OPTION", allow_hyphen_values = true)]
    pub sbatch: Vec<String>,
    /// Put the stages served by model workers in a second array with this --gres (e.g. gpu:1),
    /// after the first; the first then leaves them (`--defer-workers`).
    #[arg(long)]
    pub gres: Option<String>,
    /// Array tasks of the GPU array (each keeps one long-lived worker per model).
    #[arg(long, default_value_t = 1)]
    pub gpu_shards: u32,
    /// Partition of the GPU array [default: --partition].
    #[arg(long)]
    pub gpu_partition: Option<String>,
    /// Print the job scripts and sbatch commands instead of submitting.
    #[arg(long)]
    pub dry_run: bool,
}

/// One job to submit.
pub struct Job {
    pub name: &'static str,
    pub script: String,
    /// `--array=...`, when an array.
    pub array: Option<String>,
    /// Indices (into the job list) of the jobs it runs after.
    pub after: Vec<usize>,
}

/// The scenes with work left, as `explain` found them on the submitting node.
pub struct Pending {
    pub scenes: Vec<String>,
    pub tasks: u64,
    /// Every scene the target selects.
    pub all_scenes: usize,
    /// Whether the pipeline has stages served by model workers.
    pub has_workers: bool,
}

/// A group name: the pipeline's name and the time, unique per submission.
pub fn group_name(pipeline: &str) -> String {
    let millis = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis()).unwrap_or(0);
    format!("{pipeline}-{millis}")
}

/// The jobs of a submission: the CPU array, the GPU array when asked for and the pipeline
/// has worker stages, and the merge job after them.
pub fn jobs(target: &Target, submit: &Submit, pending: &Pending, group: &str, bin: &Path) -> Result<Vec<Job>> {
    if submit.shards == 0 || submit.gpu_shards == 0 {
        bail!("--shards and --gpu-shards are at least 1");
    }
    let dir = job_dir(&target.cache, group)?;
    let cwd = std::env::current_dir()?;
    let base = target.args()?;
    let pipeline = group.rsplit_once('-').map_or(group, |(p, _)| p);
    let scenes = pending.scenes.join(",");
    let shards = submit.shards.clamp(1, pending.scenes.len().max(1) as u32);
    let gpu = submit.gres.as_ref().filter(|_| pending.has_workers);
    let array = |n: u32| match submit.array_limit {
        Some(k) => format!("0-{}%{k}", n - 1),
        None => format!("0-{}", n - 1),
    };
    // The role first: squeue shows 8 characters of a job's name.
    let header = |role: &str, log: &str, partition: Option<&String>, gres: Option<&String>| {
        let mut h = format!("#!/bin/bash\n# Written by `dist4d slurm` for group {group}: see docs/cluster.md.\n");
        let mut options = vec![
            format!("--job-name={role}-{pipeline}"),
            format!("--output={}", dir.join(log).display()),
            // Relative paths in --set (a dataset root) mean what they meant where it was submitted.
            format!("--chdir={}", cwd.display()),
            format!("--cpus-per-task={}", submit.cpus_per_task),
        ];
        options.extend(partition.map(|p| format!("--partition={p}")));
        options.extend(gres.map(|g| format!("--gres={g}")));
        options.extend(submit.sbatch.iter().cloned());
        for o in options {
            h.push_str(&format!("#SBATCH {}\n", directive(&o)));
        }
        // SIGTERM (scancel, a time limit) reaches dist4d itself, which stops cleanly.
        h.push_str("set -euo pipefail\nexec ");
        h
    };
    let command = |verb: &str, extra: &[String]| -> String {
        let mut words = vec![bin.display().to_string(), verb.to_string()];
        words.extend(base.iter().cloned());
        words.extend(extra.iter().cloned());
        words.iter().map(|w| shell_word(w)).collect::<Vec<_>>().join(" ")
    };
    let shard_args = |n: u32, defer: bool| -> Vec<String> {
        let mut a = vec!["--scenes".into(), scenes.clone(), "--group".into(), group.into()];
        if defer {
            a.push("--defer-workers".into());
        }
        a.extend(["--progress".into(), "lines".into(), "--jobs".into(), "${SLURM_CPUS_PER_TASK:-1}".into()]);
        a.extend(["--shard".into(), format!("${{SLURM_ARRAY_TASK_ID}}/{n}")]);
        a
    };
    let mut jobs = vec![Job {
        name: "array",
        script: format!(
            "{}{}\n",
            header("shard", "shard-%a.log", submit.partition.as_ref(), None),
            command("run", &shard_args(shards, gpu.is_some()))
        ),
        array: Some(array(shards)),
        after: vec![],
    }];
    let gpu_shards = submit.gpu_shards.clamp(1, shards);
    let gpu_partition = submit.gpu_partition.as_ref().or(submit.partition.as_ref());
    if let Some(g) = gpu {
        jobs.push(Job {
            name: "gpu-array",
            script: format!(
                "{}{}\n",
                header("gpushard", "gpu-shard-%a.log", gpu_partition, Some(g)),
                command("run", &shard_args(gpu_shards, false))
            ),
            array: Some(array(gpu_shards)),
            after: vec![0],
        });
    }
    let mut merge_args = vec!["--group".into(), group.into(), "--shards".into(), shards.to_string()];
    if gpu.is_some() {
        merge_args.extend(["--gpu-shards".into(), gpu_shards.to_string()]);
    }
    if let Some(s) = &target.scenes {
        merge_args.extend(["--scenes".into(), s.join(",")]);
    }
    merge_args.extend(["--jobs".into(), "${SLURM_CPUS_PER_TASK:-1}".into()]);
    let after = (0..jobs.len()).collect();
    jobs.push(Job {
        name: "merge",
        script: format!(
            "{}{}\n",
            // With a GPU array, the merge retries failed worker tasks too: it gets a GPU.
            match gpu {
                Some(g) => header("merge", "merge.log", gpu_partition, Some(g)),
                None => header("merge", "merge.log", submit.partition.as_ref(), None),
            },
            command("merge", &merge_args)
        ),
        array: None,
        after,
    });
    Ok(jobs)
}

/// Where a group's scripts and logs go: in the store, which every node sees.
pub fn job_dir(cache: &Path, group: &str) -> Result<PathBuf> {
    let cache = if cache.is_absolute() { cache.to_path_buf() } else { std::env::current_dir()?.join(cache) };
    Ok(cache.join("slurm").join(group))
}

/// The groups of pipeline `pipeline` submitted into this store whose merge has written no
/// report yet (queued, running, or their merge cancelled).
pub fn unmerged_groups(cache: &Path, pipeline: &str) -> Vec<String> {
    let Ok(dir) = job_dir(cache, "") else { return Vec::new() };
    let Ok(rd) = std::fs::read_dir(&dir) else { return Vec::new() };
    let mut out: Vec<String> = rd
        .filter_map(|e| e.ok())
        .filter(|e| !e.path().join("report.json").exists())
        .filter_map(|e| e.file_name().to_str().map(String::from))
        .filter(|g| g.rsplit_once('-').is_some_and(|(p, t)| p == pipeline && t.chars().all(|c| c.is_ascii_digit())))
        .collect();
    out.sort();
    out
}

/// The `sbatch` command line of a job (the ids of the jobs it runs after filled in).
pub fn sbatch_args(job: &Job, ids: &[String], script: &Path) -> Vec<String> {
    let mut a = vec!["--parsable".to_string()];
    if let Some(array) = &job.array {
        a.push(format!("--array={array}"));
    }
    if !job.after.is_empty() {
        let after: Vec<&str> = job.after.iter().map(|&i| ids[i].as_str()).collect();
        a.push(format!("--dependency=afterany:{}", after.join(":")));
    }
    a.push(script.display().to_string());
    a
}

/// Writes the scripts and submits the jobs in order; returns their ids.
pub fn submit(jobs: &[Job], dir: &Path) -> Result<Vec<String>> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut ids = Vec::new();
    for job in jobs {
        let script = dir.join(format!("{}.sh", job.name));
        std::fs::write(&script, &job.script).with_context(|| format!("writing {}", script.display()))?;
        let args = sbatch_args(job, &ids, &script);
        let out = std::process::Command::new("sbatch").args(&args).output().map_err(|e| {
            anyhow::anyhow!(
                "cannot run sbatch ({e}): run `dist4d slurm` on a node of a Slurm cluster, or add --dry-run to see the job scripts"
            )
        })?;
        if !out.status.success() {
            bail!(
                "sbatch {} failed ({}): {}{}",
                args.join(" "),
                out.status,
                String::from_utf8_lossy(&out.stderr).trim(),
                if ids.is_empty() {
                    String::new()
                } else {
                    format!(
                        "; job{} {} {} submitted already (scancel, or let run)",
                        if ids.len() == 1 { "" } else { "s" },
                        ids.join(", "),
                        if ids.len() == 1 { "was" } else { "were" }
                    )
                }
            );
        }
        // `--parsable` prints `id` or `id;cluster`.
        let text = String::from_utf8_lossy(&out.stdout);
        let id = text.trim().split(';').next().unwrap_or_default().to_string();
        if id.is_empty() || !id.chars().all(|c| c.is_ascii_digit()) {
            bail!("sbatch printed {:?}, not a job id", text.trim());
        }
        ids.push(id);
    }
    Ok(ids)
}

/// An `#SBATCH` option with its value double-quoted when it holds anything but plain
/// characters (sbatch splits directives at spaces, and reads double quotes).
fn directive(option: &str) -> String {
    let Some((name, value)) = option.split_once('=') else { return option.to_string() };
    if value.chars().all(|c| c.is_ascii_alphanumeric() || "-_./:,+@%".contains(c)) {
        return option.to_string();
    }
    format!("{name}=\"{}\"", value.replace('\\', "\\\\").replace('"', "\\\""))
}

/// A word for bash: as it is when it is plain, else single-quoted. `${SLURM_...}` words are
/// double-quoted, so that the shell expands them.
pub fn shell_word(w: &str) -> String {
    if w.contains("${SLURM_") {
        return format!("\"{w}\"");
    }
    if !w.is_empty() && w.chars().all(|c| c.is_ascii_alphanumeric() || "-_./=:,+@%".contains(c)) {
        return w.to_string();
    }
    format!("'{}'", w.replace('\'', "'\\''"))
}

/// One expected shard of a group, as the merge found it.
pub struct ShardState {
    /// `i/n`.
    pub shard: String,
    /// The status of its last run (`complete`, `failed`, `interrupted`, ...), `no record` when
    /// it never wrote one.
    pub status: String,
    pub run: Option<String>,
    pub executed: u64,
    pub cached: u64,
    pub failed: u64,
    pub seconds: f64,
}

impl ShardState {
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "shard": self.shard, "status": self.status, "run": self.run, "executed": self.executed,
            "cached": self.cached, "failed": self.failed, "seconds": self.seconds,
        })
    }

    /// Its line in the merge's report.
    pub fn line(&self) -> String {
        let shard = &self.shard;
        match (self.status.as_str(), &self.run) {
            (_, None) => format!(
                "shard {shard}: no run record: it never started (cancelled while pending, or its job failed \
                 before dist4d ran: see its log)"
            ),
            ("killed", Some(run)) => format!(
                "shard {shard}: killed (run {run} started and never recorded its end: SIGKILL, a lost node, out of \
                 memory); its finished tasks are in the store"
            ),
            (status, Some(run)) => {
                let mut status = status.to_string();
                status[..1].make_ascii_uppercase();
                format!(
                    "shard {shard}: {status} in {:.1}s, {} executed, {} cached, {} failed (run {run})",
                    self.seconds, self.executed, self.cached, self.failed
                )
            }
        }
    }

    /// Whether it did not get to its end: never started, interrupted, or killed.
    fn unfinished(&self) -> bool {
        matches!(self.status.as_str(), "no record" | "interrupted" | "killed")
    }
}

/// What the shards of a group recorded, as the merge job reads it from the store.
pub struct ShardsReport {
    pub shards: Vec<ShardState>,
    /// Scenes with a failed item in a shard's last run: the merge job retries them.
    pub failed_scenes: Vec<String>,
}

impl ShardsReport {
    /// One line per expected shard.
    pub fn lines(&self) -> Vec<String> {
        self.shards.iter().map(ShardState::line).collect()
    }

    /// How many shards did not get to their end.
    pub fn unfinished(&self) -> usize {
        self.shards.iter().filter(|s| s.unfinished()).count()
    }
}

/// Reads what the shards of `group` recorded: expected shards are `(i, n)` for each `n` of
/// `arrays` (the CPU array's and the GPU array's shard counts).
pub fn shards_report(runs: &[RunRecord], group: &str, arrays: &[u32]) -> ShardsReport {
    let mut report = ShardsReport { shards: Vec::new(), failed_scenes: Vec::new() };
    for &n in arrays {
        for i in 0..n {
            let last = runs.iter().rev().find(|r| r.group.as_deref() == Some(group) && r.shard == Some((i, n)));
            for f in last.iter().flat_map(|r| &r.failures) {
                let scene = f.item.split('/').next().unwrap_or_default().to_string();
                if !report.failed_scenes.contains(&scene) {
                    report.failed_scenes.push(scene);
                }
            }
            let status = match last.map(|r| r.status) {
                None => "no record".to_string(),
                // The merge runs after the array: a shard still recorded as running died.
                Some(RunStatus::Running) => "killed".to_string(),
                Some(s) => serde_json::to_value(s).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default(),
            };
            report.shards.push(ShardState {
                shard: format!("{i}/{n}"),
                status,
                run: last.map(|r| r.id.clone()),
                executed: last.map_or(0, |r| r.executed()),
                cached: last.map_or(0, |r| r.cached()),
                failed: last.map_or(0, |r| r.failed()),
                seconds: last.map_or(0.0, |r| r.seconds),
            });
        }
    }
    report.failed_scenes.sort();
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    fn target() -> Target {
        Target {
            pipeline: "/data/p/curation.ron".into(),
            sets: vec!["dataset.root=/data/my nuscenes".into()],
            cache: "/shared/store".into(),
            out: "/shared/out".into(),
            scenes: None,
            limit: Some(8),
        }
    }

    fn submit(gres: Option<&str>) -> Submit {
        Submit {
            shards: 4,
            array_limit: Some(2),
            partition: Some("cpu".into()),
            cpus_per_task: 8,
            sbatch: vec!["--time=2:00:00".into()],
            gres: gres.map(String::from),
            gpu_shards: 2,
            gpu_partition: Some("gpu".into()),
            dry_run: true,
        }
    }

    #[test]
    fn the_array_runs_one_shard_per_task_of_the_scenes_with_work_and_the_merge_runs_after() {
        let pending = Pending {
            scenes: vec!["s1".into(), "s2".into(), "s3".into()],
            tasks: 30,
            all_scenes: 5,
            has_workers: false,
        };
        let jobs = jobs(&target(), &submit(None), &pending, "curation-1", Path::new("/opt/dist4d")).unwrap();
        assert_eq!(jobs.len(), 2);
        let array = &jobs[0];
        assert_eq!(array.array.as_deref(), Some("0-2%2"), "3 scenes with work: 3 shards, not 4");
        for want in [
            "#SBATCH --partition=cpu\n",
            "#SBATCH --cpus-per-task=8\n",
            "#SBATCH --time=2:00:00\n",
            "#SBATCH --output=/shared/store/slurm/curation-1/shard-%a.log\n",
            "exec /opt/dist4d run /data/p/curation.ron --cache /shared/store --out /shared/out --set 'dataset.root=/data/my nuscenes' --limit 8 --scenes s1,s2,s3 --group curation-1",
            "--shard \"${SLURM_ARRAY_TASK_ID}/3\"",
            "--jobs \"${SLURM_CPUS_PER_TASK:-1}\"",
        ] {
            assert!(array.script.contains(want), "{want} not in\n{}", array.script);
        }
        assert!(!array.script.contains("--defer-workers"));
        let merge = &jobs[1];
        assert_eq!((merge.array.as_ref(), &merge.after), (None, &vec![0]));
        assert!(
            merge.script.contains(" merge /data/p/curation.ron ")
                && merge.script.contains("--group curation-1 --shards 3")
        );
        let ids = vec!["101".to_string()];
        assert_eq!(
            sbatch_args(merge, &ids, Path::new("/s/merge.sh")),
            ["--parsable", "--dependency=afterany:101", "/s/merge.sh"]
        );
    }

    #[test]
    fn worker_stages_go_to_a_gpu_array_after_the_cpu_array_when_a_gres_is_given() {
        let pending = Pending {
            scenes: (0..10).map(|i| format!("s{i}")).collect(),
            tasks: 99,
            all_scenes: 10,
            has_workers: true,
        };
        let jobs = jobs(&target(), &submit(Some("gpu:1")), &pending, "g", Path::new("/opt/dist4d")).unwrap();
        assert_eq!(jobs.iter().map(|j| j.name).collect::<Vec<_>>(), ["array", "gpu-array", "merge"]);
        assert!(jobs[0].script.contains("--defer-workers"), "the CPU array leaves the worker stages");
        assert!(
            jobs[1].script.contains("#SBATCH --gres=gpu:1\n") && jobs[1].script.contains("#SBATCH --partition=gpu\n")
        );
        assert!(!jobs[1].script.contains("--defer-workers") && jobs[1].script.contains("/2\""));
        assert_eq!((jobs[1].array.as_deref(), &jobs[1].after), (Some("0-1%2"), &vec![0]));
        assert_eq!(jobs[2].after, vec![0, 1]);
        assert!(jobs[2].script.contains("#SBATCH --gres=gpu:1\n"), "the merge retries worker tasks too");
        assert!(jobs[2].script.contains("--shards 4 --gpu-shards 2"));
        // Without worker stages, --gres changes nothing.
        let cpu_only = Pending { has_workers: false, ..pending };
        assert_eq!(super::jobs(&target(), &submit(Some("gpu:1")), &cpu_only, "g", Path::new("/b")).unwrap().len(), 2);
    }

    #[test]
    fn sbatch_directives_quote_values_with_spaces() {
        assert_eq!(directive("--output=/a b/shard-%a.log"), "--output=\"/a b/shard-%a.log\"");
        assert_eq!(directive("--comment=say \"hi\""), "--comment=\"say \\\"hi\\\"\"");
        assert_eq!(directive("--time=2:00:00"), "--time=2:00:00");
        assert_eq!(directive("--exclusive"), "--exclusive");
        let spaced = Target { cache: "/shared/my store".into(), ..target() };
        let pending = Pending { scenes: vec!["s1".into()], tasks: 1, all_scenes: 1, has_workers: false };
        let jobs = jobs(&spaced, &submit(None), &pending, "g-1", Path::new("/b")).unwrap();
        assert!(
            jobs[0].script.contains("#SBATCH --output=\"/shared/my store/slurm/g-1/shard-%a.log\"\n"),
            "{}",
            jobs[0].script
        );
        assert!(jobs[0].script.contains("#SBATCH --job-name=shard-g\n"), "the role first: {}", jobs[0].script);
        let none = Submit { shards: 0, ..submit(None) };
        assert!(super::jobs(&target(), &none, &pending, "g-1", Path::new("/b")).is_err());
    }

    #[test]
    fn a_group_without_a_merge_report_is_found_unmerged() {
        let store = tempfile::tempdir().unwrap();
        for (group, merged) in [("curation-100", true), ("curation-200", false), ("occupancy-300", false)] {
            let dir = store.path().join("slurm").join(group);
            std::fs::create_dir_all(&dir).unwrap();
            if merged {
                std::fs::write(dir.join("report.json"), b"{}").unwrap();
            }
        }
        assert_eq!(unmerged_groups(store.path(), "curation"), ["curation-200"]);
        assert!(unmerged_groups(&store.path().join("nowhere"), "curation").is_empty());
    }

    #[test]
    fn words_are_quoted_for_bash() {
        assert_eq!(shell_word("plain/path.ron"), "plain/path.ron");
        assert_eq!(shell_word("it's here"), "'it'\\''s here'");
        assert_eq!(shell_word("$HOME"), "'$HOME'");
        assert_eq!(shell_word("${SLURM_ARRAY_TASK_ID}/4"), "\"${SLURM_ARRAY_TASK_ID}/4\"");
    }

    #[test]
    fn the_merge_reads_each_shards_last_record() {
        let rec = |shard: Option<(u32, u32)>, status: RunStatus, failed: &[&str]| RunRecord {
            id: "r".into(),
            pipeline: "p".into(),
            pipeline_path: String::new(),
            pipeline_digest: String::new(),
            started: 0,
            seconds: 1.0,
            status,
            jobs: 1,
            stages: vec![],
            failures: failed
                .iter()
                .map(|i| dist4d_runtime::runs::Failure { stage: "s".into(), item: i.to_string(), error: "e".into() })
                .collect(),
            exported: 0,
            out_dir: None,
            group: Some("g".into()),
            shard,
            writer: None,
            dataset: None,
            sets: vec![],
        };
        let runs = vec![
            rec(Some((0, 3)), RunStatus::Failed, &["scene-a/003/CAM_FRONT"]),
            rec(Some((2, 3)), RunStatus::Interrupted, &[]),
            rec(Some((0, 3)), RunStatus::Failed, &["scene-b/001", "scene-b/002"]),
        ];
        let r = shards_report(&runs, "g", &[3]);
        assert_eq!(r.failed_scenes, ["scene-b"], "the last record of shard 0 counts");
        assert_eq!(r.unfinished(), 2, "shard 1 never recorded, shard 2 was interrupted");
        assert!(r.lines()[1].starts_with("shard 1/3: no run record"), "{:?}", r.lines());
        assert!(shards_report(&runs, "other", &[3]).failed_scenes.is_empty());
        // A shard still recorded as running when the merge runs was killed.
        let killed = [rec(Some((0, 1)), RunStatus::Running, &[])];
        let r = shards_report(&killed, "g", &[1]);
        assert_eq!((r.unfinished(), r.shards[0].status.as_str()), (1, "killed"));
        assert!(r.lines()[0].starts_with("shard 0/1: killed"), "{:?}", r.lines());
    }
}
