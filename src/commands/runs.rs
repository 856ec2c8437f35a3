//! `dist4d runs`: the runs recorded in a store, a line per run or group of runs (or JSON).

use crate::commands::default_store;
use crate::execute::printable;
use anyhow::Result;
use std::path::PathBuf;
use std::process::ExitCode;

/// Lists the runs of the store `cache` (or the default one); the shards and merge of one
/// submission are one line.
pub fn run(cache: Option<PathBuf>, json: bool) -> Result<ExitCode> {
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
            if group.len() > 1 { (last.cached() + last.executed()).saturating_sub(executed) } else { last.cached() },
            last.failed(),
            end - first.started as f64,
            run_inputs(first)
        );
    }
    Ok(ExitCode::SUCCESS)
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
