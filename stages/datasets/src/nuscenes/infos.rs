//! The info pickles that nuScenes-based generators' training code opens (MagicDrive,
//! MagicDriveDiT, UniScene, DiST-4D): `<prefix>_infos_{train,val}.pkl`, and at 12 Hz
//! `nuscenes_interp_12Hz_infos_{train,val}_with_bid.pkl`.
//!
//! Followed: MagicDrive-V2 (flymin/MagicDrive-V2 @ 4ed72c6) `tools/prepare_data/data_converter/
//! nuscenes_converter.py` (`create_nuscenes_infos`, `_fill_trainval_infos`,
//! `_sample_data_transform`, `obtain_sensor2top`, `get_ego_velocity`, `get_box_ids`) and the
//! nuscenes-devkit 1.2.0 functions it calls (`get_sample_data`, `box_velocity`, pyquaternion's
//! `yaw_pitch_roll`, `angle`, `axis`). One format for every version, as that converter writes it:
//! `dict(infos, metadata=dict(version), scene_tokens)` (no `scene_tokens` for a test split), each
//! info with the fields, key order, dtypes and shapes listed in docs/interop.md. Written from the
//! tables alone, by the table reader of [`super`], without the devkit.
//!
//! Where we differ, on purpose: quaternions and translations are written as Python floats (the
//! JSON may hold an integer `0`; equal in Python); `camera_intrinsics` is always float64; a
//! scene's samples that break their `next` chain, a sample without a LiDAR or camera keyframe and
//! a dangling token are errors naming the file, row and field (the converter asserts or raises a
//! KeyError); a scene in no official split goes to the version's first split (train), where the
//! converter would put it in val: that is the synthetic world's rule (docs/interop.md).

use super::*;
use dist4d_types::pickle::{encode_into, Array, DictStream, Value};
use glam::{DMat3, DQuat, DVec3};
use rayon::prelude::*;
use serde_json::Number;
use std::collections::HashSet;

/// The converter's `camera_types`: the order of `cams`, which the loaders' image lists keep.
pub const INFO_CAMERAS: [&str; 6] =
    ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"];
const LIDAR: &str = "LIDAR_TOP";
/// The converter's `frames_t`: a scene's token list goes into `scene_tokens` only when longer.
const FRAMES_T: usize = 6;
/// MagicDrive's `NuScenesDataset.NameMapping`; other category names are kept as they are.
const NAME_MAPPING: [(&str, &str); 14] = [
    ("movable_object.barrier", "barrier"),
    ("vehicle.bicycle", "bicycle"),
    ("vehicle.bus.bendy", "bus"),
    ("vehicle.bus.rigid", "bus"),
    ("vehicle.car", "car"),
    ("vehicle.construction", "construction_vehicle"),
    ("vehicle.motorcycle", "motorcycle"),
    ("human.pedestrian.adult", "pedestrian"),
    ("human.pedestrian.child", "pedestrian"),
    ("human.pedestrian.construction_worker", "pedestrian"),
    ("human.pedestrian.police_officer", "pedestrian"),
    ("movable_object.trafficcone", "traffic_cone"),
    ("vehicle.trailer", "trailer"),
    ("vehicle.truck", "truck"),
];
/// Samples encoded in parallel before their bytes are written: bounds memory on trainval.
const CHUNK: usize = 4096;

/// nuScenes' official splits: nuscenes-devkit 1.2.0 `nuscenes/utils/splits.py`, as scene numbers.
const SPLITS: &str = include_str!("splits.txt");

/// The scene names of one of the devkit's split lists (`train`, `val`, `test`, `mini_train`,
/// `mini_val`), in its order.
pub fn official_split(list: &str) -> Vec<String> {
    SPLITS
        .lines()
        .find_map(|line| line.strip_prefix(list)?.strip_prefix(": "))
        .map(|numbers| numbers.split(' ').map(|n| format!("scene-{:04}", n.parse::<u32>().unwrap_or(0))).collect())
        .unwrap_or_default()
}

/// What `dist4d export-infos` was asked for.
#[derive(Clone, Debug)]
pub struct InfosOptions {
    /// The dataset root (holding the version's table folder).
    pub root: PathBuf,
    /// The table folder: `v1.0-trainval`, `v1.0-mini`, `v1.0-test`, `interp_12Hz_trainval`, ...
    pub version: String,
    pub out: PathBuf,
    /// What `lidar_path` and `data_path` start with: the converter joins its `--root-path` as
    /// typed (`./data/nuscenes`) with the table's `filename`.
    pub path_prefix: String,
    /// LiDAR sweeps per info; `None`: the converter's runs (10 for keyframes, none at 12 Hz).
    pub max_sweeps: Option<usize>,
    /// Splits to write (`train`, `val`, `test`); empty: every split of the version.
    pub splits: Vec<String>,
}

/// One pickle written.
#[derive(Debug)]
pub struct InfosFile {
    pub path: PathBuf,
    pub split: String,
    pub samples: usize,
    /// Scenes with samples in the split, and how many of them `scene_tokens` lists (> 6 samples).
    pub scenes: usize,
    pub scene_lists: usize,
}

#[derive(Debug, Default)]
pub struct InfosReport {
    pub files: Vec<InfosFile>,
    pub warnings: Vec<String>,
}

