//! `dist4d export-12hz`: the 12 Hz nuScenes tables ASAP's users load.

use anyhow::Result;
use std::path::PathBuf;
use std::process::ExitCode;

/// Writes the interp_12Hz tables of `root`'s `version` into `out` (default beside them) and says
/// how to load them.
pub fn run(root: PathBuf, version: String, out: Option<PathBuf>, drop_lone_tracks: bool) -> Result<ExitCode> {
    use dist4d_datasets::nuscenes::{interp12hz, LoneTracks, NuScenesConfig};
    let config = NuScenesConfig {
        root: root.to_string_lossy().into_owned(),
        version: version.clone(),
        lone_tracks: if drop_lone_tracks { LoneTracks::Drop } else { LoneTracks::Extrapolate },
        ..Default::default()
    };
    let out = out.unwrap_or_else(|| interp12hz::default_folder(&root, &version));
    let r = interp12hz::write_interp_12hz(&config, &out)?;
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    println!(
        "{}: {} scene(s), {} samples ({} keyframes, {} camera rounds between), {} interpolated annotations ({} extrapolated)",
        out.display(),
        r.scenes,
        r.samples,
        r.keyframes,
        r.samples - r.keyframes,
        r.annotations,
        r.extrapolated
    );
    for line in interp12hz::how_to_load(&root, &out) {
        println!("{line}");
    }
    Ok(ExitCode::SUCCESS)
}
