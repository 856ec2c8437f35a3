//! End-to-end tests of what a run writes, and where: exports confined to `--out`, one pipeline per
//! output folder, exports repaired after edits, `dist4d verify`, exported outputs kept in the
//! output folder only (not also in the store), and SIGTERM. They run on a small synthetic dataset
//! that `dist4d synth` makes, so they need no shared data.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// A tiny synthetic nuScenes dataset (3 keyframes, 160x90 images) in a fresh temp folder.
fn synthetic(keyframes: u32, width: u32, height: u32) -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    let (k, w, h) = (keyframes.to_string(), width.to_string(), height.to_string());
    let o = dist4d(&["synth", "--out", root.to_str().unwrap(), "--keyframes", &k, "--width", &w, "--height", &h]);
    assert!(o.status.success(), "{}", text(&o));
    (tmp, root)
}

fn run(pipeline: &Path, root: &Path, cache: &Path, out: &Path, extra: &[&str]) -> Output {
    Command::new(bin())
        .args(["run", pipeline.to_str().unwrap(), "--progress", "off", "--jobs", "2"])
        .args(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .args(["--set", &format!("dataset.root={}", root.display())])
        .args(extra)
        .output()
        .unwrap()
}

fn lidar_depth() -> PathBuf {
    repo().join("pipelines/lidar_depth.ron")
}

fn set_scene_name(root: &Path, name: &str) {
    let path = root.join("v1.0-mini/scene.json");
    let mut scenes: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    scenes[0]["name"] = serde_json::json!(name);
    std::fs::write(&path, serde_json::to_vec(&scenes).unwrap()).unwrap();
}

/// Every file under `dir` (relative paths, the manifest included), sorted.
fn listing(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p.strip_prefix(dir).unwrap().display().to_string());
            }
        }
    }
    out.sort();
    out
}

#[test]
fn a_scene_named_like_a_path_writes_nothing_outside_out() {
    let (tmp, root) = synthetic(2, 160, 90);
    let victim = tmp.path().join("victim");
    std::fs::create_dir_all(&victim).unwrap();
    std::fs::write(victim.join("notes.txt"), b"the user's file").unwrap();
    let out = tmp.path().join("runs/a/out");
    for (i, name) in ["../../../victim", "..", "/tmp/dist4d-escape", "a/../../b"].iter().enumerate() {
        set_scene_name(&root, name);
        let cache = tmp.path().join(format!("cache{i}"));
        // By name too: `--scenes` selects the scene, the export still refuses its path.
        let o = run(&lidar_depth(), &root, &cache, &out, &["--scenes", name]);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{name}: {t}");
        assert!(t.contains(&format!("the scene name {name:?}")), "{name}: {t}");
        assert!(t.contains("0 files in"), "{name}: {t}");
        let index: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("index.json")).unwrap()).unwrap();
        assert_eq!(index["files"].as_array().unwrap().len(), 0, "{name}");
    }
    assert_eq!(std::fs::read(victim.join("notes.txt")).unwrap(), b"the user's file");
    assert_eq!(listing(&victim), ["notes.txt"]);
    assert!(!Path::new("/tmp/dist4d-escape").exists());
    assert_eq!(listing(&tmp.path().join("runs")), ["a/out/.dist4d-manifest", "a/out/index.json"]);
}

#[test]
fn two_pipelines_cannot_share_an_output_folder() {
    let (tmp, root) = synthetic(2, 160, 90);
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
    let o = run(&lidar_depth(), &root, &cache, &out, &[]);
    assert!(o.status.success(), "{}", text(&o));
    let before = tree(&out);
    let other = tmp.path().join("other.ron");
    let shipped = std::fs::read_to_string(lidar_depth()).unwrap();
    std::fs::write(&other, shipped.replace("name: \"lidar_depth\"", "name: \"other\"").replace("80.0", "40.0"))
        .unwrap();
    let o = run(&other, &root, &cache, &out, &[]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("holds the exports of pipeline `lidar_depth`"), "{t}");
    assert!(t.contains("pipeline `other` will not overwrite them"), "{t}");
    assert_eq!(tree(&out), before, "not one file changed");
    // Its own folder is fine.
    let o = run(&other, &root, &cache, &tmp.path().join("out-other"), &[]);
    assert!(o.status.success(), "{}", text(&o));
}

