//! The surround-camera adapter every driving-log reader shares: one item tree (scene / frame /
//! camera), one set of source ports, and the one `ItemSpace` / `Dataset` implementation over them.
//!
//! A format reader (nuScenes, DGP) parses and validates its metadata into a [`Tree`] of resolved
//! [`Reading`]s, one LiDAR reading and one reading per camera a frame, and implements
//! [`SurroundReader`] for what differs: how a LiDAR file is read and digested, and where a frame's
//! boxes come from. [`Surround`] turns such a reader into the runtime's dataset. (The orphan rule
//! forbids implementing the runtime's traits for every `SurroundReader` directly, hence the wrapper.)

use crate::files::{image_dimensions, read_camera_image};
use crate::sidecar::Sidecars;
use anyhow::{anyhow, bail, Context, Result};
use dist4d_graph::{DimSpec, SourcePortSpec};
use dist4d_runtime::{Dataset, Digest, DigestBuilder, FileDigests, ItemKey, ItemSpace};
use dist4d_types::artifact::{Artifact, Box3D, Boxes3D, Calibration, Image, ImageInfo, PointCloud, Pose};
use dist4d_types::geometry::Se3;
use std::path::{Path, PathBuf};

pub(crate) const DIMS: [DimSpec; 3] = [
    DimSpec { name: "scene", ordered: false },
    DimSpec { name: "frame", ordered: true },
    DimSpec { name: "camera", ordered: false },
];
pub(crate) const PORTS: [SourcePortSpec; 15] = [
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
        doc: "annotated boxes at the time of the frame's LiDAR sweep (world frame; interpolated between keyframes)",
    },
    SourcePortSpec {
        name: "camera_boxes",
        ty: "Boxes3D",
        grain: "camera",
        doc: "annotated boxes at the camera image's own time (world frame; interpolated between keyframes)",
    },
    SourcePortSpec { name: "image", ty: "Image", grain: "camera", doc: "the camera image (RGB8)" },
    SourcePortSpec {
        name: "image_info",
        ty: "ImageInfo",
        grain: "camera",
        doc: "what an index records of the image: labels, token, file (relative to the root), time, calibration, ego pose, boxes at its time; or why it is missing",
    },
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
        name: "synth_world",
        ty: "File",
        grain: "scene",
        doc: "a synthetic dataset's world, to render any view exactly: JSON {\"scene\": label, \"synth\": groundtruth/synth.json}; empty for other datasets",
    },
    SourcePortSpec {
        name: "frame_token",
        ty: "File",
        grain: "frame",
        doc: "the dataset's id of the frame, UTF-8 (nuScenes: a keyframe's sample token, another frame's LiDAR sample_data token; DGP: the LiDAR datum key), as `{frame.token}` in export paths",
    },
    SourcePortSpec {
        name: "map",
        ty: "File",
        grain: "scene",
        doc: "the scene's map mask as the dataset has it (nuScenes `map.json`: an 8-bit PNG, drivable > 0, 0.1 m per pixel, the devkit's MapMask frame); empty when it has none",
    },
    SourcePortSpec {
        name: "semantic",
        ty: "Segmentation",
        grain: "camera",
        doc: "Cityscapes-id segmentation from the `semantics` folder; empty when none is configured",
    },
    SourcePortSpec {
        name: "source_dataset",
        ty: "File",
        grain: "scene",
        doc: "the dataset the scene was recorded for, UTF-8: `nuscenes`, `ddad`, or a py123d log's own (`wod-perception`, `av2-sensor`, ...), for outputs whose layout follows the source (Occ3D-Waymo)",
    },
];

/// One sensor reading, resolved and checked when the dataset is opened.
#[derive(Clone, Debug)]
pub struct Reading {
    pub file: PathBuf,
    pub calib: Calibration,
    pub pose: Pose,
    /// What the metadata calls it, for messages: `sample_data <token>`, `datum <key>`.
    pub what: String,
    /// Its token in the metadata (nuScenes `sample_data` token, DGP datum key).
    pub token: String,
    /// Its row in `file` when the file is a table of readings (a py123d log's Arrow file).
    pub row: Option<u64>,
    /// When that row holds a path instead of the bytes (a py123d log that stores paths into the
    /// source dataset): the file it names, which is what a loader opens.
    pub stored_file: Option<PathBuf>,
}

