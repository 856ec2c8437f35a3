//! `Py123d(root, logs, cameras, lidar, frames, sensor_root)`: the Arrow logs py123d writes from
//! Waymo, Argoverse 2, nuPlan, KITTI-360, PandaSet, nuScenes and more, read with arrow-rs.
//!
//! Format facts followed (py123d 0.7.x, see docs/datasets.md "py123d logs"): a log is a folder of
//! Arrow IPC files, one per modality (`py123d/api/scene/arrow/arrow_log_writer.py`); columns are
//! named `<modality>.<field>`, each file's metadata is msgpack under the schema key `metadata`
//! (`py123d/api/utils/arrow_metadata_utils.py`); poses are `[x, y, z, qw, qx, qy, qz]`
//! (`py123d/geometry/geometry_index.py`); cameras (`arrow_camera.py`) hold the image (JPEG or PNG
//! bytes, a path relative to the source dataset's root, or an MP4 frame index) and
//! camera -> world at the image's time; the merged LiDAR (`arrow_lidar.py`) holds one Arrow IPC
//! stream per sweep with points in the **ego** frame (`ipc_lidar_io.py`); boxes
//! (`arrow_box_detections_se3.py`) are in the world frame, `[.., length, width, height]`, with
//! track tokens and a label enum named in the metadata; the ego track (`arrow_ego_state_se3.py`)
//! is the ego (IMU) -> world pose at the LiDAR times.
//!
//! Items are the surround adapter's: a scene per log, frames by the configured clock
//! (`Keyframes`: the annotated times; `Sweeps`: every LiDAR sweep; `Camera`: the rounds of the
//! cameras), a camera dimension named from the log's camera metadata.

pub mod classes;
#[cfg(test)]
mod cross_check;
pub mod ipc;

use crate::checks::{self, Place, Renormalised, Transform};
use crate::files::decode_camera_image;
use crate::nuscenes::{camera_rounds, read_pcd_bin, FrameMode};
use crate::sidecar::Sidecars;
use crate::surround::{Frame, Reading, Scene, SurroundReader, Tree};
use anyhow::{anyhow, bail, ensure, Context, Result};
use arrow_array::{Array, BinaryArray, FixedSizeListArray, Float64Array, Int64Array, ListArray, StringArray};
use arrow_array::{Float32Array, LargeBinaryArray, UInt16Array, UInt8Array};
use dist4d_graph::{DatasetSchema, ParamsSpec, ParamsValue};
use dist4d_runtime::{Digest, DigestBuilder, FileDigests, ItemKey};
use dist4d_types::artifact::{Box3D, Boxes3D, Calibration, Image, PointCloud, Pose};
use dist4d_types::geometry::Se3;
use ipc::IpcFile;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The py123d versions whose logs this reader follows (the log metadata's `version`).
pub const VERSIONS: &str = "0.7.x";

/// How far (us) an image may be from the time of the frame it is given to (py123d's own limit).
const MAX_IMAGE_OFFSET_US: i64 = 100_000;

/// The merged LiDAR's modality key: its file is `<key>.arrow`, its columns `<key>.<field>`.
const LIDAR_KEY: &str = "lidar.lidar_merged";

#[derive(Serialize, Deserialize, Clone, Debug)]
#[serde(deny_unknown_fields, default)]
pub struct Py123dConfig {
    /// A folder of py123d logs: py123d's `logs` folder (`<split>/<log>/sync.arrow`), one split
    /// folder, or one log folder.
    pub root: String,
    /// Log names (folder names) to read, in this order; by default every log under `root`, sorted
    /// by split and name.
    pub logs: Option<Vec<String>>,
    /// Camera names as the logs' metadata gives them (`CAM_FRONT`, `FRONT`, `ring_front_center`),
    /// in item order; by default every camera of the first log, clockwise from the front.
    pub cameras: Option<Vec<String>>,
    /// The LiDAR whose points a frame holds (`LIDAR_TOP`, `TOP`); by default every LiDAR of the
    /// merged cloud, in the frame of the top one.
    pub lidar: Option<String>,
    /// `Keyframes` (the annotated times), `Sweeps` (every LiDAR sweep) or `Camera` (rounds of
    /// the cameras, every image once).
    pub frames: FrameMode,
    /// The source dataset's root, for logs that store images or LiDAR as paths into it (py123d
    /// reads it from an environment variable, e.g. `NUSCENES_DATA_ROOT`, and does not record it).
    pub sensor_root: Option<String>,
}

impl Default for Py123dConfig {
    fn default() -> Self {
        Py123dConfig {
            root: String::new(),
            logs: None,
            cameras: None,
            lidar: None,
            frames: FrameMode::Keyframes,
            sensor_root: None,
        }
    }
}

impl dist4d_graph::Validate for Py123dConfig {
    fn validate(&self) -> Vec<dist4d_graph::ParamProblem> {
        let mut checks = dist4d_graph::ParamChecks::new();
        if let Some(cameras) = &self.cameras {
            checks.path_names("cameras", cameras);
        }
        if let Some(logs) = &self.logs {
            checks.path_names("logs", logs);
        }
        if let Some(lidar) = &self.lidar {
            checks.path_name("lidar", lidar);
        }
        checks.done()
    }
}

/// How a modality stores its data.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Storage {
    /// Bytes in the log (JPEG / PNG images; LiDAR blobs).
    InLog,
    /// A path relative to the source dataset's root.
    Path,
    /// A frame index into `<modality>.mp4` beside the file.
    Mp4,
}

/// One camera of a log.
struct CameraFile {
    file: IpcFile,
    key: String,
    storage: Storage,
    /// Camera -> ego and intrinsics, or why the camera is refused (its model).
    calib: std::result::Result<Calibration, String>,
    /// (time, camera -> world) per row.
    rows: Vec<(i64, std::result::Result<Se3, String>)>,
    /// Path storage: the path of each row.
    paths: Vec<Option<String>>,
}

/// The merged LiDAR of a log.
struct LidarFile {
    file: IpcFile,
    storage: Storage,
    /// LiDAR id -> (name, LiDAR -> ego).
    sensors: Vec<(u8, String, Se3)>,
    /// The sensor whose frame the points are given in (index into `sensors`).
    sensor: usize,
    /// Only the points of this LiDAR id (the `lidar` config).
    only: Option<u8>,
    /// The points carry nuScenes-lidarseg labels (`semantic`).
    labels: bool,
    /// (sweep start, sweep end) per row.
    rows: Vec<(i64, i64)>,
    /// Path storage: the path (and lidarseg path) of each row.
    paths: Vec<(Option<String>, Option<String>)>,
}

struct Log {
    name: String,
    /// `nuscenes`, `wod-perception`, ... (the log metadata's `dataset`).
    dataset: String,
    /// The ego metadata's `vehicle_name` (`nuscenes_renault_zoe`); `dist4d_synthetic` for a log of
    /// dist4d's synthetic world, which py123d's nuScenes parser calls a Zoe too.
    vehicle: String,
    /// Ego -> world by time.
    ego: Vec<(i64, Se3)>,
    ego_box: ([f64; 3], [f64; 3]),
    cameras: Vec<Option<CameraFile>>,
    lidar: LidarFile,
    /// Annotated times and their boxes (or why a box of that time is refused).
    keyframes: Vec<(i64, std::result::Result<Vec<Box3D>, String>)>,
}

/// What a frame keeps beside its readings.
pub struct FrameTime {
    /// The frame's time: its LiDAR sweep's end, or its camera round's time.
    pub time: i64,
}

pub struct Py123d {
    pub config: Py123dConfig,
    tree: Tree<usize, FrameTime>,
    logs: Vec<Log>,
    pub warnings: Vec<String>,
    pub has_point_labels: bool,
}

