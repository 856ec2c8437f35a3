//! `dist4d export-infos` end to end: the info pickles of a synthetic scene (keyframes and the 12 Hz
//! tables of `export-12hz`) and of the shared nuScenes keyframe, checked field by field against
//! what tests/infos_check.py computes with the nuscenes-devkit, loaded with mmengine, and refused
//! cleanly on bad input.

mod common;
use common::*;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::Command;

fn export_infos(root: &Path, version: &str, out: &Path, extra: &[&str]) -> std::process::Output {
    let args = ["export-infos", "--root", root.to_str().unwrap(), "--version", version, "--out", out.to_str().unwrap()];
    dist4d(&[&args[..], extra].concat())
}

/// The pickles in `dir`, by split (`train`, `val`, `test`), sorted.
fn pickles(dir: &Path) -> Vec<(String, PathBuf)> {
    let mut out: Vec<(String, PathBuf)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "pkl"))
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            let split = ["train", "val", "test"].into_iter().find(|s| name.contains(&format!("_infos_{s}"))).unwrap();
            (split.to_string(), p)
        })
        .collect();
    out.sort();
    out
}

/// Runs the devkit comparison on every pickle of `dir` and the mmengine load.
fn check(root: &Path, version: &str, dir: &Path, max_sweeps: usize) -> String {
    let files = pickles(dir);
    assert!(!files.is_empty(), "no pickle in {}", dir.display());
    let mut said = String::new();
    if let Some(python) = peers_python() {
        let mut cmd = Command::new(python);
        cmd.arg(repo().join("tests/infos_check.py")).args([root.to_str().unwrap(), version, "./data/nuscenes"]);
        cmd.arg(max_sweeps.to_string());
        cmd.args(files.iter().map(|(s, p)| format!("{s}={}", p.display())));
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "the devkit disagrees:\n{}", text(&o));
        said += &text(&o);
    }
    if let Some(python) = mm_python() {
        let o =
            Command::new(python).arg(repo().join("tests/infos_load.py")).args(files.iter().map(|(_, p)| p)).output();
        let o = o.unwrap();
        assert!(o.status.success(), "mmengine.load:\n{}", text(&o));
        said += &text(&o);
    }
    said
}

#[test]
fn synthetic_keyframe_and_12hz_infos_equal_the_devkits() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    synth_camera_sweeps_of(&root, 8, 160, 90);

    let kf = tmp.path().join("kf");
    let o = export_infos(&root, "v1.0-mini", &kf, &[]);
    assert!(o.status.success(), "{}", text(&o));
    // The synthetic scene is in no official list: it goes to train, and the rule is said.
    assert!(text(&o).contains("synth-0000): they go to train"), "{}", text(&o));
    let names: Vec<String> =
        pickles(&kf).iter().map(|(_, p)| p.file_name().unwrap().to_string_lossy().into()).collect();
    assert_eq!(names, ["nuscenes_infos_train.pkl", "nuscenes_infos_val.pkl"]);
    let said = check(&root, "v1.0-mini", &kf, 10);
    eprintln!("{said}");

    // The 12 Hz samples of export-12hz; then the same folder with ASAP's fractional timestamps
    // on the samples between keyframes (the pickle keeps them as Python floats).
    let o = dist4d(&["export-12hz", "--root", root.to_str().unwrap(), "--version", "v1.0-mini"]);
    assert!(o.status.success(), "{}", text(&o));
    let hz = tmp.path().join("12hz");
    let o = export_infos(&root, "interp_12Hz_mini", &hz, &[]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("43 train samples of 1 scene(s), 1 in scene_tokens"), "{}", text(&o));
    eprintln!("{}", check(&root, "interp_12Hz_mini", &hz, 0));

    let samples_file = root.join("interp_12Hz_mini/sample.json");
    let mut samples: Vec<serde_json::Value> = serde_json::from_slice(&std::fs::read(&samples_file).unwrap()).unwrap();
    let mut fractional = 0;
    for s in samples.iter_mut().filter(|s| s["token"].as_str().unwrap().len() == 33) {
        s["timestamp"] = json!(s["timestamp"].as_i64().unwrap() as f64 + 0.5);
        fractional += 1;
    }
    assert!(fractional > 20, "the 12 Hz table names its new samples <keyframe><i>");
    std::fs::write(&samples_file, serde_json::to_vec(&samples).unwrap()).unwrap();
    let o = export_infos(&root, "interp_12Hz_mini", &hz, &["--max-sweeps", "3"]);
    assert!(o.status.success(), "{}", text(&o));
    eprintln!("{}", check(&root, "interp_12Hz_mini", &hz, 3));
}