impl Reading {
    /// The reading as the export index records it: token, file (relative to the dataset root
    /// when it lies under it) and timestamp (us).
    fn record(&self, root: &Path) -> serde_json::Value {
        let file = self.file.strip_prefix(root).unwrap_or(&self.file);
        let mut record = serde_json::json!({
            "token": self.token,
            "file": file.to_string_lossy(),
            "timestamp_us": self.pose.timestamp_us,
        });
        if let Some(row) = self.row {
            record["row"] = row.into();
        }
        if let Some(stored) = &self.stored_file {
            record["stored_file"] = stored.strip_prefix(root).unwrap_or(stored).to_string_lossy().into();
        }
        record
    }

    /// Where a loader finds the bytes: the file and, when that file is a table, the row.
    fn bytes_at(&self, root: &Path) -> (String, Option<u64>) {
        match &self.stored_file {
            Some(stored) => (stored.strip_prefix(root).unwrap_or(stored).to_string_lossy().into_owned(), None),
            None => (self.file.strip_prefix(root).unwrap_or(&self.file).to_string_lossy().into_owned(), self.row),
        }
    }

    /// The content digest of the reading's file.
    pub fn file_digest(&self, files: &dyn FileDigests) -> Result<Option<Digest>> {
        files.file_digest(&self.file).with_context(|| format!("{}: {}", self.what, self.file.display()))
    }
}

/// A frame's readings. Each is its own result, so that a bad row fails only the items that use it;
/// `extra` is what the format keeps per frame besides.
pub struct Frame<F> {
    pub lidar: Result<Reading, String>,
    /// One per camera, in the order of [`Tree::cameras`].
    pub cameras: Vec<Result<Reading, String>>,
    pub extra: F,
}

/// A scene: its name (the item label) and frames; `extra` is what the format keeps per scene.
pub struct Scene<S, F> {
    pub name: String,
    pub frames: Vec<Frame<F>>,
    pub extra: S,
}

/// What a surround-camera dataset resolved when it was opened: the camera names (the third item
/// dimension), the scenes with their frames and readings, and the per-image sidecar files.
pub struct Tree<S, F> {
    /// The dataset root: files are recorded relative to it.
    pub root: PathBuf,
    pub cameras: Vec<String>,
    pub scenes: Vec<Scene<S, F>>,
    pub sidecars: Sidecars,
}

impl<S, F> Tree<S, F> {
    pub fn scene_frame(&self, item: &ItemKey) -> Result<(&Scene<S, F>, &Frame<F>)> {
        let scene = self.scenes.get(item.idx[0] as usize).ok_or_else(|| anyhow!("no scene {:?}", item))?;
        let frame = scene.frames.get(item.idx[1] as usize).ok_or_else(|| anyhow!("no frame {:?}", item))?;
        Ok((scene, frame))
    }

    /// The reading a port of `item` comes from: the frame's LiDAR for the LiDAR ports, else the
    /// item's camera.
    pub fn reading(&self, port: &str, item: &ItemKey) -> Result<&Reading> {
        let (_, frame) = self.scene_frame(item)?;
        let r = match port {
            "lidar" | "lidar_calib" | "lidar_pose" => &frame.lidar,
            _ => frame.cameras.get(item.idx[2] as usize).ok_or_else(|| anyhow!("no camera {:?}", item))?,
        };
        r.as_ref().map_err(|e| anyhow!("{e}"))
    }

    fn camera(&self, item: &ItemKey) -> &str {
        &self.cameras[item.idx[2] as usize]
    }
}

/// What differs between the formats of surround-camera logs; the rest is [`Surround`]'s.
pub trait SurroundReader: Send + Sync {
    /// The format's name in messages (`nuScenes has no source port ...`).
    const FORMAT: &'static str;
    /// What the format keeps per scene and per frame beyond the shared tree.
    type Scene: Send + Sync;
    type Frame: Send + Sync;

