//! `StaticMvsPoints`: multi-view-stereo depth -> the static points it adds above the LiDAR.
//!
//! DiST-4D (supp. A) uses MVS only for what LiDAR cannot give: static structure above the ego
//! LiDAR. Each MVS pixel with depth (and confidence at least `min_confidence`) is back-projected
//! into the target frame's LiDAR frame, then dropped when it is
//! - inside a box of the target frame that is moving (attribute or speed above `moving_speed`;
//!   grown by `box_margin`): moving objects break the multi-view constraint;
//! - sky, when a sky mask is wired (`EstimateSky`, which follows the dataset's segmentation when
//!   it has one);
//! - not more than `min_height` above the LiDAR (z in the LiDAR frame): "we only keep MVS points
//!   above the ego LiDAR", where LiDAR has no returns;
//! - without support: fewer than `min_support` confident neighbours agree with its depth (see
//!   [`supported`]).
//!
//! The rest is downsampled on a `voxel` grid, one mean point per occupied voxel (Open3D's
//! `voxel_down_sample`: voxels anchored at the cloud's minimum corner less half a voxel), in voxel
//! order so the output does not depend on thread count.

use dist4d_runtime::Made;
use crate::camera::CameraView;
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_types::artifact::{Boxes3D, Calibration, DepthMap, Mask, PointCloud, Pose};
use dist4d_types::geometry::BoxTest;
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Pixels with a lower MVS confidence (1 - best / second-best aggregated cost) are not used.
    pub min_confidence: f32,
    /// A box is dynamic when its attributes say moving or its speed exceeds this (m/s).
    pub moving_speed: f64,
    /// Dynamic boxes grow by this much (m) on each side and on top.
    pub box_margin: f64,
    /// Points must be higher than this above the LiDAR origin (m, LiDAR z).
    pub min_height: f64,
    /// Voxel edge (m) of the downsampling; 0 keeps every point.
    pub voxel: f64,
    /// A pixel needs at least `min_support` confident neighbours within `support_radius`
    /// (working-resolution px, square window) whose depth is within `support_tolerance` of its own.
    pub min_support: u32,
    pub support_radius: u32,
    pub support_tolerance: f32,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            min_confidence: 0.4,
            moving_speed: 0.5,
            box_margin: 0.2,
            min_height: 0.0,
            voxel: 0.1,
            min_support: 8,
            support_radius: 2,
            support_tolerance: 0.03,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        // Confidences lie in [0, 1]; a minimum above 1 is the way to keep no MVS point at all.
        let min_confidence = self.min_confidence;
        c.check(min_confidence.is_finite() && min_confidence >= 0.0, "min_confidence", || {
            format!("must be a number >= 0 (above 1 keeps no pixel), found {min_confidence}")
        })
        .within("moving_speed", self.moving_speed, 0.0, 1000.0)
        .within("box_margin", self.box_margin, 0.0, 100.0)
        .within("min_height", self.min_height, -100.0, 100.0)
        .within("voxel", self.voxel, 0.0, 100.0)
        // Each pixel scans its (2r+1)^2 window.
        .count("support_radius", self.support_radius as u64, 0, 32)
        .within("support_tolerance", self.support_tolerance as f64, 0.0, 1.0);
        let neighbours = (2 * self.support_radius as u64 + 1).pow(2) - 1;
        if self.support_radius <= 32 && self.min_support as u64 > neighbours {
            c.push(ParamProblem {
                field: "min_support",
                index: None,
                other: Some("support_radius"),
                message: format!(
                    "can never be met: a window of radius {} holds {neighbours} neighbours, found {}",
                    self.support_radius, self.min_support
                ),
            });
        }
        c.done()
    }
}

/// Mean point per occupied voxel of edge `voxel`, with Open3D's anchoring; in voxel order.
/// Intensity is averaged like the coordinates; labels are dropped.
pub fn voxel_mean(points: &[[f32; 4]], voxel: f64) -> Vec<[f32; 4]> {
    if points.is_empty() || voxel <= 0.0 {
        return points.to_vec();
    }
    let mut min = DVec3::splat(f64::INFINITY);
    for p in points {
        min = min.min(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64));
    }
    let origin = min - DVec3::splat(voxel * 0.5);
    let mut keyed: Vec<([i64; 3], u32)> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let r = (DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) - origin) / voxel;
            ([r.x.floor() as i64, r.y.floor() as i64, r.z.floor() as i64], i as u32)
        })
        .collect();
    keyed.sort_unstable();
    let mut out = Vec::new();
    let mut i = 0;
    while i < keyed.len() {
        let mut j = i;
        let mut sum = [0f64; 4];
        while j < keyed.len() && keyed[j].0 == keyed[i].0 {
            let p = points[keyed[j].1 as usize];
            for k in 0..4 {
                sum[k] += p[k] as f64;
            }
            j += 1;
        }
        let n = (j - i) as f64;
        out.push([(sum[0] / n) as f32, (sum[1] / n) as f32, (sum[2] / n) as f32, (sum[3] / n) as f32]);
        i = j;
    }
    out
}

