//! The reader against the two references it has: the same synthetic scene read by the nuScenes
//! reader, and py123d's own Python API on the log. The logs are made by py123d itself
//! (scripts/py123d_convert.py, py123d's nuScenes parser and log writer) in the venv `.ci/run`
//! installs (`.venv-py123d`, or `DIST4D_PY123D_PYTHON`); without it the tests say so and pass.

use super::*;
use crate::nuscenes::{NuScenes, NuScenesConfig};
use crate::surround::Surround;
use dist4d_runtime::Dataset;
use dist4d_types::artifact::Artifact;
use std::process::Command;
use std::sync::OnceLock;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The py123d venv's python, when it is installed.
fn python() -> Option<PathBuf> {
    let candidates =
        [std::env::var_os("DIST4D_PY123D_PYTHON").map(PathBuf::from), Some(repo().join(".venv-py123d/bin/python"))];
    let found = candidates
        .into_iter()
        .flatten()
        .find(|p| Command::new(p).args(["-c", "import py123d"]).output().is_ok_and(|o| o.status.success()));
    if found.is_none() {
        eprintln!("skipped: no py123d venv (.venv-py123d, made by .ci/run; or DIST4D_PY123D_PYTHON)");
    }
    found
}

/// A synthetic scene (3 keyframes, LiDAR and camera sweeps, 160x90) and its py123d logs: (the
/// nuScenes root, keyframe log root with JPEG and IPC-zstd LiDAR in the log, sweep log root with
/// paths into the nuScenes root). Made once per test process.
struct Fixture {
    _dir: tempfile::TempDir,
    source: PathBuf,
    keyframes: PathBuf,
    sweeps: PathBuf,
}

fn fixture() -> Option<&'static Fixture> {
    static FIXTURE: OnceLock<Option<Fixture>> = OnceLock::new();
    FIXTURE
        .get_or_init(|| {
            let python = python()?;
            let dir = tempfile::tempdir().unwrap();
            let source = dir.path().join("source");
            let config = dist4d_synth::SynthConfig {
                keyframes: 3,
                width: 160,
                height: 90,
                camera_sweeps: true,
                ..Default::default()
            };
            dist4d_synth::write_dataset(&config, &source, &|_| {}).unwrap();
            let convert = |out: &Path, args: &[&str]| {
                let o = Command::new(&python)
                    .arg(repo().join("scripts/py123d_convert.py"))
                    .args(["--nuscenes-root", source.to_str().unwrap(), "--out", out.to_str().unwrap()])
                    .args(args)
                    .output()
                    .unwrap();
                assert!(
                    o.status.success(),
                    "{}{}",
                    String::from_utf8_lossy(&o.stdout),
                    String::from_utf8_lossy(&o.stderr)
                );
            };
            let keyframes = dir.path().join("keyframes");
            convert(
                &keyframes,
                &["--keyframes", "--camera-storage", "jpeg", "--lidar-storage", "in_log", "--lidar-codec", "ipc_zstd"],
            );
            let sweeps = dir.path().join("sweeps");
            convert(
                &sweeps,
                &["--sweeps", "--camera-storage", "path", "--lidar-storage", "path", "--ipc-compression", "lz4"],
            );
            Some(Fixture { _dir: dir, source, keyframes, sweeps })
        })
        .as_ref()
}

fn native(f: &Fixture, frames: FrameMode) -> Surround<NuScenes> {
    Surround(
        NuScenes::open(NuScenesConfig { root: f.source.display().to_string(), frames, ..Default::default() }).unwrap(),
    )
}

fn through_log(root: &Path, frames: FrameMode, sensor_root: Option<&Path>) -> Surround<Py123d> {
    Surround(
        Py123d::open(Py123dConfig {
            root: root.display().to_string(),
            frames,
            sensor_root: sensor_root.map(|p| p.display().to_string()),
            ..Default::default()
        })
        .unwrap(),
    )
}

fn close(a: &Se3, b: &Se3, tol: f64) -> bool {
    (a.translation - b.translation).length() <= tol && a.rotation.dot(b.rotation).abs() >= 1.0 - tol
}

