//! nuScenes v1.0 reader (keyframes): scenes -> keyframes (samples) -> cameras.
//!
//! Reads the tables `scene`, `sample`, `sample_data`, `ego_pose`, `calibrated_sensor` and
//! `sensor` from `<root>/<version>/`. Quaternions are `[w, x, y, z]`, timestamps microseconds.
//! Source ports: `lidar` (PointCloud, per frame, from the keyframe `.pcd.bin`), `lidar_calib`
//! and `lidar_pose` (per frame), `camera_calib` and `camera_pose` (per camera).

use crate::artifact::{Artifact, Box3D, Boxes3D, Calibration, PointCloud, Pose};
use crate::files::read_jpeg;
use crate::geometry::Se3;
use crate::sidecar::Sidecars;
use anyhow::{anyhow, bail, Context, Result};
use dist4d_graph::{DatasetSchema, DimSpec, ParamsSpec, SourcePortSpec};
use dist4d_runtime::{Dataset, Digest, DigestBuilder, FileDigests, ItemKey, ItemSpace};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The six cameras in the devkit's order.
pub const CAMERAS: [&str; 6] =
    ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"];

#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameMode {
    /// One frame per keyframe (2 Hz `sample`).
    Keyframes,
    /// One frame per LiDAR sweep (20 Hz `sample_data` chain); each camera gives its image
    /// nearest in time, and boxes are interpolated between keyframes.
    Sweeps,
}

#[derive(Serialize, Deserialize, Clone, Debug)]
#[serde(deny_unknown_fields, default)]
pub struct NuScenesConfig {
    /// The dataset root (holding `v1.0-*/`, `samples/`, `sweeps/`).
    pub root: String,
    /// Table folder: `v1.0-mini`, `v1.0-trainval` or `v1.0-test`.
    pub version: String,
    /// Camera channels, in item order.
    pub cameras: Vec<String>,
    /// LiDAR channel.
    pub lidar: String,
    /// Keyframes or Sweeps.
    pub frames: FrameMode,
    /// Folder of semantic maps (`<CAMERA>/<image stem>.png`, Cityscapes ids), relative to the
    /// root; none by default (the `semantic` port then gives empty maps).
    pub semantics: Option<String>,
}

impl Default for NuScenesConfig {
    fn default() -> Self {
        NuScenesConfig {
            root: String::new(),
            version: "v1.0-mini".into(),
            cameras: CAMERAS.iter().map(|s| s.to_string()).collect(),
            lidar: "LIDAR_TOP".into(),
            frames: FrameMode::Keyframes,
            semantics: None,
        }
    }
}

#[derive(Deserialize)]
struct SceneRow {
    token: String,
    name: String,
    first_sample_token: String,
}

#[derive(Deserialize)]
struct SampleRow {
    token: String,
    timestamp: i64,
    next: String,
}

#[derive(Deserialize)]
struct SampleDataRow {
    token: String,
    sample_token: String,
    ego_pose_token: String,
    calibrated_sensor_token: String,
    filename: String,
    is_key_frame: bool,
    #[serde(default)]
    width: u32,
    #[serde(default)]
    height: u32,
    timestamp: i64,
    #[serde(default)]
    prev: String,
    #[serde(default)]
    next: String,
}

#[derive(Deserialize)]
struct CalibratedSensorRow {
    token: String,
    sensor_token: String,
    translation: [f64; 3],
    rotation: [f64; 4],
    #[serde(default)]
    camera_intrinsic: Vec<Vec<f64>>,
}

#[derive(Deserialize)]
struct SensorRow {
    token: String,
    channel: String,
}

#[derive(Deserialize)]
struct EgoPoseRow {
    token: String,
    translation: [f64; 3],
    rotation: [f64; 4],
}

#[derive(Deserialize, Clone)]
struct AnnotationRow {
    token: String,
    sample_token: String,
    instance_token: String,
    #[serde(default)]
    attribute_tokens: Vec<String>,
    translation: [f64; 3],
    size: [f64; 3],
    rotation: [f64; 4],
    #[serde(default)]
    prev: String,
    #[serde(default)]
    next: String,
    #[serde(default)]
    num_lidar_pts: u32,
}

#[derive(Deserialize)]
struct InstanceRow {
    token: String,
    category_token: String,
}

#[derive(Deserialize)]
struct NamedRow {
    token: String,
    name: String,
}

#[derive(Deserialize)]
struct LidarsegRow {
    sample_data_token: String,
    filename: String,
}

/// One sensor reading, resolved.
#[derive(Clone, Debug)]
struct Reading {
    token: String,
    file: PathBuf,
    calib: Calibration,
    pose: Pose,
    /// nuScenes-lidarseg labels of this sweep, when the dataset has them.
    labels: Option<PathBuf>,
}

struct Frame {
    lidar: Result<Reading, String>,
    cameras: Vec<Result<Reading, String>>,
    /// The frame's time (its LiDAR timestamp) and the keyframe (sample) it is or follows.
    timestamp: i64,
    sample: Option<usize>,
    key: bool,
}

