//! Run records: one JSON file per run under `<store>/runs/`, plus the task keys it used.

use crate::store::Store;
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct StageStats {
    pub stage: String,
    pub kind: String,
    pub grain: String,
    /// Tasks planned for this run.
    pub total: u64,
    pub executed: u64,
    pub cached: u64,
    pub failed: u64,
    /// Not run because an input failed.
    pub skipped: u64,
    /// Finished with nothing to make (see [`crate::Made::Nothing`]), or passed over because an
    /// input they need had nothing; counted here and not as failed.
    #[serde(default)]
    pub not_applicable: u64,
    /// Finished tasks run again because a blob of theirs was found missing or corrupt.
    #[serde(default)]
    pub recomputed: u64,
    /// Not cached and not executed: the run executed only some items' tasks (a merge job
    /// collecting what a cluster array made; see `RunOptions::execute_only`).
    #[serde(default)]
    pub missing: u64,
    /// Left by request to a later run: tasks served by a model worker, and what reads them, in
    /// a run with `--defer-workers` (the CPU array of a GPU submission). Not missing: the run
    /// did what it was asked.
    #[serde(default)]
    pub deferred: u64,
    /// Summed run time of executed tasks.
    pub seconds: f64,
    /// Why this stage made nothing for some items: the reason its first task (by item label)
    /// with nothing to make gave ([`crate::Made::Nothing`]), and that item. `None` when no task
    /// of this run said (none had nothing, or those that had were cached or passed over).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nothing: Option<(String, String)>,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Failure {
    pub stage: String,
    /// The item's path of labels, e.g. `s0/003/cam2`.
    pub item: String,
    /// The error and its causes, outermost first, joined by `: `.
    pub error: String,
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum RunStatus {
    /// Every planned task finished.
    Complete,
    /// Some tasks failed; the others finished.
    Failed,
    /// Stopped at the first failure (`--fail-fast`).
    Stopped,
    /// Stopped by Ctrl-C; rerun the same command to continue.
    Interrupted,
    /// No task failed, but some were neither cached nor executed (a run that executes only
    /// some items: see `RunOptions::execute_only`, `defer_resources`).
    Incomplete,
    /// Started and not ended: running now, or killed before it could record its end (its
    /// writer's lease tells which: [`running_or_killed`]).
    Running,
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct RunRecord {
    pub id: String,
    pub pipeline: String,
    pub pipeline_path: String,
    /// Digest of the checked pipeline (stages, params, wiring, dataset config).
    pub pipeline_digest: String,
    /// Unix time in seconds.
    pub started: u64,
    pub seconds: f64,
    pub status: RunStatus,
    pub jobs: usize,
    pub stages: Vec<StageStats>,
    pub failures: Vec<Failure>,
    /// Files written or confirmed in the output directory.
    pub exported: u64,
    pub out_dir: Option<String>,
    /// The group of runs this one belongs to (the shards and merge of one cluster submission).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub group: Option<String>,
    /// The shard (i, n) this run was, if it was one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard: Option<(u32, u32)>,
    /// The store writer id of the process (its lease says whether a `Running` run still runs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub writer: Option<String>,
    /// The dataset the run read: its kind and checked config ([`dataset_identity`]). Pipelines
    /// of one name run on several datasets into one store, and their item keys (indices) collide:
    /// `explain` compares a task with the records of runs on the same dataset. `None` in runs
    /// recorded before it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dataset: Option<String>,
    /// The `--set` overrides the run was given, as typed: what tells two runs of one file apart.
    #[serde(default)]
    pub sets: Vec<String>,
}

impl RunRecord {
    pub fn executed(&self) -> u64 {
        self.stages.iter().map(|s| s.executed).sum()
    }
    pub fn cached(&self) -> u64 {
        self.stages.iter().map(|s| s.cached).sum()
    }
    pub fn failed(&self) -> u64 {
        self.stages.iter().map(|s| s.failed).sum()
    }
    pub fn missing(&self) -> u64 {
        self.stages.iter().map(|s| s.missing).sum()
    }
    pub fn deferred(&self) -> u64 {
        self.stages.iter().map(|s| s.deferred).sum()
    }

    /// Whether this run read the dataset `identity` ([`dataset_identity`]); a run recorded
    /// without one may have. The same kind at the same root is the same dataset whatever its
    /// other settings: a changed setting (`frames`, `lone_tracks`) is a reason for `explain` to
    /// give (inputs changed), not another dataset.
    pub fn read_dataset(&self, identity: &str) -> bool {
        same_dataset(self.dataset.as_deref(), identity)
    }

    /// The dataset as a listing shows it: `NuScenes /data/nuscenes` (its kind and root).
    pub fn dataset_label(&self) -> Option<String> {
        let d = self.dataset.as_deref()?;
        let (kind, config) = d.split_at(d.find('(').unwrap_or(d.len()));
        Some(match string_field(config, "root") {
            Some(root) => format!("{kind} {root}"),
            None => d.to_string(),
        })
    }
}

/// A pipeline's dataset as run records name it: its kind and canonical config (`NuScenes(root:..)`),
/// the root resolved (`pipelines/../data` from `dist4d run pipelines/x.ron` and `/repo/data` from
/// an absolute path are one dataset).
pub fn dataset_identity(p: &dist4d_graph::Pipeline) -> String {
    let canonical = &p.dataset.config.canonical;
    let resolved = string_field(canonical, "root").and_then(|root| {
        let real = std::fs::canonicalize(&root).ok()?.display().to_string();
        Some(canonical.replacen(&format!("{root:?}"), &format!("{real:?}"), 1))
    });
    format!("{}{}", p.dataset.kind, resolved.as_deref().unwrap_or(canonical))
}

/// Whether a run that recorded dataset `recorded` read the dataset `identity` (see
/// [`RunRecord::read_dataset`]).
fn same_dataset(recorded: Option<&str>, identity: &str) -> bool {
    let place = |d: &str| -> (String, Option<String>) {
        let (kind, config) = d.split_at(d.find('(').unwrap_or(d.len()));
        (kind.to_string(), string_field(config, "root"))
    };
    recorded.is_none_or(|d| match (place(d), place(identity)) {
        ((k1, Some(r1)), (k2, Some(r2))) => k1 == k2 && r1 == r2,
        _ => d == identity,
    })
}

/// A string field of canonical params text (`(root:"/data",version:"v1.0-mini")`).
fn string_field(canonical: &str, field: &str) -> Option<String> {
    let mut sources = dist4d_graph::source::Sources::default();
    let id = sources.add("", canonical);
    let value = dist4d_graph::syntax::parse_value(canonical, id).ok()?;
    value.field(field).and_then(|f| f.value.as_str()).map(String::from)
}

/// Path of the list of task keys a run used (32 bytes each), which `gc` keeps alive.
pub fn keys_path(store: &Store, id: &str) -> PathBuf {
    store.runs_dir().join(format!("{id}.keys"))
}

pub fn write_run(store: &Store, rec: &RunRecord) -> Result<()> {
    let json = serde_json::to_vec_pretty(rec)?;
    store.write_atomic(&store.runs_dir().join(format!("{}.json", rec.id)), &json)
}

/// Rewrites a run's record in its own file, where [`write_run`] would write a new file and rename
/// it: for a run stopped by a full disk, whose record file already holds the blocks it needs.
/// Not atomic (a crash meanwhile leaves a record `dist4d runs` skips with a warning), so only
/// when [`write_run`] failed.
pub fn overwrite_run(store: &Store, rec: &RunRecord) -> Result<()> {
    use std::io::Write;
    let json = serde_json::to_vec(rec)?;
    let path = store.runs_dir().join(format!("{}.json", rec.id));
    let mut f =
        std::fs::OpenOptions::new().write(true).open(&path).with_context(|| format!("opening {}", path.display()))?;
    // Compact JSON: shorter than the pretty record it replaces, so it needs no new block.
    f.write_all(&json)
        .and_then(|_| f.set_len(json.len() as u64))
        .and_then(|_| f.sync_all())
        .with_context(|| format!("writing {}", path.display()))
}

/// All run records in the store, oldest first.
pub fn list_runs(runs_dir: &Path) -> Result<Vec<RunRecord>> {
    let mut out = Vec::new();
    let rd = match std::fs::read_dir(runs_dir) {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(out),
        Err(e) => return Err(e).with_context(|| format!("listing {}", runs_dir.display())),
    };
    for e in rd {
        let p = e?.path();
        if p.extension().is_some_and(|x| x == "json") {
            let text = std::fs::read(&p).with_context(|| format!("reading {}", p.display()))?;
            match serde_json::from_slice::<RunRecord>(&text) {
                Ok(r) => out.push(r),
                Err(e) => eprintln!("warning: skipping unreadable run record {}: {e}", p.display()),
            }
        }
    }
    out.sort_by(|a, b| (a.started, &a.id).cmp(&(b.started, &b.id)));
    Ok(out)
}

/// For a run recorded as [`RunStatus::Running`]: "running" while its process's lease in the
/// store at `root` is live, else "killed" (it ended without recording its end: SIGKILL, a lost
/// node, an out-of-memory kill). `None` for a run that ended.
pub fn running_or_killed(root: &Path, run: &RunRecord) -> Option<&'static str> {
    if run.status != RunStatus::Running {
        return None;
    }
    let live = run.writer.as_ref().is_some_and(|w| {
        let lease = root.join("leases").join(format!("{w}.lease"));
        matches!(crate::lease::judge(&lease, std::time::SystemTime::now()), crate::lease::Liveness::Live(_))
    });
    Some(if live { "running" } else { "killed" })
}

/// Runs as users think of them: the shards and merge of one cluster submission (one group) are
/// one run; a run without a group is one by itself. Oldest first (by first start), each
/// group's runs in start order.
pub fn grouped(runs: &[RunRecord]) -> Vec<Vec<&RunRecord>> {
    let mut out: Vec<Vec<&RunRecord>> = Vec::new();
    let mut at: std::collections::HashMap<&str, usize> = std::collections::HashMap::new();
    for r in runs {
        match r.group.as_deref() {
            Some(g) => match at.get(g) {
                Some(&i) => out[i].push(r),
                None => {
                    at.insert(g, out.len());
                    out.push(vec![r]);
                }
            },
            None => out.push(vec![r]),
        }
    }
    out
}

/// A group of runs summed up as one: its status is its last run's that was not a shard (the
/// merge), or, without one, the worst of its shards'.
pub fn group_status(runs: &[&RunRecord]) -> RunStatus {
    if let Some(merge) = runs.iter().rev().find(|r| r.shard.is_none()) {
        return merge.status;
    }
    let worst = |s: RunStatus| match s {
        RunStatus::Complete => 0,
        RunStatus::Incomplete => 1,
        RunStatus::Failed => 2,
        RunStatus::Stopped => 3,
        RunStatus::Interrupted => 4,
        RunStatus::Running => 5,
    };
    runs.iter().map(|r| r.status).max_by_key(|&s| worst(s)).unwrap_or(RunStatus::Complete)
}

/// `2026-11-21 09:15:02 UTC` from Unix seconds.
pub fn format_utc(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02} UTC", rem / 3600, rem % 3600 / 60, rem % 60)
}

pub fn now_secs() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dataset_is_its_kind_and_root_whatever_its_other_settings() {
        let keyframes = r#"NuScenes(root:"/data/nuscenes",version:"v1.0-mini",frames:Keyframes)"#;
        let sweeps = r#"NuScenes(root:"/data/nuscenes",version:"v1.0-mini",frames:Sweeps)"#;
        let other = r#"NuScenes(root:"/data/other",version:"v1.0-mini",frames:Keyframes)"#;
        let dgp = r#"Dgp(root:"/data/nuscenes")"#;
        assert!(same_dataset(Some(keyframes), sweeps), "a changed setting is the same dataset");
        assert!(!same_dataset(Some(keyframes), other));
        assert!(!same_dataset(Some(keyframes), dgp));
        assert!(same_dataset(None, other), "a run recorded without a dataset may have read it");
    }

    #[test]
    fn formats_utc_dates() {
        assert_eq!(format_utc(0), "1970-01-01 00:00:00 UTC");
        assert_eq!(format_utc(1_795_000_000), "2026-11-18 11:06:40 UTC");
    }
}
