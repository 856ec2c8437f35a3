//! `dist4d synth`: a nuScenes-format dataset of a procedural street, with exact ground truth.

use crate::cli::SynthArgs;
use anyhow::Result;
use std::path::Path;
use std::process::ExitCode;

/// Writes the dataset `args.out` (deterministic per seed), or finds it already there.
pub fn run(args: SynthArgs) -> Result<ExitCode> {
    let config = dist4d_synth::SynthConfig {
        seed: args.seed,
        scenes: args.scenes,
        keyframes: args.keyframes,
        width: args.width,
        height: args.height,
        camera_sweeps: args.camera_sweeps,
        lidar_sweeps: !args.no_lidar_sweeps,
        ground_truth: !args.no_ground_truth,
        ..Default::default()
    };
    synthesize(&config, &args.out)?;
    Ok(ExitCode::SUCCESS)
}

/// Writes a synthetic dataset (or finds it already there) and says so.
pub fn synthesize(config: &dist4d_synth::SynthConfig, out: &Path) -> Result<()> {
    match dist4d_synth::write_dataset(config, out, &|m| eprintln!("synth: {m}"))? {
        None => println!("{}: the synthetic dataset is already there", out.display()),
        Some(s) => println!(
            "{}: {} scenes, {} samples, {} LiDAR sweeps, {} camera images, {} annotations in {:.1}s",
            out.display(),
            s.scenes,
            s.samples,
            s.lidar_sweeps,
            s.camera_images,
            s.annotations,
            s.seconds
        ),
    }
    Ok(())
}