/// Every log folder (holding `sync.arrow`) at `root` or up to two levels under it.
fn find_logs(root: &Path) -> Result<Vec<PathBuf>> {
    if root.join("sync.arrow").is_file() {
        return Ok(vec![root.to_path_buf()]);
    }
    let mut found = Vec::new();
    let mut level = vec![root.to_path_buf()];
    for _ in 0..2 {
        let mut next = Vec::new();
        for dir in level {
            let Ok(entries) = std::fs::read_dir(&dir) else { continue };
            for e in entries.flatten() {
                let p = e.path();
                if p.join("sync.arrow").is_file() {
                    found.push(p);
                } else if p.is_dir() {
                    next.push(p);
                }
            }
        }
        level = next;
    }
    found.sort();
    Ok(found)
}

fn column<'a, T: 'static>(batch: &'a arrow_array::RecordBatch, file: &IpcFile, name: &str) -> Result<&'a T> {
    let i = batch.schema().index_of(name).map_err(|_| anyhow!("{} has no column `{name}`", file.path.display()))?;
    batch.column(i).as_any().downcast_ref::<T>().ok_or_else(|| {
        anyhow!(
            "{}: column `{name}` is {}, not what py123d {VERSIONS} writes",
            file.path.display(),
            batch.column(i).data_type()
        )
    })
}

/// A pose `[x, y, z, qw, qx, qy, qz]` checked (finite, unit quaternion, bounded translation).
fn pose7(v: &[f64], at: &Place, field: &str, kind: Transform, notes: &mut Renormalised) -> Result<Se3, String> {
    if v.len() != 7 {
        return Err(format!("{at}: field {field} has {} values, not 7", v.len()));
    }
    let fields = checks::Fields { rotation: field, translation: field };
    checks::rigid(at, fields, [v[3], v[4], v[5], v[6]], [v[0], v[1], v[2]], kind, notes)
}

fn pose_json(v: &Value, at: &Place, field: &str, kind: Transform, notes: &mut Renormalised) -> Result<Se3, String> {
    let values: Option<Vec<f64>> = v.as_array().map(|a| a.iter().map(|x| x.as_f64().unwrap_or(f64::NAN)).collect());
    pose7(&values.unwrap_or_default(), at, field, kind, notes)
}

/// The values of row `row` of a fixed-size list column of f64.
fn fixed_row(list: &FixedSizeListArray, row: usize) -> Option<Vec<f64>> {
    if row >= list.len() || list.is_null(row) {
        return None;
    }
    let v = list.value(row);
    let f = v.as_any().downcast_ref::<Float64Array>()?;
    Some(f.values().to_vec())
}

/// Every (timestamp, pose) row of a file's `ts` and `pose` columns; a bad pose is that row's
/// error (naming file, row and field), so that only the items that use it fail.
fn timed_poses(
    file: &IpcFile,
    ts: &str,
    pose: &str,
    kind: Transform,
    notes: &mut Renormalised,
) -> Result<Vec<(i64, std::result::Result<Se3, String>)>> {
    let cols = [file.column(ts)?, file.column(pose)?];
    let mut out = Vec::new();
    for batch in file.batches(Some(&cols)) {
        let batch = batch?;
        let t = column::<Int64Array>(&batch, file, ts)?;
        let p = column::<FixedSizeListArray>(&batch, file, pose)?;
        for i in 0..batch.num_rows() {
            let row = out.len();
            let at = Place::new(&file.path, format!("row {row}"));
            ensure!(!t.is_null(i), "{at}: field {ts} is null");
            let se3 = match fixed_row(p, i) {
                None => Err(format!("{at}: field {pose} is null")),
                Some(values) => pose7(&values, &at, pose, kind, notes),
            };
            out.push((t.value(i), se3));
        }
    }
    Ok(out)
}

/// The storage a `data` column's type says.
fn storage_of(file: &IpcFile, data: &str) -> Result<Storage> {
    let field = file.schema.field(file.column(data)?);
    Ok(match field.data_type() {
        arrow_schema::DataType::Binary | arrow_schema::DataType::LargeBinary => Storage::InLog,
        arrow_schema::DataType::Utf8 | arrow_schema::DataType::LargeUtf8 => Storage::Path,
        arrow_schema::DataType::Int32 | arrow_schema::DataType::Int64 => Storage::Mp4,
        other => bail!("{}: column `{data}` is {other}, which py123d {VERSIONS} does not write", file.path.display()),
    })
}

/// The string values of a column (path storage), null as `None`.
fn strings(file: &IpcFile, name: &str) -> Result<Vec<Option<String>>> {
    let Ok(col) = file.column(name) else { return Ok(Vec::new()) };
    let mut out = Vec::new();
    for batch in file.batches(Some(&[col])) {
        let batch = batch?;
        let s = column::<StringArray>(&batch, file, name)?;
        out.extend((0..batch.num_rows()).map(|i| (!s.is_null(i)).then(|| s.value(i).to_string())));
    }
    Ok(out)
}

/// The longest gap of the ego track interpolated over: py123d logs hold ego states at 10-20 Hz (2 Hz
/// in keyframe logs); a longer gap is missing data, where a straight line is a guess.
const MAX_EGO_GAP_US: i64 = 1_000_000;

/// Slerp/lerp of the ego track at `t` (between states at most `MAX_EGO_GAP_US` apart); the
/// nearest end within `MAX_IMAGE_OFFSET_US` outside it or beside a longer gap.
fn ego_at(track: &[(i64, Se3)], t: i64) -> Option<Se3> {
    let after = track.partition_point(|(tk, _)| *tk < t);
    match (after.checked_sub(1).map(|i| &track[i]), track.get(after)) {
        (_, Some((t1, p1))) if *t1 == t => Some(*p1),
        (Some((t0, p0)), Some((t1, p1))) if t1 - t0 > MAX_EGO_GAP_US => match (t - t0).min(t1 - t) {
            d if d > MAX_IMAGE_OFFSET_US => None,
            _ if t - t0 <= t1 - t => Some(*p0),
            _ => Some(*p1),
        },
        (Some((t0, p0)), Some((t1, p1))) => {
            let w = (t - t0) as f64 / (t1 - t0) as f64;
            Some(Se3 {
                rotation: p0.rotation.slerp(p1.rotation, w),
                translation: p0.translation.lerp(p1.translation, w),
            })
        }
        (Some((t0, p0)), None) if t - t0 <= MAX_IMAGE_OFFSET_US => Some(*p0),
        (None, Some((t1, p1))) if t1 - t <= MAX_IMAGE_OFFSET_US => Some(*p1),
        _ => None,
    }
}

/// The index of the value of `times` nearest `t`.
fn nearest(times: &[i64], t: i64) -> Option<usize> {
    let at = times.partition_point(|&x| x < t);
    [at.checked_sub(1), (at < times.len()).then_some(at)].into_iter().flatten().min_by_key(|&i| (times[i] - t).abs())
}

impl Py123d {
    pub fn open(config: Py123dConfig) -> Result<Py123d> {
        let root = PathBuf::from(&config.root);
        ensure!(root.is_dir(), "{} is not a folder (dataset.root)", root.display());
        let mut dirs = find_logs(&root)?;
        ensure!(
            !dirs.is_empty(),
            "{} holds no py123d log (a folder with sync.arrow, at most two levels down: <split>/<log>/)",
            root.display()
        );
        if let Some(wanted) = &config.logs {
            let mut picked = Vec::new();
            for name in wanted {
                let dir = dirs.iter().find(|d| d.file_name().is_some_and(|n| n == name.as_str())).ok_or_else(|| {
                    anyhow!(
                        "dataset.logs names `{name}`, which {} does not hold (logs: {})",
                        root.display(),
                        dirs.iter().filter_map(|d| d.file_name()?.to_str()).collect::<Vec<_>>().join(", ")
                    )
                })?;
                picked.push(dir.clone());
            }
            dirs = picked;
        }
        let mut warnings = Vec::new();
        let mut notes = Renormalised::default();
        // The camera names: configured, or the first log's, clockwise from the front.
        let first_cameras = camera_names(&dirs[0], &mut notes)?;
        let cameras: Vec<String> = match &config.cameras {
            Some(c) => c.clone(),
            None => first_cameras,
        };
        ensure!(!cameras.is_empty(), "{} has no camera files (camera.*.arrow)", dirs[0].display());
        let mut logs = Vec::new();
        let mut names: HashMap<String, PathBuf> = HashMap::new();
        for dir in &dirs {
            // A broken log is left out, said once: the other logs of the dataset still run.
            let log = match read_log(dir, &config, &cameras, &mut notes, &mut warnings) {
                Ok(log) => log,
                Err(e) => {
                    warnings.push(format!("the py123d log {} is left out: {e:#}", dir.display()));
                    continue;
                }
            };
            if let Some(other) = names.insert(log.name.clone(), dir.clone()) {
                bail!(
                    "two logs are named {}: {} and {}; choose one with dataset.logs",
                    log.name,
                    other.display(),
                    dir.display()
                );
            }
            logs.push(log);
        }
        if logs.is_empty() {
            bail!("no py123d log under {} could be read: {}", root.display(), warnings.join("; "));
        }
        warnings.extend(notes.warnings());
        let mut scenes = Vec::new();
        for (l, log) in logs.iter().enumerate() {
            scenes.push(Scene {
                name: log.name.clone(),
                frames: frames_of(log, &cameras, &config, &mut warnings),
                extra: l,
            });
        }
        let has_point_labels = logs.iter().all(|l| l.lidar.labels);
        let tree = Tree { root, cameras, scenes, sidecars: Sidecars::default() };
        Ok(Py123d { config, tree, logs, warnings, has_point_labels })
    }
}

/// The names of a log's cameras, clockwise from the front by their viewing direction in the ego
/// frame (ties by file name): nuScenes' logs give the devkit's order.
fn camera_names(dir: &Path, notes: &mut Renormalised) -> Result<Vec<String>> {
    let mut found = Vec::new();
    for e in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))?.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if !(name.starts_with("camera.") && name.ends_with(".arrow")) {
            continue;
        }
        let file = IpcFile::open(&e.path())?;
        let meta = ipc::metadata_json(&file)?;
        let camera = meta["camera_name"].as_str().map(String::from).unwrap_or_else(|| name.clone());
        let at = Place::new(&file.path, "metadata");
        let yaw = pose_json(&meta["camera_to_imu_se3"], &at, "camera_to_imu_se3", Transform::Mount, notes)
            .map(|m| {
                let axis = m.rotation * glam::DVec3::Z;
                // Clockwise from straight ahead; a front camera a few degrees to the left of it
                // still comes first.
                ((-axis.y).atan2(axis.x) + std::f64::consts::PI / 12.0).rem_euclid(std::f64::consts::TAU)
            })
            .unwrap_or(f64::MAX);
        found.push((yaw, name, camera));
    }
    found.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    Ok(found.into_iter().map(|(_, _, c)| c).collect())
}