fn same_boxes(a: &Boxes3D, b: &Boxes3D, what: &str) {
    assert_eq!(a.timestamp_us, b.timestamp_us, "{what}");
    assert_eq!(a.boxes.len(), b.boxes.len(), "{what}");
    for x in &a.boxes {
        let y = b.boxes.iter().find(|y| y.instance == x.instance).unwrap_or_else(|| panic!("{what}: {}", x.instance));
        assert_eq!(x.category, y.category, "{what}");
        for i in 0..3 {
            assert!((x.center[i] - y.center[i]).abs() < 1e-6, "{what}: {:?} {:?}", x.center, y.center);
            assert!((x.size[i] - y.size[i]).abs() < 1e-9, "{what}: {:?} {:?}", x.size, y.size);
        }
        let (qa, qb) = (Se3::from_wxyz_t(x.rotation, [0.0; 3]), Se3::from_wxyz_t(y.rotation, [0.0; 3]));
        assert!(close(&qa, &qb, 1e-9), "{what}: {:?} {:?}", x.rotation, y.rotation);
    }
}

/// Every item of `a` and `b` (same tree) gives the same data on every port both readers share.
fn same_data(a: &dyn Dataset, b: &dyn Dataset, lidar_labels: bool) {
    let scenes = a.count(&ItemKey::new(&[]));
    assert_eq!(scenes, b.count(&ItemKey::new(&[])));
    for s in 0..scenes {
        let frames = a.count(&ItemKey::new(&[s]));
        let times = |d: &dyn Dataset| -> Vec<Option<i64>> {
            (0..d.count(&ItemKey::new(&[s])))
                .map(|f| {
                    d.load_source("camera_pose", &ItemKey::new(&[s, f, 0]))
                        .ok()
                        .map(|p| Pose::decode(&p).unwrap().timestamp_us)
                })
                .collect()
        };
        assert_eq!(frames, b.count(&ItemKey::new(&[s])), "frames of scene {s}: {:?} {:?}", times(a), times(b));
        assert!(frames > 0);
        for f in 0..frames {
            let frame = ItemKey::new(&[s, f]);
            let load = |d: &dyn Dataset, port: &str, item: &ItemKey| d.load_source(port, item).unwrap();
            let pose = |d: &dyn Dataset, port: &str, item: &ItemKey| Pose::decode(&load(d, port, item)).unwrap();
            let (pa, pb) = (pose(a, "lidar_pose", &frame), pose(b, "lidar_pose", &frame));
            assert_eq!(pa.timestamp_us, pb.timestamp_us, "{frame:?}");
            assert!(close(&pa.ego_to_world, &pb.ego_to_world, 1e-6), "{frame:?}");
            let (ca, cb) = (
                PointCloud::decode(&load(a, "lidar", &frame)).unwrap(),
                PointCloud::decode(&load(b, "lidar", &frame)).unwrap(),
            );
            // The log keeps points in the ego frame as float32: back in the sensor frame they are
            // within float32 rounding of the file's.
            assert_eq!(ca.points.len(), cb.points.len(), "{frame:?}");
            let worst = ca
                .points
                .iter()
                .zip(&cb.points)
                .map(|(p, q)| (0..3).map(|i| (p[i] - q[i]).abs()).fold(0f32, f32::max))
                .fold(0f32, f32::max);
            assert!(worst < 1e-4, "{frame:?}: {worst} m");
            assert!(ca.points.iter().zip(&cb.points).all(|(p, q)| p[3].floor() == q[3]), "intensity as uint8");
            if lidar_labels {
                assert_eq!(ca.labels, cb.labels, "{frame:?}");
            }
            same_boxes(
                &Boxes3D::decode(&load(a, "boxes", &frame)).unwrap(),
                &Boxes3D::decode(&load(b, "boxes", &frame)).unwrap(),
                &format!("{frame:?}"),
            );
            for c in 0..a.count(&frame) {
                let item = ItemKey::new(&[s, f, c]);
                assert_eq!(a.label(&item), b.label(&item), "camera order");
                assert_eq!(load(a, "image", &item), load(b, "image", &item), "{item:?}: the same pixels");
                let (ka, kb) = (
                    Calibration::decode(&load(a, "camera_calib", &item)).unwrap(),
                    Calibration::decode(&load(b, "camera_calib", &item)).unwrap(),
                );
                assert_eq!((ka.width, ka.height), (kb.width, kb.height));
                assert!(close(&ka.sensor_to_ego, &kb.sensor_to_ego, 1e-9), "{item:?}");
                let (ia, ib) = (ka.intrinsics.unwrap(), kb.intrinsics.unwrap());
                assert!((0..3).all(|r| (0..3).all(|k| (ia[r][k] - ib[r][k]).abs() < 1e-9)), "{item:?}");
                let (pa, pb) = (pose(a, "camera_pose", &item), pose(b, "camera_pose", &item));
                assert_eq!(pa.timestamp_us, pb.timestamp_us, "{item:?}");
                assert!(close(&pa.ego_to_world, &pb.ego_to_world, 1e-6), "{item:?}");
                same_boxes(
                    &Boxes3D::decode(&load(a, "camera_boxes", &item)).unwrap(),
                    &Boxes3D::decode(&load(b, "camera_boxes", &item)).unwrap(),
                    &format!("{item:?}"),
                );
            }
        }
    }
}

