//! End-to-end tests of the dataset readers' checks: the CLI on a synthetic nuScenes dataset whose
//! tables were edited the way a careless or hostile writer would.

mod common;

use common::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

fn synthetic() -> (tempfile::TempDir, PathBuf) {
    synthetic_nuscenes(2)
}

/// Index of the LiDAR keyframe sample_data row of keyframe `k` (samples in time order).
fn lidar_keyframe(root: &Path, k: usize) -> usize {
    let mut samples = table(root, "sample");
    samples.sort_by_key(|s| s["timestamp"].as_i64().unwrap());
    let sample = samples[k]["token"].clone();
    table(root, "sample_data")
        .iter()
        .position(|r| {
            r["sample_token"] == sample
                && r["is_key_frame"] == true
                && r["filename"].as_str().unwrap().contains("LIDAR_TOP")
        })
        .unwrap()
}

fn run(tmp: &Path, root: &Path) -> std::process::Output {
    run_lidar_depth(root, &tmp.join("cache"), &tmp.join("out"))
}

#[test]
fn a_lidar_file_outside_the_dataset_root_fails_its_frame_and_is_not_read() {
    let (tmp, root) = synthetic();
    let i = lidar_keyframe(&root, 1);
    let mut rows = table(&root, "sample_data");
    // A real sweep outside the root: a reader that followed the reference would run "fine".
    std::fs::create_dir_all(tmp.path().join("outside")).unwrap();
    std::fs::copy(root.join(rows[i]["filename"].as_str().unwrap()), tmp.path().join("outside/x.pcd.bin")).unwrap();
    rows[i]["filename"] = json!("../outside/x.pcd.bin");
    let token = rows[i]["token"].as_str().unwrap().to_string();
    write_table(&root, "sample_data", &rows);

    let o = run(tmp.path(), &root);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains(&format!(
            "v1.0-mini/sample_data.json row {i} (token {token}): field filename \"../outside/x.pcd.bin\" leaves the \
             dataset root"
        )),
        "{t}"
    );
    assert!(t.contains("failed: project synth-0000/001/CAM_FRONT"), "{t}");
    assert!(!t.contains("synth-0000/000/CAM_FRONT"), "frame 0 is fine: {t}");
    assert!(!tmp.path().join("out/synth-0000/CAM_FRONT/001_depth.exr").exists());
    assert!(tmp.path().join("out/synth-0000/CAM_FRONT/000_depth.exr").exists());
}

#[test]
fn a_zero_quaternion_in_ego_pose_fails_the_frame_instead_of_exiting_0_with_garbage() {
    let (tmp, root) = synthetic();
    let pose_token = table(&root, "sample_data")[lidar_keyframe(&root, 1)]["ego_pose_token"].clone();
    let mut poses = table(&root, "ego_pose");
    let p = poses.iter().position(|r| r["token"] == pose_token).unwrap();
    poses[p]["rotation"] = json!([0.0, 0.0, 0.0, 0.0]);
    write_table(&root, "ego_pose", &poses);

    let o = run(tmp.path(), &root);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains(&format!(
            "v1.0-mini/ego_pose.json row {p} (token {}): field rotation [0, 0, 0, 0] is not a rotation (norm 0",
            pose_token.as_str().unwrap()
        )),
        "{t}"
    );
    assert!(t.contains("failed: project synth-0000/001/CAM_FRONT"), "{t}");
}

#[test]
fn an_empty_sample_data_table_is_one_error_before_anything_runs() {
    let (tmp, root) = synthetic();
    write_table(&root, "sample_data", &[]);
    let o = run(tmp.path(), &root);
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert_eq!(t.matches("sample_data.json has no rows").count(), 1, "{t}");
    assert!(!t.contains("has no keyframe sample_data"), "no error per task: {t}");
    assert!(!tmp.path().join("out").join("synth-0000").exists(), "{t}");
}

/// A synthetic dataset with 12 Hz camera sweeps (3 keyframes: 13 images per camera).
fn with_camera_sweeps(tmp: &Path) -> PathBuf {
    let root = tmp.join("data");
    synth_camera_sweeps(&root, 160, 90);
    root
}