/// How a version folder name maps to file names and splits (the converter's `available_vers`,
/// plus the 12 Hz mini folder `dist4d export-12hz` writes for v1.0-mini).
#[derive(Debug, PartialEq)]
struct Layout {
    /// `nuscenes`, `nuscenes_interp_12Hz`, `nuscenes_advanced_12Hz`.
    prefix: &'static str,
    twelve_hz: bool,
    /// (file split, the devkit's list) in the converter's order; the first takes scenes no list names.
    splits: &'static [(&'static str, &'static str)],
}

impl Layout {
    fn of(version: &str) -> Result<Layout> {
        let (prefix, twelve_hz, rest) = if let Some(rest) = version.strip_prefix("v1.0-") {
            ("nuscenes", false, rest)
        } else if let Some(rest) = version.strip_prefix("interp_12Hz_") {
            ("nuscenes_interp_12Hz", true, rest)
        } else if let Some(rest) = version.strip_prefix("advanced_12Hz_") {
            ("nuscenes_advanced_12Hz", true, rest)
        } else {
            ("", false, "")
        };
        let splits: &'static [(&str, &str)] = match rest {
            "trainval" => &[("train", "train"), ("val", "val")],
            "mini" => &[("train", "mini_train"), ("val", "mini_val")],
            "test" => &[("test", "test")],
            _ => bail!(
                "version {version:?}: the info pickles know v1.0-trainval, v1.0-mini, v1.0-test and their 12 Hz folders \
                 interp_12Hz_<split> (dist4d export-12hz, ASAP) and advanced_12Hz_<split>: the version names the splits \
                 and the file names"
            ),
        };
        ensure!(!prefix.is_empty(), "version {version:?} is not a nuScenes version name");
        Ok(Layout { prefix, twelve_hz, splits })
    }

    /// The converter's file name; at 12 Hz the `_with_bid` copy the training configs load.
    fn file_name(&self, split: &str) -> String {
        let bid = if self.twelve_hz { "_with_bid" } else { "" };
        format!("{}_infos_{split}{bid}.pkl", self.prefix)
    }
}

/// A `sample` row with its timestamp as written (an integer, or a float in ASAP's tables: the
/// pickle keeps the same Python type).
#[derive(Deserialize)]
struct InfoSampleRow {
    #[serde(skip)]
    row: usize,
    token: String,
    scene_token: String,
    timestamp: Number,
    #[serde(default)]
    prev: String,
    #[serde(default)]
    next: String,
}

#[derive(Deserialize)]
struct InfoSampleDataRow {
    #[serde(skip)]
    row: usize,
    token: String,
    sample_token: String,
    ego_pose_token: String,
    calibrated_sensor_token: String,
    filename: String,
    is_key_frame: bool,
    timestamp: Number,
    #[serde(default)]
    prev: String,
}

#[derive(Deserialize)]
struct LogRow {
    token: String,
    logfile: String,
    location: String,
}

impl TableRow for InfoSampleRow {
    fn set_row(&mut self, row: usize) {
        self.row = row;
    }
}
impl TableRow for InfoSampleDataRow {
    fn set_row(&mut self, row: usize) {
        self.row = row;
    }
}
impl TableRow for LogRow {}

/// The tables of one version, indexed as the devkit indexes them.
struct InfoTables {
    dir: PathBuf,
    prefix: String,
    max_sweeps: usize,
    scenes: Vec<SceneRow>,
    samples: Vec<InfoSampleRow>,
    sample_data: Vec<InfoSampleDataRow>,
    calibs: Vec<CalibratedSensorRow>,
    poses: Vec<EgoPoseRow>,
    logs: Vec<LogRow>,
    annotations: Vec<AnnotationRow>,
    scene_by: HashMap<String, usize>,
    sample_by: HashMap<String, usize>,
    sd_by: HashMap<String, usize>,
    calib_by: HashMap<String, usize>,
    pose_by: HashMap<String, usize>,
    log_by: HashMap<String, usize>,
    ann_by: HashMap<String, usize>,
    /// The devkit's `sample["data"]`: keyframe sample_data by (sample, channel), the last row wins.
    data: HashMap<(usize, String), usize>,
    /// The devkit's `sample["anns"]`: annotation rows of each sample, in table order.
    anns: Vec<Vec<usize>>,
    /// Each annotation's category name (instance -> category), "" when the chain is broken.
    category: Vec<String>,
}

fn index<T>(rows: &[T], token: impl Fn(&T) -> &str) -> HashMap<String, usize> {
    rows.iter().enumerate().map(|(i, r)| (token(r).to_string(), i)).collect()
}