    fn tree(&self) -> &Tree<Self::Scene, Self::Frame>;
    /// The source digest of the `lidar` port of a frame whose LiDAR reading is `lidar`, from the
    /// digests of the files it is read from; `Ok(None)` when `files` declined to hash one.
    fn lidar_digest(&self, lidar: &Reading, frame: &Self::Frame, files: &dyn FileDigests) -> Result<Option<Digest>>;
    /// The `lidar` port: the point cloud of a frame whose LiDAR reading is `lidar`.
    fn read_lidar(&self, lidar: &Reading, frame: &Self::Frame) -> Result<PointCloud>;
    /// The recording vehicle's box in its ego frame (min and max corners; x forward, y left, z
    /// up; metres). LiDAR returns inside it are the car itself (its roof, the sensor's mount)
    /// and the `lidar` port drops them, as the nuscenes-devkit's `remove_close` does around the
    /// sensor; every stage then sees the scene only. `None`: the format's sweeps hold none.
    const EGO_BOX: Option<([f64; 3], [f64; 3])> = None;
    /// The ego box of scene `scene` (tree index): [`Self::EGO_BOX`] unless the format records its
    /// vehicle per scene.
    fn ego_box(&self, _scene: usize) -> Option<([f64; 3], [f64; 3])> {
        Self::EGO_BOX
    }
    /// The recording vehicle of scene `scene`, where the format names it apart from its files.
    fn vehicle(&self, _scene: usize) -> Option<String> {
        None
    }
    /// The `image` port of a camera reading: by default its file, decoded.
    fn read_image(&self, image: &Reading) -> Result<Image> {
        read_camera_image(&image.file, image.calib.width, image.calib.height, &image.what)
    }
    /// The source digest of the `image` port: by default its file's.
    fn image_digest(&self, image: &Reading, files: &dyn FileDigests) -> Result<Option<Digest>> {
        image.file_digest(files)
    }
    /// The size the image's own header declares, for the calibration's check (`None`: not
    /// there, e.g. a LiDAR-only download); by default its file's header.
    fn image_header_size(&self, image: &Reading) -> Result<Option<(u32, u32)>> {
        match image_dimensions(&image.file) {
            Ok(dims) => Ok(Some(dims)),
            Err(e) if is_not_found(&e) => Ok(None),
            Err(e) => Err(e.context(image.what.clone())),
        }
    }
    /// The format's id of frame `frame` of scene `scene` (tree indices): by default its LiDAR
    /// reading's token.
    fn frame_token(&self, scene: usize, frame: usize) -> Option<String> {
        self.tree().scenes.get(scene)?.frames.get(frame)?.lidar.as_ref().ok().map(|r| r.token.clone())
    }
    /// The dataset the format's scenes were recorded for (the `source_dataset` port), unless
    /// the format records it per scene ([`Self::source_dataset`]); empty: unknown.
    const SOURCE_DATASET: &'static str = "";
    /// The dataset scene `scene` (tree index) was recorded for: `nuscenes`, `ddad`,
    /// `wod-perception`, ... Outputs whose layout depends on the source (Occ3D-Waymo's) read it.
    fn source_dataset(&self, _scene: usize) -> String {
        Self::SOURCE_DATASET.to_string()
    }
    /// The map mask of scene `scene` (index in the tree), when the format has one.
    fn map_file(&self, _scene: usize) -> Option<&Path> {
        None
    }
    /// The `boxes` port of a frame (`item` is a frame of the tree or fails as one).
    fn boxes(&self, item: &ItemKey) -> Result<Boxes3D>;
    /// The `camera_boxes` port: the boxes at the camera image's own time. By default the frame's
    /// boxes moved with their velocities over the time from the frame to the image (a format
    /// whose cameras fire with its LiDAR, like DDAD, moves them by milliseconds).
    fn camera_boxes(&self, item: &ItemKey) -> Result<Boxes3D> {
        let frame = self.boxes(&item.prefix(2))?;
        let t = self.tree().reading("image", item)?.pose.timestamp_us;
        let s = (t - frame.timestamp_us) as f64 * 1e-6;
        let boxes = frame.boxes.into_iter().map(|b| Box3D { center: b.advanced(s), ..b }).collect();
        Ok(Boxes3D { timestamp_us: t, boxes })
    }
}

