//! A command's pipeline: loaded from its arguments and checked, and its dataset root refused
//! before anything runs when it cannot be read.

use crate::cli::PipelineArgs;
use anyhow::Result;
use dist4d_graph::{load_file, Pipeline};
use dist4d_stages::Registry;
use std::process::ExitCode;

/// For a command that reads the pipeline's data: a root that does not exist or holds another
/// kind's data is, like a bad pipeline, a problem of the command line (exit 2), found before
/// anything runs. (`check` only notes a missing root: the data may live on the cluster.)
pub fn refuse_dataset_root(args: &PipelineArgs, registry: &Registry, pipeline: &Pipeline) -> Option<ExitCode> {
    let problem = registry.dataset_root_problem(pipeline)?;
    eprintln!("error: {}: {problem}", args.pipeline.display());
    Some(ExitCode::from(2))
}

/// Loads and checks a pipeline; a bad one prints every problem and exits 2.
pub fn load(args: &PipelineArgs, registry: &Registry) -> Result<Result<Pipeline, ExitCode>> {
    let cwd = std::env::current_dir()?;
    Ok(match load_file(&args.pipeline, &args.sets, &cwd, registry) {
        Ok(p) => Ok(p),
        Err(e) => {
            eprint!("{}", e.render());
            Err(ExitCode::from(2))
        }
    })
}
