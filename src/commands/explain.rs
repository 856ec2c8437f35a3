//! `dist4d explain`: per stage, how many tasks are cached, will run or failed, and why.

use crate::cli::PipelineArgs;
use crate::load::{load, refuse_dataset_root};
use anyhow::Result;
use dist4d_runtime::{exec::Engine, Access, Store};
use dist4d_stages::Registry;
use std::path::PathBuf;
use std::process::ExitCode;

/// Walks the plan a run would execute (with the same --scenes, --limit, --shard and --out)
/// and prints what it would do, reading the store only.
pub fn run(registry: &Registry, p: &PipelineArgs, out: Option<PathBuf>) -> Result<ExitCode> {
    let pipeline = match load(p, registry)? {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    if let Some(code) = refuse_dataset_root(p, registry, &pipeline) {
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
        Some(shard) => {
            Some(dist4d_runtime::exec::shard_labels(&pipeline, dataset.as_ref(), p.scenes.as_deref(), p.limit, shard)?)
        }
        None => p.scenes.clone(),
    };
    let report = dist4d_runtime::explain::explain(&engine, scenes.as_deref(), p.limit, Some(&out_dir))?;
    for s in &report {
        let failed =
            if s.failed_last_run > 0 { format!(", {} failed last run", s.failed_last_run) } else { String::new() };
        let nothing =
            if s.not_applicable > 0 { format!(", {} with nothing to make", s.not_applicable) } else { String::new() };
        println!("{} ({}): {} cached, {} will run{failed}{nothing}", s.stage, s.kind, s.cached, s.will_run);
        for (reason, (n, example)) in &s.reasons {
            println!("    {n} x {reason}  (e.g. {example})");
        }
    }
    Ok(ExitCode::SUCCESS)
}
