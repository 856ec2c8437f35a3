//! `TemporalBlend`: where the completion of frame t is far from every sample of its prompt, take
//! the depth a neighbouring frame knows better.
//!
//! The completion fills what the LiDAR never saw (tree crowns, facades above its top beam) by
//! spreading the prompt, and each frame spreads its own prompt: a crown completed at 20 m in one
//! frame comes out at 30 m in the next, which a video model learns as flicker (issue 42: 89% of
//! DGP's static pixels agreed within 10% from frame to frame, the target is 95%). The LiDAR of a
//! neighbouring frame often did reach that surface (the car moved towards it, or the scan lines
//! fell differently), so its curated depth there is near a sample where frame t's is not.
//!
//! For each pixel of frame t with a structure depth (not 0, not sky) whose support (distance to
//! the nearest prompt sample, px) is at least `min_support`, the pixel's point (at t's depth) is
//! projected into each neighbour s of the window. Where it lands on a structure pixel of s whose
//! support is at most `better` times t's, that pixel's point is brought back into t's camera, and
//! its depth there replaces t's when it is the best supported of the candidates. A neighbour
//! pixel nearer than `occluded` of the expected depth is something in front (not the same
//! surface) and is not used; so are pixels inside boxes moving faster than `min_speed` (at the
//! target image's time), whose points were elsewhere at the neighbour's time. The output support
//! is the chosen candidate's. Depth 0 (ego body, no depth) and sky stay as they are. The
//! neighbours' depths are their completions, not their blends: no frame waits for another's
//! blend, so frames still run in parallel.
//!
//! Backward lookup (t -> s at t's depth) rather than splatting s into t: the surfaces this is for
//! are far (20-80 m) and the car moves about a metre between frames, so a depth error moves the
//! landing pixel little, and every pixel of t gets a candidate without holes.

use dist4d_runtime::Made;
use crate::box_sum::box_sum;
use crate::camera::CameraView;
use crate::stage::Stage;
use anyhow::{anyhow, ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Boxes3D, Calibration, DepthMap, Pose};
use dist4d_types::geometry::BoxTest;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Pixels nearer than this (px) to a prompt sample keep their own depth.
    pub min_support: f64,
    /// A neighbour's depth is a candidate where its support is at most this times the pixel's.
    pub better: f64,
    /// A neighbour pixel nearer than this fraction of the expected depth is an occluder.
    pub occluded: f64,
    /// A neighbour's depth differing from the pixel's by more than this (relative) is another
    /// surface seen past an edge, not the same one known better.
    pub max_change: f64,
    /// A neighbour is used for a pixel only while the camera moved by at most this fraction of
    /// the pixel's depth between the two frames (radians of parallax): the lookup at t's own
    /// depth lands on the same surface only when a depth error moves it little. 10 Hz frames
    /// (a metre apart) pass for structure beyond ~20 m, 2 Hz keyframes (~5 m apart) seldom.
    pub max_parallax: f64,
    /// Depths at or beyond this (m) are sky.
    pub max_depth: f64,
    /// Boxes faster than this (m/s) are moving: their pixels keep their own depth.
    pub min_speed: f64,
    /// The corrections are averaged over a box of this radius (px) before they are applied.
    pub smooth: usize,
    /// Moving boxes grow by this (m) on each side and on top.
    pub box_margin: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            min_support: 4.0,
            better: 0.8,
            occluded: 0.7,
            max_change: 1.0,
            max_parallax: 0.1,
            max_depth: 99.0,
            min_speed: 0.5,
            smooth: 8,
            box_margin: 0.3,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .within("min_support", self.min_support, 0.0, 1e6)
            .within("better", self.better, 0.0, 1.0)
            .within("occluded", self.occluded, 0.0, 1.0)
            .within("max_change", self.max_change, 0.0, 100.0)
            .within("max_parallax", self.max_parallax, 0.0, 10.0)
            .above("max_depth", self.max_depth, 0.0, 1e6)
            .within("min_speed", self.min_speed, 0.0, 1000.0)
            .count("smooth", self.smooth as u64, 0, 256)
            .within("box_margin", self.box_margin, 0.0, 100.0)
            .done()
    }
}

/// One frame of the window: its completion, that completion's support, where it was taken.
pub struct Frame<'a> {
    pub depth: &'a DepthMap,
    pub support: &'a DepthMap,
    pub calib: &'a Calibration,
    pub pose: &'a Pose,
}

