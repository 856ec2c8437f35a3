//! `LabelPoints`: a LiDAR sweep's points labelled from camera segmentations, for occupancy on
//! data without LiDAR labels (DGP, nuScenes without lidarseg, the 20 Hz sweeps between labelled
//! keyframes). Each camera image of the frame goes to the segmenter worker (op `segment`, the
//! one `EstimateSky` can use: Cityscapes ids per pixel), and each point takes the class of the
//! pixel it projects to, mapped to Occ3D by [`super::classes::FROM_CITYSCAPES`]:
//!
//! - the projection goes LiDAR -> ego at the sweep's time -> world -> ego at the image's time ->
//!   camera, so the ego's motion between the two is undone;
//! - of the cameras that see a point, the one nearest the sweep in time labels it;
//! - **occlusion**: the camera sits elsewhere than the LiDAR, so it may not see what the LiDAR
//!   hit (the road behind a car's roof). A point is occluded in a camera when another point of
//!   the sweep projects within `occlusion_px` pixels of it (a cell grid of that size, the 3 x 3
//!   cells around) and is nearer by more than `occlusion_margin` metres plus
//!   `occlusion_ratio` of its depth; an occluded point takes nothing from that camera;
//! - **edges**: a pixel whose neighbours within `edge_px` pixels are of another class gives
//!   nothing (a point on the rim of a pole may project onto the wall behind it);
//! - sky, void and ids Occ3D has no class for give nothing.
//!
//! A point no camera labels gets [`super::classes::UNLABELLED`]; `AggregateScene` then gives it
//! a neighbour's label or the geometry rule. Without a worker the stage outputs an empty cloud
//! (not "nothing to make", which would leave `AggregateScene`'s `All(..)` list empty and pass it
//! over), and `AggregateScene` uses what the dataset has.

use dist4d_runtime::Made;
use super::classes::{of_cityscapes, UNLABELLED};
use crate::model_worker::{npy_rgb8, read_npy_gray8, Exchange, ModelWorker, WorkerSpec};
use crate::stage::Stage;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Calibration, Image, ImageInfo, PointCloud, Pose};
use dist4d_types::geometry::Se3;
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The segmenter (op `segment`); none = nothing to make (docs/workers.md).
    pub worker: Option<WorkerSpec>,
    /// A pixel labels a point only when every pixel within this many pixels has its class.
    pub edge_px: u32,
    /// The occlusion test's neighbourhood (pixels).
    pub occlusion_px: u32,
    /// A point nearer by more than this (m) plus `occlusion_ratio` x depth occludes.
    pub occlusion_margin: f64,
    pub occlusion_ratio: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { worker: None, edge_px: 1, occlusion_px: 6, occlusion_margin: 0.3, occlusion_ratio: 0.05 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        if let Some(w) = &self.worker {
            w.check(&mut c);
        }
        c.count("edge_px", self.edge_px as u64, 0, 64)
            .count("occlusion_px", self.occlusion_px as u64, 1, 256)
            .within("occlusion_margin", self.occlusion_margin, 0.0, 100.0)
            .within("occlusion_ratio", self.occlusion_ratio, 0.0, 10.0);
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the frame's sweep
        sweep: One<PointCloud>,
        /// its LiDAR calibration
        lidar_calib: One<Calibration>,
        /// the ego pose at the sweep
        lidar_pose: One<Pose>,
        /// every camera's image of the frame (`Gather("dataset.image", camera)`)
        images: Many<Image>,
        /// what each image is: file, timestamp, intrinsics, camera -> ego, ego -> world (`Gather("dataset.image_info", camera)`)
        infos: Many<ImageInfo>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the sweep's points; labels = Occ3D classes, 254 = no camera labelled the point; empty without a worker
        sweep: One<PointCloud>,
    }
}

pub struct LabelPoints(Params, ModelWorker);