/// Which depths of `depth` (0 = none) at least `min_support` other depths within `radius` (square
/// window) agree with, within `tolerance` relative. A wrong MVS depth is mostly a lone one: on the
/// synthetic scene 6-25% of the pixels with no agreeing neighbour are off by more than 25%, at
/// most 0.6% of those with 8 or more out of 24. One such point above the LiDAR is carried up a
/// whole column by the completion.
pub fn supported(depth: &[f32], w: usize, h: usize, radius: usize, tolerance: f32, min_support: u32) -> Vec<bool> {
    let mut out = vec![false; w * h];
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(radius), (y + radius + 1).min(h));
        for x in 0..w {
            let z = depth[y * w + x];
            if z <= 0.0 {
                continue;
            }
            let (x0, x1) = (x.saturating_sub(radius), (x + radius + 1).min(w));
            let mut agree = 0u32;
            for yy in y0..y1 {
                for &n in &depth[yy * w + x0..yy * w + x1] {
                    agree += (n > 0.0 && (n - z).abs() <= tolerance * z) as u32;
                }
            }
            // The pixel agrees with itself.
            out[y * w + x] = agree > min_support;
        }
    }
    out
}

/// The inputs of [`static_points`].
pub struct MvsInputs<'a> {
    pub depth: &'a DepthMap,
    pub confidence: &'a DepthMap,
    /// Sky pixels at full image size, if known.
    pub sky: Option<&'a Mask>,
    /// Target LiDAR frame -> camera (the camera at full image size).
    pub view: &'a CameraView,
    /// World -> target LiDAR frame.
    pub cloud_from_world: dist4d_types::geometry::Se3,
    pub boxes: &'a Boxes3D,
}

/// The static MVS points above the LiDAR, in the target LiDAR frame.
pub fn static_points(params: &Params, m: &MvsInputs) -> Result<PointCloud> {
    let (w, h) = (m.depth.width as usize, m.depth.height as usize);
    ensure!(
        (m.confidence.width, m.confidence.height) == (m.depth.width, m.depth.height),
        "confidence is {}x{} but depth is {w}x{h}",
        m.confidence.width,
        m.confidence.height
    );
    let (iw, ih) = (m.view.width as usize, m.view.height as usize);
    if w == 0 || h == 0 {
        return Ok(PointCloud::default());
    }
    ensure!(iw > 0 && ih > 0, "the camera calibration has no image size but the MVS depth is {w}x{h}");
    let sky: Vec<bool> = match m.sky {
        Some(s) => {
            ensure!(
                (s.width as usize, s.height as usize) == (iw, ih),
                "the sky mask is {}x{} but the camera calibration says {iw}x{ih}",
                s.width,
                s.height
            );
            s.data.iter().map(|&v| v != 0).collect()
        }
        None => vec![false; iw * ih],
    };
    let boxes: Vec<BoxTest> = m
        .boxes
        .boxes
        .iter()
        .filter(|b| b.is_moving(params.moving_speed))
        .map(|b| b.test(&m.cloud_from_world, params.box_margin, 0.0))
        .collect();
    // Depth pixels are 1/downscale of image pixels.
    let (sx, sy) = (iw as f64 / w.max(1) as f64, ih as f64 / h.max(1) as f64);
    let cloud_from_cam = m.view.cloud_from_cam();
    let confident: Vec<f32> = m
        .depth
        .data
        .iter()
        .zip(&m.confidence.data)
        .map(|(&z, &c)| if z > 0.0 && z.is_finite() && c >= params.min_confidence { z } else { 0.0 })
        .collect();
    let supported =
        supported(&confident, w, h, params.support_radius as usize, params.support_tolerance, params.min_support);
    let mut kept = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let z = confident[i];
            if !supported[i] {
                continue;
            }
            let (u, v) = ((x as f64 + 0.5) * sx, (y as f64 + 0.5) * sy);
            if sky[(v as usize).min(ih - 1) * iw + (u as usize).min(iw - 1)] {
                continue;
            }
            let p = cloud_from_cam.apply(m.view.unproject(u, v, z as f64));
            if p.z <= params.min_height || boxes.iter().any(|b| b.contains(p)) {
                continue;
            }
            kept.push([p.x as f32, p.y as f32, p.z as f32, 0.0]);
        }
    }
    Ok(PointCloud { points: voxel_mean(&kept, params.voxel), labels: Vec::new(), rgb: Vec::new() })
}

