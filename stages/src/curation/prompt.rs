//! `DepthPrompt`: points -> the sparse z-buffered depth of one camera (DiST-4D Sec. 3.2, "depth
//! prompt": projection with a z-buffer). The paper's nearest-neighbour fill of it is its own stage,
//! `NearestFill`, so that only pipelines whose completer reads it pay for it (the built-in
//! `CompleteDepth` reads the sparse map).

use crate::camera::{CameraView, CloudInView, ZBuffer};
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use anyhow::Result;
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_types::artifact::{DepthMap, PointCloud};
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Points at or nearer than this depth (m) are dropped (nuScenes devkit: 1 m).
    pub min_depth: f64,
    /// Points farther than this depth (m) are dropped.
    pub max_depth: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { min_depth: 1.0, max_depth: 100.0 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .within("min_depth", self.min_depth, 0.0, 1000.0)
            .above("max_depth", self.max_depth, 0.0, 1e6)
            .below("min_depth", self.min_depth, "max_depth", self.max_depth)
            .done()
    }
}

/// Z-buffered projection of `points` into the camera of `view`.
pub fn project_points(params: &Params, points: &PointCloud, view: &CameraView) -> DepthMap {
    let mut z = ZBuffer::new(view.width, view.height);
    for p in &points.points {
        let c = view.to_camera(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64));
        if c.z > params.min_depth && c.z <= params.max_depth {
            let (u, v) = view.pixel(c);
            z.splat(u, v, c.z as f32);
        }
    }
    DepthMap { width: view.width, height: view.height, data: z.depth }
}

crate::ports! {
    pub struct Outputs {
        /// z-buffered projection, 0 = no point
        sparse: One<DepthMap>,
    }
}

pub struct DepthPrompt(Params);

impl Stage for DepthPrompt {
    const KIND: &'static str = "DepthPrompt";
    const VERSION: u32 = 2;
    const SUMMARY: &'static str = "Points -> sparse z-buffered depth of one camera (the depth prompt before its fill)";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = CloudInView;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(DepthPrompt(params))
    }
    fn run(&self, _: &TaskContext, i: CloudInView) -> Result<Outputs> {
        let view = i.view.view()?;
        Ok(Outputs { sparse: project_points(&self.0, &i.points, &view) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_nearest_point_of_a_pixel_wins_and_the_depth_range_is_kept() {
        let view = CameraView::looking_along_z(160, 120, 100.0);
        // A point at pixel (u, v) and depth z.
        let at = |u: f32, v: f32, z: f32| [(u + 0.5 - 80.0) / 100.0 * z, (v + 0.5 - 60.0) / 100.0 * z, z, 0.0];
        let points = PointCloud {
            points: vec![
                at(10.0, 20.0, 30.0),
                at(10.0, 20.0, 12.0), // same pixel, nearer: wins whatever the order
                at(10.0, 20.0, 50.0),
                at(50.0, 50.0, 0.5),   // nearer than min_depth
                at(60.0, 50.0, 120.0), // beyond max_depth
                at(70.0, 50.0, 100.0), // at max_depth: kept
                at(500.0, 50.0, 10.0), // outside the image
            ],
            labels: vec![],
        };
        let d = project_points(&Params::default(), &points, &view);
        let px = |u: usize, v: usize| d.data[v * 160 + u];
        assert!((px(10, 20) - 12.0).abs() < 1e-4, "{}", px(10, 20));
        assert_eq!(px(50, 50), 0.0);
        assert_eq!(px(60, 50), 0.0);
        assert!((px(70, 50) - 100.0).abs() < 1e-3);
        assert_eq!(d.data.iter().filter(|&&z| z > 0.0).count(), 2);
    }
}