impl Stage for LabelPoints {
    const KIND: &'static str = "LabelPoints";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "a sweep's points labelled by the segmented camera images they project to (occlusion-checked), Occ3D classes";
    const GRAINS: &'static [&'static str] = &["frame"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["images", "infos"]];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        let worker = ModelWorker::new(params.worker.clone());
        Ok(LabelPoints(params, worker))
    }
    fn identity(&self) -> Result<Option<String>> {
        self.1.identity()
    }
    /// Without a worker the images are never read: not loading them saves decoding every
    /// camera's JPEG of every frame (0.28 s of a nuScenes keyframe's 1 s).
    fn unused_inputs(params: &Params) -> Vec<&'static str> {
        if params.worker.is_some() {
            Vec::new()
        } else {
            vec!["images", "infos"]
        }
    }
    fn resource(&self) -> Option<dist4d_runtime::Resource> {
        self.1.resource()
    }

    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        if !self.1.is_set() {
            return Ok(Outputs { sweep: PointCloud::default() }.into());
        }
        ensure!(
            i.images.len() == i.infos.len(),
            "`images` and `infos` hold {} and {} items: wire both with Gather(.., camera)",
            i.images.len(),
            i.infos.len()
        );
        let mut views = Vec::new();
        for ((_, image), (_, info)) in i.images.iter().zip(&i.infos) {
            if info.missing.is_some() || image.width == 0 {
                continue;
            }
            let (w, h) = (image.width, image.height);
            let ex = Exchange::new()?;
            let inputs = vec![ex.put("image", "image.npy", &npy_rgb8(w, h, &image.rgb))?];
            let params = serde_json::json!({"file": info.file, "camera": info.camera, "timestamp_us": info.timestamp_us});
            let outputs = self.1.call(ctx, &ex, "segment", inputs, params)?;
            let ids = read_npy_gray8(&ex.get(&outputs, "semantic")?, w, h)
                .map_err(|e| e.context(format!("the worker's `semantic` for {} (uint8 Cityscapes ids)", info.file)))?;
            let k = info.intrinsics.with_context(|| format!("{}: the image has no intrinsics", info.file))?;
            views.push(View {
                camera_from_world: info.ego_to_world.then_from(&info.camera_to_ego).inverse(),
                k,
                width: w,
                height: h,
                timestamp_us: info.timestamp_us,
                ids,
            });
        }
        let labels = label_points(&self.0, &i.sweep, &i.lidar_calib, &i.lidar_pose, &views);
        Ok(Outputs { sweep: PointCloud { labels, ..i.sweep } }.into())
    }
}

/// A segmented camera image and where it was taken.
pub struct View {
    pub camera_from_world: Se3,
    pub k: [[f64; 3]; 3],
    pub width: u32,
    pub height: u32,
    pub timestamp_us: i64,
    /// Cityscapes ids, row-major.
    pub ids: Vec<u8>,
}

