//! End-to-end on a real Slurm: `dist4d slurm` submits a job array and a merge job to a
//! single-node cluster started on this machine (scripts/slurm-single-node.sh: Debian's
//! slurm-wlm with munge). One shard is cancelled mid-run (`scancel`); the merge job reports the
//! missing work; the same command resubmitted runs only the scenes with work left; the final
//! outputs are byte for byte those of one process.
//!
//! Skipped, saying so, where Slurm cannot be had (not root and not installed).

mod common;
use common::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// The cluster, stopped when dropped.
struct Cluster {
    dir: PathBuf,
    conf: PathBuf,
}

impl Cluster {
    fn start(dir: &Path) -> Option<Cluster> {
        // A port of its own, away from a cluster the user may run on the default one.
        let base = 20_000 + (std::process::id() % 20_000) * 2;
        let o = Command::new(repo().join("scripts/slurm-single-node.sh"))
            .args(["start", dir.to_str().unwrap()])
            .env("SLURM_PORT_BASE", base.to_string())
            .output()
            .unwrap();
        match o.status.code() {
            Some(0) => Some(Cluster { dir: dir.to_path_buf(), conf: dir.join("slurm.conf") }),
            Some(3) => {
                eprintln!("SKIPPED: no Slurm here: {}", text(&o));
                None
            }
            _ => panic!("the single-node Slurm did not start: {}", text(&o)),
        }
    }

    fn cmd(&self, program: &str) -> Command {
        let mut c = Command::new(program);
        c.env("SLURM_CONF", &self.conf);
        c
    }

    /// The state of job `id` (`RUNNING`, `PENDING`, ...), None once it has left the queue.
    fn state(&self, id: &str) -> Option<String> {
        let o = self.cmd("squeue").args(["-h", "-j", id, "-o", "%T"]).output().unwrap();
        let s = String::from_utf8_lossy(&o.stdout).trim().to_string();
        (!s.is_empty()).then_some(s)
    }

