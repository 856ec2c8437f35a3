//! `ProjectLidar`: a LiDAR sweep projected into one camera as a sparse metric depth map.
//!
//! The nuScenes devkit's chain (`map_pointcloud_to_image`): lidar -> ego at the LiDAR time ->
//! world -> ego at the camera time -> camera, in f64. Points are kept when their depth exceeds
//! `min_depth` and they fall strictly inside the image less a `border_px` margin (devkit: 1 m,
//! 1 px). The depth map takes, per pixel (floor(u), floor(v)), the nearest point (z-buffer).

use crate::artifact::{Calibration, DepthMap, PointCloud, Pose, ProjectedPoints};
use crate::stage::{input, one, StageDef, TypedOp};
use anyhow::{anyhow, Result};
use dist4d_graph::{ParamChecks, ParamProblem, PortSpec, Validate};
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Points at or nearer than this depth (metres, along the optical axis) are dropped.
    pub min_depth: f64,
    /// Points must lie strictly inside the image shrunk by this many pixels on each side.
    pub border_px: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { min_depth: 1.0, border_px: 1.0 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        // A negative border would let points land outside the depth map.
        ParamChecks::new()
            .within("min_depth", self.min_depth, 0.0, 1000.0)
            .within("border_px", self.border_px, 0.0, 1000.0)
            .done()
    }
}

/// The sparse depth map and the projected points (in the order of the sweep's points).
pub fn project(
    params: &Params,
    points: &PointCloud,
    lidar: &Calibration,
    lidar_pose: &Pose,
    camera: &Calibration,
    camera_pose: &Pose,
) -> Result<(DepthMap, ProjectedPoints)> {
    let k = camera.intrinsics.ok_or_else(|| anyhow!("camera calibration has no intrinsics"))?;
    let (w, h) = (camera.width as f64, camera.height as f64);
    let r1 = lidar.sensor_to_ego.matrix();
    let t1 = lidar.sensor_to_ego.translation;
    let r2 = lidar_pose.ego_to_world.matrix();
    let t2 = lidar_pose.ego_to_world.translation;
    let r3t = camera_pose.ego_to_world.matrix().transpose();
    let t3 = camera_pose.ego_to_world.translation;
    let r4t = camera.sensor_to_ego.matrix().transpose();
    let t4 = camera.sensor_to_ego.translation;
    let mut depth = DepthMap::new(camera.width, camera.height);
    let mut rows = Vec::new();
    for p in &points.points {
        let p = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let p = r1 * p + t1;
        let p = r2 * p + t2;
        let p = r3t * (p - t3);
        let c = r4t * (p - t4);
        let z = c.z;
        // view_points(normalize=True): divide by the third row of K p (z for a pinhole K).
        let kz = k[2][0] * c.x + k[2][1] * c.y + k[2][2] * c.z;
        let u = (k[0][0] * c.x + k[0][1] * c.y + k[0][2] * c.z) / kz;
        let v = (k[1][0] * c.x + k[1][1] * c.y + k[1][2] * c.z) / kz;
        let b = params.border_px;
        if !(z > params.min_depth && u > b && u < w - b && v > b && v < h - b) {
            continue;
        }
        rows.push([u as f32, v as f32, z as f32]);
        let idx = v.floor() as usize * camera.width as usize + u.floor() as usize;
        let d = &mut depth.data[idx];
        if *d == 0.0 || (z as f32) < *d {
            *d = z as f32;
        }
    }
    Ok((depth, ProjectedPoints { rows }))
}

struct Op(Params);

impl TypedOp for Op {
    fn run(
        &self,
        _ctx: &dist4d_runtime::TaskContext,
        inputs: &[Vec<dist4d_runtime::Artifact>],
    ) -> Result<Vec<Vec<u8>>> {
        let (depth, uvz) = project(
            &self.0,
            &one::<PointCloud>(inputs, 0)?,
            &one::<Calibration>(inputs, 1)?,
            &one::<Pose>(inputs, 2)?,
            &one::<Calibration>(inputs, 3)?,
            &one::<Pose>(inputs, 4)?,
        )?;
        use crate::artifact::Artifact;
        Ok(vec![depth.encode(), uvz.encode()])
    }
}

pub fn def() -> StageDef {
    StageDef::new::<Params>(
        "ProjectLidar",
        1,
        "LiDAR sweep -> sparse z-buffered depth map of one camera (nuScenes devkit projection)",
        vec![
            input::<PointCloud>("points", "the sweep, in the LiDAR frame"),
            input::<Calibration>("lidar_calib", "LiDAR mounting"),
            input::<Pose>("lidar_pose", "ego pose at the LiDAR time"),
            input::<Calibration>("camera_calib", "camera mounting and intrinsics"),
            input::<Pose>("camera_pose", "ego pose at the camera time"),
        ],
        vec![
            PortSpec::one("depth", "DepthMap", "sparse depth, 0 = none"),
            PortSpec::one("uvz", "ProjectedPoints", "u, v, depth of every kept point"),
        ],
        vec!["camera"],
        |p: Params| Ok(Box::new(Op(p))),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;

    fn identity() -> Se3 {
        Se3::from_wxyz_t([1.0, 0.0, 0.0, 0.0], [0.0; 3])
    }

    #[test]
    fn projects_with_a_z_buffer_and_the_devkit_border() {
        // Camera looking along +z of the ego frame, f = 10, principal point (5, 5), 10x10 image.
        let cam = Calibration {
            sensor_to_ego: identity(),
            intrinsics: Some([[10.0, 0.0, 5.0], [0.0, 10.0, 5.0], [0.0, 0.0, 1.0]]),
            width: 10,
            height: 10,
        };
        let lidar = Calibration { sensor_to_ego: identity(), intrinsics: None, width: 0, height: 0 };
        let pose = Pose { ego_to_world: identity(), timestamp_us: 0 };
        let pts = PointCloud {
            points: vec![
                [0.0, 0.0, 4.0, 0.0],  // centre, far
                [0.0, 0.0, 2.0, 0.0],  // centre, near: wins the pixel
                [0.0, 0.0, 0.5, 0.0],  // too close
                [2.0, 0.0, 5.0, 0.0],  // u = 9: outside the 1 px border (u < 9 required)
                [0.0, 0.0, -3.0, 0.0], // behind
            ],
            labels: vec![],
        };
        let (d, uvz) = project(&Params::default(), &pts, &lidar, &pose, &cam, &pose).unwrap();
        assert_eq!(uvz.rows, vec![[5.0, 5.0, 4.0], [5.0, 5.0, 2.0]]);
        assert_eq!(d.data[5 * 10 + 5], 2.0);
        assert_eq!(d.data.iter().filter(|x| **x > 0.0).count(), 1);
    }
}
