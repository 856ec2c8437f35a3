//! Golden digests: the bytes the shipped pipelines export, on a small synthetic seed and on the
//! shared real data, pinned in `tests/golden/*.txt` (one `<blake3> <path>` line per file).
//!
//! Any change in any exported byte fails here, so a restructuring that must not change outputs is
//! checked, and a change that should change them is deliberate: bump the version of the stage
//! whose output changed (its task keys change with it) and re-pin with
//! `DIST4D_BLESS=1 cargo test --release --test golden`.

mod common;

use common::*;
use std::path::Path;

/// `<digest> <path>` of every exported file (`tree` of the output folder: the manifest, which
/// records inodes, left out).
fn digests(files: &[(String, Vec<u8>)]) -> String {
    files.iter().map(|(path, bytes)| format!("{} {path}\n", blake3::hash(bytes).to_hex())).collect()
}

/// No curated depth (`*_depth.npy`) beyond 1 km: the sky is 100 m and the farthest LiDAR return a
/// few hundred (a completion once gave three pixels of the shared DGP scene 26-53 km).
fn farthest_depth_is_plausible(name: &str, files: &[(String, Vec<u8>)]) {
    for (path, bytes) in files.iter().filter(|(path, _)| path.ends_with("_depth.npy")) {
        let (_, values) = dist4d_types::formats::read_npy_f32(bytes).unwrap();
        let far = values.iter().copied().fold(0f32, f32::max);
        assert!(far <= 1000.0, "{name}: {path} holds a depth of {far} m");
    }
}

/// Runs `pipeline` on `root` (with `sets`) and compares the export digests with `golden/<name>.txt`.
fn check(name: &str, pipeline: &Path, sets: &[String]) {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let mut args = vec!["run".to_string(), pipeline.display().to_string(), "--progress".into(), "off".into()];
    args.extend(["--cache".into(), tmp.path().join("cache").display().to_string()]);
    args.extend(["--out".into(), out.display().to_string()]);
    for s in sets {
        args.extend(["--set".into(), s.clone()]);
    }
    let o = dist4d(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{name}: {}", text(&o));
    let files = tree(&out);
    farthest_depth_is_plausible(name, &files);
    let got = digests(&files);
    let file = repo().join("tests/golden").join(format!("{name}.txt"));
    if std::env::var_os("DIST4D_BLESS").is_some() {
        std::fs::write(&file, &got).unwrap();
        eprintln!("pinned {} files in {}", got.lines().count(), file.display());
        return;
    }
    let want = std::fs::read_to_string(&file).unwrap_or_default();
    if got == want {
        return;
    }
    let lines = |t: &str| t.lines().map(String::from).collect::<std::collections::BTreeSet<_>>();
    let (got_set, want_set) = (lines(&got), lines(&want));
    let path_of = |l: &String| l.split_once(' ').map(|(_, p)| p.to_string()).unwrap_or_default();
    let mut changed: Vec<String> = got_set.symmetric_difference(&want_set).map(path_of).collect();
    changed.dedup();
    panic!(
        "{name}: {} of {} exported files differ from {}:\n  {}\nIf the change is deliberate, bump the version of \
         the stage whose output changed and re-pin: DIST4D_BLESS=1 cargo test --release --test golden",
        changed.len(),
        got_set.len().max(want_set.len()),
        file.display(),
        changed.iter().take(20).cloned().collect::<Vec<_>>().join("\n  ")
    );
}

#[test]
fn shipped_pipelines_on_a_small_synthetic_seed() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", root.to_str().unwrap(), "--keyframes", "3", "--width", "320", "--height", "180"]);
    assert!(o.status.success(), "{}", text(&o));
    let set_root = format!("dataset.root={}", root.display());
    for name in ["curation", "lidar_depth"] {
        check(&format!("synth-{name}"), &repo().join(format!("pipelines/{name}.ron")), &[set_root.clone()]);
    }
}

#[test]
fn curation_on_the_shared_nuscenes_keyframe() {
    let Some(root) = shared_nuscenes() else { return };
    check("nuscenes-curation", &repo().join("pipelines/curation.ron"), &[format!("dataset.root={}", root.display())]);
}

#[test]
fn curation_on_the_shared_dgp_scene() {
    let Some(root) = shared_dgp() else { return };
    // The same pipeline with the DGP reader in place of the nuScenes one.
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("curation.ron");
    std::fs::write(&file, with_dataset("curation", &format!("Dgp(root: {:?})", root.display().to_string()))).unwrap();
    check("dgp-curation", &file, &[]);
}

#[test]
fn the_12_hz_pipeline_on_a_small_synthetic_seed_with_camera_sweeps() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    synth_camera_sweeps(&root, 320, 180);
    let sets = [format!("dataset.root={}", root.display()), "clips.frames=4".into(), "clips.stride=2".into()];
    check("synth-video_12hz", &repo().join("pipelines/video_12hz.ron"), &sets);
}
