//! `FusePoints`: LiDAR first, MVS points only where the LiDAR gives nothing.
//!
//! DiST-4D (Sec. 3.2): "LiDAR points have priority; MVS points are used where LiDAR is missing".
//! Missing is decided per image region, because LiDAR is sparse per pixel everywhere: the image
//! is cut into square cells of `cell_px` pixels; an MVS point is kept only when its cell and the
//! 8 cells around it hold no LiDAR point (so MVS never lands between two LiDAR scan lines, and
//! stays at least one cell away from the LiDAR's coverage). Both clouds are in the same frame
//! (the target LiDAR's); the output is the whole LiDAR cloud followed by the kept MVS points.

use dist4d_runtime::Made;
use crate::camera::{CameraView, ViewPorts};
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_types::artifact::PointCloud;
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Edge of the coverage cells (image pixels).
    pub cell_px: u32,
    /// Points must be this far in front of the camera (m) to count.
    pub min_depth: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { cell_px: 16, min_depth: 0.1 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .count("cell_px", self.cell_px as u64, 1, 4096)
            .within("min_depth", self.min_depth, 0.0, 1000.0)
            .done()
    }
}

/// The LiDAR cloud plus the MVS points that fall where, seen from `view`, no LiDAR is near.
pub fn fuse(params: &Params, lidar: &PointCloud, mvs: &PointCloud, view: &CameraView) -> Result<PointCloud> {
    ensure!(params.cell_px >= 1, "cell_px must be at least 1");
    let cell = params.cell_px as f64;
    let (cw, ch) = ((view.width as f64 / cell).ceil() as usize, (view.height as f64 / cell).ceil() as usize);
    // Covered cells, with a one-cell border so that neighbours never go out of range.
    let stride = cw + 2;
    let mut covered = vec![false; stride * (ch + 2)];
    let cell_of = |p: &[f32; 4]| -> Option<usize> {
        let c = view.to_camera(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64));
        if c.z <= params.min_depth {
            return None;
        }
        let (u, v) = view.pixel(c);
        (u >= 0.0 && v >= 0.0 && u < view.width as f64 && v < view.height as f64)
            .then(|| ((v / cell) as usize + 1) * stride + (u / cell) as usize + 1)
    };
    for p in &lidar.points {
        if let Some(i) = cell_of(p) {
            covered[i] = true;
        }
    }
    let mut out = lidar.clone();
    let labelled = lidar.labels.len() == lidar.points.len() && !lidar.points.is_empty();
    for p in &mvs.points {
        let Some(i) = cell_of(p) else { continue };
        let near =
            [i - stride - 1, i - stride, i - stride + 1, i - 1, i, i + 1, i + stride - 1, i + stride, i + stride + 1];
        if near.iter().all(|&j| !covered[j]) {
            out.points.push(*p);
            if labelled {
                // lidarseg 0 = noise / unlabelled.
                out.labels.push(0);
            }
        }
    }
    Ok(out)
}

crate::inputs! {
    pub struct Inputs {
        /// the LiDAR cloud (has priority), e.g. aggregate.points
        points: One<PointCloud>,
        /// the cloud's sensor and pose, the camera's calibration and pose
        view: Group<ViewPorts>,
        /// static MVS points in the same frame, e.g. StaticMvsPoints
        mvs: One<PointCloud>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the LiDAR points, then the kept MVS points (same frame)
        points: One<PointCloud>,
    }
}

pub struct FusePoints(Params);

impl Stage for FusePoints {
    const KIND: &'static str = "FusePoints";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "LiDAR cloud + MVS points -> one cloud: MVS only in image regions without LiDAR";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(FusePoints(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let view = i.view.view()?;
        Ok(Outputs { points: fuse(&self.0, &i.points, &i.mvs, &view)? }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mvs_points_fill_only_regions_without_lidar() {
        // Camera at the origin looking along +z of the cloud frame, 160x120, f = 100.
        let view = CameraView::looking_along_z(160, 120, 100.0);
        // A point at pixel (u, v), depth 10.
        let at = |u: f64, v: f64| [((u - 80.0) / 100.0 * 10.0) as f32, ((v - 60.0) / 100.0 * 10.0) as f32, 10.0, 0.0];
        let lidar = PointCloud { points: vec![at(20.0, 100.0), at(24.0, 100.0)], labels: vec![7, 7], rgb: Vec::new() };
        let mvs = PointCloud {
            points: vec![
                at(22.0, 101.0),       // same cell as LiDAR
                at(40.0, 100.0),       // neighbouring cell
                at(60.0, 100.0),       // two cells away
                at(140.0, 10.0),       // far from any LiDAR
                [0.0, 0.0, -5.0, 0.0], // behind the camera
            ],
            labels: vec![],
            rgb: Vec::new(),
        };
        let out = fuse(&Params::default(), &lidar, &mvs, &view).unwrap();
        assert_eq!(&out.points[..2], &lidar.points[..]);
        assert_eq!(&out.points[2..], &[at(60.0, 100.0), at(140.0, 10.0)]);
        assert_eq!(out.labels, vec![7, 7, 0, 0]);
    }
}