/// A format reader as the runtime's dataset.
pub struct Surround<R>(pub R);

/// `cloud` (in the sensor frame) without the points that lie inside `ego` (min and max corners
/// in the ego frame; `sensor_to_ego` places the sensor), every column kept in step.
pub fn without_ego_returns(cloud: PointCloud, sensor_to_ego: &Se3, ego: ([f64; 3], [f64; 3])) -> PointCloud {
    let keep: Vec<bool> = cloud
        .points
        .iter()
        .map(|p| {
            let e = sensor_to_ego.apply(glam::DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64));
            !dist4d_types::geometry::ego_box::contains(&ego, e)
        })
        .collect();
    if keep.iter().all(|&k| k) {
        return cloud;
    }
    let pick = |k: usize| keep[k];
    PointCloud {
        points: cloud.points.iter().enumerate().filter(|(k, _)| pick(*k)).map(|(_, p)| *p).collect(),
        labels: cloud.labels.iter().enumerate().filter(|(k, _)| pick(*k)).map(|(_, l)| *l).collect(),
        rgb: cloud.rgb.iter().enumerate().filter(|(k, _)| pick(*k)).map(|(_, c)| *c).collect(),
    }
}

impl<R: SurroundReader> ItemSpace for Surround<R> {
    fn count(&self, prefix: &ItemKey) -> u32 {
        let tree = self.0.tree();
        match prefix.depth {
            0 => tree.scenes.len() as u32,
            1 => tree.scenes.get(prefix.idx[0] as usize).map_or(0, |s| s.frames.len()) as u32,
            2 => tree.cameras.len() as u32,
            _ => 0,
        }
    }

    /// Scene name, zero-padded frame index, camera name.
    fn label(&self, item: &ItemKey) -> String {
        let tree = self.0.tree();
        let i = item.idx[item.depth as usize - 1] as usize;
        match item.depth {
            1 => tree.scenes.get(i).map(|s| s.name.clone()).unwrap_or_else(|| format!("scene{i}")),
            2 => format!("{i:03}"),
            _ => tree.cameras.get(i).cloned().unwrap_or_else(|| format!("camera{i}")),
        }
    }
}

impl<R: SurroundReader> Dataset for Surround<R> {
    fn source_digest(&self, port: &str, item: &ItemKey, files: &dyn FileDigests) -> Result<Option<Digest>> {
        let tree = self.0.tree();
        Ok(match port {
            "lidar" => {
                let (_, frame) = tree.scene_frame(item)?;
                let files_digest = self.0.lidar_digest(tree.reading(port, item)?, &frame.extra, files)?;
                // The port drops the ego box's returns: the box is part of what it gives.
                match (files_digest, self.0.ego_box(item.idx[0] as usize)) {
                    (Some(d), Some((lo, hi))) => {
                        let mut b = DigestBuilder::new("lidar without the ego box");
                        b.digest(&d);
                        for v in lo.iter().chain(&hi) {
                            b.u64(v.to_bits());
                        }
                        Some(b.finish())
                    }
                    (d, _) => d,
                }
            }
            "image" => self.0.image_digest(tree.reading(port, item)?, files)?,
            "gt_depth" | "semantic" => {
                let r = tree.reading("image", item)?;
                sidecar_digest(&tree.sidecars, port, tree.camera(item), &r.file, files)?
            }
            "map" => match self.0.map_file(item.idx[0] as usize) {
                Some(path) => files.file_digest(path).with_context(|| format!("reading {}", path.display()))?,
                None => Some(Digest::of(&[])),
            },
            "synth_world" => {
                let mut b = DigestBuilder::new(port);
                b.str(&self.label(&item.prefix(1)));
                let path = tree.root.join(SYNTH_WORLD);
                if path.is_file() {
                    let Some(d) = files.file_digest(&path).with_context(|| format!("reading {}", path.display()))?
                    else {
                        return Ok(None);
                    };
                    b.digest(&d);
                }
                Some(b.finish())
            }
            // The metadata's values, not the file check `load_source` adds: planning stays free
            // of image reads.
            "lidar_calib" | "camera_calib" => Some(Digest::of(&tree.reading(port, item)?.calib.encode())),
            _ => Some(Digest::of(&self.load_source(port, item)?)),
        })
    }