/// One box annotation with what its frame needs.
struct Annotation {
    row: AnnotationRow,
    category: String,
    attributes: Vec<String>,
}

struct Scene {
    name: String,
    frames: Vec<Frame>,
    /// Keyframe timestamps, and the annotations of each keyframe (indices into `annotations`).
    samples: Vec<(i64, Vec<usize>)>,
}

pub struct NuScenes {
    pub config: NuScenesConfig,
    scenes: Vec<Scene>,
    annotations: Vec<Annotation>,
    annotation_by_token: HashMap<String, usize>,
    sample_time: HashMap<String, i64>,
    /// What was missing but optional (printed when the dataset is opened).
    pub warnings: Vec<String>,
    sidecars: Sidecars,
}

/// Reads a table; a malformed row is reported with its index, token and the field at fault.
fn read_table<T: for<'de> Deserialize<'de>>(dir: &Path, name: &str) -> Result<Vec<T>> {
    let path = dir.join(format!("{name}.json"));
    let bytes = std::fs::read(&path).with_context(|| format!("reading nuScenes table {}", path.display()))?;
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&bytes)
        .with_context(|| format!("malformed nuScenes table {}: not a JSON list", path.display()))?;
    rows.into_iter()
        .enumerate()
        .map(|(i, row)| {
            let token = row.get("token").and_then(|t| t.as_str()).unwrap_or("?").to_string();
            serde_path_to_error::deserialize(row).map_err(|e| {
                anyhow!(
                    "malformed nuScenes table {}: row {i} (token {token}), field `{}`: {}",
                    path.display(),
                    e.path(),
                    e.inner()
                )
            })
        })
        .collect()
}

/// An optional table: missing is a warning and no rows; malformed is still an error.
fn read_optional<T: for<'de> Deserialize<'de>>(
    dir: &Path,
    name: &str,
    warnings: &mut Vec<String>,
    why: &str,
) -> Result<Vec<T>> {
    if !dir.join(format!("{name}.json")).exists() {
        warnings.push(format!("{}/{name}.json is missing: {why}", dir.display()));
        return Ok(Vec::new());
    }
    read_table(dir, name)
}

