//! `EvalTemporal`: does the curated depth of one static scene agree with itself from frame to
//! frame?
//!
//! A depth map can score well against sparse LiDAR and still be useless for a temporal model:
//! a tree crown completed at 20 m in one frame and at 60 m in the next teaches a video model
//! flicker. Each pixel of the target frame t with a structure depth (not 0, the ego body or no
//! depth; not at or beyond `max_depth`, the sky) and outside every box moving faster than
//! `min_speed` at the image's time is lifted to the world and projected into each other frame s
//! of the window; where it lands inside s on a pixel with a structure depth, and that pixel is
//! not nearer than `occluded` of the expected depth (something in front of it in s: the two
//! frames do not see the same surface), the pair is *seen by both*, and it *agrees* when the
//! depths differ by at most `agree` (relative). Reported per frame offset: the share of agreeing
//! pixels among those seen by both. With a ground truth (the synthetic world's exact depth) the
//! same share is computed for it too, a ceiling the curated depth can be compared with (it
//! differs from 100% by sampling at pixel centres and object edges only).

use dist4d_runtime::Made;
use crate::camera::CameraView;
use crate::stage::Stage;
use anyhow::{anyhow, ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Boxes3D, Calibration, DepthMap, File, Pose};
use dist4d_types::geometry::BoxTest;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Two depths of one surface agree when they differ by at most this, relative.
    pub agree: f64,
    /// A pixel of frame s nearer than this fraction of the expected depth is an occluder: the
    /// pixel is not seen by both frames.
    pub occluded: f64,
    /// Depths at or beyond this (m) are sky, not structure.
    pub max_depth: f64,
    /// Boxes faster than this (m/s) are moving: their pixels are left out.
    pub min_speed: f64,
    /// Moving boxes grow by this (m) on each side and on top.
    pub box_margin: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { agree: 0.1, occluded: 0.7, max_depth: 99.0, min_speed: 0.5, box_margin: 0.3 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .within("agree", self.agree, 0.0, 10.0)
            .within("occluded", self.occluded, 0.0, 1.0)
            .above("max_depth", self.max_depth, 0.0, 1e6)
            .within("min_speed", self.min_speed, 0.0, 1000.0)
            .within("box_margin", self.box_margin, 0.0, 100.0)
            .done()
    }
}

/// One frame of the window.
pub struct Frame<'a> {
    pub depth: &'a DepthMap,
    pub calib: &'a Calibration,
    pub pose: &'a Pose,
}

/// Pixels seen by both frames, and of those the ones that agree.
#[derive(Serialize, Deserialize, Debug, Clone, Copy, Default, PartialEq)]
pub struct Agreement {
    pub seen_by_both: u64,
    pub agree: u64,
}

impl Agreement {
    pub fn add(&mut self, other: &Agreement) {
        self.seen_by_both += other.seen_by_both;
        self.agree += other.agree;
    }

    pub fn share(&self) -> Option<f64> {
        (self.seen_by_both > 0).then(|| self.agree as f64 / self.seen_by_both as f64)
    }
}

/// The agreement of `target`'s static structure with `other`'s (see the module doc).
pub fn agreement(p: &Params, target: &Frame, other: &Frame, moving: &Boxes3D) -> Result<Agreement> {
    let w = target.depth.width as usize;
    for f in [target, other] {
        ensure!(
            (f.depth.width, f.depth.height) == (f.calib.width, f.calib.height),
            "a depth map is {}x{} but its camera calibration says {}x{}",
            f.depth.width,
            f.depth.height,
            f.calib.width,
            f.calib.height
        );
    }
    let own = CameraView::new(target.calib, target.pose, target.calib, target.pose)?;
    let into_other = CameraView::new(target.calib, target.pose, other.calib, other.pose)?;
    let cam_from_world = target.pose.ego_to_world.then_from(&target.calib.sensor_to_ego).inverse();
    let boxes: Vec<BoxTest> = moving
        .boxes
        .iter()
        .filter(|b| b.speed() > p.min_speed)
        .map(|b| b.test(&cam_from_world, p.box_margin, 0.1))
        .collect();
    let structure = |z: f32| z > 0.0 && (z as f64) < p.max_depth;
    let (ow, oh) = (other.depth.width as usize, other.depth.height as usize);
    let mut a = Agreement::default();
    for (i, &z) in target.depth.data.iter().enumerate() {
        if !structure(z) {
            continue;
        }
        let c = own.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, z as f64);
        if boxes.iter().any(|b| b.contains(c)) {
            continue;
        }
        let q = into_other.to_camera(c);
        if q.z <= 0.0 {
            continue;
        }
        let (u, v) = into_other.pixel(q);
        if !(u >= 0.0 && v >= 0.0 && u < ow as f64 && v < oh as f64) {
            continue;
        }
        let found = other.depth.data[v as usize * ow + u as usize];
        if !structure(found) || (found as f64) < p.occluded * q.z {
            continue;
        }
        a.seen_by_both += 1;
        a.agree += (((found as f64) - q.z).abs() <= p.agree * q.z) as u64;
    }
    Ok(a)
}