fn run_camera_clock(tmp: &Path, root: &Path) -> std::process::Output {
    run_lidar_depth_with(root, &tmp.join("cache"), &tmp.join("out"), &["--set", "dataset.frames=Camera"])
}

#[test]
fn the_camera_clock_exports_every_image_once_and_the_index_names_each_source() {
    let tmp = tempfile::tempdir().unwrap();
    let root = with_camera_sweeps(tmp.path());
    let o = run_camera_clock(tmp.path(), &root);
    assert!(o.status.success(), "{}", text(&o));
    let index: Value = serde_json::from_slice(&std::fs::read(tmp.path().join("out/index.json")).unwrap()).unwrap();
    let sources = index["sources"].as_object().unwrap();
    let cameras: Vec<String> = table(&root, "sensor")
        .iter()
        .filter(|s| s["modality"] == "camera")
        .map(|s| s["channel"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(cameras.len(), 6);
    // 13 rounds x 6 cameras, each a depth map of its own image, every image named once.
    let images: Vec<&str> = sources.values().map(|s| s["file"].as_str().unwrap()).collect();
    assert_eq!(images.len(), 78);
    let distinct: std::collections::BTreeSet<&str> = images.iter().copied().collect();
    assert_eq!(distinct.len(), 78, "no image is used twice");
    let camera_rows: Vec<Value> =
        table(&root, "sample_data").into_iter().filter(|r| r["filename"].as_str().unwrap().ends_with(".jpg")).collect();
    assert_eq!(camera_rows.len(), 78, "and none is left out");
    for (item, s) in sources {
        let row = camera_rows.iter().find(|r| r["token"] == s["token"]).unwrap_or_else(|| panic!("{item}: {s}"));
        assert_eq!(row["filename"], s["file"], "{item}");
        assert_eq!(row["timestamp"], s["timestamp_us"], "{item}");
        assert!(item.ends_with(row["filename"].as_str().unwrap().split("__").nth(1).unwrap()), "{item} vs {s}");
        assert!(root.join(s["file"].as_str().unwrap()).is_file());
    }
    // Each exported file's item has its source.
    for f in index["files"].as_array().unwrap() {
        assert!(sources.contains_key(f["item"].as_str().unwrap()), "{f}");
    }
}

#[test]
fn a_dropped_camera_image_makes_an_incomplete_round_reported_and_nothing_else_fails() {
    let tmp = tempfile::tempdir().unwrap();
    let root = with_camera_sweeps(tmp.path());
    // CAM_BACK loses its 5th image (a dropped frame): the row goes, its neighbours are relinked.
    let mut rows = table(&root, "sample_data");
    let mut back: Vec<usize> =
        (0..rows.len()).filter(|&i| rows[i]["filename"].as_str().unwrap().contains("__CAM_BACK__")).collect();
    back.sort_by_key(|&i| rows[i]["timestamp"].as_i64().unwrap());
    let gone = rows[back[4]].clone();
    assert_eq!(gone["is_key_frame"], false);
    for r in rows.iter_mut() {
        if r["token"] == gone["prev"] {
            r["next"] = gone["next"].clone();
        }
        if r["token"] == gone["next"] {
            r["prev"] = gone["prev"].clone();
        }
    }
    rows.retain(|r| r["token"] != gone["token"]);
    write_table(&root, "sample_data", &rows);
    let o = run_camera_clock(tmp.path(), &root);
    let out = text(&o);
    assert!(!o.status.success(), "{out}");
    assert!(out.contains("1 of 13 camera rounds are incomplete (round 4 without CAM_BACK)"), "{out}");
    assert!(out.contains("camera round 4") && out.contains("has no CAM_BACK image"), "{out}");
    let index: Value = serde_json::from_slice(&std::fs::read(tmp.path().join("out/index.json")).unwrap()).unwrap();
    let sources = index["sources"].as_object().unwrap();
    assert_eq!(sources.len(), 77, "every other camera image is exported");
    assert!(!sources.contains_key("synth-0000/004/CAM_BACK"));
}

/// The 12 Hz tables: `dist4d export-12hz` writes them, the official devkit loads them and draws
/// the boxes of a sample between keyframes, and dist4d's own pipelines run on them.
#[test]
fn the_12hz_tables_load_in_the_devkit_and_run_as_keyframes() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    synth_camera_sweeps(&root, 160, 90);
    let o = dist4d(&["export-12hz", "--root", root.to_str().unwrap()]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("13 samples (3 keyframes, 10 camera rounds between)"), "{t}");
    assert!(t.contains("NuScenes(version='interp_12Hz_mini'"), "{t}");

    // dist4d reads it as keyframes: 13 frames x 6 cameras.
    let o = run_lidar_depth_with(
        &root,
        &tmp.path().join("cache"),
        &tmp.path().join("out"),
        &["--set", "dataset.version=\"interp_12Hz_mini\""],
    );
    assert!(o.status.success(), "{}", text(&o));
    let index: Value = serde_json::from_slice(&std::fs::read(tmp.path().join("out/index.json")).unwrap()).unwrap();
    assert_eq!(index["sources"].as_object().unwrap().len(), 78, "{index}");

    let Some(python) = peers_python() else { return };
    let script = r#"
import json, sys, matplotlib
matplotlib.use("Agg")
from nuscenes.nuscenes import NuScenes
nusc = NuScenes(version="interp_12Hz_mini", dataroot=sys.argv[1], verbose=False)
scene = nusc.scene[0]
tokens, token = [], scene["first_sample_token"]
while token:
    tokens.append(token)
    token = nusc.get("sample", token)["next"]
between = [t for t in tokens if len(t) > 32]
sample = nusc.get("sample", between[2])
_, boxes, _ = nusc.get_sample_data(sample["data"]["CAM_FRONT"])
nusc.render_sample(sample["token"], out_path=sys.argv[2], verbose=False)
moving = [a for a in sample["anns"] if "moving" in json.dumps([nusc.get("attribute", t)["name"] for t in nusc.get("sample_annotation", a)["attribute_tokens"]])]
speeds = [float((nusc.box_velocity(a)[:2] ** 2).sum() ** 0.5) for a in moving]
print(json.dumps({"samples": len(tokens), "nbr_samples": scene["nbr_samples"], "between": len(between),
                  "channels": sorted(sample["data"]), "anns": len(sample["anns"]), "boxes_in_cam_front": len(boxes),
                  "moving_speeds": speeds}))
"#;
    let png = tmp.path().join("render.png");
    let o = std::process::Command::new(&python)
        .args(["-c", script, root.to_str().unwrap(), png.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let v: Value = serde_json::from_slice(o.stdout.trim_ascii()).unwrap();
    assert_eq!(
        (v["samples"].as_u64(), v["nbr_samples"].as_u64(), v["between"].as_u64()),
        (Some(13), Some(13), Some(10))
    );
    let channels: Vec<&str> = v["channels"].as_array().unwrap().iter().map(|c| c.as_str().unwrap()).collect();
    assert_eq!(channels.len(), 7, "six cameras and the LiDAR: {channels:?}");
    assert!(v["anns"].as_u64() > Some(0) && v["boxes_in_cam_front"].as_u64() > Some(0), "{v}");
    // The devkit's velocities from the 12 Hz tracks: moving agents drive at 3-15 m/s.
    let speeds: Vec<f64> = v["moving_speeds"].as_array().unwrap().iter().filter_map(Value::as_f64).collect();
    assert!(!speeds.is_empty() && speeds.iter().all(|s| (0.5..20.0).contains(s)), "{v}");
    assert!(std::fs::metadata(&png).unwrap().len() > 10_000, "render_sample wrote its figure");
}

/// `export-12hz --out` outside the dataset root writes tables the devkit cannot load from the
/// folder's parent (no images, no map masks there): it says so, and how to load them.
#[test]
fn the_12hz_tables_written_outside_the_root_say_how_to_load_them() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    synth_camera_sweeps(&root, 160, 90);
    let out = tmp.path().join("elsewhere/interp_12Hz_mini");
    let o = dist4d(&["export-12hz", "--root", root.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let root = root.canonicalize().unwrap();
    assert!(t.contains("is outside the dataset root") && t.contains("map masks"), "{t}");
    assert!(t.contains(&format!("ln -s {} {}", out.display(), root.join("interp_12Hz_mini").display())), "{t}");
    assert!(t.contains(&format!("NuScenes(version='interp_12Hz_mini', dataroot='{}')", root.display())), "{t}");
}

#[test]
fn check_and_run_say_when_the_root_is_missing_or_holds_another_kind() {
    let tmp = tempfile::tempdir().unwrap();
    let lidar = repo().join("pipelines/lidar_depth.ron").display().to_string();
    // Missing: `check` notes it (the data may be on the cluster), `run` refuses before any work.
    let missing = tmp.path().join("not-here");
    let set = format!("dataset.root={}", missing.display());
    let o = dist4d(&["check", &lidar, "--set", &set]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains(&format!("dataset root {} does not exist", missing.display())), "{}", text(&o));
    let (cache, out) = (tmp.path().join("c"), tmp.path().join("o"));
    let o = run_lidar_depth(&missing, &cache, &out);
    assert_eq!(o.status.code(), Some(2), "a command-line problem, as check says: {}", text(&o));
    assert!(text(&o).contains("does not exist"), "{}", text(&o));
    // A nuScenes pipeline pointed at a DGP root (a scene_dataset*.json): `check` names the kind.
    let dgp = tmp.path().join("ddad");
    std::fs::create_dir_all(&dgp).unwrap();
    std::fs::write(dgp.join("scene_dataset_v1.0.json"), "{}").unwrap();
    let o = dist4d(&["check", &lidar, "--set", &format!("dataset.root={}", dgp.display())]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    let said = text(&o);
    assert!(said.contains(&format!("did you mean `Dgp(root: \"{}\")`?", dgp.display())), "{said}");
    assert!(said.contains("dataset kinds: NuScenes, Dgp, Synth"), "{said}");
    // `run` exits as `check` does, before anything runs.
    let o = run_lidar_depth(&dgp, &cache, &out);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(text(&o).contains("did you mean `Dgp(root: "), "{}", text(&o));
    assert!(!cache.join("runs").exists(), "nothing ran");
    // And a DGP pipeline at a nuScenes root, the other way round.
    let (_keep, nus) = synthetic_nuscenes(1);
    let o = dist4d(&["check", &lidar, "--set", &format!("dataset=Dgp(root: \"{}\")", nus.display())]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(text(&o).contains("did you mean `NuScenes(root: "), "{}", text(&o));
}

#[test]
fn a_synth_dataset_is_made_on_first_use_and_read_like_the_folder_dist4d_synth_writes() {
    let tmp = tempfile::tempdir().unwrap();
    let lidar = repo().join("pipelines/lidar_depth.ron").display().to_string();
    let world = tmp.path().join("world");
    let dataset = format!("dataset=Synth(root: \"{}\", keyframes: 2, width: 96, height: 54, seed: 3)", world.display());
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("o1"));
    let o = dist4d(&[
        "run",
        &lidar,
        "--progress",
        "off",
        "--cache",
        cache.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--set",
        &dataset,
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(world.join("groundtruth/synth.json").is_file());
    // The same world written by `dist4d synth` and read as NuScenes gives the same files.
    let written = tmp.path().join("written");
    let o = dist4d(&[
        "synth",
        "--out",
        written.to_str().unwrap(),
        "--seed",
        "3",
        "--keyframes",
        "2",
        "--width",
        "96",
        "--height",
        "54",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let out2 = tmp.path().join("o2");
    let o = run_lidar_depth(&written, &tmp.path().join("cache2"), &out2);
    assert!(o.status.success(), "{}", text(&o));
    let depths = |dir: &Path| tree(dir).into_iter().filter(|(name, _)| name.ends_with("_uvz.npy")).collect::<Vec<_>>();
    let (a, b) = (depths(&out), depths(&out2));
    assert!(a.len() >= 12, "{}", a.len());
    assert_eq!(a, b);
    // A second run finds the world in place; another seed in the same folder is refused.
    let o = dist4d(&["check", &lidar, "--set", &dataset]);
    assert!(o.status.success(), "{}", text(&o));
    let other = dataset.replace("seed: 3", "seed: 4");
    let o = dist4d(&[
        "run",
        &lidar,
        "--progress",
        "off",
        "--cache",
        cache.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--set",
        &other,
    ]);
    assert!(!o.status.success() && text(&o).contains("other settings"), "{}", text(&o));
}