impl NuScenes {
    pub fn open(config: NuScenesConfig) -> Result<NuScenes> {
        let root = PathBuf::from(&config.root);
        let tables = root.join(&config.version);
        if !tables.is_dir() {
            bail!(
                "{} is not a nuScenes {} folder (dataset.root = {:?}, dataset.version = {:?})",
                tables.display(),
                config.version,
                config.root,
                config.version
            );
        }
        let mut warnings = Vec::new();
        let scenes: Vec<SceneRow> = read_table(&tables, "scene")?;
        let samples: Vec<SampleRow> = read_table(&tables, "sample")?;
        let sample_data: Vec<SampleDataRow> = read_table(&tables, "sample_data")?;
        let calibs: Vec<CalibratedSensorRow> = read_table(&tables, "calibrated_sensor")?;
        let sensors: Vec<SensorRow> = read_table(&tables, "sensor")?;
        let poses: Vec<EgoPoseRow> = read_table(&tables, "ego_pose")?;
        let no_boxes = "frames have no boxes";
        let anns: Vec<AnnotationRow> = read_optional(&tables, "sample_annotation", &mut warnings, no_boxes)?;
        let instances: Vec<InstanceRow> = read_optional(&tables, "instance", &mut warnings, no_boxes)?;
        let categories: Vec<NamedRow> = read_optional(&tables, "category", &mut warnings, "boxes have no category")?;
        let attributes: Vec<NamedRow> = read_optional(&tables, "attribute", &mut warnings, "boxes have no attributes")?;
        for t in ["log", "map", "visibility"] {
            if !tables.join(format!("{t}.json")).exists() {
                warnings.push(format!("{}/{t}.json is missing (not needed by dist4d)", tables.display()));
            }
        }
        // lidarseg is an add-on: absent means no labels, without a warning.
        let lidarseg: Vec<LidarsegRow> =
            if tables.join("lidarseg.json").exists() { read_table(&tables, "lidarseg")? } else { Vec::new() };
        let labels_by: HashMap<&str, PathBuf> =
            lidarseg.iter().map(|l| (l.sample_data_token.as_str(), root.join(&l.filename))).collect();

        let sample_by: HashMap<&str, &SampleRow> = samples.iter().map(|s| (s.token.as_str(), s)).collect();
        let calib_by: HashMap<&str, &CalibratedSensorRow> = calibs.iter().map(|c| (c.token.as_str(), c)).collect();
        let channel_by: HashMap<&str, &str> = sensors.iter().map(|s| (s.token.as_str(), s.channel.as_str())).collect();
        let pose_by: HashMap<&str, &EgoPoseRow> = poses.iter().map(|p| (p.token.as_str(), p)).collect();
        let sd_by: HashMap<&str, &SampleDataRow> = sample_data.iter().map(|s| (s.token.as_str(), s)).collect();
        let channel_of = |sd: &SampleDataRow| -> &str {
            calib_by
                .get(sd.calibrated_sensor_token.as_str())
                .and_then(|c| channel_by.get(c.sensor_token.as_str()))
                .copied()
                .unwrap_or("")
        };
        // Keyframe sample_data by (sample, channel).
        let mut keyframe: HashMap<(&str, &str), &SampleDataRow> = HashMap::new();
        for sd in sample_data.iter().filter(|sd| sd.is_key_frame) {
            keyframe.insert((sd.sample_token.as_str(), channel_of(sd)), sd);
        }
        let resolve = |sd: &SampleDataRow| -> Result<Reading, String> {
            let cs = calib_by.get(sd.calibrated_sensor_token.as_str()).ok_or_else(|| {
                format!(
                    "sample_data {}: field calibrated_sensor_token {} names no calibrated_sensor row",
                    sd.token, sd.calibrated_sensor_token
                )
            })?;
            let ep = pose_by.get(sd.ego_pose_token.as_str()).ok_or_else(|| {
                format!("sample_data {}: field ego_pose_token {} names no ego_pose row", sd.token, sd.ego_pose_token)
            })?;
            let intrinsics = if cs.camera_intrinsic.is_empty() {
                None
            } else {
                if cs.camera_intrinsic.len() != 3 || cs.camera_intrinsic.iter().any(|r| r.len() != 3) {
                    return Err(format!("calibrated_sensor {}: field camera_intrinsic is not 3x3", cs.token));
                }
                let k = &cs.camera_intrinsic;
                Some([[k[0][0], k[0][1], k[0][2]], [k[1][0], k[1][1], k[1][2]], [k[2][0], k[2][1], k[2][2]]])
            };
            Ok(Reading {
                token: sd.token.clone(),
                file: root.join(&sd.filename),
                calib: Calibration {
                    sensor_to_ego: Se3::from_wxyz_t(cs.rotation, cs.translation),
                    intrinsics,
                    width: sd.width,
                    height: sd.height,
                },
                pose: Pose { ego_to_world: Se3::from_wxyz_t(ep.rotation, ep.translation), timestamp_us: sd.timestamp },
                labels: labels_by.get(sd.token.as_str()).cloned(),
            })
        };
        let key_reading = |sample: &str, channel: &str| -> Result<Reading, String> {
            let sd = keyframe
                .get(&(sample, channel))
                .ok_or_else(|| format!("sample {sample} has no keyframe sample_data for channel {channel}"))?;
            resolve(sd)
        };
        // A channel's whole sample_data chain through a keyframe (prev to the start, next to the end).
        fn chain<'a>(
            start: &'a SampleDataRow,
            sd_by: &HashMap<&str, &'a SampleDataRow>,
            tables: &Path,
        ) -> Result<Vec<&'a SampleDataRow>> {
            let mut first = start;
            let mut guard = 0;
            while !first.prev.is_empty() {
                first = sd_by.get(first.prev.as_str()).ok_or_else(|| {
                    anyhow!(
                        "{}/sample_data.json: sample_data {}: field prev {} names no row",
                        tables.display(),
                        first.token,
                        first.prev
                    )
                })?;
                guard += 1;
                anyhow::ensure!(guard < 1_000_000, "sample_data {}: the prev chain does not end", start.token);
            }
            let mut out = vec![first];
            while !out.last().map_or(true, |s| s.next.is_empty()) {
                let cur = out[out.len() - 1];
                out.push(sd_by.get(cur.next.as_str()).ok_or_else(|| {
                    anyhow!(
                        "{}/sample_data.json: sample_data {}: field next {} names no row",
                        tables.display(),
                        cur.token,
                        cur.next
                    )
                })?);
                anyhow::ensure!(out.len() < 1_000_000, "sample_data {}: the next chain does not end", start.token);
            }
            Ok(out)
        }

        // Annotations, with names resolved.
        let cat_name: HashMap<&str, &str> = categories.iter().map(|c| (c.token.as_str(), c.name.as_str())).collect();
        let attr_name: HashMap<&str, &str> = attributes.iter().map(|c| (c.token.as_str(), c.name.as_str())).collect();
        let inst_cat: HashMap<&str, &str> = instances
            .iter()
            .map(|i| (i.token.as_str(), cat_name.get(i.category_token.as_str()).copied().unwrap_or("")))
            .collect();
        let annotations: Vec<Annotation> = anns
            .into_iter()
            .map(|row| Annotation {
                category: inst_cat.get(row.instance_token.as_str()).copied().unwrap_or("").to_string(),
                attributes: row
                    .attribute_tokens
                    .iter()
                    .filter_map(|t| attr_name.get(t.as_str()).map(|s| s.to_string()))
                    .collect(),
                row,
            })
            .collect();
        let mut anns_of_sample: HashMap<&str, Vec<usize>> = HashMap::new();
        for (i, a) in annotations.iter().enumerate() {
            anns_of_sample.entry(a.row.sample_token.as_str()).or_default().push(i);
        }

        let mut out = Vec::new();
        for scene in &scenes {
            let mut keys: Vec<&SampleRow> = Vec::new();
            let mut token = scene.first_sample_token.as_str();
            while !token.is_empty() {
                let sample = sample_by.get(token).ok_or_else(|| {
                    anyhow!(
                        "{}/sample.json: no sample with token {token} (named by scene {} or a sample's `next`)",
                        tables.display(),
                        scene.token
                    )
                })?;
                keys.push(sample);
                token = sample.next.as_str();
                if keys.len() > 100_000 {
                    bail!("scene {}: the sample `next` chain does not end", scene.name);
                }
            }
            let samples_of_scene: Vec<(i64, Vec<usize>)> = keys
                .iter()
                .map(|k| (k.timestamp, anns_of_sample.get(k.token.as_str()).cloned().unwrap_or_default()))
                .collect();
            let frames = match config.frames {
                FrameMode::Keyframes => keys
                    .iter()
                    .enumerate()
                    .map(|(i, k)| Frame {
                        lidar: key_reading(&k.token, &config.lidar),
                        cameras: config.cameras.iter().map(|c| key_reading(&k.token, c)).collect(),
                        timestamp: k.timestamp,
                        sample: Some(i),
                        key: true,
                    })
                    .collect(),
                FrameMode::Sweeps => {
                    let Some(first_key) =
                        keys.first().and_then(|k| keyframe.get(&(k.token.as_str(), config.lidar.as_str())))
                    else {
                        bail!("scene {}: its first sample has no {} keyframe", scene.name, config.lidar);
                    };
                    let lidar_chain = chain(first_key, &sd_by, &tables)?;
                    let camera_chains: Vec<Option<Vec<&SampleDataRow>>> = config
                        .cameras
                        .iter()
                        .map(|c| {
                            keys.first()
                                .and_then(|k| keyframe.get(&(k.token.as_str(), c.as_str())))
                                .map(|sd| chain(sd, &sd_by, &tables))
                                .transpose()
                        })
                        .collect::<Result<_>>()?;
                    lidar_chain
                        .iter()
                        .map(|sd| {
                            let t = sd.timestamp;
                            let sample = keys.iter().rposition(|k| k.timestamp <= t);
                            Frame {
                                lidar: resolve(sd),
                                cameras: camera_chains
                                    .iter()
                                    .zip(&config.cameras)
                                    .map(|(ch, name)| {
                                        let ch = ch
                                            .as_ref()
                                            .ok_or_else(|| format!("scene {}: no {name} images", scene.name))?;
                                        let nearest =
                                            ch.iter().min_by_key(|c| (c.timestamp - t).abs()).ok_or("empty chain")?;
                                        resolve(nearest)
                                    })
                                    .collect(),
                                timestamp: t,
                                sample,
                                key: sd.is_key_frame,
                            }
                        })
                        .collect()
                }
            };
            out.push(Scene { name: scene.name.clone(), frames, samples: samples_of_scene });
        }
        let annotation_by_token = annotations.iter().enumerate().map(|(i, a)| (a.row.token.clone(), i)).collect();
        let sample_time = samples.iter().map(|s| (s.token.clone(), s.timestamp)).collect();
        let sidecars = Sidecars::new(&root, config.semantics.as_deref());
        Ok(NuScenes { config, scenes: out, annotations, annotation_by_token, sample_time, warnings, sidecars })
    }

    fn scene_frame(&self, item: &ItemKey) -> Result<(&Scene, &Frame)> {
        let scene = self.scenes.get(item.idx[0] as usize).ok_or_else(|| anyhow!("no scene {:?}", item))?;
        let frame = scene.frames.get(item.idx[1] as usize).ok_or_else(|| anyhow!("no frame {:?}", item))?;
        Ok((scene, frame))
    }

    fn reading(&self, port: &str, item: &ItemKey) -> Result<&Reading> {
        let (_, frame) = self.scene_frame(item)?;
        let r = match port {
            "lidar" | "lidar_calib" | "lidar_pose" => &frame.lidar,
            _ => frame.cameras.get(item.idx[2] as usize).ok_or_else(|| anyhow!("no camera {:?}", item))?,
        };
        r.as_ref().map_err(|e| anyhow!("{e}"))
    }

    /// The devkit's `box_velocity`: centre difference of the neighbouring annotations, NaN when
    /// the track has one annotation or the neighbours are too far apart in time.
    fn velocity(&self, a: &AnnotationRow) -> [f64; 3] {
        let get = |t: &str| self.annotation_by_token.get(t).map(|&i| &self.annotations[i].row);
        let (prev, next) = (get(&a.prev), get(&a.next));
        if prev.is_none() && next.is_none() {
            return [f64::NAN; 3];
        }
        let (first, last) = (prev.unwrap_or(a), next.unwrap_or(a));
        let time = |r: &AnnotationRow| self.sample_time.get(&r.sample_token).copied().unwrap_or(0);
        let dt = (time(last) - time(first)) as f64 * 1e-6;
        let max_dt = if prev.is_some() && next.is_some() { 3.0 } else { 1.5 };
        if dt <= 0.0 || dt > max_dt {
            return [f64::NAN; 3];
        }
        [0, 1, 2].map(|i| (last.translation[i] - first.translation[i]) / dt)
    }

    fn box_of(&self, a: &Annotation) -> Box3D {
        Box3D {
            center: a.row.translation,
            size: a.row.size,
            rotation: a.row.rotation,
            velocity: self.velocity(&a.row),
            instance: a.row.instance_token.clone(),
            category: a.category.clone(),
            attributes: a.attributes.clone(),
            num_lidar_pts: a.row.num_lidar_pts,
            interpolated: false,
        }
    }

    /// Boxes at the frame's time: the keyframe's own annotations, or for a sweep the tracks
    /// annotated on both neighbouring keyframes, interpolated (linear centre and velocity,
    /// slerp rotation).
    fn boxes(&self, item: &ItemKey) -> Result<Boxes3D> {
        let (scene, frame) = self.scene_frame(item)?;
        let t = frame.timestamp;
        let Some(k0) = frame.sample else { return Ok(Boxes3D { timestamp_us: t, boxes: Vec::new() }) };
        let (t0, anns0) = &scene.samples[k0];
        let own: Vec<Box3D> = anns0.iter().map(|&i| self.box_of(&self.annotations[i])).collect();
        if frame.key || *t0 == t {
            return Ok(Boxes3D { timestamp_us: t, boxes: own });
        }
        let Some((t1, anns1)) = scene.samples.get(k0 + 1) else {
            return Ok(Boxes3D { timestamp_us: t, boxes: Vec::new() });
        };
        let w = (t - t0) as f64 / (t1 - t0) as f64;
        let later: HashMap<&str, Box3D> = anns1
            .iter()
            .map(|&i| (self.annotations[i].row.instance_token.as_str(), self.box_of(&self.annotations[i])))
            .collect();
        let boxes = own
            .into_iter()
            .filter_map(|a| {
                let b = later.get(a.instance.as_str())?;
                let lerp = |x: [f64; 3], y: [f64; 3]| [0, 1, 2].map(|i| x[i] + (y[i] - x[i]) * w);
                let q0 = glam::DQuat::from_xyzw(a.rotation[1], a.rotation[2], a.rotation[3], a.rotation[0]).normalize();
                let q1 = glam::DQuat::from_xyzw(b.rotation[1], b.rotation[2], b.rotation[3], b.rotation[0]).normalize();
                let q = q0.slerp(q1, w);
                Some(Box3D {
                    center: lerp(a.center, b.center),
                    size: lerp(a.size, b.size),
                    rotation: [q.w, q.x, q.y, q.z],
                    velocity: lerp(a.velocity, b.velocity),
                    num_lidar_pts: 0,
                    interpolated: true,
                    ..a
                })
            })
            .collect();
        Ok(Boxes3D { timestamp_us: t, boxes })
    }
}