    fn load_source(&self, port: &str, item: &ItemKey) -> Result<Vec<u8>> {
        let tree = self.0.tree();
        match port {
            "boxes" => return Ok(self.0.boxes(item)?.encode()),
            "camera_boxes" => return Ok(self.0.camera_boxes(item)?.encode()),
            "frame_token" => return Ok(self.token(item).unwrap_or_default().into_bytes()),
            "source_dataset" => return Ok(self.0.source_dataset(item.idx[0] as usize).into_bytes()),
            "map" => {
                return match self.0.map_file(item.idx[0] as usize) {
                    Some(path) => crate::files::read_input(path, "the map", crate::checks::MAX_SENSOR_FILE_BYTES),
                    None => Ok(Vec::new()),
                }
            }
            "synth_world" => {
                let path = tree.root.join(SYNTH_WORLD);
                if !path.is_file() {
                    return Ok(Vec::new());
                }
                let text = crate::files::read_input(&path, "the synthetic world", crate::checks::MAX_TABLE_FILE_BYTES)?;
                let synth: serde_json::Value =
                    serde_json::from_slice(&text).with_context(|| format!("{} is not JSON", path.display()))?;
                return Ok(serde_json::to_vec(
                    &serde_json::json!({ "scene": self.label(&item.prefix(1)), "synth": synth }),
                )?);
            }
            "image_info" => {
                let labels = ImageInfo {
                    scene: self.label(&item.prefix(1)),
                    frame: self.label(&item.prefix(2)),
                    camera: self.label(item),
                    ..ImageInfo::default()
                };
                // A missing image (a dropped frame) is an answer here, not an error: what indexes
                // the items (training clips) skips it instead of losing the whole scene.
                let info = match tree.reading("image", item) {
                    Err(e) => ImageInfo { missing: Some(format!("{e:#}")), ..labels },
                    Ok(r) => ImageInfo {
                        token: r.token.clone(),
                        file: r.bytes_at(&tree.root).0,
                        row: r.bytes_at(&tree.root).1,
                        timestamp_us: r.pose.timestamp_us,
                        width: r.calib.width,
                        height: r.calib.height,
                        intrinsics: r.calib.intrinsics,
                        camera_to_ego: r.calib.sensor_to_ego,
                        ego_to_world: r.pose.ego_to_world,
                        boxes: self.0.camera_boxes(item)?,
                        vehicle: self.0.vehicle(item.idx[0] as usize).unwrap_or_default(),
                        ..labels
                    },
                };
                return Ok(info.encode());
            }
            _ => {}
        }
        let r = tree.reading(port, item)?;
        Ok(match port {
            "lidar" => {
                let cloud = self.0.read_lidar(r, &tree.scene_frame(item)?.1.extra)?;
                crate::checks::lidar_points(&r.file, &r.what, &cloud.points).map_err(anyhow::Error::msg)?;
                match self.0.ego_box(item.idx[0] as usize) {
                    Some(ego) => without_ego_returns(cloud, &r.calib.sensor_to_ego, ego).encode(),
                    None => cloud.encode(),
                }
            }
            "image" => self.0.read_image(r)?.encode(),
            "gt_depth" => tree.sidecars.gt_depth(tree.camera(item), &r.file)?.encode(),
            "semantic" => tree.sidecars.semantic(tree.camera(item), &r.file)?.encode(),
            "lidar_calib" => r.calib.encode(),
            "camera_calib" => {
                // A stage that sizes its maps by the calibration (LiDAR projection) never decodes
                // the image: so the metadata's size is checked against the file's header here.
                // An image that is not there (a LiDAR-only download) leaves the metadata's size,
                // which is bounded when the dataset is opened.
                let dims = self.0.image_header_size(r)?;
                if let Some((w, h)) = dims.filter(|&d| d != (r.calib.width, r.calib.height)) {
                    bail!(
                        "{} is {w}x{h} but {} (fields width, height) says {}x{}",
                        r.file.display(),
                        r.what,
                        r.calib.width,
                        r.calib.height
                    );
                }
                r.calib.encode()
            }
            "lidar_pose" | "camera_pose" => r.pose.encode(),
            other => bail!("{} has no source port `{other}`", R::FORMAT),
        })
    }