#[test]
fn the_shared_keyframe_infos_equal_the_devkits_and_a_missing_split_is_refused() {
    let Some(root) = shared_nuscenes() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("infos");
    // scene-0061 is in mini_train: the val pickle would be empty, which a partial folder (ASAP's
    // val-only tables) gives too; the error says which split to ask for, and nothing is written.
    let o = export_infos(&root, "v1.0-mini", &out, &[]);
    assert!(!o.status.success());
    let said = text(&o);
    assert!(
        said.contains("v1.0-mini/sample.json") && said.contains("val split") && said.contains("--split train"),
        "{said}"
    );
    assert!(!out.exists() || pickles(&out).is_empty(), "a refused export wrote {:?}", pickles(&out));

    let o = export_infos(&root, "v1.0-mini", &out, &["--split", "train"]);
    assert!(o.status.success(), "{}", text(&o));
    eprintln!("{}", check(&root, "v1.0-mini", &out, 10));
}

#[test]
fn bad_input_names_the_file_row_and_field_and_leaves_the_old_pickles() {
    let (tmp, root) = synthetic_nuscenes(3);
    let out = tmp.path().join("infos");
    let o = export_infos(&root, "v1.0-mini", &out, &[]);
    assert!(o.status.success(), "{}", text(&o));
    let before = std::fs::read(out.join("nuscenes_infos_train.pkl")).unwrap();

    // A sample without its LiDAR keyframe.
    let sample = table(&root, "sample")[1]["token"].as_str().unwrap().to_string();
    let lidar_sensor = table(&root, "sensor").iter().find(|s| s["channel"] == "LIDAR_TOP").unwrap()["token"].clone();
    let lidar_calibs: Vec<serde_json::Value> = table(&root, "calibrated_sensor")
        .into_iter()
        .filter(|c| c["sensor_token"] == lidar_sensor)
        .map(|c| c["token"].clone())
        .collect();
    let original = table(&root, "sample_data");
    let mut without_key = original.clone();
    for sd in without_key.iter_mut() {
        if sd["sample_token"] == sample.as_str() && lidar_calibs.contains(&sd["calibrated_sensor_token"]) {
            sd["is_key_frame"] = json!(false);
        }
    }
    assert!(without_key != original);
    write_table(&root, "sample_data", &without_key);
    let o = export_infos(&root, "v1.0-mini", &out, &[]);
    assert!(!o.status.success());
    let said = text(&o);
    assert!(
        said.contains("sample.json") && said.contains(&sample) && said.contains("no LIDAR_TOP sample_data"),
        "{said}"
    );
    assert!(!said.contains("panicked"), "{said}");
    assert_eq!(std::fs::read(out.join("nuscenes_infos_train.pkl")).unwrap(), before, "the old pickle was touched");
    let leftovers: Vec<_> = std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(leftovers.len(), 2, "temp files left behind: {leftovers:?}");
    write_table(&root, "sample_data", &original);

    // A dangling calibration, a missing table, a visibility that is no level.
    let mut calibs = table(&root, "sample_data");
    calibs[0]["calibrated_sensor_token"] = json!("nope");
    write_table(&root, "sample_data", &calibs);
    let said = text(&export_infos(&root, "v1.0-mini", &out, &[]));
    assert!(said.contains("sample_data.json row 0") && said.contains("calibrated_sensor_token nope"), "{said}");
    write_table(&root, "sample_data", &original);

    let mut anns = table(&root, "sample_annotation");
    anns[2]["visibility_token"] = json!("mostly");
    write_table(&root, "sample_annotation", &anns);
    let said = text(&export_infos(&root, "v1.0-mini", &out, &[]));
    assert!(said.contains("sample_annotation.json row 2") && said.contains("visibility_token \"mostly\""), "{said}");

    std::fs::remove_file(root.join("v1.0-mini/log.json")).unwrap();
    let said = text(&export_infos(&root, "v1.0-mini", &out, &[]));
    assert!(said.contains("log.json"), "{said}");
    let said = text(&export_infos(&root, "v2.0-custom", &out, &[]));
    assert!(said.contains("v1.0-trainval") && said.contains("interp_12Hz"), "{said}");
    assert_eq!(std::fs::read(out.join("nuscenes_infos_train.pkl")).unwrap(), before);
}

#[test]
fn the_official_split_lists_are_the_devkits() {
    let Some(python) = peers_python() else { return };
    let o = Command::new(python)
        .args(["-c", "from nuscenes.utils import splits as s\nfor n in ['train','val','test','mini_train','mini_val']: print(n, *getattr(s, n))"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    for line in String::from_utf8_lossy(&o.stdout).lines() {
        let mut words = line.split(' ');
        let list = words.next().unwrap();
        let devkit: Vec<String> = words.map(String::from).collect();
        assert_eq!(dist4d_datasets::nuscenes::infos::official_split(list), devkit, "splits.{list}");
    }
}