/// Reads a nuScenes `.pcd.bin`: float32 x, y, z, intensity, ring per point.
pub fn read_pcd_bin(path: &Path) -> Result<PointCloud> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    if bytes.len() % 20 != 0 {
        bail!("{} is truncated: {} bytes is not a whole number of 20-byte points", path.display(), bytes.len());
    }
    let f = |c: &[u8]| f32::from_le_bytes(c.try_into().unwrap());
    Ok(PointCloud {
        points: bytes.chunks_exact(20).map(|p| [f(&p[0..4]), f(&p[4..8]), f(&p[8..12]), f(&p[12..16])]).collect(),
        labels: Vec::new(),
    })
}

impl ItemSpace for NuScenes {
    fn count(&self, prefix: &ItemKey) -> u32 {
        surround_count(
            prefix,
            self.scenes.len(),
            |s| self.scenes.get(s).map(|s| s.frames.len()),
            self.config.cameras.len(),
        )
    }

    fn label(&self, item: &ItemKey) -> String {
        surround_label(item, |s| self.scenes.get(s).map(|s| s.name.clone()), &self.config.cameras)
    }
}

impl Dataset for NuScenes {
    fn source_digest(&self, port: &str, item: &ItemKey, files: &dyn FileDigests) -> Result<Option<Digest>> {
        let file_digest = |path: &Path, token: &str| -> Result<Option<Digest>> {
            files.file_digest(path).with_context(|| format!("sample_data {token}: {}", path.display()))
        };
        Ok(match port {
            "lidar" => {
                let r = self.reading(port, item)?;
                let Some(points) = file_digest(&r.file, &r.token)? else { return Ok(None) };
                let mut b = DigestBuilder::new("nuscenes.lidar");
                b.digest(&points);
                if let Some(labels) = &r.labels {
                    let Some(l) = file_digest(labels, &r.token)? else { return Ok(None) };
                    b.digest(&l);
                }
                Some(b.finish())
            }
            "image" => {
                let r = self.reading(port, item)?;
                file_digest(&r.file, &r.token)?
            }
            "gt_depth" | "semantic" => {
                let r = self.reading("image", item)?;
                let camera = &self.config.cameras[item.idx[2] as usize];
                sidecar_digest(&self.sidecars, port, camera, &r.file, files)?
            }
            _ => Some(Digest::of(&self.load_source(port, item)?)),
        })
    }

