//! `DepthPrompt`: points -> the sparse z-buffered depth of one camera (DiST-4D Sec. 3.2, "depth
//! prompt": projection with a z-buffer). The paper's nearest-neighbour fill of it is its own stage,
//! `NearestFill`, so that only pipelines whose completer reads it pay for it (the built-in
//! `CompleteDepth` reads the sparse map).

use crate::artifact::{DepthMap, PointCloud};
use crate::camera::{CameraView, ZBuffer};
use crate::stage::{one, StageDef, TypedOp};
use anyhow::Result;
use dist4d_graph::PortSpec;
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

struct Op(Params);

impl TypedOp for Op {
    fn run(&self, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Vec<Vec<u8>>> {
        let view = CameraView::from_inputs(inputs)?;
        let sparse = project_points(&self.0, &one::<PointCloud>(inputs, 0)?, &view);
        use crate::artifact::Artifact;
        Ok(vec![sparse.encode()])
    }
}

pub fn def() -> StageDef {
    StageDef::new::<Params>(
        "DepthPrompt",
        2,
        "Points -> sparse z-buffered depth of one camera (the depth prompt before its fill)",
        crate::camera::cloud_and_camera_ports("the cloud, in the frame of `cloud_calib` at `cloud_pose`"),
        vec![PortSpec::one("sparse", "DepthMap", "z-buffered projection, 0 = no point")],
        vec!["camera"],
        |p: Params| Ok(Box::new(Op(p))),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::rng::Rng;
}
