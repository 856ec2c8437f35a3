//! `dist4d export-infos`: the info pickles nuScenes-based generators train on.

use anyhow::Result;
use std::path::PathBuf;
use std::process::ExitCode;

/// Writes the pickles of every split asked for (each whole or not at all) and lists them.
pub fn run(
    root: PathBuf,
    version: String,
    out: Option<PathBuf>,
    path_prefix: String,
    max_sweeps: Option<usize>,
    split: Vec<String>,
) -> Result<ExitCode> {
    use dist4d_datasets::nuscenes::infos::{write_infos, InfosOptions};
    let out = out.unwrap_or_else(|| root.clone());
    let r = write_infos(&InfosOptions { root, version, out, path_prefix, max_sweeps, splits: split })?;
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    for f in &r.files {
        println!(
            "{}: {} {} samples of {} scene(s), {} in scene_tokens",
            f.path.display(),
            f.samples,
            f.split,
            f.scenes,
            f.scene_lists
        );
    }
    Ok(ExitCode::SUCCESS)
}