crate::inputs! {
    pub struct Inputs {
        /// MultiViewStereo depth (any size; pixels scale to the image)
        depth: One<DepthMap>,
        /// MultiViewStereo confidence (same size)
        confidence: One<DepthMap>,
        /// the sensor of the output frame (the target frame's LiDAR)
        cloud_calib: One<Calibration>,
        /// ego pose of that sensor's frame
        cloud_pose: One<Pose>,
        /// camera mounting and intrinsics
        camera_calib: One<Calibration>,
        /// ego pose at the camera time
        camera_pose: One<Pose>,
        /// the target frame's boxes
        boxes: One<Boxes3D>,
        /// sky pixels (EstimateSky); MVS depth there is dropped
        sky: Optional<Mask>,
        /// the ego vehicle's body (EgoMask.mask, image size); MVS depth there is dropped (a body
        /// fixed in the camera matches as if at infinity)
        ego: Optional<Mask>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// static MVS points in the target LiDAR frame
        points: One<PointCloud>,
    }
}

pub struct StaticMvsPoints(Params);

impl Stage for StaticMvsPoints {
    const KIND: &'static str = "StaticMvsPoints";
    const VERSION: u32 = 4;
    const SUMMARY: &'static str = "MVS depth -> static points above the LiDAR (no moving boxes, no sky), voxel-downsampled";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(StaticMvsPoints(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let view = CameraView::new(&i.cloud_calib, &i.cloud_pose, &i.camera_calib, &i.camera_pose)?;
        let cloud_from_world = i.cloud_pose.ego_to_world.then_from(&i.cloud_calib.sensor_to_ego).inverse();
        // Both masks say "no MVS point here": one map of their union.
        let dropped = match (i.sky, i.ego.filter(|e| e.width > 0 && e.height > 0)) {
            (Some(sky), Some(ego)) if sky.width > 0 => {
                ensure!(
                    (sky.width, sky.height) == (ego.width, ego.height),
                    "the sky mask is {}x{} but the ego mask {}x{}",
                    sky.width,
                    sky.height,
                    ego.width,
                    ego.height
                );
                let data = sky.data.iter().zip(&ego.data).map(|(&s, &e)| s | e).collect();
                Some(Mask { data, ..sky })
            }
            (_, Some(ego)) => Some(ego),
            (sky, None) => sky,
        };
        let m = MvsInputs {
            depth: &i.depth,
            confidence: &i.confidence,
            sky: dropped.as_ref(),
            view: &view,
            cloud_from_world,
            boxes: &i.boxes,
        };
        Ok(Outputs { points: static_points(&self.0, &m)? }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::Box3D;
    use dist4d_types::geometry::Se3;

    #[test]
    fn voxel_mean_averages_each_voxel_with_open3d_anchoring() {
        // Anchored at min - v/2 = -0.05: 0.0 and 0.04 share voxel 0; 0.06 is in voxel 1.
        let pts = [[0.0, 0.0, 0.0, 1.0], [0.04, 0.0, 0.0, 3.0], [0.06, 0.0, 0.0, 5.0], [1.0, 1.0, 1.0, 0.0]];
        let out = voxel_mean(&pts, 0.1);
        assert_eq!(out.len(), 3);
        assert!((out[0][0] - 0.02).abs() < 1e-6 && out[0][3] == 2.0);
        assert_eq!(out[1], [0.06, 0.0, 0.0, 5.0]);
        assert_eq!(voxel_mean(&pts, 0.0).len(), 4);
    }

    #[test]
    fn lone_depths_lack_support_and_surfaces_have_it() {
        // A 6x6 patch at 20 m with one wrong pixel in it, and a lone pixel at 50 m elsewhere.
        let (w, h) = (12, 8);
        let mut d = vec![0f32; w * h];
        for y in 1..7 {
            for x in 1..7 {
                d[y * w + x] = 20.0 + 0.01 * x as f32;
            }
        }
        d[3 * w + 3] = 35.0;
        d[2 * w + 10] = 50.0;
        let ok = supported(&d, w, h, 2, 0.03, 8);
        assert!(!ok[3 * w + 3], "a wrong depth inside a surface");
        assert!(!ok[2 * w + 10], "a lone depth");
        assert!(ok[4 * w + 4] && ok[5 * w + 2], "inside the patch");
        // A corner of the patch sees 3x3 of it, 8 agreeing neighbours: just enough.
        assert!(ok[6 * w + 6]);
        assert!(!supported(&d, w, h, 2, 0.03, 9)[6 * w + 6]);
        assert!(ok.iter().zip(&d).all(|(o, z)| !o || *z > 0.0), "no support without depth");
    }

    /// A forward camera at the LiDAR's position; depth 20 m everywhere at 1/2 size.
    fn setup() -> (Calibration, Pose, Calibration, DepthMap) {
        let lidar = Calibration {
            sensor_to_ego: Se3::from_yaw(0.0, DVec3::new(0.0, 0.0, 1.8)),
            intrinsics: None,
            width: 0,
            height: 0,
        };
        let pose = Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::ZERO), timestamp_us: 0 };
        // Camera z = ego x, camera x = ego -y, camera y = ego -z.
        let cam = Calibration {
            sensor_to_ego: Se3::from_wxyz_t([0.5, -0.5, 0.5, -0.5], [0.0, 0.0, 1.8]),
            intrinsics: Some([[100.0, 0.0, 40.0], [0.0, 100.0, 30.0], [0.0, 0.0, 1.0]]),
            width: 80,
            height: 60,
        };
        let depth = DepthMap { width: 40, height: 30, data: vec![20.0; 1200] };
        (lidar, pose, cam, depth)
    }

    #[test]
    fn keeps_only_static_points_above_the_lidar_outside_sky() {
        let (lidar, pose, cam, depth) = setup();
        // Confident everywhere but in the left half of row 10 (below the default 0.4).
        let mut conf = DepthMap { width: 40, height: 30, data: vec![0.8; 1200] };
        conf.data[10 * 40..10 * 40 + 20].fill(0.3);
        let view = CameraView::new(&lidar, &pose, &cam, &pose).unwrap();
        let cloud_from_world = pose.ego_to_world.then_from(&lidar.sensor_to_ego).inverse();
        let car = |speed: f64| Box3D {
            center: [20.0, -5.0, 3.0],
            size: [4.0, 1.0, 6.0],
            rotation: [1.0, 0.0, 0.0, 0.0],
            velocity: [speed, 0.0, 0.0],
            instance: "a".into(),
            category: "vehicle.car".into(),
            attributes: vec![],
            num_lidar_pts: 0,
            interpolated: false,
            extrapolated: false,
        };
        let boxes = Boxes3D { timestamp_us: 0, boxes: vec![car(5.0)] };
        let mut sky = Mask { width: 80, height: 60, data: vec![0; 4800] };
        sky.data[..80 * 4].fill(1);
        let m = MvsInputs {
            depth: &depth,
            confidence: &conf,
            sky: Some(&sky),
            view: &view,
            cloud_from_world,
            boxes: &boxes,
        };
        let params = Params { voxel: 0.0, ..Params::default() };
        let out = static_points(&params, &m).unwrap();
        // Upper half of the image is above the LiDAR (z > 0): 15 rows, less the 2 sky rows,
        // less the moving box's pixels.
        assert!(!out.points.is_empty());
        for p in &out.points {
            assert!(p[2] > 0.0, "{p:?}");
            assert!(p[2] < 20.0 * 0.3 - 4.0 * 20.0 / 100.0 + 0.05, "sky rows must go: {p:?}");
            assert!(!(p[1] < -4.3 && p[1] > -5.7 && p[2] < 4.3), "inside the moving box: {p:?}");
        }
        let row_10_left = |c: &PointCloud| {
            c.points
                .iter()
                .filter(|p| {
                    (view.pixel(view.to_camera(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))).1 / 2.0) as usize
                        == 10
                        && p[1] > 0.0
                })
                .count()
        };
        assert_eq!(row_10_left(&out), 0, "low-confidence pixels are not used");
        let any_confidence = static_points(&Params { min_confidence: 0.0, ..params.clone() }, &m).unwrap();
        assert!(row_10_left(&any_confidence) > 0);
        let parked = Boxes3D { timestamp_us: 0, boxes: vec![car(0.0)] };
        let all = static_points(&params, &MvsInputs { boxes: &parked, ..m }).unwrap();
        assert!(all.points.len() > out.points.len(), "a parked car's points stay");
    }
}
