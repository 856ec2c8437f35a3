//! `dist4d occ3d-annotations`: the per-scene parts of Occ3D's annotations.json that
//! `pipelines/occupancy.ron` exports, merged into one file with the splits.

use anyhow::{Context, Result};
use std::path::PathBuf;
use std::process::ExitCode;

/// Merges OUT/occ3d/scenes/<scene>.json into OUT/annotations.json (written whole or not at all);
/// the scenes `val` are the validation split, the others training.
pub fn run(out: PathBuf, val: Vec<String>) -> Result<ExitCode> {
    let dir = out.join("occ3d/scenes");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .with_context(|| {
            format!("reading {} (run pipelines/occupancy.ron into {} first)", dir.display(), out.display())
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    files.sort();
    let mut parts = Vec::new();
    for f in &files {
        let text = std::fs::read(f).with_context(|| format!("reading {}", f.display()))?;
        parts.push(serde_json::from_slice(&text).with_context(|| format!("{} is not JSON", f.display()))?);
    }
    anyhow::ensure!(!parts.is_empty(), "{} holds no scene's part", dir.display());
    let merged = dist4d_stages::occupancy::annotations::merge(&parts, &val)?;
    let target = out.join("annotations.json");
    let tmp = out.join(".annotations.json.tmp");
    std::fs::write(&tmp, serde_json::to_vec(&merged)?).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &target).with_context(|| format!("writing {}", target.display()))?;
    let frames: usize = merged["scene_infos"]
        .as_object()
        .map_or(0, |s| s.values().filter_map(|v| v.as_object()).map(|f| f.len()).sum());
    println!(
        "{}: {} scene(s) ({} train, {} val), {frames} frames",
        target.display(),
        parts.len(),
        merged["train_split"].as_array().map_or(0, Vec::len),
        merged["val_split"].as_array().map_or(0, Vec::len)
    );
    Ok(ExitCode::SUCCESS)
}