#[test]
fn keyframes_through_the_log_are_the_keyframes_of_the_nuscenes_reader() {
    let Some(f) = fixture() else { return };
    same_data(&native(f, FrameMode::Keyframes), &through_log(&f.keyframes, FrameMode::Keyframes, None), true);
}

#[test]
fn sweeps_and_camera_rounds_through_a_log_of_paths_are_the_nuscenes_readers() {
    let Some(f) = fixture() else { return };
    // Keyframes of a log of every image: the keyframe's own images (one round), not each
    // camera's nearest, which for a camera firing half a period late is the round before's.
    for frames in [FrameMode::Sweeps, FrameMode::Camera, FrameMode::Keyframes] {
        let log = through_log(&f.sweeps, frames, Some(&f.source));
        // py123d keeps lidarseg labels only in keyframe logs (its sweep parser drops them).
        same_data(&native(f, frames), &log, false);
    }
}

/// The log folder under a converter's output.
fn log_dir(root: &Path) -> PathBuf {
    find_logs(root).unwrap().remove(0)
}

#[test]
fn what_the_reader_gives_equals_what_py123ds_api_returns() {
    let Some(f) = fixture() else { return };
    let python = python().unwrap();
    for (root, sensor_root) in [(&f.keyframes, None), (&f.sweeps, Some(&f.source))] {
        let log = log_dir(root);
        let mut cmd = Command::new(&python);
        cmd.arg(repo().join("scripts/py123d_readback.py")).arg(&log);
        if let Some(s) = sensor_root {
            cmd.arg(s);
        }
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let api: Value = serde_json::from_slice(&o.stdout).unwrap();
        // Camera rounds give every image once: every image py123d lists is an item here.
        let ds = through_log(root, FrameMode::Camera, sensor_root.map(|p| p.as_path()));
        let tree = ds.0.tree();
        let mut images = 0;
        for (c, name) in tree.cameras.iter().enumerate() {
            let cam = &api["cameras"][name];
            let k: Vec<f64> = cam["intrinsics"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
            for (fi, frame) in tree.scenes[0].frames.iter().enumerate() {
                let Ok(r) = &frame.cameras[c] else { continue };
                let m = r.calib.intrinsics.unwrap();
                // serde_json's float parsing may round the last bit of what Python printed.
                let ours = [m[0][0], m[1][1], m[0][2], m[1][2], m[0][1]];
                assert!(
                    ours.iter().zip(&k).all(|(a, b)| (a - b).abs() <= 1e-12 * b.abs().max(1.0)),
                    "{name}: {ours:?} {k:?}"
                );
                assert_eq!(
                    (r.calib.width as u64, r.calib.height as u64),
                    (cam["width"].as_u64().unwrap(), cam["height"].as_u64().unwrap())
                );
                let image = cam["images"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .find(|i| i["timestamp_us"].as_i64() == Some(r.pose.timestamp_us))
                    .unwrap_or_else(|| panic!("{name} frame {fi}: py123d has no image at {}", r.pose.timestamp_us));
                let v: Vec<f64> =
                    image["camera_to_global"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
                let theirs = Se3::from_wxyz_t([v[3], v[4], v[5], v[6]], [v[0], v[1], v[2]]);
                let ours = r.pose.ego_to_world.then_from(&r.calib.sensor_to_ego);
                assert!(close(&ours, &theirs, 1e-6), "{name} at {}", r.pose.timestamp_us);
                images += 1;
            }
            assert_eq!(images % cam["images"].as_array().unwrap().len(), 0, "every image of {name} once");
        }
        assert!(images > 0);
        // Boxes at every annotated time, as py123d returns them (its [l, w, h] is our [w, l, h]).
        let log_reader = &ds.0.logs[0];
        for frame in api["boxes"].as_array().unwrap() {
            let t = frame["timestamp_us"].as_i64().unwrap();
            let ours = Py123d::boxes_at(log_reader, t).unwrap();
            let theirs = frame["boxes"].as_array().unwrap();
            assert_eq!(ours.len(), theirs.len(), "at {t}");
            for b in theirs {
                let o = ours.iter().find(|o| o.instance == b["track"].as_str().unwrap()).unwrap();
                let v: Vec<f64> = b["box"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
                assert!((0..3).all(|i| (o.center[i] - v[i]).abs() < 1e-9), "{t}");
                let size = [o.size[1], o.size[0], o.size[2]];
                assert!((0..3).all(|i| (size[i] - v[7 + i]).abs() < 1e-12), "{size:?} {v:?}");
                let label = b["label"].as_u64().unwrap() as usize;
                assert_eq!(o.category, classes::table("NuScenesBoxDetectionLabel").unwrap()[label].1);
            }
        }
    }
}

/// A copy of the keyframe log to break.
fn broken_copy(f: &Fixture) -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let log = log_dir(&f.keyframes);
    let dst = tmp.path().join("split").join(log.file_name().unwrap());
    std::fs::create_dir_all(&dst).unwrap();
    for e in std::fs::read_dir(&log).unwrap().flatten() {
        std::fs::copy(e.path(), dst.join(e.file_name())).unwrap();
    }
    (tmp, dst)
}

fn open_err(root: &Path) -> String {
    let config = Py123dConfig { root: root.display().to_string(), ..Default::default() };
    format!("{:#}", Py123d::open(config).err().expect("refused"))
}

#[test]
fn bad_logs_are_errors_naming_the_file_the_modality_and_the_row() {
    let Some(f) = fixture() else { return };
    // A truncated camera file (the dataset's only log: nothing is left to read).
    let (tmp, log) = broken_copy(f);
    let cam = log.join("camera.pcam_f0.arrow");
    let bytes = std::fs::read(&cam).unwrap();
    std::fs::write(&cam, &bytes[..bytes.len() / 2]).unwrap();
    let e = open_err(tmp.path());
    assert!(e.contains("camera.pcam_f0.arrow") && e.contains("truncated"), "{e}");
    // A missing modality.
    let (tmp, log) = broken_copy(f);
    std::fs::remove_file(log.join("ego_state_se3.arrow")).unwrap();
    let e = open_err(tmp.path());
    assert!(e.contains("ego_state_se3.arrow"), "{e}");
    // A NaN camera pose: only the items of that image fail, naming file, row and field.
    let (tmp, log) = broken_copy(f);
    let cam = log.join("camera.pcam_f0.arrow");
    let file = IpcFile::open(&cam).unwrap();
    let (batch, i) = file.batch_of(1, Some(&[file.column("camera.pcam_f0.camera_to_global_se3").unwrap()])).unwrap();
    let x = fixed_row(batch.column(0).as_any().downcast_ref::<FixedSizeListArray>().unwrap(), i).unwrap()[0];
    let mut bytes = std::fs::read(&cam).unwrap();
    let at = bytes.windows(8).position(|w| w == x.to_le_bytes()).expect("the pose's bytes, uncompressed");
    bytes[at..at + 8].copy_from_slice(&f64::NAN.to_le_bytes());
    std::fs::write(&cam, bytes).unwrap();
    let ds = through_log(tmp.path(), FrameMode::Keyframes, None);
    let front = ds.0.tree().cameras.iter().position(|c| c == "CAM_FRONT").unwrap() as u32;
    let e = format!("{:#}", ds.load_source("camera_pose", &ItemKey::new(&[0, 1, front])).unwrap_err());
    assert!(
        e.contains("camera.pcam_f0.arrow")
            && e.contains("row 1")
            && e.contains("camera_to_global_se3")
            && e.contains("not finite"),
        "{e}"
    );
    assert!(ds.load_source("camera_pose", &ItemKey::new(&[0, 0, front])).is_ok(), "other rows are read");
    // A LiDAR sweep in a codec py123d does not write: its frame fails, naming file and row.
    let (tmp, log) = broken_copy(f);
    let lidar = log.join("lidar.lidar_merged.arrow");
    let mut bytes = std::fs::read(&lidar).unwrap();
    let blob = {
        let file = IpcFile::open(&lidar).unwrap();
        let (batch, i) = file.batch_of(0, Some(&[file.column("lidar.lidar_merged.data").unwrap()])).unwrap();
        batch.column(0).as_any().downcast_ref::<BinaryArray>().unwrap().value(i)[..64].to_vec()
    };
    let at = bytes.windows(64).position(|w| w == blob.as_slice()).unwrap();
    bytes[at..at + 4].copy_from_slice(b"ZZZZ");
    std::fs::write(&lidar, bytes).unwrap();
    let ds = through_log(tmp.path(), FrameMode::Keyframes, None);
    let e = format!("{:#}", ds.load_source("lidar", &ItemKey::new(&[0, 0])).unwrap_err());
    assert!(e.contains("lidar.lidar_merged.arrow row 0") && e.contains("no codec"), "{e}");
    assert!(ds.load_source("lidar", &ItemKey::new(&[0, 1])).is_ok());
}

#[test]
fn a_fisheye_camera_fails_its_own_items_and_the_pinhole_ones_are_read() {
    let Some(python) = python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    // Written by py123d's own log writer (its KITTI-360 parser needs KITTI-360).
    let o = Command::new(&python)
        .arg(repo().join("tests/fixtures/py123d/write_fisheye_log.py"))
        .arg(tmp.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ds = through_log(tmp.path(), FrameMode::Keyframes, None);
    assert!(ds.0.warnings.iter().any(|w| w.contains("camera image_02 is a fisheye_mei camera")), "{:?}", ds.0.warnings);
    let cameras = &ds.0.tree().cameras;
    let fisheye = cameras.iter().position(|c| c == "image_02").unwrap() as u32;
    let front = cameras.iter().position(|c| c == "CAM_FRONT").unwrap() as u32;
    for f in 0..3 {
        let e = format!("{:#}", ds.load_source("image", &ItemKey::new(&[0, f, fisheye])).unwrap_err());
        assert!(e.contains("camera.fmcam_l.arrow") && e.contains("pinhole model only"), "{e}");
        assert!(ds.load_source("image", &ItemKey::new(&[0, f, front])).is_ok());
        assert!(ds.load_source("lidar", &ItemKey::new(&[0, f])).is_ok());
    }
}

#[test]
fn mp4_cameras_and_laz_sweeps_fail_their_items_saying_how_to_convert() {
    let Some(f) = fixture() else { return };
    let python = python().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let o = Command::new(&python)
        .arg(repo().join("scripts/py123d_convert.py"))
        .args(["--nuscenes-root", f.source.to_str().unwrap(), "--out", tmp.path().to_str().unwrap()])
        .args(["--keyframes", "--camera-storage", "mp4", "--lidar-storage", "in_log", "--lidar-codec", "laz"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ds = through_log(tmp.path(), FrameMode::Keyframes, None);
    assert!(ds.0.warnings.iter().any(|w| w.contains("MP4")), "{:?}", ds.0.warnings);
    let e = format!("{:#}", ds.load_source("image", &ItemKey::new(&[0, 0, 0])).unwrap_err());
    assert!(e.contains("MP4") && e.contains("jpeg_binary"), "{e}");
    let e = format!("{:#}", ds.load_source("lidar", &ItemKey::new(&[0, 0])).unwrap_err());
    assert!(e.contains("LAZ") && e.contains("ipc_zstd"), "{e}");
    // Calibrations and poses are read all the same.
    assert!(ds.load_source("camera_calib", &ItemKey::new(&[0, 0, 0])).is_ok());
    assert!(ds.load_source("lidar_pose", &ItemKey::new(&[0, 0])).is_ok());
}

/// File digests that hash the bytes (the runtime's own memoise by stat).
struct Hashing;
impl FileDigests for Hashing {
    fn file_digest(&self, path: &Path) -> Result<Option<Digest>> {
        Ok(Some(Digest::of(&std::fs::read(path)?)))
    }
}

#[test]
fn a_path_stored_sweep_changed_under_sensor_root_changes_its_frames_digest() {
    let Some(f) = fixture() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let copy = tmp.path().join("source");
    let o = Command::new("cp").args(["-r", f.source.to_str().unwrap(), copy.to_str().unwrap()]).status().unwrap();
    assert!(o.success());
    let ds = through_log(&f.sweeps, FrameMode::Sweeps, Some(&copy));
    let item = ItemKey::new(&[0, 0]);
    let before = ds.source_digest("lidar", &item, &Hashing).unwrap();
    let (_, frame) = ds.0.tree().scene_frame(&item).unwrap();
    // The reading names the file its row points at (what index.json records as `stored_file`).
    let sweep = frame.lidar.as_ref().unwrap().stored_file.clone().unwrap();
    assert!(sweep.to_string_lossy().ends_with(".pcd.bin"), "{}", sweep.display());
    let bytes = std::fs::read(&sweep).unwrap();
    std::fs::write(&sweep, &bytes[..bytes.len() / 2 / 20 * 20]).unwrap();
    assert_ne!(ds.source_digest("lidar", &item, &Hashing).unwrap(), before, "a rerun must read the changed sweep");
}

#[test]
fn frames_past_the_last_sweep_get_no_old_sweep_and_a_broken_log_is_left_out() {
    let Some(f) = fixture() else { return };
    let python = python().unwrap();
    // A log whose LiDAR stops after its first sweep: py123d's own writer, from the source with
    // every LiDAR sample_data but the first keyframe's removed is more than a test needs; the
    // keyframe log's LiDAR file is cut to its first batch row by rewriting it with pyarrow.
    let (tmp, log) = broken_copy(f);
    let cut = r#"
import sys, pyarrow as pa, pyarrow.ipc as ipc
p = sys.argv[1]
r = ipc.open_file(p)
t = r.read_all().slice(0, 1)
with ipc.new_file(p + ".new", t.schema) as w:
    w.write_table(t)
import os; os.replace(p + ".new", p)
"#;
    let o = Command::new(&python).args(["-c", cut]).arg(log.join("lidar.lidar_merged.arrow")).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ds = through_log(tmp.path(), FrameMode::Keyframes, None);
    assert!(ds.load_source("lidar", &ItemKey::new(&[0, 0])).is_ok());
    let e = format!("{:#}", ds.load_source("lidar", &ItemKey::new(&[0, 1])).unwrap_err());
    assert!(e.contains("no LiDAR sweep within"), "{e}");
    // Beside it, a log whose ego track is gone: left out with a warning, the other one read.
    let (_, other) = {
        let dst = tmp.path().join("split").join("broken-0000");
        std::fs::create_dir_all(&dst).unwrap();
        for e in std::fs::read_dir(&log).unwrap().flatten() {
            std::fs::copy(e.path(), dst.join(e.file_name())).unwrap();
        }
        std::fs::remove_file(dst.join("ego_state_se3.arrow")).unwrap();
        ((), dst)
    };
    let config = Py123dConfig { root: tmp.path().display().to_string(), logs: None, ..Default::default() };
    let ds = Py123d::open(config).unwrap();
    assert_eq!(ds.tree().scenes.len(), 1);
    assert!(
        ds.warnings.iter().any(|w| w.contains("is left out") && w.contains("ego_state_se3.arrow")),
        "{:?}",
        ds.warnings
    );
    let _ = other;
}