fn read_log(
    dir: &Path,
    config: &Py123dConfig,
    cameras: &[String],
    notes: &mut Renormalised,
    warnings: &mut Vec<String>,
) -> Result<Log> {
    let sync = IpcFile::open(&dir.join("sync.arrow"))?;
    let meta = ipc::metadata_json(&sync)?;
    let name = meta["log_name"]
        .as_str()
        .map(String::from)
        .unwrap_or_else(|| dir.file_name().unwrap_or_default().to_string_lossy().into_owned());
    let dataset = meta["dataset"].as_str().unwrap_or("").to_string();
    if let Some(v) = meta["version"].as_str().filter(|v| !v.starts_with("0.7.")) {
        warnings.push(format!(
            "{}: written by py123d {v}; this reader follows py123d {VERSIONS}",
            dir.join("sync.arrow").display()
        ));
    }
    // The ego track.
    let ego_file = IpcFile::open(&dir.join("ego_state_se3.arrow"))
        .context("the ego track (every py123d log has ego_state_se3.arrow)")?;
    let mut ego = Vec::new();
    for (t, pose) in
        timed_poses(&ego_file, "ego_state_se3.timestamp_us", "ego_state_se3.imu_se3", Transform::Pose, notes)?
    {
        match pose {
            Ok(p) => ego.push((t, p)),
            // The ego pose at that time is then interpolated from its neighbours.
            Err(why) => warnings.push(format!("{why}: the ego track leaves this row out")),
        }
    }
    ego.sort_by_key(|(t, _)| *t);
    ensure!(!ego.is_empty(), "{} has no rows", ego_file.path.display());
    let ego_meta = ipc::metadata_json(&ego_file)?;
    let vehicle = if meta["location"].as_str() == Some("dist4d-synthetic") {
        "dist4d_synthetic".to_string()
    } else {
        ego_meta["vehicle_name"].as_str().unwrap_or("").to_string()
    };
    let ego_box = ego_box_of(&dataset, &ego_meta, &ego_file.path, notes)?;

    // Cameras, by name; each file opened and its metadata parsed once.
    let mut by_name: HashMap<String, (IpcFile, Value)> = HashMap::new();
    for e in std::fs::read_dir(dir)?.flatten() {
        let file = e.file_name().to_string_lossy().into_owned();
        if file.starts_with("camera.") && file.ends_with(".arrow") {
            let f = IpcFile::open(&e.path())?;
            let m = ipc::metadata_json(&f)?;
            if let Some(n) = m["camera_name"].as_str() {
                by_name.insert(n.to_string(), (f, m));
            }
        }
    }
    let mut have: Vec<String> = by_name.keys().cloned().collect();
    have.sort();
    let mut files = Vec::new();
    for camera in cameras {
        let Some((file, meta)) = by_name.remove(camera) else {
            warnings.push(format!(
                "log {name} has no camera {camera} (it has: {}): its items of that camera fail",
                have.join(", ")
            ));
            files.push(None);
            continue;
        };
        files.push(Some(read_camera(file, meta, config, notes, warnings)?));
    }
    let lidar = read_lidar_file(dir, config, notes)?;
    let keyframes = read_boxes(dir, notes, warnings)?;
    Ok(Log { name, dataset, vehicle, ego, ego_box, cameras: files, lidar, keyframes })
}

/// The recording car's box (ego frame) whose LiDAR returns the `lidar` port drops: dist4d's
/// nuScenes box for nuScenes logs (the same the nuScenes reader drops), else the vehicle's box
/// the log records (`center_to_imu_se3`, length, width, height) grown by 0.3 m.
fn ego_box_of(dataset: &str, meta: &Value, file: &Path, notes: &mut Renormalised) -> Result<([f64; 3], [f64; 3])> {
    if dataset.starts_with("nuscenes") {
        return Ok(dist4d_types::geometry::ego_box::NUSCENES);
    }
    let at = Place::new(file, "metadata");
    let center = pose_json(&meta["center_to_imu_se3"], &at, "center_to_imu_se3", Transform::Mount, notes)
        .map_err(anyhow::Error::msg)?;
    let dim = |k: &str| meta[k].as_f64().filter(|v| v.is_finite() && *v > 0.0 && *v < 100.0);
    let (Some(l), Some(w), Some(h)) = (dim("length"), dim("width"), dim("height")) else {
        bail!("{at}: fields length, width, height are not the vehicle's size in metres");
    };
    let c = center.translation;
    let m = 0.3;
    Ok((
        [c.x - l / 2.0 - m, c.y - w / 2.0 - m, c.z - h / 2.0 - m],
        [c.x + l / 2.0 + m, c.y + w / 2.0 + m, c.z + h / 2.0 + m],
    ))
}

