//! End-to-end tests of the dataset readers' checks: the CLI on a synthetic nuScenes dataset whose
//! tables were edited the way a careless or hostile writer would.

mod common;

use common::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// A tiny synthetic nuScenes dataset (2 keyframes, 160 x 90 images) under a temp folder.
fn synthetic() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    let o = dist4d(&["synth", "--out", root.to_str().unwrap(), "--keyframes", "2", "--width", "160", "--height", "90"]);
    assert!(o.status.success(), "{}", text(&o));
    (tmp, root)
}

fn table(root: &Path, name: &str) -> Vec<Value> {
    serde_json::from_slice(&std::fs::read(root.join(format!("v1.0-mini/{name}.json"))).unwrap()).unwrap()
}

fn write_table(root: &Path, name: &str, rows: &[Value]) {
    std::fs::write(root.join(format!("v1.0-mini/{name}.json")), serde_json::to_vec(rows).unwrap()).unwrap();
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
