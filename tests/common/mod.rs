//! Helpers for end-to-end tests: the built binary, the shared data, and a multi-frame nuScenes
//! dataset made from the shared keyframe (tests copy what they modify; the shared data is read-only).

#![allow(dead_code)]

use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_dist4d"))
}

pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub fn shared_nuscenes() -> Option<PathBuf> {
    let p = repo().join("../shared/data/nuscenes-scene0061-kf0");
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("SKIPPED: the shared nuScenes data is not at {} (CI always has it)", p.display());
        None
    }
}

pub fn shared_dgp() -> Option<PathBuf> {
    let p = repo().join("../shared/data/dgp-scene02");
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("SKIPPED: the shared DGP data is not at {} (CI always has it)", p.display());
        None
    }
}

/// The text of shipped pipeline `name` (`pipelines/<name>.ron`) with its `dataset: NuScenes(..)`
/// replaced by `dataset` (e.g. `Dgp(root: "..")`): both readers give the same ports and items.
pub fn with_dataset(name: &str, dataset: &str) -> String {
    let text = std::fs::read_to_string(repo().join(format!("pipelines/{name}.ron"))).unwrap();
    let start = text.find("dataset: NuScenes(").expect("the shipped pipeline reads NuScenes");
    let end = start + text[start..].find("\n    ),\n").expect("its dataset ends with `    ),`") + 7;
    format!("{}dataset: {dataset},{}", &text[..start], &text[end..])
}

