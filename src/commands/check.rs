//! `dist4d check`: a pipeline file checked without running it.

use crate::cli::PipelineArgs;
use crate::load::load;
use anyhow::Result;
use dist4d_stages::Registry;
use std::process::ExitCode;

/// Prints every problem of the pipeline (exit 2), or a line saying it is fine.
pub fn run(registry: &Registry, p: &PipelineArgs) -> Result<ExitCode> {
    let pipeline = match load(p, registry)? {
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
