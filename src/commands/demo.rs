//! `dist4d demo`: a small synthetic dataset and the shipped pipeline run on it.

use super::synth::synthesize;
use crate::cli::PipelineArgs;
use crate::execute::run_pipeline;
use anyhow::{Context, Result};
use dist4d_stages::Registry;
use std::path::Path;
use std::process::ExitCode;

/// The shipped pipeline the demo runs, built into the binary so the demo works from anywhere.
const DEMO_PIPELINE: &str = include_str!("../../pipelines/curation.ron");

/// `dist4d demo`: synthesize a small dataset (once), write the shipped pipeline beside it as it
/// ships (its `root: "../data/nuscenes"` finds the data in the same layout as in the repository),
/// run it with the default store and output folder, and print its scores.
pub fn run(dir: &Path, keyframes: u32, width: u32, height: u32, progress: &str) -> Result<ExitCode> {
    let data = dir.join("data/nuscenes");
    let config = dist4d_synth::SynthConfig { keyframes, width, height, ..Default::default() };
    synthesize(&config, &data)?;
    let pipeline_file = dir.join("pipelines/curation.ron");
    if std::fs::read_to_string(&pipeline_file).ok().as_deref() != Some(DEMO_PIPELINE) {
        std::fs::create_dir_all(dir.join("pipelines"))?;
        std::fs::write(&pipeline_file, DEMO_PIPELINE)
            .with_context(|| format!("writing {}", pipeline_file.display()))?;
    }
    let registry = Registry::default();
    let args = PipelineArgs {
        pipeline: pipeline_file.clone(),
        sets: vec![],
        cache: None,
        scenes: None,
        limit: None,
        shard: None,
    };
    let (pipeline, out_dir, code) =
        match run_pipeline(&registry, &args, |_| Ok(()), None, false, None, progress, |_| ())? {
            Ok(x) => x,
            Err(code) => return Ok(code),
        };
    print!("{}", dist4d_stages::eval::report::tables(&pipeline, &out_dir)?);
    println!();
    println!("demo outputs:");
    println!("  synthetic nuScenes dataset   {}", data.display());
    println!("  its ground truth             {}", data.join("groundtruth").display());
    println!("  dense depth per camera       {}", out_dir.display());
    println!("  e.g. open                    {}", out_dir.join("synth-0000/sheets/001.png").display());
    println!("  rerun or edit the pipeline   dist4d run {}", pipeline_file.display());
    Ok(code)
}