/// The Occ3D class of each point of `sweep` (module doc), [`UNLABELLED`] where no view gives one.
pub fn label_points(p: &Params, sweep: &PointCloud, calib: &Calibration, pose: &Pose, views: &[View]) -> Vec<u8> {
    let n = sweep.points.len();
    let world: Vec<DVec3> = sweep
        .points
        .iter()
        .map(|q| pose.ego_to_world.apply(calib.sensor_to_ego.apply(DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64))))
        .collect();
    let mut labels = vec![UNLABELLED; n];
    let mut best_dt = vec![i64::MAX; n];
    let cell = p.occlusion_px.max(1) as f64;
    let edge = p.edge_px as i64;
    for v in views {
        let (w, h) = (v.width as i64, v.height as i64);
        // Pixel coordinates and depth of each point in this camera.
        let proj: Vec<Option<(f64, f64, f64)>> = world
            .iter()
            .map(|&x| {
                let c = v.camera_from_world.apply(x);
                if c.z <= 0.1 {
                    return None;
                }
                let u = v.k[0][0] * c.x / c.z + v.k[0][1] * c.y / c.z + v.k[0][2];
                let r = v.k[1][1] * c.y / c.z + v.k[1][2];
                (u >= 0.0 && r >= 0.0 && u < w as f64 && r < h as f64).then_some((u, r, c.z))
            })
            .collect();
        // The nearest depth per cell of `occlusion_px` pixels.
        let (cw, ch) = ((w as f64 / cell).ceil() as usize + 1, (h as f64 / cell).ceil() as usize + 1);
        let mut nearest = vec![f64::INFINITY; cw * ch];
        for &(u, r, z) in proj.iter().flatten() {
            let c = (r / cell) as usize * cw + (u / cell) as usize;
            nearest[c] = nearest[c].min(z);
        }
        let dt = (v.timestamp_us - pose.timestamp_us).abs();
        for (k, pr) in proj.iter().enumerate() {
            let Some((u, r, z)) = *pr else { continue };
            if dt >= best_dt[k] {
                continue;
            }
            let (cx, cy) = ((u / cell) as usize, (r / cell) as usize);
            let limit = z - p.occlusion_margin - p.occlusion_ratio * z;
            let occluded = (cy.saturating_sub(1)..=(cy + 1).min(ch - 1))
                .any(|yy| (cx.saturating_sub(1)..=(cx + 1).min(cw - 1)).any(|xx| nearest[yy * cw + xx] < limit));
            if occluded {
                continue;
            }
            let (px, py) = (u as i64, r as i64);
            let id = v.ids[(py * w + px) as usize];
            let uniform = (py - edge..=py + edge).all(|yy| {
                (px - edge..=px + edge)
                    .all(|xx| xx < 0 || yy < 0 || xx >= w || yy >= h || v.ids[(yy * w + xx) as usize] == id)
            });
            let class = of_cityscapes(id);
            if uniform && class != UNLABELLED {
                labels[k] = class;
                best_dt[k] = dt;
            }
        }
    }
    labels
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera at the origin looking along world +x (z forward, x right = world -y, y down =
    /// world -z), 100 x 100 pixels, focal 50.
    fn view(ids: impl Fn(i64, i64) -> u8, timestamp_us: i64) -> View {
        let camera_to_world = Se3::from_wxyz_t([0.5, -0.5, 0.5, -0.5], [0.0, 0.0, 0.0]);
        View {
            camera_from_world: camera_to_world.inverse(),
            k: [[50.0, 0.0, 50.0], [0.0, 50.0, 50.0], [0.0, 0.0, 1.0]],
            width: 100,
            height: 100,
            timestamp_us,
            ids: (0..100).flat_map(|y| (0..100).map(move |x| (x, y))).map(|(x, y)| ids(x, y)).collect(),
        }
    }

    fn identity() -> (Calibration, Pose) {
        (
            Calibration { sensor_to_ego: Se3::default(), intrinsics: None, width: 0, height: 0 },
            Pose { ego_to_world: Se3::default(), timestamp_us: 0 },
        )
    }

    fn cloud(points: &[[f32; 3]]) -> PointCloud {
        PointCloud { points: points.iter().map(|q| [q[0], q[1], q[2], 0.0]).collect(), ..PointCloud::default() }
    }

    #[test]
    fn a_point_takes_its_pixels_class_unless_occluded_on_an_edge_or_sky() {
        // Left half of the image (world +y) road, right half terrain; a sky band at the top.
        let ids = |x: i64, y: i64| if y < 10 { 23 } else if x < 50 { 7 } else { 22 };
        let (calib, pose) = identity();
        let sweep = cloud(&[
            [10.0, 2.0, -1.0],  // left: road
            [10.0, -2.0, -1.0], // right: terrain
            [20.0, 4.0, -2.0],  // left, behind the next point: occluded
            [10.0, 2.0, -1.0],  // the first point's twin (the occluder of the one before)
            [10.0, 0.0, -1.0],  // on the road / terrain edge (column 50)
            [10.0, 2.0, 8.5],   // in the sky band
            [-10.0, 0.0, 0.0],  // behind the camera
        ]);
        let labels = label_points(&Params::default(), &sweep, &calib, &pose, &[view(ids, 0)]);
        assert_eq!(labels, vec![11, 14, UNLABELLED, 11, UNLABELLED, UNLABELLED, UNLABELLED]);
        // Without the occlusion test the hidden point takes the road of the pixel it lands on.
        let far = Params { occlusion_margin: 1e3, ..Params::default() };
        assert_eq!(label_points(&far, &sweep, &calib, &pose, &[view(ids, 0)])[2], 11);
    }

    #[test]
    fn the_camera_nearest_in_time_labels_a_point_and_ego_motion_is_undone() {
        let (calib, pose) = identity();
        let sweep = cloud(&[[10.0, 0.0, -1.0]]);
        let sidewalk = view(|_, _| 8, 40_000);
        let road = view(|_, _| 7, -10_000);
        assert_eq!(label_points(&Params::default(), &sweep, &calib, &pose, &[sidewalk, road])[0], 11);
        // At the sweep the ego is 5 m along world x, the camera at 8 m: the point 10 m ahead of
        // the LiDAR is 7 m ahead of the camera, in the building's rows (< 60). Read in the wrong
        // frame (the point at world x = 10) it would be 2 m ahead, in the car's rows.
        let moved = Pose { ego_to_world: Se3::from_wxyz_t([1.0, 0.0, 0.0, 0.0], [5.0, 0.0, 0.0]), timestamp_us: 0 };
        let mut v = view(|_, y| if y >= 60 { 26 } else { 11 }, 0);
        v.camera_from_world = Se3::from_wxyz_t([0.5, -0.5, 0.5, -0.5], [8.0, 0.0, 0.0]).inverse();
        // From (8, 0, 0), the point at world (15, 0, -1) is 7 m ahead, 1 m down: row 50 + 50/7 = 57.
        assert_eq!(label_points(&Params::default(), &cloud(&[[10.0, 0.0, -1.0]]), &calib, &moved, &[v])[0], 15);
    }
}
