//! `dist4d eval`: a pipeline run, then the scores of its EvalDepth stages tabulated.

use crate::cli::PipelineArgs;
use crate::execute::run_pipeline;
use anyhow::Result;
use dist4d_graph::Pipeline;
use dist4d_stages::Registry;
use std::path::PathBuf;
use std::process::ExitCode;

/// Runs the pipeline (cached tasks are not redone) and prints its score tables.
pub fn run(
    registry: &Registry,
    p: &PipelineArgs,
    jobs: Option<usize>,
    out: Option<PathBuf>,
    progress: &str,
) -> Result<ExitCode> {
    // A pipeline that cannot be reported on fails before its run, not after.
    let reportable = |p: &Pipeline| dist4d_stages::eval::report::scored_stages(p).map(|_| ());
    let (pipeline, out_dir, code) = match run_pipeline(registry, p, reportable, jobs, false, out, progress, |_| ())? {
        Ok(x) => x,
        Err(code) => return Ok(code),
    };
    // A stopped run has not exported every score: say how it ended, not what is missing.
    if code == ExitCode::SUCCESS || code == ExitCode::from(1) {
        print!("{}", dist4d_stages::eval::report::tables(&pipeline, &out_dir)?);
    }
    Ok(code)
}