/// Frame `target`'s depth and support with its weakly supported pixels taken from `others`
/// where they know the surface better (see the module doc).
pub fn blend(p: &Params, target: &Frame, others: &[Frame], moving: &Boxes3D) -> Result<(DepthMap, DepthMap)> {
    for f in std::iter::once(target).chain(others) {
        let size = (f.calib.width, f.calib.height);
        ensure!(
            (f.depth.width, f.depth.height) == size && (f.support.width, f.support.height) == size,
            "a depth map is {}x{} and its support {}x{}, but the camera calibration says {}x{}",
            f.depth.width,
            f.depth.height,
            f.support.width,
            f.support.height,
            size.0,
            size.1
        );
    }
    let w = target.depth.width as usize;
    let own = CameraView::new(target.calib, target.pose, target.calib, target.pose)?;
    let views = others
        .iter()
        .map(|o| {
            let into = CameraView::new(target.calib, target.pose, o.calib, o.pose)?;
            let back = CameraView::new(o.calib, o.pose, target.calib, target.pose)?;
            let from = CameraView::new(o.calib, o.pose, o.calib, o.pose)?;
            // How far the camera moved between the frames (m).
            let baseline = into.cam_from_cloud.translation.length();
            Ok((o, into, back, from, baseline))
        })
        .collect::<Result<Vec<_>>>()?;
    let cam_from_world = target.pose.ego_to_world.then_from(&target.calib.sensor_to_ego).inverse();
    let boxes: Vec<BoxTest> = moving
        .boxes
        .iter()
        .filter(|b| b.speed() > p.min_speed)
        .map(|b| b.test(&cam_from_world, p.box_margin, 0.1))
        .collect();
    let structure = |z: f32| z > 0.0 && (z as f64) < p.max_depth;
    let n = target.depth.data.len();
    // Per pixel with a candidate: ln(candidate / own depth), and the candidate's support.
    let mut log_ratio = vec![0.0f64; n];
    let mut cand_support = vec![0.0f64; n];
    let mut has = vec![0.0f64; n];
    // Pixels of moving objects: they keep their depth, even where static neighbours are corrected.
    let mut moving = vec![false; n];
    for (i, &z) in target.depth.data.iter().enumerate() {
        let s = target.support.data[i] as f64;
        if !structure(z) || s < p.min_support {
            continue;
        }
        let (u, v) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        let c = own.unproject(u, v, z as f64);
        if boxes.iter().any(|b| b.contains(c)) {
            moving[i] = true;
            continue;
        }
        let mut best: Option<(f64, f32)> = None;
        for (o, into, back, from, baseline) in &views {
            if *baseline > p.max_parallax * z as f64 {
                continue;
            }
            let q = into.to_camera(c);
            if q.z <= 0.0 {
                continue;
            }
            let (ou, ov) = into.pixel(q);
            let (ow, oh) = (o.depth.width as usize, o.depth.height as usize);
            if !(ou >= 0.0 && ov >= 0.0 && ou < ow as f64 && ov < oh as f64) {
                continue;
            }
            let j = ov as usize * ow + ou as usize;
            let (found, found_support) = (o.depth.data[j], o.support.data[j] as f64);
            if !structure(found) || (found as f64) < p.occluded * q.z || found_support > p.better * s {
                continue;
            }
            // The neighbour's own point at that pixel, in t's camera.
            let point = back.to_camera(from.unproject((j % ow) as f64 + 0.5, (j / ow) as f64 + 0.5, found as f64));
            if point.z <= 0.0 || (point.z - z as f64).abs() > p.max_change * z as f64 {
                continue;
            }
            if best.is_none_or(|(bs, _)| found_support < bs) {
                best = Some((found_support, point.z as f32));
            }
        }
        if let Some((s_best, z_best)) = best {
            log_ratio[i] = (z_best as f64 / z as f64).ln();
            cand_support[i] = s_best;
            has[i] = 1.0;
        }
    }
    // The corrections are applied smoothed (a box of `smooth` px): a per-pixel switch between
    // frames' depths cuts the frame's own smooth fill into patches with steps between them, and
    // lifting drops pixels at steps. Scaling the own depth by the neighbourhood's mean ratio keeps
    // the frame's own edges and moves its levels to the better supported ones.
    let h = target.depth.height as usize;
    let r = p.smooth;
    let (count, sum_ratio, sum_support) =
        (box_sum(&has, w, h, r), box_sum(&log_ratio, w, h, r), box_sum(&cand_support, w, h, r));
    // The box's own size (smaller at the image's edges).
    let area = box_sum(&vec![1.0; n], w, h, r);
    let mut depth = target.depth.clone();
    let mut support = target.support.clone();
    for i in 0..n {
        let (z, s) = (target.depth.data[i], target.support.data[i] as f64);
        if !structure(z) || s < p.min_support || count[i] == 0.0 || moving[i] {
            continue;
        }
        // How much of the neighbourhood had a candidate, and how far the pixel is into the
        // weakly supported region: both ramp the correction in.
        let weight = (count[i] / area[i]) * ((s - p.min_support) / p.min_support).clamp(0.0, 1.0);
        depth.data[i] = (z as f64 * (weight * sum_ratio[i] / count[i]).exp()) as f32;
        support.data[i] = (s + weight * (sum_support[i] / count[i] - s)) as f32;
    }
    Ok((depth, support))
}