fn read_camera(
    file: IpcFile,
    meta: Value,
    config: &Py123dConfig,
    notes: &mut Renormalised,
    warnings: &mut Vec<String>,
) -> Result<CameraFile> {
    let path = file.path.clone();
    let path = path.as_path();
    let key = path.file_stem().unwrap_or_default().to_string_lossy().into_owned();
    let at = Place::new(path, "metadata");
    let name = meta["camera_name"].as_str().unwrap_or(&key).to_string();
    let storage = storage_of(&file, &format!("{key}.data"))?;
    let calib = camera_calib(&meta, &at, notes, warnings, &name);
    if let Err(why) = &calib {
        warnings.push(why.clone());
    }
    if storage == Storage::Mp4 {
        warnings.push(format!(
            "{}: camera {name} is stored as MP4 video, which dist4d does not decode: convert the log with \
             py123d's camera_store_option \"jpeg_binary\" (or \"path\"); its image items fail",
            path.display()
        ));
    }
    if storage == Storage::Path && config.sensor_root.is_none() {
        bail!(
            "{}: camera {name} stores paths into the source dataset, whose root py123d does not record: \
             set dataset.sensor_root (py123d reads it from an environment variable, e.g. NUSCENES_DATA_ROOT)",
            path.display()
        );
    }
    let rows = timed_poses(
        &file,
        &format!("{key}.timestamp_us"),
        &format!("{key}.camera_to_global_se3"),
        Transform::Pose,
        notes,
    )?;
    ensure!(rows.windows(2).all(|w| w[0].0 <= w[1].0), "{}: rows are not in time order", path.display());
    let paths = if storage == Storage::Path { strings(&file, &format!("{key}.data"))? } else { Vec::new() };
    Ok(CameraFile { file, key, storage, calib, rows, paths })
}

/// A pinhole camera's mounting and intrinsics; another model is refused, per camera.
fn camera_calib(
    meta: &Value,
    at: &Place,
    notes: &mut Renormalised,
    warnings: &mut Vec<String>,
    name: &str,
) -> std::result::Result<Calibration, String> {
    let model = meta["camera_model"].as_str().unwrap_or("pinhole");
    if model != "pinhole" {
        return Err(format!(
            "{at}: camera {name} is a {model} camera; dist4d projects with the pinhole model only, so its items fail \
             (leave it out with dataset.cameras)"
        ));
    }
    let sensor_to_ego = pose_json(&meta["camera_to_imu_se3"], at, "camera_to_imu_se3", Transform::Mount, notes)?;
    let k: Vec<f64> =
        meta["intrinsics"].as_array().map(|a| a.iter().filter_map(|v| v.as_f64()).collect()).unwrap_or_default();
    if k.len() < 4 {
        return Err(format!("{at}: field intrinsics is not [fx, fy, cx, cy, skew]"));
    }
    let skew = k.get(4).copied().unwrap_or(0.0);
    let intrinsics = checks::pinhole(at, "intrinsics", [[k[0], skew, k[2]], [0.0, k[1], k[3]], [0.0, 0.0, 1.0]])?;
    let dim = |f: &str| meta[f].as_u64().map_or(0, |v| u32::try_from(v).unwrap_or(u32::MAX));
    let (width, height) = (dim("width"), dim("height"));
    checks::image_size(&at.to_string(), "fields width, height", width, height)?;
    let distortion: Vec<f64> =
        meta["distortion"].as_array().map(|a| a.iter().filter_map(|v| v.as_f64()).collect()).unwrap_or_default();
    if meta["is_undistorted"].as_bool() != Some(true) && distortion.iter().any(|d| *d != 0.0) {
        warnings.push(format!(
            "{at}: camera {name} has lens distortion {distortion:?} (OpenCV k1, k2, p1, p2, k3), which dist4d's pinhole \
             projection leaves out: projected points land off their pixel where the distortion is large (the image borders)"
        ));
    }
    Ok(Calibration { sensor_to_ego, intrinsics: Some(intrinsics), width, height })
}

fn read_lidar_file(dir: &Path, config: &Py123dConfig, notes: &mut Renormalised) -> Result<LidarFile> {
    let path = dir.join(format!("{LIDAR_KEY}.arrow"));
    let file = IpcFile::open(&path).context("the merged LiDAR (py123d writes lidar.lidar_merged.arrow)")?;
    let meta = ipc::metadata_json(&file)?;
    let at = Place::new(&path, "metadata");
    let mut sensors = Vec::new();
    let mut labels = false;
    for (id, m) in meta.as_object().into_iter().flatten() {
        let id: u8 = id.parse().map_err(|_| anyhow!("{at}: LiDAR id {id:?} is not a number"))?;
        let name = m["lidar_name"].as_str().unwrap_or("lidar").to_string();
        let to_ego = pose_json(&m["lidar_to_imu_se3"], &at, "lidar_to_imu_se3", Transform::Mount, notes)
            .map_err(anyhow::Error::msg)?;
        labels |= m["segmentation_label_class"].as_str().is_some_and(|c| c.ends_with("NuScenesLidarSegmentationLabel"));
        sensors.push((id, name, to_ego));
    }
    sensors.sort_by_key(|s| s.0);
    ensure!(!sensors.is_empty(), "{at}: lists no LiDAR");
    let only = match &config.lidar {
        Some(want) => Some(
            sensors
                .iter()
                .find(|s| &s.1 == want)
                .ok_or_else(|| {
                    anyhow!(
                        "dataset.lidar is {want}, which {} does not have (it has: {})",
                        path.display(),
                        sensors.iter().map(|s| s.1.as_str()).collect::<Vec<_>>().join(", ")
                    )
                })?
                .0,
        ),
        None => None,
    };
    // The frame the points are given in: the chosen LiDAR's, else the top one's (py123d LidarID
    // TOP = 2), else the first.
    let sensor = match only {
        Some(id) => sensors.iter().position(|s| s.0 == id).unwrap(),
        None => sensors.iter().position(|s| s.0 == 2).unwrap_or(0),
    };
    let storage = storage_of(&file, &format!("{LIDAR_KEY}.data"))?;
    let (t0, t1) =
        (file.column("lidar.lidar_merged.timestamp_us")?, file.column("lidar.lidar_merged.end_timestamp_us"));
    let mut rows = Vec::new();
    let cols: Vec<usize> = [Some(t0), t1.as_ref().ok().copied()].into_iter().flatten().collect();
    for batch in file.batches(Some(&cols)) {
        let batch = batch?;
        let start = column::<Int64Array>(&batch, &file, "lidar.lidar_merged.timestamp_us")?;
        let end = batch
            .schema()
            .index_of(&format!("{LIDAR_KEY}.end_timestamp_us"))
            .ok()
            .and_then(|i| batch.column(i).as_any().downcast_ref::<Int64Array>().cloned());
        for i in 0..batch.num_rows() {
            let s = start.value(i);
            let e = end.as_ref().filter(|e| !e.is_null(i)).map_or(s, |e| e.value(i));
            rows.push((s, e));
        }
    }
    ensure!(rows.windows(2).all(|w| w[0].1 <= w[1].1), "{}: sweeps are not in time order", path.display());
    let paths = if storage == Storage::Path {
        ensure!(
            config.sensor_root.is_some(),
            "{}: the LiDAR is stored as paths into the source dataset, whose root py123d does not record: set \
             dataset.sensor_root (py123d reads it from an environment variable, e.g. NUSCENES_DATA_ROOT)",
            path.display()
        );
        let data = strings(&file, &format!("{LIDAR_KEY}.data"))?;
        let kwargs = strings(&file, &format!("{LIDAR_KEY}.kwargs"))?;
        data.into_iter()
            .enumerate()
            .map(|(i, d)| {
                let seg = kwargs.get(i).cloned().flatten().and_then(|k| {
                    serde_json::from_str::<Value>(&k).ok()?["lidarseg_relative_path"].as_str().map(String::from)
                });
                (d, seg)
            })
            .collect()
    } else {
        Vec::new()
    };
    if storage == Storage::Path {
        labels = paths.iter().any(|(_, seg)| seg.is_some());
    }
    Ok(LidarFile { file, storage, sensors, sensor, only, labels, rows, paths })
}