impl InfoTables {
    fn read(options: &InfosOptions, test: bool) -> Result<(InfoTables, Vec<String>)> {
        let dir = options.root.join(&options.version);
        if !dir.is_dir() {
            let config = NuScenesConfig {
                root: options.root.display().to_string(),
                version: options.version.clone(),
                ..Default::default()
            };
            bail!("{}", not_nuscenes(&options.root, &config));
        }
        let mut warnings = Vec::new();
        let w = &mut warnings;
        let scenes: Vec<SceneRow> = read_table(&dir, "scene", w)?;
        let samples: Vec<InfoSampleRow> = read_table(&dir, "sample", w)?;
        let sample_data: Vec<InfoSampleDataRow> = read_table(&dir, "sample_data", w)?;
        let calibs: Vec<CalibratedSensorRow> = read_table(&dir, "calibrated_sensor", w)?;
        let sensors: Vec<SensorRow> = read_table(&dir, "sensor", w)?;
        let poses: Vec<EgoPoseRow> = read_table(&dir, "ego_pose", w)?;
        let logs: Vec<LogRow> = read_table(&dir, "log", w)?;
        // A test split has no annotations; any other version without them would give infos
        // without boxes, which no training run wants: that is an error, not a warning.
        let (annotations, instances, categories): (Vec<AnnotationRow>, Vec<InstanceRow>, Vec<NamedRow>) = if test {
            let why = "a test split has no boxes";
            (
                read_optional(&dir, "sample_annotation", w, why)?,
                read_optional(&dir, "instance", w, why)?,
                read_optional(&dir, "category", w, why)?,
            )
        } else {
            (
                read_table(&dir, "sample_annotation", w)?,
                read_table(&dir, "instance", w)?,
                read_table(&dir, "category", w)?,
            )
        };

        let sample_by = index(&samples, |s| &s.token);
        let calib_by = index(&calibs, |c| &c.token);
        let channel_of_sensor: HashMap<&str, &str> =
            sensors.iter().map(|s| (s.token.as_str(), s.channel.as_str())).collect();
        let sd_file = dir.join("sample_data.json");
        let mut data = HashMap::new();
        for (i, sd) in sample_data.iter().enumerate().filter(|(_, sd)| sd.is_key_frame) {
            let at = Place::row(&sd_file, sd.row, &sd.token);
            let &c = calib_by.get(&sd.calibrated_sensor_token).ok_or_else(|| {
                anyhow!(
                    "{at}: field calibrated_sensor_token {} names no calibrated_sensor row",
                    sd.calibrated_sensor_token
                )
            })?;
            let channel = channel_of_sensor.get(calibs[c].sensor_token.as_str()).ok_or_else(|| {
                anyhow!(
                    "{}: field sensor_token {} names no sensor row",
                    Place::row(&dir.join("calibrated_sensor.json"), calibs[c].row, &calibs[c].token),
                    calibs[c].sensor_token
                )
            })?;
            let &s = sample_by
                .get(&sd.sample_token)
                .ok_or_else(|| anyhow!("{at}: field sample_token {} names no sample row", sd.sample_token))?;
            data.insert((s, channel.to_string()), i);
        }
        let ann_file = dir.join("sample_annotation.json");
        let mut anns = vec![Vec::new(); samples.len()];
        for (i, a) in annotations.iter().enumerate() {
            let &s = sample_by.get(&a.sample_token).ok_or_else(|| {
                anyhow!(
                    "{}: field sample_token {} names no sample row",
                    Place::row(&ann_file, a.row, &a.token),
                    a.sample_token
                )
            })?;
            anns[s].push(i);
        }
        let cat_name: HashMap<&str, &str> = categories.iter().map(|c| (c.token.as_str(), c.name.as_str())).collect();
        let inst_cat: HashMap<&str, &str> =
            instances.iter().map(|i| (i.token.as_str(), i.category_token.as_str())).collect();
        let category = annotations
            .iter()
            .map(|a| {
                let cat = inst_cat.get(a.instance_token.as_str()).ok_or_else(|| {
                    anyhow!(
                        "{}: field instance_token {} names no instance row",
                        Place::row(&ann_file, a.row, &a.token),
                        a.instance_token
                    )
                })?;
                cat_name.get(cat).map(|n| n.to_string()).ok_or_else(|| {
                    anyhow!(
                        "{}/instance.json: instance {}: field category_token {cat} names no category row",
                        dir.display(),
                        a.instance_token
                    )
                })
            })
            .collect::<Result<Vec<String>>>()?;
        let tables = InfoTables {
            prefix: options.path_prefix.clone(),
            max_sweeps: 0,
            scene_by: index(&scenes, |s| &s.token),
            sd_by: index(&sample_data, |s| &s.token),
            pose_by: index(&poses, |p| &p.token),
            log_by: index(&logs, |l| &l.token),
            ann_by: index(&annotations, |a| &a.token),
            sample_by,
            calib_by,
            data,
            anns,
            category,
            dir,
            scenes,
            samples,
            sample_data,
            calibs,
            poses,
            logs,
            annotations,
        };
        Ok((tables, warnings))
    }

    fn file(&self, table: &str) -> PathBuf {
        self.dir.join(format!("{table}.json"))
    }

    /// The keyframe sample_data of `channel` of sample `s`, as `sample["data"][channel]`.
    fn data_of(&self, s: usize, channel: &str) -> Result<&InfoSampleDataRow> {
        let sample = &self.samples[s];
        let i = self.data.get(&(s, channel.to_string())).ok_or_else(|| {
            anyhow!(
                "{}: sample {} has no {channel} sample_data with is_key_frame: true (the infos need its {} and the six \
                 cameras {})",
                Place::row(&self.file("sample"), sample.row, &sample.token),
                sample.token,
                LIDAR,
                INFO_CAMERAS.join(", ")
            )
        })?;
        Ok(&self.sample_data[*i])
    }

    fn sd(&self, token: &str, named_by: &str) -> Result<&InfoSampleDataRow> {
        let i = self.sd_by.get(token).ok_or_else(|| anyhow!("{named_by} {token} names no sample_data row"))?;
        Ok(&self.sample_data[*i])
    }

    fn calib(&self, sd: &InfoSampleDataRow) -> Result<&CalibratedSensorRow> {
        let i = self.calib_by.get(&sd.calibrated_sensor_token).ok_or_else(|| {
            anyhow!(
                "{}: field calibrated_sensor_token {} names no calibrated_sensor row",
                Place::row(&self.file("sample_data"), sd.row, &sd.token),
                sd.calibrated_sensor_token
            )
        })?;
        Ok(&self.calibs[*i])
    }