#[test]
fn an_export_edited_in_place_is_reported_by_verify_and_repaired_by_a_rerun() {
    let (tmp, root) = synthetic(2, 160, 90);
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
    let o = run(&lidar_depth(), &root, &cache, &out, &[]);
    assert!(o.status.success(), "{}", text(&o));
    let reference = tree(&out);
    let o = dist4d(&["verify", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("48 files intact, 0 modified, 0 missing"), "{}", text(&o));

    // The same size and the same mtime: only the bytes (and ctime) differ.
    let edited = out.join("synth-0000/CAM_BACK/001_depth.png");
    let mtime = std::fs::metadata(&edited).unwrap().modified().unwrap();
    let mut bytes = std::fs::read(&edited).unwrap();
    let n = bytes.len();
    bytes[n / 2] ^= 0x55;
    std::fs::write(&edited, &bytes).unwrap();
    std::fs::File::options().write(true).open(&edited).unwrap().set_modified(mtime).unwrap();
    std::fs::remove_file(out.join("synth-0000/CAM_FRONT/000_uvz.npy")).unwrap();

    let o = dist4d(&["verify", out.to_str().unwrap()]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("modified: synth-0000/CAM_BACK/001_depth.png"), "{t}");
    assert!(t.contains("missing:  synth-0000/CAM_FRONT/000_uvz.npy"), "{t}");
    assert!(t.contains("46 files intact, 1 modified, 1 missing"), "{t}");

    // The edited 160x90 PNG is small enough to be kept in the store as well: written again from
    // there. The projected points (tens of KB) are kept only in the output folder: their encoder
    // runs again, and nothing upstream.
    let o = run(&lidar_depth(), &root, &cache, &out, &[]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("1 executed, 35 cached"), "{}", text(&o));
    assert_eq!(tree(&out), reference);
    assert!(dist4d(&["verify", out.to_str().unwrap()]).status.success());
}

/// Whether the store `cache` holds a blob of the bytes of digest `hex`.
fn has_blob(cache: &Path, hex: &str) -> bool {
    cache.join("cas").join(&hex[..2]).join(&hex[2..]).is_file()
}

fn explain(root: &Path, cache: &Path, out: &Path) -> String {
    let (pipeline, cache, out) = (lidar_depth(), cache.to_str().unwrap(), out.to_str().unwrap());
    let set = format!("dataset.root={}", root.display());
    let o = dist4d(&["explain", pipeline.to_str().unwrap(), "--cache", cache, "--out", out, "--set", &set]);
    assert!(o.status.success(), "{}", text(&o));
    text(&o)
}

#[test]
fn exported_files_are_kept_once_and_a_deleted_one_is_made_again_by_its_task_alone() {
    // 800x450: every export is over 16 KiB, so none is stored when only exported.
    let (tmp, root) = synthetic(2, 800, 450);
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
    let o = run(&lidar_depth(), &root, &cache, &out, &[]);
    assert!(o.status.success(), "{}", text(&o));
    let reference = tree(&out);
    // No exported file is in the store too: lidar_depth exports what EncodeDepth and EncodePoints
    // make, which no stage reads. (ProjectLidar's outputs, which they read, are blobs.)
    let index: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("index.json")).unwrap()).unwrap();
    let digests: Vec<&str> = index["files"].as_array().unwrap().iter().map(|f| f["digest"].as_str().unwrap()).collect();
    assert_eq!(digests.len(), 48);
    assert!(digests.iter().all(|d| !has_blob(&cache, d)), "exported bytes are not in the store");

    let deleted = out.join("synth-0000/CAM_BACK/001_depth.exr");
    std::fs::remove_file(&deleted).unwrap();
    let t = explain(&root, &cache, &out);
    assert!(t.contains("encode (EncodeDepth): 11 cached, 1 will run"), "{t}");
    assert!(
        t.contains("1 x output `exr` is kept only in the output folder, and its file there is missing or changed"),
        "{t}"
    );
    let o = run(&lidar_depth(), &root, &cache, &out, &[]);
    assert!(text(&o).contains("1 executed, 35 cached"), "{}", text(&o));
    assert_eq!(tree(&out), reference);

    // Records outlive gc without blobs; the folder still holds their bytes, so nothing runs.
    let o = dist4d(&["gc", "--cache", cache.to_str().unwrap(), "--keep-runs", "1"]);
    assert!(o.status.success(), "{}", text(&o));
    let o = run(&lidar_depth(), &root, &cache, &out, &[]);
    assert!(text(&o).contains("0 executed, 36 cached"), "{}", text(&o));

    // Another folder holds none of them: the encoders run, the projections stay cached.
    let elsewhere = tmp.path().join("elsewhere");
    let t = explain(&root, &cache, &elsewhere);
    assert!(t.contains("project (ProjectLidar): 12 cached, 0 will run"), "{t}");
    assert!(t.contains("encode (EncodeDepth): 0 cached, 12 will run"), "{t}");
    let o = run(&lidar_depth(), &root, &cache, &elsewhere, &[]);
    assert!(text(&o).contains("24 executed, 12 cached"), "{}", text(&o));
    assert_eq!(tree(&elsewhere), reference);
}

#[test]
fn sigterm_stops_like_ctrl_c_with_a_run_record() {
    // Multi-view stereo on 800x450 images keeps one job busy for several seconds.
    let (tmp, root) = synthetic(4, 800, 450);
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
    let child = Command::new(bin())
        .args(["run", repo().join("pipelines/curation.ron").to_str().unwrap(), "--progress", "off", "--jobs", "1"])
        .args(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .args(["--set", &format!("dataset.root={}", root.display())])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Signal once the first task record is in the store: the run is under way.
    let t0 = Instant::now();
    let started = || {
        std::fs::read_dir(cache.join("ac"))
            .map(|d| d.filter_map(|e| e.ok()).any(|e| e.metadata().is_ok_and(|m| m.len() > 64)))
            .unwrap_or(false)
    };
    while !started() {
        assert!(t0.elapsed() < Duration::from_secs(120), "the run never started");
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = Command::new("kill").args(["-TERM", &child.id().to_string()]).status();
    let o = child.wait_with_output().unwrap();
    let t = text(&o);
    assert_eq!(o.status.code(), Some(143), "{t}");
    assert!(t.contains("stopping on SIGTERM"), "{t}");
    assert!(t.contains("Interrupted"), "{t}");
    let record = last_run(&cache);
    assert_eq!(record["status"], "interrupted");
    let leftovers: Vec<_> = std::fs::read_dir(cache.join("tmp")).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert!(leftovers.is_empty(), "store temp files left: {leftovers:?}");
    let out_tmp: Vec<_> = std::fs::read_dir(out.join(".dist4d-tmp"))
        .map(|d| d.map(|e| e.unwrap().file_name()).collect())
        .unwrap_or_default();
    assert!(out_tmp.is_empty(), "output temp files left: {out_tmp:?}");
}