/// The annotated times and their boxes (world frame, nuScenes size order and categories).
#[allow(clippy::type_complexity)]
fn read_boxes(
    dir: &Path,
    notes: &mut Renormalised,
    warnings: &mut Vec<String>,
) -> Result<Vec<(i64, std::result::Result<Vec<Box3D>, String>)>> {
    let path = dir.join("box_detections_se3.arrow");
    if !path.is_file() {
        return Ok(Vec::new());
    }
    let file = IpcFile::open(&path)?;
    let meta = ipc::metadata_json(&file)?;
    let class = meta["box_detection_label_class"].as_str().unwrap_or("").to_string();
    let table = classes::table(&class);
    if table.is_none() {
        warnings.push(format!(
            "{}: box labels of {class:?}, which dist4d has no table for: categories are `py123d.<value>` (occupancy: others)",
            path.display()
        ));
    }
    let k = |f: &str| format!("box_detections_se3.{f}");
    let mut out = Vec::new();
    for batch in file.batches(None) {
        let batch = batch?;
        let ts = column::<Int64Array>(&batch, &file, &k("timestamp_us"))?;
        let boxes = column::<ListArray>(&batch, &file, &k("bounding_box_se3"))?;
        let tracks = column::<ListArray>(&batch, &file, &k("track_token"))?;
        let labels = column::<ListArray>(&batch, &file, &k("label"))?;
        let velocity = batch
            .schema()
            .index_of(&k("velocity_3d"))
            .ok()
            .and_then(|i| batch.column(i).as_any().downcast_ref::<ListArray>().cloned());
        let points = batch
            .schema()
            .index_of(&k("num_lidar_points"))
            .ok()
            .and_then(|i| batch.column(i).as_any().downcast_ref::<ListArray>().cloned());
        for i in 0..batch.num_rows() {
            let row = out.len();
            let place = |j: usize| Place::new(&path, format!("row {row} box {j}"));
            let b = boxes.value(i);
            let b = b
                .as_any()
                .downcast_ref::<FixedSizeListArray>()
                .ok_or_else(|| anyhow!("{}: bounding_box_se3 is not [10] lists", path.display()))?;
            let t = tracks.value(i);
            let t = t
                .as_any()
                .downcast_ref::<StringArray>()
                .ok_or_else(|| anyhow!("{}: track_token is not strings", path.display()))?;
            let l = labels.value(i);
            let l = l
                .as_any()
                .downcast_ref::<UInt16Array>()
                .ok_or_else(|| anyhow!("{}: label is not uint16", path.display()))?;
            let v = velocity.as_ref().map(|v| v.value(i));
            let v = v.as_ref().and_then(|v| v.as_any().downcast_ref::<FixedSizeListArray>());
            let n = points.as_ref().map(|p| p.value(i));
            let n = n.as_ref().and_then(|n| n.as_any().downcast_ref::<arrow_array::Int32Array>());
            let mut frame = Vec::new();
            let mut refused = None;
            if b.len() != t.len() || b.len() != l.len() {
                ensure!(!ts.is_null(i), "{}: row {row}: field timestamp_us is null", path.display());
                let why = format!(
                    "{}: row {row}: its box lists are null or differ in length (boxes {}, track tokens {}, labels {})",
                    path.display(),
                    b.len(),
                    t.len(),
                    l.len()
                );
                out.push((ts.value(i), Err(why)));
                continue;
            }
            for j in 0..b.len() {
                let Some(values) = fixed_row(b, j).filter(|x| x.len() == 10) else {
                    refused = Some(format!("{}: field bounding_box_se3 is not 10 values", place(j)));
                    continue;
                };
                let center = [values[0], values[1], values[2]];
                let size = [values[8], values[7], values[9]];
                let rotation = match checks::box_values(
                    &place(j),
                    center,
                    size,
                    [values[3], values[4], values[5], values[6]],
                    notes,
                ) {
                    Ok(r) => r,
                    Err(why) => {
                        refused = Some(why);
                        continue;
                    }
                };
                let label = l.value(j);
                let category = table
                    .and_then(|t| t.get(label as usize))
                    .map(|(_, c)| c.to_string())
                    .unwrap_or_else(|| format!("py123d.{label}"));
                let velocity =
                    v.and_then(|v| fixed_row(v, j)).filter(|x| x.len() == 3 && x.iter().all(|c| c.is_finite()));
                frame.push(Box3D {
                    center,
                    size,
                    rotation,
                    velocity: velocity.map_or([f64::NAN; 3], |x| [x[0], x[1], x[2]]),
                    // A box without a track token is its own track: matching the untracked boxes
                    // of two annotated times to each other would interpolate between strangers.
                    instance: match t.is_null(j) || t.value(j).is_empty() {
                        true => format!("untracked:{}:{row}:{j}", path.display()),
                        false => t.value(j).to_string(),
                    },
                    category,
                    attributes: Vec::new(),
                    num_lidar_pts: n.filter(|n| j < n.len()).map_or(0, |n| n.value(j).max(0) as u32),
                    interpolated: false,
                    extrapolated: false,
                });
            }
            ensure!(!ts.is_null(i), "{}: row {row}: field timestamp_us is null", path.display());
            out.push((ts.value(i), refused.map_or(Ok(frame), Err)));
        }
    }
    out.sort_by_key(|(t, _)| *t);
    Ok(out)
}

