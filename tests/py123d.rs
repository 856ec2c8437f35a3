//! End-to-end: the shipped pipelines on py123d logs (`--set 'dataset=Py123d(root: ..)'`), made by
//! py123d itself from a synthetic scene and from the shared nuScenes keyframe. Skipped (with a
//! message) where the py123d venv is not installed; `.ci/run` installs it.

mod common;

use common::*;
use std::path::Path;

/// A synthetic scene (3 keyframes, sweeps, 12 Hz camera images, 160x90) and its logs: keyframes
/// with JPEGs and LiDAR in the log, and every sweep and image likewise.
fn scene(python: &Path, dir: &Path) -> (std::path::PathBuf, std::path::PathBuf, std::path::PathBuf) {
    let source = dir.join("source");
    let o = dist4d(&[
        "synth",
        "--out",
        source.to_str().unwrap(),
        "--keyframes",
        "3",
        "--width",
        "160",
        "--height",
        "90",
        "--camera-sweeps",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let (keyframes, sweeps) = (dir.join("keyframes"), dir.join("sweeps"));
    py123d_convert(
        python,
        &source,
        &keyframes,
        &["--keyframes", "--camera-storage", "jpeg", "--lidar-storage", "in_log"],
    );
    py123d_convert(python, &source, &sweeps, &["--sweeps", "--camera-storage", "jpeg", "--lidar-storage", "in_log"]);
    (source, keyframes, sweeps)
}

fn run(pipeline: &str, dataset: &str, cache: &Path, out: &Path) -> std::process::Output {
    let file = repo().join(format!("pipelines/{pipeline}.ron"));
    dist4d(&[
        "run",
        file.to_str().unwrap(),
        "--progress",
        "off",
        "--cache",
        cache.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--set",
        &format!("dataset={dataset}"),
    ])
}

#[test]
fn every_shipped_pipeline_runs_on_a_py123d_log() {
    let Some(python) = py123d_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (_, keyframes, sweeps) = scene(&python, tmp.path());
    let cache = tmp.path().join("cache");
    let kf = format!("Py123d(root: \"{}\")", keyframes.display());
    // video_12hz.ron says `frames: Camera`; the swap keeps it (no edited copy, no extra field).
    let rounds = format!("Py123d(root: \"{}\")", sweeps.display());
    let every_sweep = format!("Py123d(root: \"{}\", frames: Sweeps)", sweeps.display());
    for (pipeline, dataset) in [
        ("curation", &kf),
        ("lidar_depth", &kf),
        ("dist_s_pairs", &kf),
        ("scc", &kf),
        ("novel_views", &kf),
        ("temporal", &kf),
        ("occupancy", &kf),
        ("occupancy", &every_sweep),
        ("video_12hz", &rounds),
    ] {
        let out = tmp.path().join(format!("out-{pipeline}-{}", dataset.len()));
        let o = run(pipeline, dataset, &cache, &out);
        assert!(o.status.success(), "{pipeline} on {dataset}: {}", text(&o));
        assert!(text(&o).contains(" 0 failed"), "{pipeline}: {}", text(&o));
        let index: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("index.json")).unwrap()).unwrap();
        assert!(!index["files"].as_array().unwrap().is_empty(), "{pipeline} wrote files");
        // Every image's source is the log's file and row.
        let sources = index["sources"].to_string();
        assert!(sources.contains(".arrow\"") && sources.contains("\"row\":"), "{pipeline}: {sources}");
    }
    // 12 Hz: every image of the log is in exactly one round.
    let v12 = tmp.path().join(format!("out-video_12hz-{}", rounds.len()));
    let index: serde_json::Value = serde_json::from_slice(&std::fs::read(v12.join("index.json")).unwrap()).unwrap();
    let images = index["sources"].as_object().unwrap().values().filter(|s| s["row"].is_u64()).count();
    assert_eq!(images, 6 * 13, "13 images of each of 6 cameras between the 3 keyframes");
}

#[test]
fn curated_depth_through_the_log_is_the_native_readers_within_float_rounding() {
    let Some(python) = py123d_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (source, keyframes, _) = scene(&python, tmp.path());
    let cache = tmp.path().join("cache");
    let (native, logged) = (tmp.path().join("native"), tmp.path().join("logged"));
    assert!(run("curation", &format!("NuScenes(root: \"{}\")", source.display()), &cache, &native).status.success());
    assert!(run("curation", &format!("Py123d(root: \"{}\")", keyframes.display()), &cache, &logged).status.success());
    let (mut pixels, mut off) = (0usize, 0usize);
    let mut compared = 0;
    for (name, bytes) in tree(&native) {
        if !name.ends_with("_depth.npy") {
            continue;
        }
        let a = npy_f32(&bytes);
        let b = npy_f32(&std::fs::read(logged.join(&name)).unwrap());
        assert_eq!(a.len(), b.len(), "{name}");
        for (x, y) in a.iter().zip(&b) {
            pixels += 1;
            // The log keeps LiDAR points in the ego frame as float32: their last bits differ.
            if (x - y).abs() > 0.01 * y.abs().max(0.01) {
                off += 1;
            }
        }
        compared += 1;
    }
    assert_eq!(compared, 18);
    assert!((off as f64) < 0.005 * pixels as f64, "{off} of {pixels} pixels more than 1% apart");
}

