//! `AboveLidarFov`: a depth map kept only where its surface lies above the LiDAR's vertical field
//! of view, where the LiDAR cannot measure anything and only MVS (or the completion) gives depth.
//!
//! DiST-4D adds MVS for exactly these pixels (building tops, tree crowns, the far street end above
//! the top beam), so the curation is scored on them separately: each pixel of the input depth
//! (e.g. the synthetic ground truth) is lifted to 3D, moved into the target LiDAR's frame, and
//! kept when its elevation seen from the LiDAR exceeds the top beam's. The top beam's elevation is
//! read off the sweep itself (the highest elevation among its points beyond `min_range`, ignoring
//! the highest `outlier_share` of them), so no sensor table is needed; `top_elevation_deg`
//! overrides it for sweeps that were cropped.

use dist4d_runtime::Made;
use crate::camera::{CameraView, ViewPorts};
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_types::artifact::{DepthMap, PointCloud};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The top beam's elevation (degrees); `None`: read off the sweep.
    pub top_elevation_deg: Option<f64>,
    /// Points nearer than this (m) do not count when reading the top elevation (the ego body).
    pub min_range: f64,
    /// Share of the highest elevations ignored as outliers when reading the top elevation.
    pub outlier_share: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { top_elevation_deg: None, min_range: 2.0, outlier_share: 0.001 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        if let Some(deg) = self.top_elevation_deg {
            c.within("top_elevation_deg", deg, -90.0, 90.0);
        }
        c.within("min_range", self.min_range, 0.0, 1000.0)
            .check((0.0..1.0).contains(&self.outlier_share), "outlier_share", || {
                format!("must be a fraction in [0, 1), found {}", self.outlier_share)
            })
            .done()
    }
}

/// The top beam's elevation (radians) in the sweep's sensor frame; `None` for an empty sweep.
pub fn top_elevation(params: &Params, sweep: &PointCloud) -> Option<f64> {
    if let Some(deg) = params.top_elevation_deg {
        return Some(deg.to_radians());
    }
    let mut elevations: Vec<f64> = sweep
        .points
        .iter()
        .filter_map(|p| {
            let (x, y, z) = (p[0] as f64, p[1] as f64, p[2] as f64);
            let across = x.hypot(y);
            (across.hypot(z) >= params.min_range).then(|| z.atan2(across))
        })
        .collect();
    if elevations.is_empty() {
        return None;
    }
    let skip = ((elevations.len() as f64 * params.outlier_share) as usize).min(elevations.len() - 1);
    let at = elevations.len() - 1 - skip;
    Some(*elevations.select_nth_unstable_by(at, f64::total_cmp).1)
}

/// `depth` where its point lies above `top` (radians) seen from the cloud frame of `view`, else 0.
pub fn above_fov(depth: &DepthMap, view: &CameraView, top: f64) -> Result<DepthMap> {
    ensure!(
        (depth.width, depth.height) == (view.width, view.height),
        "the depth map is {}x{} but the camera calibration says {}x{}",
        depth.width,
        depth.height,
        view.width,
        view.height
    );
    let cloud_from_cam = view.cloud_from_cam();
    let w = depth.width as usize;
    // Above the top beam: z > tan(top) * hypot(x, y), compared without a square root or atan2
    // per pixel (1.4 M of them per image).
    let slope = top.tan();
    let data = depth
        .data
        .iter()
        .enumerate()
        .map(|(i, &z)| {
            if !(z > 0.0 && z.is_finite()) {
                return 0.0;
            }
            let (u, v) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
            let p = cloud_from_cam.apply(view.unproject(u, v, z as f64));
            if above_slope(p, slope) {
                z
            } else {
                0.0
            }
        })
        .collect();
    Ok(DepthMap { width: depth.width, height: depth.height, data })
}

/// Whether `p`'s elevation from the origin exceeds the one whose tangent is `slope`.
#[inline]
fn above_slope(p: glam::DVec3, slope: f64) -> bool {
    let across2 = p.x * p.x + p.y * p.y;
    if slope >= 0.0 {
        p.z > 0.0 && p.z * p.z > slope * slope * across2
    } else {
        p.z >= 0.0 || p.z * p.z < slope * slope * across2
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the target frame's sweep, in its sensor frame (for its top beam)
        points: One<PointCloud>,
        /// the cloud's sensor and pose, the camera's calibration and pose
        view: Group<ViewPorts>,
        /// the depth to restrict (e.g. dataset.gt_depth; empty = none)
        depth: One<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the input depth above the top beam, 0 elsewhere (empty if the input is)
        depth: One<DepthMap>,
    }
}