/// The frames of a log by the configured clock.
fn frames_of(
    log: &Log,
    cameras: &[String],
    config: &Py123dConfig,
    warnings: &mut Vec<String>,
) -> Vec<Frame<FrameTime>> {
    let sweep_ends: Vec<i64> = log.lidar.rows.iter().map(|r| r.1).collect();
    // The sweep of a time: the nearest, if within half the sweep period (and a tenth): a log
    // whose sweeps stop must not give later frames an old sweep, and boxes at its time.
    let reach = {
        let mut steps: Vec<i64> = sweep_ends.windows(2).map(|w| w[1] - w[0]).filter(|&d| d > 0).collect();
        steps.sort_unstable();
        steps.get(steps.len() / 2).map_or(MAX_IMAGE_OFFSET_US, |&p| p / 2 + p / 10)
    };
    let sweep_at = |t: i64| nearest(&sweep_ends, t).filter(|&i| (sweep_ends[i] - t).abs() <= reach);
    // Why a camera has no image in a frame depends on the clock: a round of the cameras lacks
    // it, or no image lies near the frame's time.
    let frame_at = |time: i64, lidar_row: Option<usize>, images: Vec<Option<usize>>, in_rounds: bool| Frame {
        lidar: match lidar_row {
            Some(row) => lidar_reading(log, row, config),
            None => Err(format!("log {} has no LiDAR sweep within {} ms of {time} us", log.name, reach / 1000)),
        },
        cameras: images
            .iter()
            .enumerate()
            .map(|(c, row)| match (&log.cameras[c], row) {
                (None, _) => Err(format!("log {} has no camera {}", log.name, cameras[c])),
                (Some(_), None) if in_rounds => Err(format!(
                    "log {}: the camera round at {time} us has no image of {} (the camera skipped this round, \
                     or the log thins it to a lower rate than the other cameras)",
                    log.name, cameras[c]
                )),
                (Some(_), None) => Err(format!(
                    "log {} has no image of {} within {} ms of {time} us",
                    log.name,
                    cameras[c],
                    MAX_IMAGE_OFFSET_US / 1000
                )),
                (Some(cam), Some(row)) => camera_reading(log, cam, &cameras[c], *row, config),
            })
            .collect(),
        extra: FrameTime { time },
    };
    let nearest_images = |t: i64| -> Vec<Option<usize>> {
        log.cameras
            .iter()
            .map(|c| {
                let c = c.as_ref()?;
                let times: Vec<i64> = c.rows.iter().map(|r| r.0).collect();
                nearest(&times, t).filter(|&i| (times[i] - t).abs() <= MAX_IMAGE_OFFSET_US)
            })
            .collect()
    };
    let keyframes = match config.frames {
        FrameMode::Keyframes if log.keyframes.is_empty() => {
            warnings.push(format!(
                "log {} has no annotated times (box_detections_se3): its keyframes are its LiDAR sweeps",
                log.name
            ));
            false
        }
        FrameMode::Keyframes => true,
        _ => false,
    };
    match config.frames {
        FrameMode::Keyframes if keyframes => {
            // A keyframe's images are one round of the cameras: the round of the reference
            // camera's image nearest the keyframe. The nearest image of each camera alone would
            // take, for a camera that fires half a period from the reference, the image of the
            // round before (on a log of every image; a keyframe log has only the rounds).
            let rounds = rounds_of(log);
            let round_times: Vec<i64> = rounds.iter().map(|r| r.time).collect();
            log.keyframes
                .iter()
                .map(|(t, _)| {
                    let images = match nearest(&round_times, *t)
                        .filter(|&r| (round_times[r] - t).abs() <= MAX_IMAGE_OFFSET_US)
                    {
                        Some(r) => {
                            let near = nearest_images(*t);
                            rounds[r].images.iter().zip(near).map(|(own, near)| own.or(near)).collect()
                        }
                        None => nearest_images(*t),
                    };
                    frame_at(*t, sweep_at(*t), images, false)
                })
                .collect()
        }
        FrameMode::Keyframes | FrameMode::Sweeps => {
            sweep_ends.iter().enumerate().map(|(row, &t)| frame_at(t, Some(row), nearest_images(t), false)).collect()
        }
        FrameMode::Camera => rounds_of(log)
            .into_iter()
            .map(|round| frame_at(round.time, sweep_at(round.time), round.images, true))
            .collect(),
    }
}

/// The rounds of a log's cameras (every image once; see `NuScenes(frames: Camera)`).
fn rounds_of(log: &Log) -> Vec<crate::nuscenes::CameraRound> {
    let times: Vec<Vec<i64>> = log
        .cameras
        .iter()
        .map(|c| c.as_ref().map(|c| c.rows.iter().map(|r| r.0).collect()).unwrap_or_default())
        .collect();
    // Each camera's offset from the reference. The nuScenes reader takes it from the
    // keyframe images, which a log does not mark; here it is the median gap from a
    // reference image to the camera's nearest image, or that gap a period earlier or
    // later, whichever pairs the two cameras into the fewest rounds (a camera that fires
    // half a period after the reference is as near the next reference image as its own;
    // only one of the two choices starts and ends the log with whole rounds).
    let period = {
        let mut steps: Vec<i64> = times[0].windows(2).map(|w| w[1] - w[0]).filter(|&d| d > 0).collect();
        steps.sort_unstable();
        steps.get(steps.len() / 2).copied().unwrap_or(83_333)
    };
    let offsets: Vec<i64> = times
        .iter()
        .map(|own| {
            let mut d: Vec<i64> = times[0].iter().filter_map(|&t| Some(own[nearest(own, t)?] - t)).collect();
            d.sort_unstable();
            let gap = d.get(d.len() / 2).copied().unwrap_or(0);
            [gap, gap - period, gap + period]
                .into_iter()
                .filter(|o| o.abs() < period)
                .min_by_key(|&o| (camera_rounds(&[times[0].clone(), own.clone()], &[0, o]).len(), o.abs()))
                .unwrap_or(gap)
        })
        .collect();
    camera_rounds(&times, &offsets)
}

fn lidar_reading(log: &Log, row: usize, config: &Py123dConfig) -> std::result::Result<Reading, String> {
    let lidar = &log.lidar;
    let (_, end) = lidar.rows[row];
    let (_, name, to_ego) = &lidar.sensors[lidar.sensor];
    let ego_to_world = ego_at(&log.ego, end).ok_or_else(|| {
        format!(
            "log {}: no ego pose within 100 ms of the LiDAR sweep at {end} us ({})",
            log.name,
            lidar.file.path.display()
        )
    })?;
    let stored_file = match lidar.storage {
        Storage::Path => Some(lidar_paths(log, row, config)?.0),
        _ => None,
    };
    Ok(Reading {
        file: lidar.file.path.clone(),
        calib: Calibration { sensor_to_ego: *to_ego, intrinsics: None, width: 0, height: 0 },
        pose: Pose { ego_to_world, timestamp_us: end },
        what: format!("{} row {row} ({name})", lidar.file.path.display()),
        token: format!("{}:{LIDAR_KEY}:{end}", log.name),
        row: Some(row as u64),
        stored_file,
    })
}

/// A path-stored sweep's file and lidarseg file under `sensor_root`.
fn lidar_paths(
    log: &Log,
    row: usize,
    config: &Py123dConfig,
) -> std::result::Result<(PathBuf, Option<PathBuf>), String> {
    let root = PathBuf::from(config.sensor_root.as_deref().unwrap_or(""));
    let (rel, seg) = log.lidar.paths.get(row).cloned().unwrap_or_default();
    let at = Place::new(&log.lidar.file.path, format!("row {row}"));
    let rel = rel.ok_or_else(|| format!("{at}: no path"))?;
    let file = checks::join_inside(&root, &at, &format!("{LIDAR_KEY}.data"), &rel)?;
    let seg = match seg {
        Some(seg) => Some(checks::join_inside(&root, &at, "lidarseg_relative_path", &seg)?),
        None => None,
    };
    Ok((file, seg))
}

fn camera_reading(
    log: &Log,
    cam: &CameraFile,
    name: &str,
    row: usize,
    config: &Py123dConfig,
) -> std::result::Result<Reading, String> {
    let calib = cam.calib.clone()?;
    let (t, camera_to_world) = (cam.rows[row].0, cam.rows[row].1.clone()?);
    let stored_file = match cam.storage {
        Storage::Path => {
            let rel = cam
                .paths
                .get(row)
                .cloned()
                .flatten()
                .ok_or_else(|| format!("{} row {row}: no path", cam.file.path.display()))?;
            let root = PathBuf::from(config.sensor_root.as_deref().unwrap_or(""));
            Some(checks::join_inside(
                &root,
                &Place::new(&cam.file.path, format!("row {row}")),
                &format!("{}.data", cam.key),
                &rel,
            )?)
        }
        _ => None,
    };
    Ok(Reading {
        file: cam.file.path.clone(),
        stored_file,
        pose: Pose { ego_to_world: camera_to_world.then_from(&calib.sensor_to_ego.inverse()), timestamp_us: t },
        calib,
        what: format!("{} row {row} ({name} of log {})", cam.file.path.display(), log.name),
        token: format!("{}:{}:{t}", log.name, cam.key),
        row: Some(row as u64),
    })
}