    /// A frame: the format's frame token ([`SurroundReader::frame_token`]); a camera item: its
    /// image's token.
    fn token(&self, item: &ItemKey) -> Option<String> {
        match item.depth {
            2 => self.0.frame_token(item.idx[0] as usize, item.idx[1] as usize),
            3 => self.0.tree().reading("image", item).ok().map(|r| r.token.clone()),
            _ => None,
        }
    }

    /// A camera item: its image. A frame: its LiDAR sweep and its images, by camera. Readings
    /// that failed are left out (their items fail on their own account).
    fn source_record(&self, item: &ItemKey) -> Option<serde_json::Value> {
        let tree = self.0.tree();
        match item.depth {
            3 => tree.reading("image", item).ok().map(|r| r.record(&tree.root)),
            2 => {
                let (_, frame) = tree.scene_frame(item).ok()?;
                let cameras: serde_json::Map<String, serde_json::Value> = tree
                    .cameras
                    .iter()
                    .zip(&frame.cameras)
                    .filter_map(|(name, r)| Some((name.clone(), r.as_ref().ok()?.record(&tree.root))))
                    .collect();
                let mut record = serde_json::json!({ "cameras": cameras });
                if let Ok(lidar) = &frame.lidar {
                    record["lidar"] = lidar.record(&tree.root);
                }
                Some(record)
            }
            _ => None,
        }
    }
}

/// Digest of a sidecar port: its file's content digest, or a fixed "none" when there is no file.
/// Where a dataset written by `dist4d synth` keeps its world's config (dist4d-synth's
/// `GROUND_TRUTH_DIR/synth.json`).
const SYNTH_WORLD: &str = "groundtruth/synth.json";

fn sidecar_digest(
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

/// Whether an error is a file that does not exist.
fn is_not_found(e: &anyhow::Error) -> bool {
    e.chain().any(|c| c.downcast_ref::<std::io::Error>().is_some_and(|io| io.kind() == std::io::ErrorKind::NotFound))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn returns_inside_the_ego_box_are_dropped_with_their_labels_and_colours() {
        // The sensor 1.8 m up, 1 m ahead of the ego origin; the box the car's.
        let sensor_to_ego = Se3::from_yaw(0.0, glam::DVec3::new(1.0, 0.0, 1.8));
        let cloud = PointCloud {
            points: vec![
                [0.3, 0.2, 0.0, 1.0],   // the sensor's mount: ego (1.3, 0.2, 1.8)
                [10.0, 0.0, -1.7, 2.0], // the road ahead
                [0.0, -2.5, -1.0, 3.0], // beside the car
                [2.0, 0.0, -1.5, 4.0],  // the hood: ego (3.0, 0, 0.3)
            ],
            labels: vec![1, 2, 3, 4],
            rgb: vec![[1; 3], [2; 3], [3; 3], [4; 3]],
        };
        let kept = without_ego_returns(cloud.clone(), &sensor_to_ego, ([-1.0, -1.0, -1.0], [3.4, 1.0, 2.0]));
        assert_eq!(kept.points.iter().map(|p| p[3]).collect::<Vec<_>>(), [2.0, 3.0]);
        assert_eq!(kept.labels, [2, 3]);
        assert_eq!(kept.rgb, [[2; 3], [3; 3]]);
        // A box nothing falls in gives the cloud back.
        assert_eq!(without_ego_returns(cloud.clone(), &sensor_to_ego, ([50.0; 3], [60.0; 3])), cloud);
    }
}