    fn load_source(&self, port: &str, item: &ItemKey) -> Result<Vec<u8>> {
        if port == "boxes" {
            return Ok(self.boxes(item)?.encode());
        }
        let r = self.reading(port, item)?;
        Ok(match port {
            "lidar" => {
                let mut pc = read_pcd_bin(&r.file).with_context(|| format!("sample_data {}", r.token))?;
                if let Some(path) = &r.labels {
                    let labels = std::fs::read(path).with_context(|| {
                        format!("reading the lidarseg labels of sample_data {}: {}", r.token, path.display())
                    })?;
                    if labels.len() != pc.points.len() {
                        bail!(
                            "{} has {} labels but {} has {} points",
                            path.display(),
                            labels.len(),
                            r.file.display(),
                            pc.points.len()
                        );
                    }
                    pc.labels = labels;
                }
                pc.encode()
            }
            "image" => read_jpeg(&r.file).with_context(|| format!("sample_data {}", r.token))?.encode(),
            "gt_depth" => self.sidecars.gt_depth(&self.config.cameras[item.idx[2] as usize], &r.file)?.encode(),
            "semantic" => self.sidecars.semantic(&self.config.cameras[item.idx[2] as usize], &r.file)?.encode(),
            "lidar_calib" | "camera_calib" => r.calib.encode(),
            "lidar_pose" | "camera_pose" => r.pose.encode(),
            other => bail!("nuScenes has no source port `{other}`"),
        })
    }
}