impl Py123d {
    fn log_of(&self, item: &ItemKey) -> Result<&Log> {
        let (scene, _) = self.tree.scene_frame(item)?;
        Ok(&self.logs[scene.extra])
    }

    fn camera_file(&self, image: &Reading) -> Result<&CameraFile> {
        self.logs
            .iter()
            .flat_map(|l| l.cameras.iter().flatten())
            .find(|c| c.file.path == image.file)
            .ok_or_else(|| anyhow!("{}: not a camera file of this dataset", image.what))
    }

    /// The log whose merged LiDAR file `lidar` reads.
    fn lidar_log(&self, lidar: &Reading) -> Result<&Log> {
        self.logs
            .iter()
            .find(|l| l.lidar.file.path == lidar.file)
            .ok_or_else(|| anyhow!("{}: not a LiDAR file of this dataset", lidar.what))
    }

    /// A path-stored sweep's file and lidarseg file under `sensor_root`.
    fn sweep_files(&self, log: &Log, lidar: &Reading) -> Result<(PathBuf, Option<PathBuf>)> {
        lidar_paths(log, lidar.row.unwrap_or(0) as usize, &self.config).map_err(anyhow::Error::msg)
    }

    /// The boxes of `log` at time `t`: an annotated time's own, otherwise the tracks of the two
    /// annotated times around `t` interpolated, and tracks of only one of them moved with their
    /// velocity up to half the interval (as the nuScenes reader does).
    fn boxes_at(log: &Log, t: i64) -> Result<Vec<Box3D>> {
        let times: Vec<i64> = log.keyframes.iter().map(|(tk, _)| *tk).collect();
        let own = |k: usize| log.keyframes[k].1.clone().map_err(|why| anyhow!("{why}"));
        crate::nuscenes::boxes_at_time(&times, &own, t, true)
    }

    /// The points of sweep `row` of the merged file, in the frame of the configured sensor.
    fn read_in_log_lidar(&self, log: &Log, row: u64) -> Result<PointCloud> {
        let lidar = &log.lidar;
        let data = lidar.file.column(&format!("{LIDAR_KEY}.data"))?;
        let (batch, i) = lidar.file.batch_of(row, Some(&[data]))?;
        let column = batch.column(0);
        let blob: &[u8] = if let Some(b) = column.as_any().downcast_ref::<BinaryArray>() {
            b.value(i)
        } else if let Some(b) = column.as_any().downcast_ref::<LargeBinaryArray>() {
            b.value(i)
        } else {
            bail!("{}: column lidar.lidar_merged.data is not binary", lidar.file.path.display())
        };
        let what = format!("{} row {row}", lidar.file.path.display());
        let codec_help = "convert the log with py123d's lidar_codec \"ipc_zstd\" (or \"ipc\", \"ipc_lz4\")";
        match blob {
            [0xFF, 0xFF, 0xFF, 0xFF, ..] => {}
            [b'L', b'A', b'S', b'F', ..] => {
                bail!("{what}: the sweep is LAZ-compressed, which dist4d does not decode: {codec_help}")
            }
            [b'D', b'R', b'A', b'C', b'O', ..] => {
                bail!("{what}: the sweep is Draco-compressed, which dist4d does not decode: {codec_help}")
            }
            _ => bail!(
                "{what}: the sweep is in no codec py123d {VERSIONS} writes (not an Arrow IPC stream, LAZ or Draco)"
            ),
        }
        let batches = ipc::read_stream(blob).with_context(|| format!("{what}: the sweep's Arrow stream"))?;
        let sensor_from_ego = lidar.sensors[lidar.sensor].2.inverse();
        let mut cloud = PointCloud { points: Vec::new(), labels: Vec::new(), rgb: Vec::new() };
        for b in &batches {
            let f = |name: &str| -> Result<&Float32Array> {
                b.column_by_name(name)
                    .and_then(|c| c.as_any().downcast_ref::<Float32Array>())
                    .ok_or_else(|| anyhow!("{what}: the sweep has no float32 column `{name}`"))
            };
            let u8col = |name: &str| b.column_by_name(name).and_then(|c| c.as_any().downcast_ref::<UInt8Array>());
            let (x, y, z) = (f("x")?, f("y")?, f("z")?);
            let intensity = u8col("intensity");
            let ids = u8col("ids");
            let semantic = u8col("semantic").filter(|_| lidar.labels);
            // `dataset.lidar` picks one LiDAR of the merged cloud by its per-point id; a sweep
            // without ids cannot be split, and giving every LiDAR's points would be silently wrong.
            ensure!(
                lidar.only.is_none() || ids.is_some() || lidar.sensors.len() == 1,
                "{what}: dataset.lidar picks one LiDAR, but the sweep has no `ids` column to tell its {} LiDARs \
                 apart: leave dataset.lidar unset to read them all",
                lidar.sensors.len()
            );
            for k in 0..b.num_rows() {
                if let (Some(only), Some(ids)) = (lidar.only, ids) {
                    if ids.value(k) != only {
                        continue;
                    }
                }
                let p =
                    sensor_from_ego.apply(glam::DVec3::new(x.value(k) as f64, y.value(k) as f64, z.value(k) as f64));
                let i = intensity.map_or(0.0, |v| v.value(k) as f32);
                cloud.points.push([p.x as f32, p.y as f32, p.z as f32, i]);
                if let Some(s) = semantic {
                    cloud.labels.push(s.value(k));
                }
            }
        }
        Ok(cloud)
    }
}

impl SurroundReader for Py123d {
    const FORMAT: &'static str = "py123d";
    type Scene = usize;
    type Frame = FrameTime;

    fn tree(&self) -> &Tree<usize, FrameTime> {
        &self.tree
    }

    fn vehicle(&self, scene: usize) -> Option<String> {
        self.logs.get(*self.tree.scenes.get(scene).map(|s| &s.extra)?).map(|l| l.vehicle.clone())
    }

    fn ego_box(&self, scene: usize) -> Option<([f64; 3], [f64; 3])> {
        self.logs.get(*self.tree.scenes.get(scene).map(|s| &s.extra)?).map(|l| l.ego_box)
    }

    /// The log metadata's `dataset` (`wod-perception`, `nuscenes`, `av2-sensor`, ...).
    fn source_dataset(&self, scene: usize) -> String {
        self.tree.scenes.get(scene).and_then(|s| self.logs.get(s.extra)).map(|l| l.dataset.clone()).unwrap_or_default()
    }

    fn lidar_digest(&self, lidar: &Reading, _frame: &FrameTime, files: &dyn FileDigests) -> Result<Option<Digest>> {
        let log = self.lidar_log(lidar)?;
        let mut b = DigestBuilder::new("py123d.lidar");
        let Some(d) = lidar.file_digest(files)? else { return Ok(None) };
        b.digest(&d);
        b.u64(lidar.row.unwrap_or(u64::MAX));
        b.u64(log.lidar.only.map_or(u64::MAX, |o| o as u64));
        b.u64(log.lidar.sensor as u64);
        // Stored as paths: the files read are the sweep and its labels under `sensor_root`.
        if log.lidar.storage == Storage::Path {
            let (sweep, labels) = self.sweep_files(log, lidar)?;
            for path in std::iter::once(sweep).chain(labels) {
                let Some(d) =
                    files.file_digest(&path).with_context(|| format!("{}: {}", lidar.what, path.display()))?
                else {
                    return Ok(None);
                };
                b.digest(&d);
            }
        }
        Ok(Some(b.finish()))
    }