    fn pose(&self, sd: &InfoSampleDataRow) -> Result<&EgoPoseRow> {
        let i = self.pose_by.get(&sd.ego_pose_token).ok_or_else(|| {
            anyhow!(
                "{}: field ego_pose_token {} names no ego_pose row",
                Place::row(&self.file("sample_data"), sd.row, &sd.token),
                sd.ego_pose_token
            )
        })?;
        Ok(&self.poses[*i])
    }

    /// The info of sample `s`, in the converter's key order.
    fn info(&self, s: usize) -> Result<Value> {
        let sample = &self.samples[s];
        let lidar = self.data_of(s, LIDAR)?;
        let cs = self.calib(lidar)?;
        let pose = self.pose(lidar)?;
        let scene = self.scene_by.get(&sample.scene_token).map(|&i| &self.scenes[i]).ok_or_else(|| {
            anyhow!(
                "{}: field scene_token {} names no scene row",
                Place::row(&self.file("sample"), sample.row, &sample.token),
                sample.scene_token
            )
        })?;
        let log = self.log_by.get(&scene.log_token).map(|&i| &self.logs[i]).ok_or_else(|| {
            anyhow!(
                "{}: scene {}: field log_token {} names no log row",
                self.file("scene").display(),
                scene.token,
                scene.log_token
            )
        })?;
        let l2e = rotation(cs.rotation, &self.file("calibrated_sensor"), cs.row, &cs.token)?;
        let e2g = rotation(pose.rotation, &self.file("ego_pose"), pose.row, &pose.token)?;
        let lidar_frame = LidarFrame { l2e, l2e_t: cs.translation.into(), e2g, e2g_t: pose.translation.into() };

        let mut cams = Vec::with_capacity(INFO_CAMERAS.len());
        for cam in INFO_CAMERAS {
            let sd = self.data_of(s, cam)?;
            let mut entry = self.sensor_to_lidar(sd, cam, &lidar_frame)?;
            let cam_cs = self.calib(sd)?;
            let k = match cam_cs.camera_intrinsic.as_slice() {
                [a, b, c] if [a, b, c].iter().all(|r| r.len() == 3) => [a, b, c].map(|r| [r[0], r[1], r[2]]),
                _ => bail!(
                    "{}: field camera_intrinsic is not a 3x3 matrix, but sample_data {} is a {cam} image",
                    Place::row(&self.file("calibrated_sensor"), cam_cs.row, &cam_cs.token),
                    sd.token
                ),
            };
            entry.push(("camera_intrinsics".into(), Value::Array(Array::f64(&[3, 3], &k.concat()))));
            cams.push((cam.to_string(), Value::Dict(entry)));
        }
        let mut sweeps = Vec::new();
        let mut at = lidar;
        while sweeps.len() < self.max_sweeps && !at.prev.is_empty() {
            let prev = self.sd(&at.prev, &format!("sample_data {}: field prev", at.token))?;
            sweeps.push(Value::Dict(self.sensor_to_lidar(prev, "lidar", &lidar_frame)?));
            at = prev;
        }

        let boxes = self.boxes(s, &lidar_frame)?;
        let floats = |v: &[f64]| Value::List(v.iter().map(|&x| Value::Float(x)).collect());
        let (v, w) = self.ego_velocity(s)?;
        let n = boxes.ids.len();
        // `np.array([])` of an empty list is float64: what the converter writes for empty counts
        // and names.
        let empty = || Value::Array(Array::f64(&[0], &[]));
        let counts = |c: &[i64]| if c.is_empty() { empty() } else { Value::Array(Array::i64(&[n], c)) };
        let names: Vec<&str> = boxes.names.iter().map(String::as_str).collect();
        Ok(Value::Dict(vec![
            ("lidar_path".into(), Value::Str(py_join(&self.prefix, &lidar.filename))),
            ("token".into(), Value::Str(sample.token.clone())),
            ("sweeps".into(), Value::List(sweeps)),
            ("cams".into(), Value::Dict(cams)),
            ("lidar2ego_translation".into(), floats(&cs.translation)),
            ("lidar2ego_rotation".into(), floats(&cs.rotation)),
            ("ego2global_translation".into(), floats(&pose.translation)),
            ("ego2global_rotation".into(), floats(&pose.rotation)),
            ("timestamp".into(), number(&sample.timestamp)),
            ("location".into(), Value::Str(log.location.clone())),
            ("description".into(), Value::Str(scene.description.clone())),
            ("timeofday".into(), Value::Str(log.logfile.chars().skip(5).collect())),
            ("is_key_frame".into(), Value::Bool(true)),
            (
                "ego_velocity".into(),
                Value::Tuple(vec![
                    Value::Array(Array::f64(&[3], &v.to_array())),
                    Value::Array(Array::f64(&[3], &w.to_array())),
                ]),
            ),
            ("gt_boxes".into(), Value::Array(Array::f64(&[n, 7], &boxes.boxes))),
            ("gt_box_ids".into(), Value::List(boxes.ids.into_iter().map(Value::Str).collect())),
            ("gt_names".into(), if n == 0 { empty() } else { Value::Array(Array::strings(&names)) }),
            ("gt_velocity".into(), Value::Array(Array::f64(&[n, 2], &boxes.velocity))),
            ("num_lidar_pts".into(), counts(&boxes.lidar_pts)),
            ("num_radar_pts".into(), counts(&boxes.radar_pts)),
            ("visibility".into(), Value::Array(Array::u8(&[n], &boxes.visibility))),
            ("valid_flag".into(), Value::Array(Array::bool(&[n], &boxes.valid))),
        ]))
    }