/// The scores one task exports: per frame offset (`"-1"`, `"+1"`, ...), of the curated depth
/// and, when there is one, of the ground truth.
#[derive(Serialize, Deserialize, Debug, Clone, Default, PartialEq)]
pub struct TemporalScores {
    pub depth: BTreeMap<String, Agreement>,
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub gt: BTreeMap<String, Agreement>,
}

crate::inputs! {
    pub struct Inputs {
        /// the curated depth of the window's frames: Window("complete.depth", frame, -2, 2)
        depths: Many<DepthMap>,
        /// their camera calibrations (same window)
        calibs: Many<Calibration>,
        /// their ego poses (same window)
        poses: Many<Pose>,
        /// the boxes at the target image's time (dataset.camera_boxes): moving ones are left out
        boxes: One<Boxes3D>,
        /// a ground truth of the same frames (dataset.gt_depth, same window; empty maps = none)
        gts: OptionalMany<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// TemporalScores as JSON; `dist4d eval` tabulates them
        json: One<File>,
    }
}

pub struct EvalTemporal(Params);

impl Stage for EvalTemporal {
    const KIND: &'static str = "EvalTemporal";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "Depth of a window of frames -> share of static pixels seen by two frames whose depths agree";
    const GRAINS: &'static [&'static str] = &["camera"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["depths", "calibs", "poses"]];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EvalTemporal(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let at = |pos: i64| -> Result<(&Calibration, &Pose)> {
            let c = i.calibs.iter().find(|(p, _)| *p == pos).ok_or_else(|| anyhow!("no camera_calib at position {pos}"))?;
            let p = i.poses.iter().find(|(p, _)| *p == pos).ok_or_else(|| anyhow!("no camera_pose at position {pos}"))?;
            Ok((&c.1, &p.1))
        };
        let score = |maps: &[(i64, DepthMap)]| -> Result<BTreeMap<String, Agreement>> {
            let mut out = BTreeMap::new();
            let Some((_, target)) = maps.iter().find(|(p, _)| *p == 0) else { return Ok(out) };
            if target.data.is_empty() {
                return Ok(out);
            }
            let (calib, pose) = at(0)?;
            let t = Frame { depth: target, calib, pose };
            for (pos, depth) in maps.iter().filter(|(p, d)| *p != 0 && !d.data.is_empty()) {
                let (calib, pose) = at(*pos)?;
                let a = agreement(&self.0, &t, &Frame { depth, calib, pose }, &i.boxes)?;
                out.insert(format!("{pos:+}"), a);
            }
            Ok(out)
        };
        let scores = TemporalScores { depth: score(&i.depths)?, gt: score(&i.gts)? };
        Ok(Outputs { json: File(serde_json::to_vec_pretty(&scores)?) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::geometry::Se3;
    use glam::DVec3;

    /// A 60x40 camera looking along ego +y (left) from x = `x`, at a wall 10 m away; the ego
    /// moves along +x, so the wall slides sideways between frames.
    fn frame(x: f64, wall: impl Fn(usize, usize) -> f32) -> (DepthMap, Calibration, Pose) {
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
        let data = (0..(w * h) as usize).map(|i| wall(i % w as usize, i / w as usize)).collect();
        (DepthMap { width: w, height: h, data }, calib, pose)
    }

    #[test]
    fn a_wall_seen_at_one_depth_agrees_and_one_that_flickers_does_not() {
        let p = Params::default();
        let (d0, c0, p0) = frame(0.0, |_, _| 10.0);
        let (d1, c1, p1) = frame(1.0, |_, _| 10.0);
        let t = Frame { depth: &d0, calib: &c0, pose: &p0 };
        let a = agreement(&p, &t, &Frame { depth: &d1, calib: &c1, pose: &p1 }, &Boxes3D::default()).unwrap();
        // 1 m at 10 m with f = 50 px: 5 px of the 60 slide out of view.
        assert!(a.seen_by_both > 40 * 50 && a.seen_by_both < 40 * 56, "{a:?}");
        assert_eq!(a.agree, a.seen_by_both);
        // The next frame's right half at 13 m (+30%): that half disagrees, unless it is sky.
        let (d2, c2, p2) = frame(1.0, |x, _| if x >= 30 { 13.0 } else { 10.0 });
        let b = agreement(&p, &t, &Frame { depth: &d2, calib: &c2, pose: &p2 }, &Boxes3D::default()).unwrap();
        let share = b.share().unwrap();
        assert!(share > 0.4 && share < 0.6, "{b:?}");
        let (d3, c3, p3) = frame(1.0, |x, _| if x >= 30 { 100.0 } else { 10.0 });
        let c = agreement(&p, &t, &Frame { depth: &d3, calib: &c3, pose: &p3 }, &Boxes3D::default()).unwrap();
        assert_eq!(c.share(), Some(1.0), "sky is not structure: {c:?}");
        assert!(c.seen_by_both < b.seen_by_both);
        // An occluder 4 m away in the other frame hides the wall: not seen by both.
        let (d4, c4, p4) = frame(1.0, |x, _| if x < 10 { 4.0 } else { 10.0 });
        let d = agreement(&p, &t, &Frame { depth: &d4, calib: &c4, pose: &p4 }, &Boxes3D::default()).unwrap();
        assert_eq!(d.share(), Some(1.0), "{d:?}");
    }
}