    fn read_lidar(&self, lidar: &Reading, frame: &FrameTime) -> Result<PointCloud> {
        let _ = frame;
        let log = self.lidar_log(lidar)?;
        match log.lidar.storage {
            Storage::InLog => self.read_in_log_lidar(log, lidar.row.unwrap_or(0)),
            Storage::Path => {
                let row = lidar.row.unwrap_or(0) as usize;
                ensure!(
                    log.dataset.starts_with("nuscenes"),
                    "{}: LiDAR stored as paths into a {} dataset, whose files dist4d does not read: convert the log \
                     with py123d's lidar_store_option \"binary\" and lidar_codec \"ipc_zstd\"",
                    lidar.what,
                    log.dataset
                );
                let _ = row;
                let (file, seg) = self.sweep_files(log, lidar)?;
                let mut cloud = read_pcd_bin(&file).with_context(|| lidar.what.clone())?;
                if let Some(path) = seg {
                    let labels = crate::files::read_input(&path, "the lidarseg labels", checks::MAX_SENSOR_FILE_BYTES)?;
                    ensure!(
                        labels.len() == cloud.points.len(),
                        "{} has {} labels for {} points",
                        path.display(),
                        labels.len(),
                        cloud.points.len()
                    );
                    cloud.labels = labels;
                }
                Ok(cloud)
            }
            Storage::Mp4 => bail!("{}: a LiDAR column of integers is not a py123d {VERSIONS} LiDAR", lidar.what),
        }
    }

    fn frame_token(&self, scene: usize, frame: usize) -> Option<String> {
        let s = self.tree.scenes.get(scene)?;
        let f = s.frames.get(frame)?;
        Some(format!("{}:{}", s.name, f.extra.time))
    }

    fn boxes(&self, item: &ItemKey) -> Result<Boxes3D> {
        let (_, frame) = self.tree.scene_frame(item)?;
        let log = self.log_of(item)?;
        let t = frame.lidar.as_ref().map_or(frame.extra.time, |l| l.pose.timestamp_us);
        Ok(Boxes3D { timestamp_us: t, boxes: Py123d::boxes_at(log, t)? })
    }

    fn camera_boxes(&self, item: &ItemKey) -> Result<Boxes3D> {
        let log = self.log_of(item)?;
        let t = self.tree.reading("image", item)?.pose.timestamp_us;
        Ok(Boxes3D { timestamp_us: t, boxes: Py123d::boxes_at(log, t)? })
    }

    fn read_image(&self, image: &Reading) -> Result<Image> {
        if let Some(stored) = &image.stored_file {
            // Path storage: a file of the source dataset.
            return crate::files::read_camera_image(stored, image.calib.width, image.calib.height, &image.what);
        }
        let row = image.row.ok_or_else(|| anyhow!("{}: no row", image.what))?;
        let cam = self.camera_file(image)?;
        ensure!(
            cam.storage == Storage::InLog,
            "{}: the camera is stored as MP4 video, which dist4d does not decode: convert the log with py123d's \
             camera_store_option \"jpeg_binary\" (or \"path\")",
            image.what
        );
        let data = cam.file.column(&format!("{}.data", cam.key))?;
        let (batch, i) = cam.file.batch_of(row, Some(&[data]))?;
        let column = batch.column(0);
        let bytes: &[u8] = if let Some(b) = column.as_any().downcast_ref::<BinaryArray>() {
            ensure!(!b.is_null(i), "{}: no image (null)", image.what);
            b.value(i)
        } else if let Some(b) = column.as_any().downcast_ref::<LargeBinaryArray>() {
            ensure!(!b.is_null(i), "{}: no image (null)", image.what);
            b.value(i)
        } else {
            bail!("{}: the image column is not binary", image.what)
        };
        decode_camera_image(bytes, image.calib.width, image.calib.height, &image.what)
    }

    fn image_digest(&self, image: &Reading, files: &dyn FileDigests) -> Result<Option<Digest>> {
        // The bytes read: the file a path-stored row names, or the camera file's row.
        let digest = match &image.stored_file {
            Some(stored) => {
                files.file_digest(stored).with_context(|| format!("{}: {}", image.what, stored.display()))?
            }
            None => image.file_digest(files)?,
        };
        let Some(d) = digest else { return Ok(None) };
        let mut b = DigestBuilder::new("py123d.image");
        b.digest(&d);
        b.u64(image.row.unwrap_or(u64::MAX));
        Ok(Some(b.finish()))
    }

    fn image_header_size(&self, image: &Reading) -> Result<Option<(u32, u32)>> {
        match &image.stored_file {
            // In the log: decoding checks the size against the metadata.
            None => Ok(None),
            Some(stored) => match crate::files::image_dimensions(stored) {
                Ok(d) => Ok(Some(d)),
                Err(e) => Err(e.context(image.what.clone())),
            },
        }
    }
}

/// The `Py123d(..)` dataset kind.
pub const DATASET: crate::DatasetDef =
    crate::DatasetDef { schema, open: open_checked, root: root_of, recognises, makes_root: false };

fn open_checked(checked: &ParamsValue) -> Result<crate::Opened> {
    let ds =
        Py123d::open(crate::registry::config::<Py123dConfig>(checked)?.clone()).context("opening the py123d logs")?;
    Ok(crate::Opened {
        description: format!("Py123d at {}", ds.config.root),
        warnings: ds.warnings.clone(),
        has_point_labels: ds.has_point_labels,
        dataset: Box::new(crate::surround::Surround(ds)),
    })
}

fn root_of(checked: &ParamsValue) -> Option<PathBuf> {
    checked.get::<Py123dConfig>().map(|c| PathBuf::from(&c.root))
}

/// A py123d log folder, a split folder of them, or their parent (`sync.arrow` up to two down).
fn recognises(folder: &Path) -> bool {
    find_logs(folder).is_ok_and(|l| !l.is_empty())
}

pub fn schema() -> DatasetSchema {
    DatasetSchema {
        kind: "Py123d",
        summary:
            "py123d Arrow logs (Waymo, Argoverse 2, nuPlan, KITTI-360, PandaSet, nuScenes, ... converted by py123d)",
        dims: crate::surround::DIMS.to_vec(),
        ports: crate::surround::PORTS.to_vec(),
        config: ParamsSpec::of::<Py123dConfig>(),
        path_fields: vec!["root", "sensor_root"],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(x: f64) -> Se3 {
        Se3 { rotation: glam::DQuat::IDENTITY, translation: glam::DVec3::new(x, 0.0, 0.0) }
    }

    #[test]
    fn the_ego_track_is_interpolated_over_its_own_rate_but_not_across_a_gap() {
        let x = |p: Option<Se3>| p.map(|p| p.translation.x);
        // 10 Hz: interpolated.
        let track = [(0, at(0.0)), (100_000, at(1.0))];
        assert_eq!(x(ego_at(&track, 25_000)), Some(0.25));
        // 2 s without a state: the nearest state near its ends, nothing in the middle.
        let track = [(0, at(0.0)), (2_000_000, at(40.0))];
        assert_eq!(x(ego_at(&track, 50_000)), Some(0.0));
        assert_eq!(x(ego_at(&track, 1_000_000)), None);
        assert_eq!(x(ego_at(&track, 1_950_000)), Some(40.0));
        // Past the ends: within 100 ms only.
        assert_eq!(x(ego_at(&track, 2_090_000)), Some(40.0));
        assert_eq!(x(ego_at(&track, 2_200_000)), None);
    }
}
