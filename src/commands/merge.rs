//! `dist4d merge`: the last job of a `dist4d slurm` submission.

use crate::cli::PipelineArgs;
use crate::execute::{execute, progress_mode};
use crate::load::load;
use crate::slurm;
use anyhow::{Context, Result};
use dist4d_runtime::RunOptions;
use dist4d_stages::Registry;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Reports the group's shards, retries the scenes with failed items (unless `no_retry`), collects
/// the rest from the cache, and writes the group's report.
#[allow(clippy::too_many_arguments)]
pub fn run(
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