    /// `obtain_sensor2top`: a camera image or a LiDAR sweep, with the transform from its sensor
    /// to the sample's LiDAR (the LiDAR at its own time and pose).
    fn sensor_to_lidar(&self, sd: &InfoSampleDataRow, kind: &str, lidar: &LidarFrame) -> Result<Vec<(String, Value)>> {
        let cs = self.calib(sd)?;
        let pose = self.pose(sd)?;
        let s2e = rotation(cs.rotation, &self.file("calibrated_sensor"), cs.row, &cs.token)?;
        let e2g = rotation(pose.rotation, &self.file("ego_pose"), pose.row, &pose.token)?;
        // sensor -> ego -> global -> the LiDAR's ego -> LiDAR.
        let to_lidar = lidar.l2e.transpose() * lidar.e2g.transpose();
        let r = to_lidar * e2g * s2e;
        let origin = e2g * DVec3::from(cs.translation) + DVec3::from(pose.translation);
        let t = lidar.l2e.transpose() * (lidar.e2g.transpose() * (origin - lidar.e2g_t) - lidar.l2e_t);
        let floats = |v: &[f64]| Value::List(v.iter().map(|&x| Value::Float(x)).collect());
        Ok(vec![
            ("data_path".into(), Value::Str(py_join(&self.prefix, &sd.filename))),
            ("type".into(), Value::Str(kind.to_string())),
            ("sample_data_token".into(), Value::Str(sd.token.clone())),
            ("sensor2ego_translation".into(), floats(&cs.translation)),
            ("sensor2ego_rotation".into(), floats(&cs.rotation)),
            ("ego2global_translation".into(), floats(&pose.translation)),
            ("ego2global_rotation".into(), floats(&pose.rotation)),
            ("timestamp".into(), number(&sd.timestamp)),
            ("sensor2lidar_rotation".into(), Value::Array(Array::f64(&[3, 3], &row_major(r)))),
            ("sensor2lidar_translation".into(), Value::Array(Array::f64(&[3], &t.to_array()))),
        ])
    }

    /// The sample's boxes in its LiDAR frame (`get_sample_data` of its LiDAR keyframe: the
    /// sample's annotations, global -> ego -> LiDAR), in `sample["anns"]` order.
    fn boxes(&self, s: usize, lidar: &LidarFrame) -> Result<Boxes> {
        let mut b = Boxes::default();
        let file = self.file("sample_annotation");
        let to_lidar = lidar.l2e.transpose() * lidar.e2g.transpose();
        let q_to_lidar = DQuat::from_mat3(&to_lidar).normalize();
        for &i in &self.anns[s] {
            let a = &self.annotations[i];
            let q = unit_quat(a.rotation).ok_or_else(|| {
                anyhow!("{}: field rotation {:?} is not a rotation", Place::row(&file, a.row, &a.token), a.rotation)
            })?;
            let centre = lidar.l2e.transpose()
                * (lidar.e2g.transpose() * (DVec3::from(a.translation) - lidar.e2g_t) - lidar.l2e_t);
            let q = q_to_lidar * q;
            // pyquaternion's yaw_pitch_roll[0], with its sign convention, then mmdet3d v0.x's
            // "SECOND" yaw the converter writes.
            let yaw = (2.0 * (q.w * q.z - q.x * q.y)).atan2(1.0 - 2.0 * (q.y * q.y + q.z * q.z));
            b.boxes.extend_from_slice(&[
                centre.x,
                centre.y,
                centre.z,
                a.size[0],
                a.size[1],
                a.size[2],
                -yaw - std::f64::consts::FRAC_PI_2,
            ]);
            let v = self.box_velocity(a);
            let v = to_lidar * DVec3::new(v[0], v[1], 0.0);
            b.velocity.extend_from_slice(&[v.x, v.y]);
            b.ids.push(a.instance_token.clone());
            let name = &self.category[i];
            b.names.push(NAME_MAPPING.iter().find(|(k, _)| k == name).map_or(name.as_str(), |(_, v)| v).to_string());
            b.lidar_pts.push(a.num_lidar_pts as i64);
            b.radar_pts.push(a.num_radar_pts as i64);
            b.valid.push(a.num_lidar_pts + a.num_radar_pts > 0);
            // `np.array([visibility_token], dtype=np.uint8)` parses the level's token '1'..'4'.
            b.visibility.push(a.visibility_token.trim().parse::<u8>().map_err(|_| {
                anyhow!(
                    "{}: field visibility_token {:?} is not a visibility level (the pickles store it as uint8, as the \
                     converter does with nuScenes' tokens '1'..'4')",
                    Place::row(&file, a.row, &a.token),
                    a.visibility_token
                )
            })?);
        }
        Ok(b)
    }