pub fn peers_python() -> Option<PathBuf> {
    let p = std::env::var_os("DIST4D_PEERS_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo().join(".venv-peers/bin/python"));
    if p.exists() {
        Some(p)
    } else {
        eprintln!("SKIPPED: no peer venv at {} (make it with ../shared/bench/peers/setup.sh .venv-peers)", p.display());
        None
    }
}

pub fn dist4d(args: &[&str]) -> Output {
    Command::new(bin()).args(args).output().expect("dist4d runs")
}

pub fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

fn read_json(p: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

fn write_json(p: &Path, v: &Value) {
    std::fs::write(p, serde_json::to_vec(v).unwrap()).unwrap();
}

/// A nuScenes dataset with `frames` keyframes in one scene, made from the shared keyframe: each
/// frame's LiDAR sweep is the shared one with its points turned a little (so that every frame has
/// its own content) and the ego a little further along.
pub fn multi_frame_nuscenes(dest: &Path, frames: usize) -> PathBuf {
    let src = shared_nuscenes().expect("caller checks");
    let tables = dest.join("v1.0-mini");
    std::fs::create_dir_all(&tables).unwrap();
    for t in [
        "scene",
        "sample",
        "sample_data",
        "ego_pose",
        "calibrated_sensor",
        "sensor",
        "log",
        "category",
        "attribute",
        "visibility",
        "instance",
        "sample_annotation",
        "map",
    ] {
        std::fs::copy(src.join("v1.0-mini").join(format!("{t}.json")), tables.join(format!("{t}.json"))).unwrap();
    }
    let lidar_src = std::fs::read_dir(src.join("samples/LIDAR_TOP")).unwrap().next().unwrap().unwrap().path();
    let lidar = std::fs::read(&lidar_src).unwrap();
    std::fs::create_dir_all(dest.join("samples/LIDAR_TOP")).unwrap();

    let sample0 = read_json(&tables.join("sample.json"))[0].clone();
    let sd0: Vec<Value> = read_json(&tables.join("sample_data.json")).as_array().unwrap().clone();
    let poses0: Vec<Value> = read_json(&tables.join("ego_pose.json")).as_array().unwrap().clone();
    let mut samples = Vec::new();
    let mut sds = Vec::new();
    let mut poses = Vec::new();
    let tok = |f: usize, base: &str| if f == 0 { base.to_string() } else { format!("{base}_{f}") };
    for f in 0..frames {
        let s_tok = tok(f, sample0["token"].as_str().unwrap());
        let mut s = sample0.clone();
        s["token"] = json!(s_tok);
        s["timestamp"] = json!(sample0["timestamp"].as_i64().unwrap() + 500_000 * f as i64);
        s["prev"] = json!(if f == 0 { String::new() } else { tok(f - 1, sample0["token"].as_str().unwrap()) });
        s["next"] = json!(if f + 1 == frames { String::new() } else { tok(f + 1, sample0["token"].as_str().unwrap()) });
        samples.push(s);
        for sd in &sd0 {
            let mut d = sd.clone();
            d["token"] = json!(tok(f, sd["token"].as_str().unwrap()));
            d["sample_token"] = json!(s_tok);
            d["ego_pose_token"] = json!(tok(f, sd["ego_pose_token"].as_str().unwrap()));
            if sd["filename"].as_str().unwrap().contains("LIDAR_TOP") {
                let name = format!("samples/LIDAR_TOP/frame{f:03}.pcd.bin");
                d["filename"] = json!(name);
                // Turn the sweep by f * 0.3 degrees about z so that each frame differs.
                let a = (f as f32) * 0.3f32.to_radians();
                let mut bytes = lidar.clone();
                for p in bytes.chunks_exact_mut(20) {
                    let x = f32::from_le_bytes(p[0..4].try_into().unwrap());
                    let y = f32::from_le_bytes(p[4..8].try_into().unwrap());
                    p[0..4].copy_from_slice(&(x * a.cos() - y * a.sin()).to_le_bytes());
                    p[4..8].copy_from_slice(&(x * a.sin() + y * a.cos()).to_le_bytes());
                }
                std::fs::write(dest.join(&name), bytes).unwrap();
            }
            sds.push(d);
        }
        for pose in &poses0 {
            let mut p = pose.clone();
            p["token"] = json!(tok(f, pose["token"].as_str().unwrap()));
            p["translation"][0] = json!(pose["translation"][0].as_f64().unwrap() + 0.5 * f as f64);
            poses.push(p);
        }
    }
    write_json(&tables.join("sample.json"), &Value::Array(samples));
    write_json(&tables.join("sample_data.json"), &Value::Array(sds));
    write_json(&tables.join("ego_pose.json"), &Value::Array(poses));
    let mut scenes = read_json(&tables.join("scene.json"));
    scenes[0]["nbr_samples"] = json!(frames);
    scenes[0]["last_sample_token"] = json!(tok(frames - 1, sample0["token"].as_str().unwrap()));
    write_json(&tables.join("scene.json"), &scenes);
    dest.to_path_buf()
}

/// Every file under `dir` (relative path -> bytes) but dist4d's bookkeeping (`.dist4d-*`): the
/// export manifest records each file's inode and ctime and so differs between two runs that
/// wrote the same bytes, and shards leave manifest deltas and index parts that one process does not.
pub fn tree(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    fn walk(base: &Path, d: &Path, out: &mut Vec<(String, Vec<u8>)>) {
        let mut entries: Vec<_> = std::fs::read_dir(d).unwrap().map(|e| e.unwrap().path()).collect();
        entries.sort();
        for p in entries {
            if p.file_name().is_some_and(|n| n.to_string_lossy().starts_with(".dist4d")) {
                continue;
            }
            if p.is_dir() {
                walk(base, &p, out);
            } else {
                out.push((p.strip_prefix(base).unwrap().display().to_string(), std::fs::read(&p).unwrap()));
            }
        }
    }
    walk(dir, dir, &mut out);
    out
}

/// The last run record of a store, as JSON.
pub fn last_run(cache: &Path) -> Value {
    let o = dist4d(&["runs", "--cache", cache.to_str().unwrap(), "--json"]);
    let runs: Value = serde_json::from_slice(&o.stdout).unwrap();
    runs.as_array().unwrap().last().unwrap().clone()
}

/// stage -> executed count of a run record.
pub fn executed(run: &Value) -> std::collections::BTreeMap<String, u64> {
    run["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| (s["stage"].as_str().unwrap().to_string(), s["executed"].as_u64().unwrap()))
        .collect()
}

/// Reads an NPY float32 (N, 3) file written by EncodePoints.
pub fn read_npy_rows(path: &Path) -> Vec<[f32; 3]> {
    let b = std::fs::read(path).unwrap();
    let hlen = u16::from_le_bytes([b[8], b[9]]) as usize;
    b[10 + hlen..]
        .chunks_exact(12)
        .map(|c| [0, 4, 8].map(|o| f32::from_le_bytes(c[o..o + 4].try_into().unwrap())))
        .collect()
}

/// `dist4d run pipelines/lidar_depth.ron` on a nuScenes-format root, progress off.
pub fn run_lidar_depth(root: &Path, cache: &Path, out: &Path) -> Output {
    run_lidar_depth_with(root, cache, out, &[])
}

/// The same with more arguments (`--set dataset.frames=Camera`).
pub fn run_lidar_depth_with(root: &Path, cache: &Path, out: &Path, extra: &[&str]) -> Output {
    let pipeline = repo().join("pipelines/lidar_depth.ron");
    let set_root = format!("dataset.root={}", root.display());
    let mut args = vec!["run", pipeline.to_str().unwrap(), "--progress", "off"];
    args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap(), "--set", &set_root]);
    args.extend(extra);
    dist4d(&args)
}

/// `dist4d synth` of a small dataset with 12 Hz camera sweeps at `root` (3 keyframes: 13 images
/// per camera).
pub fn synth_camera_sweeps(root: &Path, width: u32, height: u32) {
    synth_camera_sweeps_of(root, 3, width, height)
}

/// The same with `keyframes` keyframes.
pub fn synth_camera_sweeps_of(root: &Path, keyframes: u32, width: u32, height: u32) {
    let (k, w, h) = (keyframes.to_string(), width.to_string(), height.to_string());
    let args = ["synth", "--out", root.to_str().unwrap(), "--keyframes", &k, "--width", &w, "--height", &h];
    let o = dist4d(&[&args[..], &["--camera-sweeps"]].concat());
    assert!(o.status.success(), "{}", text(&o));
}

/// Runs the devkit peer (`nusc_project.py`) on `root`, writing its points to `peer_out`, and
/// checks each of its (sample, camera) projections against ours at `ours(sample, camera)`: same
/// point count, coordinates within 0.05 px / m (the devkit keeps intermediate world coordinates
/// in float32, we compute in f64). Returns how many were checked.
pub fn check_against_devkit(
    python: &Path,
    root: &Path,
    peer_out: &Path,
    ours: impl Fn(&str, &str) -> PathBuf,
) -> usize {
    let script = repo().join("../shared/bench/peers/nusc_project.py");
    let o = Command::new(python)
        .args([
            script.to_str().unwrap(),
            root.to_str().unwrap(),
            "v1.0-mini",
            "--out-dir",
            peer_out.to_str().unwrap(),
            "--repeat",
            "1",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let mut checked = 0;
    for line in String::from_utf8_lossy(&o.stdout).lines() {
        let v: Value = serde_json::from_str(line).unwrap();
        let (cam, sample) = (v["camera"].as_str().unwrap(), v["sample"].as_str().unwrap());
        let mine = read_npy_rows(&ours(sample, cam));
        let theirs = read_npy_rows(&peer_out.join(format!("{sample}_{cam}.npy")));
        assert_eq!(mine.len() as u64, v["points"].as_u64().unwrap(), "{sample} {cam}: point count");
        let worst =
            mine.iter().zip(&theirs).flat_map(|(a, b)| (0..3).map(move |i| (a[i] - b[i]).abs())).fold(0f32, f32::max);
        assert!(worst < 0.05, "{sample} {cam}: coordinates differ by {worst}");
        checked += 1;
    }
    checked
}

/// A tiny synthetic nuScenes dataset (`keyframes` keyframes, 160 x 90 images) under a temp folder,
/// for tests that edit its tables the way a careless or hostile writer would.
pub fn synthetic_nuscenes(keyframes: u32) -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    let k = keyframes.to_string();
    let o = dist4d(&["synth", "--out", root.to_str().unwrap(), "--keyframes", &k, "--width", "160", "--height", "90"]);
    assert!(o.status.success(), "{}", text(&o));
    (tmp, root)
}

/// The rows of nuScenes table `name` of the dataset at `root`.
pub fn table(root: &Path, name: &str) -> Vec<Value> {
    serde_json::from_slice(&std::fs::read(root.join(format!("v1.0-mini/{name}.json"))).unwrap()).unwrap()
}

/// Replaces nuScenes table `name` of the dataset at `root` with `rows`.
pub fn write_table(root: &Path, name: &str, rows: &[Value]) {
    std::fs::write(root.join(format!("v1.0-mini/{name}.json")), serde_json::to_vec(rows).unwrap()).unwrap();
}

/// A python with mmengine (`.venv-mm`, which `.ci/run` makes, or `DIST4D_MM_PYTHON`): what
/// MagicDriveDiT's and DiST-4D's datasets load their info pickles with.
pub fn mm_python() -> Option<PathBuf> {
    let p =
        std::env::var_os("DIST4D_MM_PYTHON").map(PathBuf::from).unwrap_or_else(|| repo().join(".venv-mm/bin/python"));
    if Command::new(&p).args(["-c", "import mmengine"]).output().is_ok_and(|o| o.status.success()) {
        Some(p)
    } else {
        eprintln!("SKIPPED: no python with mmengine at {} (.ci/run makes .venv-mm)", p.display());
        None
    }
}

/// The py123d venv's python (`.venv-py123d`, which `.ci/run` makes, or `DIST4D_PY123D_PYTHON`).
pub fn py123d_python() -> Option<PathBuf> {
    let p = std::env::var_os("DIST4D_PY123D_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo().join(".venv-py123d/bin/python"));
    if Command::new(&p).args(["-c", "import py123d"]).output().is_ok_and(|o| o.status.success()) {
        Some(p)
    } else {
        eprintln!("SKIPPED: no py123d venv at {} (.ci/run makes it: pip install py123d)", p.display());
        None
    }
}

/// Converts the nuScenes-format dataset at `source` into py123d logs under `out` with py123d's
/// own parser and writer (scripts/py123d_convert.py; `args` as it takes them).
pub fn py123d_convert(python: &Path, source: &Path, out: &Path, args: &[&str]) {
    let o = Command::new(python)
        .arg(repo().join("scripts/py123d_convert.py"))
        .args(["--nuscenes-root", source.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .args(args)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
}
