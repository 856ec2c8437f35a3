//! pipelines/dist4d_layout.ron and `dist4d depthroot` end to end: DiST-4D's depth files for the
//! keyframes and the 12 Hz samples of a synthetic scene, found by a numpy-only reader through
//! `nus_sampletoken2depthroot.json` from the tokens of the info pickles, equal to the curated NPY.

mod common;
use common::*;
use std::path::Path;
use std::process::Command;

fn run_layout(root: &Path, version: &str, out: &Path, cache: &Path, extra: &[&str]) {
    let pipeline = repo().join("pipelines/dist4d_layout.ron");
    let (set_root, set_version) = (format!("dataset.root={}", root.display()), format!("dataset.version={version}"));
    let args = ["run", pipeline.to_str().unwrap(), "--set", &set_root, "--set", &set_version];
    let args = [&args[..], &["--out", out.to_str().unwrap(), "--cache", cache.to_str().unwrap()], extra].concat();
    let o = dist4d(&args);
    assert!(o.status.success(), "{}", text(&o));
}

fn read_back(python: &Path, out: &Path, pkl: &Path, sky: u8) -> String {
    let o = Command::new(python)
        .arg(repo().join("tests/dist4d_layout_read.py"))
        .args([out.to_str().unwrap(), pkl.to_str().unwrap(), &sky.to_string()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    text(&o)
}

#[test]
fn keyframes_and_12hz_samples_are_found_through_the_depthroot_index() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    synth_camera_sweeps_of(&root, 3, 160, 90);
    let o = dist4d(&["export-12hz", "--root", root.to_str().unwrap(), "--version", "v1.0-mini"]);
    assert!(o.status.success(), "{}", text(&o));
    let infos = tmp.path().join("infos");
    for version in ["v1.0-mini", "interp_12Hz_mini"] {
        let args = ["export-infos", "--root", root.to_str().unwrap(), "--version", version];
        let o = dist4d(&[&args[..], &["--out", infos.to_str().unwrap()]].concat());
        assert!(o.status.success(), "{}", text(&o));
    }
    let (out, cache) = (tmp.path().join("nus_Rdepth"), tmp.path().join("cache"));
    let o = dist4d(&["depthroot", out.to_str().unwrap()]);
    assert!(!o.status.success(), "an index of nothing: {}", text(&o));
    // The 12 Hz tables hold the keyframes as samples too: one run writes both.
    run_layout(&root, "interp_12Hz_mini", &out, &cache, &[]);
    let o = dist4d(&["depthroot", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("13 samples (78 depth files)"), "{}", text(&o));
    let index: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(&std::fs::read(out.join("nus_sampletoken2depthroot.json")).unwrap()).unwrap();
    let key = table(&root, "sample")[0]["token"].as_str().unwrap().to_string();
    assert_eq!(index[&key], format!("synth-0000/{key}"));
    assert_eq!(index[&format!("{key}3")], format!("synth-0000/{key}3"), "the 12 Hz sample's own token");

    let Some(python) = peers_python() else { return };
    for pkl in ["nuscenes_infos_train.pkl", "nuscenes_interp_12Hz_infos_train_with_bid.pkl"] {
        eprintln!("{}", read_back(&python, &out, &infos.join(pkl), 27));
    }
    // ADE20K ids on request: sky 2.
    let ade = tmp.path().join("ade");
    run_layout(&root, "v1.0-mini", &ade, &cache, &["--set", "dist.label_space=Ade20k150"]);
    assert!(dist4d(&["depthroot", ade.to_str().unwrap()]).status.success());
    let said = read_back(&python, &ade, &infos.join("nuscenes_infos_train.pkl"), 2);
    assert!(!said.contains(" 0 sky pixels"), "{said}");
}