    /// The devkit's `box_velocity` (global frame): the centre difference over the track's
    /// neighbouring annotations, NaN with none or when they are too far apart. A dangling
    /// neighbour is the devkit's KeyError, which the converter turns into NaN.
    fn box_velocity(&self, a: &AnnotationRow) -> [f64; 2] {
        const NAN: [f64; 2] = [f64::NAN; 2];
        let (has_prev, has_next) = (!a.prev.is_empty(), !a.next.is_empty());
        if !has_prev && !has_next {
            return NAN;
        }
        let get = |t: &str| self.ann_by.get(t).map(|&i| &self.annotations[i]);
        let (Some(first), Some(last)) =
            (if has_prev { get(&a.prev) } else { Some(a) }, if has_next { get(&a.next) } else { Some(a) })
        else {
            return NAN;
        };
        let time =
            |r: &AnnotationRow| self.sample_by.get(&r.sample_token).map(|&s| 1e-6 * as_f64(&self.samples[s].timestamp));
        let (Some(t_last), Some(t_first)) = (time(last), time(first)) else { return NAN };
        let dt = t_last - t_first;
        let max_dt = if has_prev && has_next { 3.0 } else { 1.5 };
        if dt > max_dt {
            return NAN;
        }
        [(last.translation[0] - first.translation[0]) / dt, (last.translation[1] - first.translation[1]) / dt]
    }

    /// `get_ego_velocity` on a keyframe: the LiDAR ego poses of the previous and next samples
    /// (or this one), linear and angular (pyquaternion's angle times axis), global frame.
    fn ego_velocity(&self, s: usize) -> Result<(DVec3, DVec3)> {
        let sample = &self.samples[s];
        let neighbour = |token: &str, field: &str| -> Result<usize> {
            if token.is_empty() {
                return Ok(s);
            }
            self.sample_by.get(token).copied().ok_or_else(|| {
                anyhow!(
                    "{}: field {field} {token} names no sample row",
                    Place::row(&self.file("sample"), sample.row, &sample.token)
                )
            })
        };
        let (first, last) = (neighbour(&sample.prev, "prev")?, neighbour(&sample.next, "next")?);
        let pose_of = |s: usize| -> Result<&EgoPoseRow> { self.pose(self.data_of(s, LIDAR)?) };
        let (p_first, p_last) = (pose_of(first)?, pose_of(last)?);
        let dt = 1e-6 * as_f64(&self.samples[last].timestamp) - 1e-6 * as_f64(&self.samples[first].timestamp);
        let v = (DVec3::from(p_last.translation) - DVec3::from(p_first.translation)) / dt;
        let quat = |p: &EgoPoseRow| {
            unit_quat(p.rotation).ok_or_else(|| {
                anyhow!(
                    "{}: field rotation {:?} is not a rotation",
                    Place::row(&self.file("ego_pose"), p.row, &p.token),
                    p.rotation
                )
            })
        };
        let q = (quat(p_last)? * quat(p_first)?.conjugate()).normalize();
        let axis_len = DVec3::new(q.x, q.y, q.z).length();
        let mut angle = (2.0 * axis_len.atan2(q.w) + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI)
            - std::f64::consts::PI;
        if angle == -std::f64::consts::PI {
            angle = std::f64::consts::PI;
        }
        let axis = if axis_len < 1e-17 { DVec3::ZERO } else { DVec3::new(q.x, q.y, q.z) / axis_len };
        Ok((v, angle * axis / dt))
    }
}

/// The sample's LiDAR: its mounting and its ego pose.
struct LidarFrame {
    l2e: DMat3,
    l2e_t: DVec3,
    e2g: DMat3,
    e2g_t: DVec3,
}

#[derive(Default)]
struct Boxes {
    boxes: Vec<f64>,
    velocity: Vec<f64>,
    ids: Vec<String>,
    names: Vec<String>,
    lidar_pts: Vec<i64>,
    radar_pts: Vec<i64>,
    visibility: Vec<u8>,
    valid: Vec<bool>,
}

/// A `[w, x, y, z]` quaternion made unit length, as pyquaternion does before it rotates.
fn unit_quat(q: [f64; 4]) -> Option<DQuat> {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    (n.is_finite() && n > 0.0).then(|| DQuat::from_xyzw(q[1] / n, q[2] / n, q[3] / n, q[0] / n))
}

fn rotation(q: [f64; 4], file: &Path, row: usize, token: &str) -> Result<DMat3> {
    unit_quat(q)
        .map(DMat3::from_quat)
        .ok_or_else(|| anyhow!("{}: field rotation {q:?} is not a rotation", Place::row(file, row, token)))
}

fn row_major(m: DMat3) -> [f64; 9] {
    m.transpose().to_cols_array()
}

fn as_f64(n: &Number) -> f64 {
    n.as_f64().unwrap_or(f64::NAN)
}

/// A JSON number as `json.load` gives it: an int, or a float.
fn number(n: &Number) -> Value {
    match n.as_i64() {
        Some(i) => Value::Int(i),
        None => Value::Float(as_f64(n)),
    }
}

/// `os.path.join(prefix, name)` for the relative names nuScenes tables hold.
fn py_join(prefix: &str, name: &str) -> String {
    if prefix.is_empty() || name.starts_with('/') {
        name.to_string()
    } else if prefix.ends_with('/') {
        format!("{prefix}{name}")
    } else {
        format!("{prefix}/{name}")
    }
}

