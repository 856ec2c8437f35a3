//! `dist4d graph`: the stage DAG as Graphviz DOT.

use crate::cli::PipelineArgs;
use crate::load::load;
use anyhow::Result;
use dist4d_stages::Registry;
use std::process::ExitCode;

/// Prints the loaded pipeline's DAG.
pub fn run(registry: &Registry, p: &PipelineArgs) -> Result<ExitCode> {
    let pipeline = match load(p, registry)? {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    print!("{}", pipeline.to_dot());
    Ok(ExitCode::SUCCESS)
}