pub struct AboveLidarFov(Params);

impl Stage for AboveLidarFov {
    const KIND: &'static str = "AboveLidarFov";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "Depth map -> the same depth only where its point lies above the LiDAR's vertical field of view";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(AboveLidarFov(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        // No reference (a dataset without ground truth) or no sweep: nothing to restrict.
        let top = top_elevation(&self.0, &i.points);
        let (Some(top), true) = (top, i.depth.width > 0 && i.depth.height > 0) else {
            return Ok(Outputs { depth: DepthMap::new(0, 0) }.into());
        };
        let view = i.view.view()?;
        Ok(Outputs { depth: above_fov(&i.depth, &view, top)? }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sweep of two beams at +10 and -20 degrees, plus a point on the ego body (near, high).
    fn sweep() -> PointCloud {
        let mut points = Vec::new();
        for (el, r) in [(10f64, 20.0f64), (-20.0, 10.0)] {
            for a in 0..360 {
                let (a, el) = ((a as f64).to_radians(), el.to_radians());
                let p = [r * el.cos() * a.cos(), r * el.cos() * a.sin(), r * el.sin()];
                points.push([p[0] as f32, p[1] as f32, p[2] as f32, 0.0]);
            }
        }
        points.push([0.5, 0.0, 1.0, 0.0]);
        PointCloud { points, labels: vec![], rgb: vec![] }
    }

    #[test]
    fn the_top_beam_is_read_off_the_sweep_without_the_ego_body() {
        let top = top_elevation(&Params::default(), &sweep()).unwrap();
        assert!((top.to_degrees() - 10.0).abs() < 1e-4, "{}", top.to_degrees());
        let fixed = Params { top_elevation_deg: Some(12.0), ..Params::default() };
        assert_eq!(top_elevation(&fixed, &sweep()).unwrap(), 12f64.to_radians());
        assert_eq!(top_elevation(&Params::default(), &PointCloud::default()), None);
    }

    #[test]
    fn the_slope_test_agrees_with_the_elevation_angle() {
        let mut rng = dist4d_types::rng::Rng::new(3);
        for _ in 0..20_000 {
            let p = glam::DVec3::new(rng.range(-50.0, 50.0), rng.range(-50.0, 50.0), rng.range(-20.0, 20.0));
            let top = rng.range(-80.0, 80.0).to_radians();
            assert_eq!(above_slope(p, top.tan()), p.z.atan2(p.x.hypot(p.y)) > top, "{p:?} {top}");
        }
    }

    #[test]
    fn keeps_only_pixels_whose_point_is_above_the_top_beam() {
        // Camera at the LiDAR's origin looking along the cloud's +z: a pixel's elevation from the
        // LiDAR is that of the cloud-frame point, atan2(z, hypot(x, y)); a wall at depth 10 m.
        let view = CameraView::looking_along_z(64, 48, 50.0);
        let depth = DepthMap { width: 64, height: 48, data: vec![10.0; 64 * 48] };
        let out = above_fov(&depth, &view, 80f64.to_radians()).unwrap();
        for (i, &z) in out.data.iter().enumerate() {
            let p = view.unproject((i % 64) as f64 + 0.5, (i / 64) as f64 + 0.5, 10.0);
            let el = p.z.atan2(p.x.hypot(p.y));
            assert_eq!(z > 0.0, el > 80f64.to_radians(), "pixel {i}");
        }
        // Near the optical axis (elevation ~90 degrees) above, the corners (~67 degrees) not.
        assert_eq!(out.data[24 * 64 + 32], 10.0);
        assert_eq!(out.data[0], 0.0);
        let wrong = DepthMap { width: 10, height: 10, data: vec![1.0; 100] };
        assert!(above_fov(&wrong, &view, 0.1).unwrap_err().to_string().contains("10x10"));
    }
}