crate::inputs! {
    pub struct Inputs {
        /// the completions of the window's frames: Window("complete.depth", frame, -1, 1)
        depths: Many<DepthMap>,
        /// their supports (same window): Window("complete.support", frame, -1, 1)
        supports: Many<DepthMap>,
        /// their camera calibrations (same window)
        calibs: Many<Calibration>,
        /// their ego poses (same window)
        poses: Many<Pose>,
        /// the boxes at the target image's time (dataset.camera_boxes): moving ones keep their depth
        boxes: One<Boxes3D>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the target frame's depth, weakly supported structure taken from better-supported neighbours
        depth: One<DepthMap>,
        /// its support (px to the nearest prompt sample of the frame the depth came from)
        support: One<DepthMap>,
    }
}

pub struct TemporalBlend(Params);

impl Stage for TemporalBlend {
    const KIND: &'static str = "TemporalBlend";
    // 2: corrections smoothed over a box instead of switched per pixel; 3: `max_parallax`.
    const VERSION: u32 = 3;
    const SUMMARY: &'static str =
        "Completions of a window of frames -> the target's, weakly supported pixels taken from neighbours that know them better";
    const GRAINS: &'static [&'static str] = &["camera"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["depths", "supports", "calibs", "poses"]];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(TemporalBlend(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        use crate::stage::at_position as at;
        let frame = |pos: i64| -> Result<Option<Frame>> {
            let depth = at(&i.depths, pos, "depths")?;
            if depth.data.is_empty() {
                return Ok(None);
            }
            let support = at(&i.supports, pos, "supports")?;
            Ok(Some(Frame { depth, support, calib: at(&i.calibs, pos, "calibs")?, pose: at(&i.poses, pos, "poses")? }))
        };
        let target = frame(0)?.ok_or_else(|| anyhow!("the target frame has no depth"))?;
        let mut others = Vec::new();
        for (pos, _) in i.depths.iter().filter(|(p, _)| *p != 0) {
            others.extend(frame(*pos)?);
        }
        let (depth, support) = blend(&self.0, &target, &others, &i.boxes)?;
        Ok(Outputs { depth, support }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::geometry::Se3;
    use glam::DVec3;

    /// A 60x40 camera looking along ego +y (left) from x = `x` at a wall `d(col, row)` away; the
    /// ego moves along +x, so the wall slides sideways between frames.
    fn frame(x: f64, d: impl Fn(usize, usize) -> f32, s: impl Fn(usize, usize) -> f32) -> (DepthMap, DepthMap, Calibration, Pose) {
        let (w, h) = (60u32, 40u32);
        let calib = Calibration {
            sensor_to_ego: Se3::from_wxyz_t(
                [std::f64::consts::FRAC_1_SQRT_2, -std::f64::consts::FRAC_1_SQRT_2, 0.0, 0.0],
                [0.0, 0.0, 1.5],
            ),
            intrinsics: Some([[50.0, 0.0, 30.0], [0.0, 50.0, 20.0], [0.0, 0.0, 1.0]]),
            width: w,
            height: h,
        };
        let pose = Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::new(x, 0.0, 0.0)), timestamp_us: 0 };
        let map = |f: &dyn Fn(usize, usize) -> f32| DepthMap {
            width: w,
            height: h,
            data: (0..(w * h) as usize).map(|i| f(i % w as usize, i / w as usize)).collect(),
        };
        (map(&d), map(&s), calib, pose)
    }

    #[test]
    fn weakly_supported_pixels_take_the_depth_a_better_supported_neighbour_has() {
        let p = Params::default();
        // Frame t completed the wall at 12 m, far from its samples (support 30 px) in its upper
        // half; the next frame, 1 m on, has it at 10 m beside a sample (support 1 px).
        let (d0, s0, c0, p0) = frame(0.0, |_, r| if r < 20 { 12.0 } else { 10.0 }, |_, r| if r < 20 { 30.0 } else { 0.0 });
        let (d1, s1, c1, p1) = frame(1.0, |_, _| 10.0, |_, _| 1.0);
        let t = Frame { depth: &d0, support: &s0, calib: &c0, pose: &p0 };
        let n = Frame { depth: &d1, support: &s1, calib: &c1, pose: &p1 };
        let (depth, support) = blend(&p, &t, &[n], &Boxes3D::default()).unwrap();
        let at = |m: &DepthMap, c: usize, r: usize| m.data[r * 60 + c];
        // Upper half, where the point lands inside the neighbour and so do its neighbours: the
        // neighbour's depth and support.
        assert!((at(&depth, 20, 5) - 10.0).abs() < 0.01, "{}", at(&depth, 20, 5));
        assert!((at(&support, 20, 5) - 1.0).abs() < 1e-4, "{}", at(&support, 20, 5));
        // The columns on the side the car moves away from land outside the neighbour's view
        // (about 4 px at 12 m): the correction fades in over the smoothing box, no step.
        let edge: Vec<f32> = (0..14).map(|c| at(&depth, c, 5)).collect();
        assert!(edge[0] > 10.5 && edge[0] < 12.0, "{edge:?}");
        assert!(edge.windows(2).all(|p| p[1] <= p[0] && p[0] - p[1] < 0.3), "{edge:?}");
        assert!((edge[13] - 10.0).abs() < 0.01, "{edge:?}");
        // Supported pixels keep their own depth, whatever the neighbour says.
        assert_eq!(at(&depth, 20, 30), 10.0);
        assert_eq!(at(&support, 20, 30), 0.0);

        // A neighbour no better supported, a neighbour that sees sky or an occluder there, and a
        // moving box over the pixels: no change.
        for (nd, ns) in [(10.0, 28.0), (100.0, 1.0), (4.0, 1.0)] {
            let (d2, s2, c2, p2) = frame(1.0, |_, _| nd, |_, _| ns);
            let n = Frame { depth: &d2, support: &s2, calib: &c2, pose: &p2 };
            let (depth, _) = blend(&p, &t, &[n], &Boxes3D::default()).unwrap();
            assert!(depth.data == d0.data, "neighbour at {nd} m, support {ns}: the depth changed");
        }
        // A neighbour 3 m away sees a 12 m wall with 0.25 rad of parallax (> `max_parallax`):
        // t's own depth error would move the lookup onto another surface, so it is not used.
        let (d3, s3, c3, p3) = frame(3.0, |_, _| 10.0, |_, _| 1.0);
        let far = Frame { depth: &d3, support: &s3, calib: &c3, pose: &p3 };
        assert!(blend(&p, &t, &[far], &Boxes3D::default()).unwrap().0.data == d0.data, "a wide baseline is not used");
        let moving = Boxes3D {
            timestamp_us: 0,
            boxes: vec![dist4d_types::artifact::Box3D {
                center: [0.0, 11.0, 3.0],
                size: [30.0, 4.0, 6.0],
                rotation: [1.0, 0.0, 0.0, 0.0],
                velocity: [5.0, 0.0, 0.0],
                instance: "car".into(),
                category: "vehicle.car".into(),
                attributes: vec![],
                num_lidar_pts: 0,
                interpolated: false,
                extrapolated: false,
            }],
        };
        let (depth, _) = blend(&p, &t, &[Frame { depth: &d1, support: &s1, calib: &c1, pose: &p1 }], &moving).unwrap();
        assert_eq!(at(&depth, 20, 5), 12.0, "a moving object's pixels keep their depth");
    }
}
