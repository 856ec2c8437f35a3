//! nuScenes v1.0 reader (keyframes): scenes -> keyframes (samples) -> cameras.
//!
//! Reads the tables `scene`, `sample`, `sample_data`, `ego_pose`, `calibrated_sensor` and
//! `sensor` from `<root>/<version>/`. Quaternions are `[w, x, y, z]`, timestamps microseconds.
//! Source ports: `lidar` (PointCloud, per frame, from the keyframe `.pcd.bin`), `lidar_calib`
//! and `lidar_pose` (per frame), `camera_calib` and `camera_pose` (per camera).

use crate::artifact::{Artifact, Calibration, PointCloud, Pose};
use crate::geometry::Se3;
use anyhow::{anyhow, bail, Context, Result};
use dist4d_graph::{DatasetSchema, DimSpec, ParamsSpec, SourcePortSpec};
use dist4d_runtime::{Dataset, Digest, FileDigests, ItemKey, ItemSpace};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The six cameras in the devkit's order.
pub const CAMERAS: [&str; 6] =
    ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"];

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
}

impl Default for NuScenesConfig {
    fn default() -> Self {
        NuScenesConfig {
            root: String::new(),
            version: "v1.0-mini".into(),
            cameras: CAMERAS.iter().map(|s| s.to_string()).collect(),
            lidar: "LIDAR_TOP".into(),
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

/// One sensor reading of a keyframe, resolved.
#[derive(Clone, Debug)]
struct Reading {
    token: String,
    file: PathBuf,
    calib: Calibration,
    pose: Pose,
}

struct Frame {
    lidar: Result<Reading, String>,
    cameras: Vec<Result<Reading, String>>,
}

struct Scene {
    name: String,
    frames: Vec<Frame>,
}

pub struct NuScenes {
    pub config: NuScenesConfig,
    scenes: Vec<Scene>,
}

fn read_table<T: for<'de> Deserialize<'de>>(dir: &Path, name: &str) -> Result<Vec<T>> {
    let path = dir.join(format!("{name}.json"));
    let bytes = std::fs::read(&path).with_context(|| format!("reading nuScenes table {}", path.display()))?;
    serde_json::from_slice(&bytes).with_context(|| format!("malformed nuScenes table {}", path.display()))
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
        let scenes: Vec<SceneRow> = read_table(&tables, "scene")?;
        let samples: Vec<SampleRow> = read_table(&tables, "sample")?;
        let sample_data: Vec<SampleDataRow> = read_table(&tables, "sample_data")?;
        let calibs: Vec<CalibratedSensorRow> = read_table(&tables, "calibrated_sensor")?;
        let sensors: Vec<SensorRow> = read_table(&tables, "sensor")?;
        let poses: Vec<EgoPoseRow> = read_table(&tables, "ego_pose")?;

        let sample_by: HashMap<&str, &SampleRow> = samples.iter().map(|s| (s.token.as_str(), s)).collect();
        let calib_by: HashMap<&str, &CalibratedSensorRow> = calibs.iter().map(|c| (c.token.as_str(), c)).collect();
        let channel_by: HashMap<&str, &str> = sensors.iter().map(|s| (s.token.as_str(), s.channel.as_str())).collect();
        let pose_by: HashMap<&str, &EgoPoseRow> = poses.iter().map(|p| (p.token.as_str(), p)).collect();
        // Keyframe sample_data by (sample, channel).
        let mut keyframe: HashMap<(&str, &str), &SampleDataRow> = HashMap::new();
        for sd in sample_data.iter().filter(|sd| sd.is_key_frame) {
            let channel = calib_by
                .get(sd.calibrated_sensor_token.as_str())
                .and_then(|c| channel_by.get(c.sensor_token.as_str()))
                .copied()
                .unwrap_or("");
            keyframe.insert((sd.sample_token.as_str(), channel), sd);
        }
        let resolve = |sample: &str, channel: &str| -> Result<Reading, String> {
            let sd = keyframe
                .get(&(sample, channel))
                .ok_or_else(|| format!("sample {sample} has no keyframe sample_data for channel {channel}"))?;
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
            })
        };
        let mut out = Vec::new();
        for scene in &scenes {
            let mut frames = Vec::new();
            let mut token = scene.first_sample_token.as_str();
            while !token.is_empty() {
                let sample = sample_by.get(token).ok_or_else(|| {
                    anyhow!(
                        "{}/sample.json: no sample with token {token} (named by scene {} or a sample's `next`)",
                        tables.display(),
                        scene.token
                    )
                })?;
                frames.push(Frame {
                    lidar: resolve(token, &config.lidar),
                    cameras: config.cameras.iter().map(|c| resolve(token, c)).collect(),
                });
                token = sample.next.as_str();
                if frames.len() > 100_000 {
                    bail!("scene {}: the sample `next` chain does not end", scene.name);
                }
            }
            out.push(Scene { name: scene.name.clone(), frames });
        }
        Ok(NuScenes { config, scenes: out })
    }