/// The values of a little-endian float32 .npy.
fn npy_f32(bytes: &[u8]) -> Vec<f32> {
    let header = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    bytes[10 + header..].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
}

#[test]
fn the_shared_nuscenes_keyframe_through_py123d_runs_the_curation() {
    let (Some(python), Some(shared)) = (py123d_python(), shared_nuscenes()) else { return };
    let tmp = tempfile::tempdir().unwrap();
    let logs = tmp.path().join("logs");
    // py123d's parser opens the CAN bus expansion; the script gives it an empty one in a folder
    // of links, so the shared data is only read.
    py123d_convert(&python, &shared, &logs, &["--keyframes", "--camera-storage", "jpeg", "--lidar-storage", "in_log"]);
    let out = tmp.path().join("out");
    let o = run("curation", &format!("Py123d(root: \"{}\")", logs.display()), &tmp.path().join("c"), &out);
    assert!(o.status.success() && text(&o).contains(" 0 failed"), "{}", text(&o));
    assert!(out.join("scene-0061/CAM_BACK/000_depth.npy").is_file());
    // Its car's body: the nuScenes rig masks the boot in CAM_BACK (the log keeps the file names
    // nowhere, so the vehicle is matched by the image size alone).
    assert!(out.join("scene-0061/CAM_BACK/000_ego.png").is_file());
}

#[test]
fn a_log_of_another_car_with_a_fisheye_camera_says_what_it_lacks_once_and_goes_on() {
    let Some(python) = py123d_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let logs = tmp.path().join("logs");
    let o = std::process::Command::new(&python)
        .arg(repo().join("tests/fixtures/py123d/write_fisheye_log.py"))
        .arg(&logs)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let o =
        run("curation", &format!("Py123d(root: \"{}\")", logs.display()), &tmp.path().join("c"), &tmp.path().join("o"));
    let said = text(&o);
    // The fisheye camera's items fail (the run says why once up front), the pinhole one's are made.
    let warned = |what: &str| said.lines().filter(|l| l.starts_with("warning: ") && l.contains(what)).count();
    assert_eq!(warned("camera image_02 is a fisheye_mei camera"), 1, "{said}");
    assert!(said.contains("failed: ") && said.contains("image_02"), "{said}");
    assert!(tmp.path().join("o/fisheye-0000/CAM_FRONT/000_depth.npy").is_file(), "{said}");
    // No rig knows this car: the run says so once instead of leaving the body unmasked silently.
    assert_eq!(warned("no built-in rig fits camera(s) CAM_FRONT (160x90)"), 1, "{said}");
    // No lidarseg and no segmenter: occupancy would be geometry only, and its run says so.
    let o = run(
        "occupancy",
        &format!("Py123d(root: \"{}\")", logs.display()),
        &tmp.path().join("c"),
        &tmp.path().join("occ"),
    );
    assert!(text(&o).contains("occupancy semantics are geometry only"), "{}", text(&o));
}

#[test]
fn training_clips_from_a_log_name_each_images_row_and_the_loader_reads_it() {
    let Some(python) = py123d_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (_, _, sweeps) = scene(&python, tmp.path());
    let out = tmp.path().join("out");
    let file = repo().join("pipelines/video_12hz.ron");
    let dataset = format!("dataset=Py123d(root: \"{}\")", sweeps.display());
    let cache = tmp.path().join("cache");
    let args = ["run", file.to_str().unwrap(), "--progress", "off", "--cache", cache.to_str().unwrap()];
    let o =
        dist4d(&[&args[..], &["--out", out.to_str().unwrap(), "--set", &dataset, "--set", "clips.frames=4"]].concat());
    assert!(o.status.success(), "{}", text(&o));
    let clips = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path().join("clips.jsonl"))
        .find(|p| p.is_file())
        .expect("a clips.jsonl");
    let first: serde_json::Value =
        serde_json::from_str(std::fs::read_to_string(&clips).unwrap().lines().next().unwrap()).unwrap();
    let camera = &first["frames"][0]["cameras"][0];
    assert!(camera["image"].as_str().unwrap().ends_with(".arrow"), "{camera}");
    assert!(camera["image_row"].is_u64(), "{camera}");
    // The loader of docs/examples gives every image of the clip's first frame as JPEG bytes.
    let script = format!(
        "import sys, json; sys.path.insert(0, {examples:?})\n\
         import clip_loader as c\n\
         clip = next(c.clips({out:?}))\n\
         images = [c.image_bytes({root:?}, cam) for f in clip['frames'] for cam in f['cameras']]\n\
         assert all(i[:3] == b'\\xff\\xd8\\xff' for i in images), [i[:4] for i in images]\n\
         assert len(set(images)) == len(images), 'every image its own'\n\
         print(len(images), c.load_clip({out:?}, {root:?}, clip)['image_rows'][0])",
        examples = repo().join("docs/examples").display().to_string(),
        out = out.display().to_string(),
        root = sweeps.display().to_string(),
    );
    let o = std::process::Command::new(&python).args(["-c", &script]).output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    assert!(String::from_utf8_lossy(&o.stdout).starts_with("24 "), "{}", text(&o));
}
