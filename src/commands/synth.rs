//! `dist4d synth`: a nuScenes-format dataset of a procedural street, with exact ground truth.

use anyhow::Result;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Writes the dataset `out` (deterministic per seed), or finds it already there.
#[allow(clippy::too_many_arguments)]
pub fn run(
    out: PathBuf,
    seed: u64,
    scenes: u32,
    keyframes: u32,
    width: u32,
    height: u32,
    camera_sweeps: bool,
    no_lidar_sweeps: bool,
    no_ground_truth: bool,
) -> Result<ExitCode> {
    let config = dist4d_synth::SynthConfig {
        seed,
        scenes,
        keyframes,
        width,
        height,
        camera_sweeps,
        lidar_sweeps: !no_lidar_sweeps,
        ground_truth: !no_ground_truth,
        ..Default::default()
    };
    synthesize(&config, &out)?;
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
