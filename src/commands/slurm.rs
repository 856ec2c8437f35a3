//! `dist4d slurm`: a pipeline submitted to Slurm, a job array over the scenes with work left and
//! a merge job after it (the scripts themselves: `crate::slurm`).

use crate::cli::PipelineArgs;
use crate::load::{load, refuse_dataset_root};
use crate::slurm;
use anyhow::{Context, Result};
use dist4d_runtime::{exec::Engine, Access, Store};
use dist4d_stages::Registry;
use std::path::PathBuf;
use std::process::ExitCode;

/// Plans on this node, then writes and submits the job scripts.
pub fn run(registry: &Registry, p: &PipelineArgs, out: Option<PathBuf>, submit: &slurm::Submit) -> Result<ExitCode> {
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