/// Which split each scene's samples go to, in the order the converter meets them.
struct Plan {
    /// Per split of the version: sample indices in sample.json order, and `scene_tokens`.
    splits: Vec<(&'static str, Vec<usize>, Vec<Vec<String>>, usize)>,
}

fn plan(tables: &InfoTables, layout: &Layout, warnings: &mut Vec<String>) -> Result<Plan> {
    let mut split_of_scene: HashMap<String, usize> = HashMap::new();
    for (k, (_, list)) in layout.splits.iter().enumerate() {
        for name in official_split(list) {
            split_of_scene.insert(name, k);
        }
    }
    let mut unlisted = Vec::new();
    let scene_split: Vec<usize> = tables
        .scenes
        .iter()
        .map(|s| {
            split_of_scene.get(&s.name).copied().unwrap_or_else(|| {
                unlisted.push(s.name.as_str());
                0
            })
        })
        .collect();
    let mut splits: Vec<(&'static str, Vec<usize>, Vec<Vec<String>>, usize)> =
        layout.splits.iter().map(|(name, _)| (*name, Vec::new(), Vec::new(), 0)).collect();
    let sample_file = tables.file("sample");
    // The converter's walk over sample.json: a scene's token list ends where another scene's
    // sample comes; within a scene, each sample must be the `next` of the one before.
    let mut current: Option<(usize, Vec<String>)> = None;
    let mut seen = HashSet::new();
    let close = |run: Option<(usize, Vec<String>)>, splits: &mut Vec<(&str, Vec<usize>, Vec<Vec<String>>, usize)>| {
        if let Some((scene, tokens)) = run {
            let k = scene_split[scene];
            splits[k].3 += 1;
            if tokens.len() > FRAMES_T {
                splits[k].2.push(tokens);
            }
        }
    };
    for (i, sample) in tables.samples.iter().enumerate() {
        let at = Place::row(&sample_file, sample.row, &sample.token);
        let &scene = tables
            .scene_by
            .get(&sample.scene_token)
            .ok_or_else(|| anyhow!("{at}: field scene_token {} names no scene row", sample.scene_token))?;
        match &mut current {
            Some((run, tokens)) if *run == scene => {
                let prev = &tables.samples[i - 1];
                ensure!(
                    prev.next == sample.token,
                    "{at}: it follows sample {} of the same scene in sample.json, whose field next is {:?}: the \
                     converter (and the scene_tokens of the pickles) needs each scene's samples in their chain order",
                    prev.token,
                    prev.next
                );
                tokens.push(sample.token.clone());
            }
            _ => {
                ensure!(
                    seen.insert(scene),
                    "{at}: scene {} has samples earlier in sample.json, with samples of another scene between: its \
                     samples must be together (the converter splits the scene in two)",
                    tables.scenes[scene].name
                );
                close(current.take(), &mut splits);
                current = Some((scene, vec![sample.token.clone()]));
            }
        }
        splits[scene_split[scene]].1.push(i);
    }
    close(current.take(), &mut splits);
    let sampled: HashSet<usize> = seen;
    let unlisted_sampled: Vec<&str> = unlisted
        .iter()
        .copied()
        .filter(|name| tables.scenes.iter().position(|s| s.name == *name).is_some_and(|i| sampled.contains(&i)))
        .collect();
    if let Some(first) = unlisted_sampled.first() {
        warnings.push(format!(
            "{} scene(s) with samples are in no official {} split of the nuScenes devkit (first: {first}): they go \
             to {} (dist4d's rule for synthetic and renamed scenes; see docs/interop.md)",
            unlisted_sampled.len(),
            layout.splits.iter().map(|(_, l)| *l).collect::<Vec<_>>().join("/"),
            layout.splits[0].0
        ));
    }
    Ok(Plan { splits })
}

/// Writes the info pickles of every split of `options.version` (or of `options.splits`) into
/// `options.out`: each file whole or not at all, and none unless every one could be made.
pub fn write_infos(options: &InfosOptions) -> Result<InfosReport> {
    let layout = Layout::of(&options.version)?;
    for s in &options.splits {
        ensure!(
            layout.splits.iter().any(|(name, _)| name == s),
            "--split {s}: version {} has the splits {}",
            options.version,
            layout.splits.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")
        );
    }
    let test = layout.splits.iter().any(|(n, _)| *n == "test");
    let (mut tables, mut warnings) = InfoTables::read(options, test)?;
    tables.max_sweeps = options.max_sweeps.unwrap_or(if layout.twelve_hz { 0 } else { 10 });
    let plan = plan(&tables, &layout, &mut warnings)?;
    let official = tables.scenes.iter().any(|s| layout.splits.iter().any(|(_, l)| official_split(l).contains(&s.name)));
    let wanted: Vec<_> = plan
        .splits
        .iter()
        .filter(|(name, ..)| options.splits.is_empty() || options.splits.iter().any(|s| s == name))
        .collect();
    for (name, samples, ..) in &wanted {
        if !samples.is_empty() {
            continue;
        }
        let list = layout.splits.iter().find(|(n, _)| n == name).map_or("", |(_, l)| *l);
        let others: Vec<String> = plan
            .splits
            .iter()
            .filter(|(_, samples, ..)| !samples.is_empty())
            .map(|(other, ..)| format!("--split {other}"))
            .collect();
        let msg = format!(
            "{}: no sample belongs to a scene of the {name} split (nuscenes-devkit splits.{list}), so its pickle would \
             be empty: the folder holds part of the dataset (ASAP's generator writes the val scenes alone); write the \
             split(s) it has with {}",
            tables.file("sample").display(),
            if others.is_empty() { "nothing: no sample has a scene".to_string() } else { others.join(" ") }
        );
        // Synthetic scenes are in no list: an empty split is what the rule gives, said once.
        if official || !options.splits.is_empty() {
            bail!(msg);
        }
        warnings.push(format!("the {name} pickle has no samples: every scene went to {}", layout.splits[0].0));
    }
    let missing: Vec<&str> = tables
        .samples
        .par_iter()
        .enumerate()
        .filter_map(|(s, _)| tables.data_of(s, LIDAR).ok())
        .filter(|sd| !options.root.join(&sd.filename).is_file())
        .map(|sd| sd.filename.as_str())
        .collect();
    if let Some(first) = missing.first() {
        warnings.push(format!(
            "{} LiDAR file(s) the infos name are not under {} (first: {first}); the pickles are written all the same",
            missing.len(),
            options.root.display()
        ));
    }

    std::fs::create_dir_all(&options.out).with_context(|| format!("creating {}", options.out.display()))?;
    let mut written: Vec<(PathBuf, PathBuf)> = Vec::new();
    let mut files = Vec::new();
    let result = (|| -> Result<()> {
        for (name, samples, scene_tokens, scenes) in &wanted {
            let path = options.out.join(layout.file_name(name));
            let tmp = options.out.join(format!(".{}.tmp-{}", layout.file_name(name), std::process::id()));
            written.push((tmp.clone(), path.clone()));
            write_one(&tables, &tmp, samples, scene_tokens, !test, &options.version)
                .with_context(|| format!("writing {}", path.display()))?;
            files.push(InfosFile {
                path,
                split: name.to_string(),
                samples: samples.len(),
                scenes: *scenes,
                scene_lists: scene_tokens.len(),
            });
        }
        Ok(())
    })();
    if let Err(e) = result {
        for (tmp, _) in &written {
            let _ = std::fs::remove_file(tmp);
        }
        return Err(e);
    }
    for (tmp, path) in &written {
        std::fs::rename(tmp, path).with_context(|| format!("moving {} to {}", tmp.display(), path.display()))?;
    }
    if let Ok(dir) = std::fs::File::open(&options.out) {
        let _ = dir.sync_all();
    }
    Ok(InfosReport { files, warnings })
}

/// One pickle: the infos encoded in parallel a chunk at a time and written in order, then
/// `metadata` and `scene_tokens`; synced before the caller renames it into place.
fn write_one(
    tables: &InfoTables,
    tmp: &Path,
    samples: &[usize],
    scene_tokens: &[Vec<String>],
    with_scene_tokens: bool,
    version: &str,
) -> Result<()> {
    let file = std::fs::File::create(tmp).with_context(|| format!("creating {}", tmp.display()))?;
    let mut stream = DictStream::new(std::io::BufWriter::with_capacity(1 << 20, file))?;
    stream.begin_list("infos")?;
    for chunk in samples.chunks(CHUNK) {
        let encoded: Vec<Result<Vec<u8>>> = chunk
            .par_iter()
            .map(|&s| {
                let mut bytes = Vec::new();
                encode_into(&mut bytes, &tables.info(s)?);
                Ok(bytes)
            })
            .collect();
        for bytes in encoded {
            stream.item(&bytes?)?;
        }
    }
    stream.end_list()?;
    stream.entry("metadata", &Value::Dict(vec![("version".into(), Value::Str(version.to_string()))]))?;
    if with_scene_tokens {
        let lists = scene_tokens
            .iter()
            .map(|tokens| Value::List(tokens.iter().map(|t| Value::Str(t.clone())).collect()))
            .collect();
        stream.entry("scene_tokens", &Value::List(lists))?;
    }
    let out = stream.finish()?;
    let file = out.into_inner().map_err(|e| e.into_error())?;
    file.sync_all()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn versions_name_their_splits_and_files() {
        let l = Layout::of("interp_12Hz_trainval").unwrap();
        assert!(l.twelve_hz);
        assert_eq!(l.file_name("val"), "nuscenes_interp_12Hz_infos_val_with_bid.pkl");
        let l = Layout::of("v1.0-mini").unwrap();
        assert_eq!(l.splits, &[("train", "mini_train"), ("val", "mini_val")]);
        assert_eq!(l.file_name("train"), "nuscenes_infos_train.pkl");
        let e = Layout::of("v2.0-custom").unwrap_err().to_string();
        assert!(e.contains("v1.0-trainval") && e.contains("interp_12Hz"), "{e}");
    }

    #[test]
    fn the_official_splits_are_the_devkits() {
        let (train, val) = (official_split("train"), official_split("val"));
        assert_eq!((train.len(), val.len(), official_split("test").len()), (700, 150, 150));
        assert_eq!(&val[..2], &["scene-0003".to_string(), "scene-0012".to_string()]);
        assert!(official_split("mini_train").contains(&"scene-0061".to_string()));
        assert!(train.iter().all(|s| !val.contains(s)));
    }

    #[test]
    fn paths_join_as_os_path_join() {
        assert_eq!(py_join("./data/nuscenes", "samples/a.jpg"), "./data/nuscenes/samples/a.jpg");
        assert_eq!(py_join("/d/", "samples/a.jpg"), "/d/samples/a.jpg");
        assert_eq!(py_join("", "samples/a.jpg"), "samples/a.jpg");
    }

    #[test]
    fn timestamps_keep_their_python_type() {
        assert_eq!(number(&serde_json::from_str("1533151603512404").unwrap()), Value::Int(1533151603512404));
        assert_eq!(number(&serde_json::from_str("1533151603595737.5").unwrap()), Value::Float(1533151603595737.5));
    }
}