/// Digest of a sidecar port: its file's content digest, or a fixed "none" when there is no file.
pub(crate) fn sidecar_digest(
    sidecars: &Sidecars,
    port: &str,
    camera: &str,
    image: &Path,
    files: &dyn FileDigests,
) -> Result<Option<Digest>> {
    let mut b = DigestBuilder::new(port);
    match sidecars.path(port, camera, image) {
        None => {
            b.str("none");
        }
        Some(p) => {
            let Some(d) = files.file_digest(&p).with_context(|| format!("{port} of {}", image.display()))? else {
                return Ok(None);
            };
            b.digest(&d);
        }
    }
    Ok(Some(b.finish()))
}

/// The scene / frame / camera item tree both readers share: `frames(i)` is scene i's frame count,
/// `scene_name(i)` its name.
pub(crate) fn surround_count(
    prefix: &ItemKey,
    scenes: usize,
    frames: impl Fn(usize) -> Option<usize>,
    cameras: usize,
) -> u32 {
    match prefix.depth {
        0 => scenes as u32,
        1 => frames(prefix.idx[0] as usize).unwrap_or(0) as u32,
        2 => cameras as u32,
        _ => 0,
    }
}

/// Labels of the shared item tree: scene name, zero-padded frame index, camera channel.
pub(crate) fn surround_label(
    item: &ItemKey,
    scene_name: impl Fn(usize) -> Option<String>,
    cameras: &[String],
) -> String {
    let i = item.idx[item.depth as usize - 1] as usize;
    match item.depth {
        1 => scene_name(i).unwrap_or_else(|| format!("scene{i}")),
        2 => format!("{i:03}"),
        _ => cameras.get(i).cloned().unwrap_or_else(|| format!("camera{i}")),
    }
}

/// Camera and LiDAR names become folder and file names of exports (and the version a folder
/// under the root), so each must be one safe path component; the cameras, at least one, once each.
impl dist4d_graph::Validate for NuScenesConfig {
    fn validate(&self) -> Vec<dist4d_graph::ParamProblem> {
        dist4d_graph::ParamChecks::new()
            .path_names("cameras", &self.cameras)
            .path_name("lidar", &self.lidar)
            .path_name("version", &self.version)
            .done()
    }
}

pub struct NuScenesSchema {
    config: ParamsSpec,
}

impl Default for NuScenesSchema {
    fn default() -> Self {
        NuScenesSchema { config: ParamsSpec::of::<NuScenesConfig>() }
    }
}