    fn frame(&self, item: &ItemKey) -> Result<&Frame> {
        self.scenes
            .get(item.idx[0] as usize)
            .and_then(|s| s.frames.get(item.idx[1] as usize))
            .ok_or_else(|| anyhow!("no frame {:?}", item))
    }

    fn reading(&self, port: &str, item: &ItemKey) -> Result<&Reading> {
        let frame = self.frame(item)?;
        let r = match port {
            "lidar" | "lidar_calib" | "lidar_pose" => &frame.lidar,
            _ => frame.cameras.get(item.idx[2] as usize).ok_or_else(|| anyhow!("no camera {:?}", item))?,
        };
        r.as_ref().map_err(|e| anyhow!("{e}"))
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
    })
}

impl ItemSpace for NuScenes {
    fn count(&self, prefix: &ItemKey) -> u32 {
        match prefix.depth {
            0 => self.scenes.len() as u32,
            1 => self.scenes.get(prefix.idx[0] as usize).map_or(0, |s| s.frames.len() as u32),
            2 => self.config.cameras.len() as u32,
            _ => 0,
        }
    }

    fn label(&self, item: &ItemKey) -> String {
        let i = item.idx[item.depth as usize - 1] as usize;
        match item.depth {
            1 => self.scenes.get(i).map_or_else(|| format!("scene{i}"), |s| s.name.clone()),
            2 => format!("{i:03}"),
            _ => self.config.cameras.get(i).cloned().unwrap_or_else(|| format!("camera{i}")),
        }
    }
}

impl Dataset for NuScenes {
    fn source_digest(&self, port: &str, item: &ItemKey, files: &dyn FileDigests) -> Result<Option<Digest>> {
        let r = self.reading(port, item)?;
        Ok(match port {
            "lidar" => files.file_digest(&r.file).with_context(|| format!("sample_data {}", r.token))?,
            _ => Some(Digest::of(&self.load_source(port, item)?)),
        })
    }

    fn load_source(&self, port: &str, item: &ItemKey) -> Result<Vec<u8>> {
        let r = self.reading(port, item)?;
        Ok(match port {
            "lidar" => read_pcd_bin(&r.file).with_context(|| format!("sample_data {}", r.token))?.encode(),
            "lidar_calib" | "camera_calib" => r.calib.encode(),
            "lidar_pose" | "camera_pose" => r.pose.encode(),
            other => bail!("nuScenes has no source port `{other}`"),
        })
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

const DIMS: [DimSpec; 3] = [
    DimSpec { name: "scene", ordered: false },
    DimSpec { name: "frame", ordered: true },
    DimSpec { name: "camera", ordered: false },
];
const PORTS: [SourcePortSpec; 5] = [
    SourcePortSpec { name: "lidar", ty: "PointCloud", grain: "frame", doc: "keyframe LiDAR sweep in the sensor frame" },
    SourcePortSpec { name: "lidar_calib", ty: "Calibration", grain: "frame", doc: "LiDAR mounting (sensor -> ego)" },
    SourcePortSpec { name: "lidar_pose", ty: "Pose", grain: "frame", doc: "ego pose at the LiDAR timestamp" },
    SourcePortSpec {
        name: "camera_calib",
        ty: "Calibration",
        grain: "camera",
        doc: "camera mounting, intrinsics and image size",
    },
    SourcePortSpec { name: "camera_pose", ty: "Pose", grain: "camera", doc: "ego pose at the camera timestamp" },
];

impl DatasetSchema for NuScenesSchema {
    fn kind(&self) -> &'static str {
        "NuScenes"
    }
    fn summary(&self) -> &'static str {
        "nuScenes v1.0 tables and files: scenes, keyframes, six cameras"
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
