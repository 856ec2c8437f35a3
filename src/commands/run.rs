//! `dist4d run`: a pipeline run; only the tasks whose inputs, params or stage version changed
//! are executed.

use crate::cli::PipelineArgs;
use crate::execute::run_pipeline;
use anyhow::Result;
use dist4d_runtime::RunOptions;
use dist4d_stages::Registry;
use std::path::PathBuf;
use std::process::ExitCode;

/// Runs the pipeline; the exit code says how the run ended (see `Command::Run`).
#[allow(clippy::too_many_arguments)]
pub fn run(
    registry: &Registry,
    p: &PipelineArgs,
    jobs: Option<usize>,
    fail_fast: bool,
    out: Option<PathBuf>,
    progress: &str,
    group: Option<String>,
    defer_workers: bool,
) -> Result<ExitCode> {
    let tweak = |o: &mut RunOptions| {
        o.group = group;
        o.defer_resources = defer_workers;
    };
    Ok(run_pipeline(registry, p, |_| Ok(()), jobs, fail_fast, out, progress, tweak)?
        .map_or_else(|code| code, |(_, _, code)| code))
}