pub(crate) const DIMS: [DimSpec; 3] = [
    DimSpec { name: "scene", ordered: false },
    DimSpec { name: "frame", ordered: true },
    DimSpec { name: "camera", ordered: false },
];
pub(crate) const PORTS: [SourcePortSpec; 9] = [
    SourcePortSpec {
        name: "lidar",
        ty: "PointCloud",
        grain: "frame",
        doc: "LiDAR sweep in the sensor frame, with nuScenes-lidarseg labels when present",
    },
    SourcePortSpec {
        name: "boxes",
        ty: "Boxes3D",
        grain: "frame",
        doc: "annotated boxes at the frame's time (world frame; interpolated for sweeps)",
    },
    SourcePortSpec { name: "image", ty: "Image", grain: "camera", doc: "the camera image (RGB8)" },
    SourcePortSpec { name: "lidar_calib", ty: "Calibration", grain: "frame", doc: "LiDAR mounting (sensor -> ego)" },
    SourcePortSpec { name: "lidar_pose", ty: "Pose", grain: "frame", doc: "ego pose at the LiDAR timestamp" },
    SourcePortSpec {
        name: "camera_calib",
        ty: "Calibration",
        grain: "camera",
        doc: "camera mounting, intrinsics and image size",
    },
    SourcePortSpec { name: "camera_pose", ty: "Pose", grain: "camera", doc: "ego pose at the camera timestamp" },
    SourcePortSpec {
        name: "gt_depth",
        ty: "DepthMap",
        grain: "camera",
        doc: "dense ground-truth depth (groundtruth/depth/, synthetic data); empty when the dataset has none",
    },
    SourcePortSpec {
        name: "semantic",
        ty: "Segmentation",
        grain: "camera",
        doc: "Cityscapes-id segmentation from the `semantics` folder; empty when none is configured",
    },
];