    fn wait_gone(&self, ids: &[&str], what: &str) {
        let started = Instant::now();
        while ids.iter().any(|id| self.state(id).is_some()) {
            assert!(started.elapsed() < Duration::from_secs(300), "{what} still queued after 5 minutes");
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new(repo().join("scripts/slurm-single-node.sh"))
            .args(["stop", self.dir.to_str().unwrap()])
            .output();
    }
}

/// The job ids `dist4d slurm` printed ("submitted array as job 12 (array 0-1)").
fn submitted(out: &str) -> BTreeMap<String, String> {
    out.lines()
        .filter_map(|l| l.strip_prefix("submitted "))
        .map(|l| {
            let mut w = l.split_whitespace();
            let name = w.next().unwrap().to_string();
            (name, w.nth(2).unwrap().to_string())
        })
        .collect()
}

#[test]
fn a_submission_with_a_cancelled_shard_resubmitted_gives_the_bytes_of_one_process() {
    let tmp = tempfile::tempdir().unwrap();
    let Some(cluster) = Cluster::start(&tmp.path().join("slurm")) else { return };
    let data = tmp.path().join("data");
    let o = dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--scenes",
        "4",
        "--keyframes",
        "5",
        "--width",
        "480",
        "--height",
        "270",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let pipeline = repo().join("pipelines/curation.ron");
    let root = format!("dataset.root={}", data.display());
    let (store, out) = (tmp.path().join("store"), tmp.path().join("out"));

    let reference = tmp.path().join("reference");
    let o = dist4d(&[
        "run",
        pipeline.to_str().unwrap(),
        "--set",
        &root,
        "--cache",
        tmp.path().join("reference-store").to_str().unwrap(),
        "--out",
        reference.to_str().unwrap(),
        "--progress",
        "off",
    ]);
    assert!(o.status.success(), "{}", text(&o));

    let submit = || {
        let o = cluster
            .cmd(bin().to_str().unwrap())
            .args(["slurm", pipeline.to_str().unwrap(), "--set", &root])
            .args(["--cache", store.to_str().unwrap(), "--out", out.to_str().unwrap()])
            .args(["--shards", "2", "--cpus-per-task", "1"])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", text(&o));
        text(&o)
    };
    let first = submit();
    assert!(first.contains("4 of 4 scenes have work left"), "{first}");
    let ids = submitted(&first);
    let (array, merge) = (ids["array"].clone(), ids["merge"].clone());

    // Shard 1 is cancelled once it has been running for a moment (mid-run: a shard takes
    // several seconds). scancel sends SIGTERM: dist4d stops cleanly and records the run as
    // interrupted.
    let task = format!("{array}_1");
    let started = Instant::now();
    while cluster.state(&task).as_deref() != Some("RUNNING") {
        assert!(started.elapsed() < Duration::from_secs(120), "shard 1 never ran");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(1500));
    let o = cluster.cmd("scancel").arg(&task).output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    cluster.wait_gone(&[&array, &merge], "the first submission");

    // The newest submission's scripts and logs (group names end in the submission time).
    let newest_group = || -> PathBuf {
        let mut groups: Vec<PathBuf> =
            std::fs::read_dir(store.join("slurm")).unwrap().map(|e| e.unwrap().path()).collect();
        groups.sort();
        groups.pop().unwrap()
    };
    let merge_log = std::fs::read_to_string(newest_group().join("merge.log")).unwrap();
    assert!(merge_log.contains("shard 0/2: Complete"), "{merge_log}");
    assert!(
        merge_log.contains("shard 1/2: Interrupted") || merge_log.contains("shard 1/2: no run record"),
        "{merge_log}"
    );
    assert!(
        merge_log.contains("tasks are missing") && merge_log.contains("rerun the same `dist4d slurm` command"),
        "{merge_log}"
    );
    let runs = text(&dist4d(&["runs", "--cache", store.to_str().unwrap()]));
    assert!(runs.contains("Incomplete") && runs.contains("2 shard runs + merge"), "{runs}");

    // Resubmitted: only the scenes the cancelled shard left unfinished become shards.
    let second = submit();
    assert!(!second.contains("no merge report yet"), "the first group's merge reported: {second}");
    let left: usize =
        second.split(" of 4 scenes have work left").next().unwrap().rsplit(' ').next().unwrap().parse().unwrap();
    assert!((1..=2).contains(&left), "{second}");
    let ids = submitted(&second);
    cluster.wait_gone(&[&ids["array"], &ids["merge"]], "the resubmission");
    let merge_log = std::fs::read_to_string(newest_group().join("merge.log")).unwrap();
    assert!(merge_log.contains("Complete in") && !merge_log.contains("missing"), "{merge_log}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(newest_group().join("report.json")).unwrap()).unwrap();
    assert_eq!((report["status"].as_str(), report["missing"].as_u64()), (Some("complete"), Some(0)), "{report}");

    let (got, want): (BTreeMap<_, _>, BTreeMap<_, _>) =
        (tree(&out).into_iter().collect(), tree(&reference).into_iter().collect());
    assert_eq!(got.keys().collect::<Vec<_>>(), want.keys().collect::<Vec<_>>());
    for (path, bytes) in &want {
        assert!(got[path] == *bytes, "{path} differs between the cluster and one process");
    }
    // Nothing half-written anywhere.
    for dir in [store.join("tmp"), out.join(".dist4d-tmp")] {
        let left: Vec<_> = std::fs::read_dir(&dir).map(|d| d.map(|e| e.unwrap().path()).collect()).unwrap_or_default();
        assert!(left.is_empty(), "left in {}: {left:?}", dir.display());
    }
    let runs = text(&dist4d(&["runs", "--cache", store.to_str().unwrap()]));
    assert_eq!(runs.lines().count(), 2, "two submissions, two runs: {runs}");
    assert!(runs.lines().last().unwrap().contains("Complete"), "{runs}");
    // Everything is cached now: nothing to submit.
    let third = submit();
    assert!(third.contains("nothing to submit"), "{third}");
}