impl DatasetSchema for NuScenesSchema {
    fn kind(&self) -> &'static str {
        "NuScenes"
    }
    fn summary(&self) -> &'static str {
        "nuScenes v1.0 tables and files: scenes, keyframes or sweeps, six cameras, boxes, lidarseg"
    }
    fn dims(&self) -> &[DimSpec] {
        &DIMS
    }
    fn ports(&self) -> &[SourcePortSpec] {
        &PORTS
    }
    fn config(&self) -> &ParamsSpec {
        &self.config
    }
    fn path_fields(&self) -> &[&'static str] {
        &["root"]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub fn shared_nuscenes() -> Option<PathBuf> {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/nuscenes-scene0061-kf0");
        if p.is_dir() {
            Some(p)
        } else {
            eprintln!("SKIPPED: shared nuScenes data not found at {}", p.display());
            None
        }
    }

    #[test]
    fn reads_the_shared_keyframe() {
        let Some(root) = shared_nuscenes() else { return };
        let ds = NuScenes::open(NuScenesConfig { root: root.display().to_string(), ..Default::default() }).unwrap();
        assert_eq!(ds.count(&ItemKey::new(&[])), 1);
        assert_eq!(ds.count(&ItemKey::new(&[0])), 1);
        assert_eq!(ds.label(&ItemKey::new(&[0])), "scene-0061");
        assert_eq!(ds.path(&ItemKey::new(&[0, 0, 0])), "scene-0061/000/CAM_FRONT");
        let pc = PointCloud::decode(&ds.load_source("lidar", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert_eq!(pc.points.len(), 34_688);
        let cal = Calibration::decode(&ds.load_source("camera_calib", &ItemKey::new(&[0, 0, 0])).unwrap()).unwrap();
        assert_eq!((cal.width, cal.height), (1600, 900));
        let boxes = Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert_eq!(boxes.boxes.len(), 69, "the shared keyframe's 69 annotated boxes");
        // One keyframe: single-annotation tracks have unknown velocity, like the devkit's NaN.
        assert!(boxes.boxes.iter().all(|b| b.velocity[0].is_nan()));
    }

    /// A small synthetic nuScenes dataset (3 keyframes, LiDAR sweeps, tiny images).
    fn synthetic() -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("synth");
        let config = crate::synth::SynthConfig { keyframes: 3, width: 160, height: 90, ..Default::default() };
        crate::synth::write_dataset(&config, &root, &|_| {}).unwrap();
        (dir, root)
    }

    fn open(root: &Path, frames: FrameMode) -> Result<NuScenes> {
        NuScenes::open(NuScenesConfig { root: root.display().to_string(), frames, ..Default::default() })
    }

    #[test]
    fn keyframes_carry_boxes_with_devkit_velocities_images_and_lidarseg() {
        let (_tmp, root) = synthetic();
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        assert!(ds.warnings.is_empty(), "{:?}", ds.warnings);
        assert_eq!(ds.count(&ItemKey::new(&[0])), 3);
        let boxes = Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, 1])).unwrap()).unwrap();
        assert!(!boxes.boxes.is_empty());
        let moving: Vec<&Box3D> =
            boxes.boxes.iter().filter(|b| b.attributes.contains(&"vehicle.moving".to_string())).collect();
        assert!(!moving.is_empty());
        for b in &moving {
            let v = b.velocity[0].hypot(b.velocity[1]);
            assert!((6.0..15.5).contains(&v), "{v} m/s");
            assert!(b.is_moving(1.0));
        }
        assert!(boxes.boxes.iter().any(|b| b.category == "vehicle.car" && !b.is_moving(0.5)));
        let pc = PointCloud::decode(&ds.load_source("lidar", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert_eq!(pc.labels.len(), pc.points.len());
        assert!(pc.labels.contains(&24) && pc.labels.contains(&17));
        let img = crate::artifact::Image::decode(&ds.load_source("image", &ItemKey::new(&[0, 0, 3])).unwrap()).unwrap();
        assert_eq!((img.width, img.height, img.rgb.len()), (160, 90, 160 * 90 * 3));
    }

    #[test]
    fn sweeps_are_frames_with_interpolated_boxes_and_the_nearest_images() {
        let (_tmp, root) = synthetic();
        let ds = open(&root, FrameMode::Sweeps).unwrap();
        // 3 keyframes 0.5 s apart at 20 Hz: 21 sweeps.
        assert_eq!(ds.count(&ItemKey::new(&[0])), 21);
        let at = |f: u32| Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, f])).unwrap()).unwrap();
        let (k0, mid, k1) = (at(0), at(5), at(10));
        assert!(!k0.boxes[0].interpolated && mid.boxes.iter().all(|b| b.interpolated));
        assert_eq!(mid.timestamp_us - k0.timestamp_us, 250_000);
        // Halfway between two keyframes, a box is halfway between its two annotations.
        let b = &mid.boxes[0];
        let (a0, a1) = (
            k0.boxes.iter().find(|x| x.instance == b.instance).unwrap(),
            k1.boxes.iter().find(|x| x.instance == b.instance).unwrap(),
        );
        for i in 0..3 {
            assert!((b.center[i] - (a0.center[i] + a1.center[i]) / 2.0).abs() < 1e-9);
        }
        // Sweeps have no lidarseg labels; keyframes do.
        let pc = |f: u32| PointCloud::decode(&ds.load_source("lidar", &ItemKey::new(&[0, f])).unwrap()).unwrap();
        assert!(pc(5).labels.is_empty() && !pc(10).labels.is_empty());
        // Each camera gives its image nearest in time.
        let pose = Pose::decode(&ds.load_source("camera_pose", &ItemKey::new(&[0, 5, 0])).unwrap()).unwrap();
        let lidar = Pose::decode(&ds.load_source("lidar_pose", &ItemKey::new(&[0, 5])).unwrap()).unwrap();
        assert!((pose.timestamp_us - lidar.timestamp_us).abs() <= 250_000);
    }

    #[test]
    fn malformed_rows_name_file_token_and_field_and_optional_tables_only_warn() {
        let (_tmp, root) = synthetic();
        let table = root.join("v1.0-mini/ego_pose.json");
        let text = std::fs::read_to_string(&table).unwrap();
        let mut rows: Vec<serde_json::Value> = serde_json::from_str(&text).unwrap();
        rows[2]["translation"][1] = serde_json::json!("north");
        let token = rows[2]["token"].as_str().unwrap().to_string();
        std::fs::write(&table, serde_json::to_vec(&rows).unwrap()).unwrap();
        let err = format!("{:#}", open(&root, FrameMode::Keyframes).err().unwrap());
        assert!(err.contains("ego_pose.json") && err.contains(&token) && err.contains("translation[1]"), "{err}");
        std::fs::write(&table, text).unwrap();

        for t in ["sample_annotation", "instance", "log", "map"] {
            std::fs::remove_file(root.join(format!("v1.0-mini/{t}.json"))).unwrap();
        }
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        assert_eq!(ds.warnings.len(), 4, "{:?}", ds.warnings);
        assert!(ds.warnings[0].contains("sample_annotation.json is missing"));
        let boxes = Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert!(boxes.boxes.is_empty());
        // An unreadable JPEG fails that camera's image only.
        let cam = ds.reading("image", &ItemKey::new(&[0, 1, 2])).unwrap().file.clone();
        std::fs::write(&cam, b"not a jpeg").unwrap();
        let err = format!("{:#}", ds.load_source("image", &ItemKey::new(&[0, 1, 2])).unwrap_err());
        assert!(err.contains("not a readable image") && err.contains(&cam.display().to_string()), "{err}");
        assert!(ds.load_source("image", &ItemKey::new(&[0, 1, 3])).is_ok());
    }

    #[test]
    fn missing_tables_and_truncated_sweeps_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("v1.0-mini")).unwrap();
        let err = NuScenes::open(NuScenesConfig { root: dir.path().display().to_string(), ..Default::default() })
            .err()
            .unwrap();
        assert!(format!("{err:#}").contains("v1.0-mini/scene.json"), "{err:#}");
        let f = dir.path().join("x.pcd.bin");
        std::fs::write(&f, [0u8; 30]).unwrap();
        let err = read_pcd_bin(&f).unwrap_err().to_string();
        assert!(err.contains("truncated"), "{err}");
    }
}
