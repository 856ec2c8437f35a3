//! `ProjectLidar`: a LiDAR sweep projected into one camera as a sparse metric depth map.
//!
//! The nuScenes devkit's chain (`map_pointcloud_to_image`): lidar -> ego at the LiDAR time ->
//! world -> ego at the camera time -> camera, in f64. Points are kept when their depth exceeds
//! `min_depth` and they fall strictly inside the image less a `border_px` margin (devkit: 1 m,
//! 1 px). The depth map takes, per pixel (floor(u), floor(v)), the nearest point (z-buffer).

use dist4d_runtime::Made;
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use anyhow::{anyhow, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_types::artifact::{Calibration, DepthMap, PointCloud, Pose, ProjectedPoints};
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

crate::inputs! {
    pub struct Inputs {
        /// the sweep, in the LiDAR frame
        points: One<PointCloud>,
        /// LiDAR mounting
        lidar_calib: One<Calibration>,
        /// ego pose at the LiDAR time
        lidar_pose: One<Pose>,
        /// camera mounting and intrinsics
        camera_calib: One<Calibration>,
        /// ego pose at the camera time
        camera_pose: One<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// sparse depth, 0 = none
        depth: One<DepthMap>,
        /// u, v, depth of every kept point (kept only when the run reads it)
        uvz: OnDemand<ProjectedPoints>,
    }
}

pub struct ProjectLidar(Params);

impl Stage for ProjectLidar {
    const KIND: &'static str = "ProjectLidar";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "LiDAR sweep -> sparse z-buffered depth map of one camera (nuScenes devkit projection)";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(ProjectLidar(params))
    }
    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let (depth, uvz) = project(&self.0, &i.points, &i.lidar_calib, &i.lidar_pose, &i.camera_calib, &i.camera_pose)?;
        Ok(Outputs { depth, uvz: ctx.wants("uvz").then_some(uvz) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::geometry::Se3;

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
            rgb: Vec::new(),
        };
        let (d, uvz) = project(&Params::default(), &pts, &lidar, &pose, &cam, &pose).unwrap();
        assert_eq!(uvz.rows, vec![[5.0, 5.0, 4.0], [5.0, 5.0, 2.0]]);
        assert_eq!(d.data[5 * 10 + 5], 2.0);
        assert_eq!(d.data.iter().filter(|x| **x > 0.0).count(), 1);
    }

    /// LiDAR projected into CAMERA_01 (front): hand-checked against the image. The road ahead is
    /// the nearest surface low in the image, the sky rows get nothing, and the depths in the
    /// lower middle (road a few metres ahead) are short and grow towards the horizon.
    #[test]
    fn projected_lidar_lands_on_plausible_geometry_in_every_camera_of_the_shared_dgp_scene() {
        use dist4d_datasets::dgp::{Dgp, DgpConfig};
        use dist4d_datasets::surround::Surround;
        use dist4d_runtime::{Dataset, ItemKey};
        use dist4d_types::artifact::{Artifact, Calibration, PointCloud, Pose};
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/dgp-scene02");
        if !root.is_dir() {
            eprintln!("SKIPPED: shared DGP data not found at {}", root.display());
            return;
        }
        let ds = Surround(Dgp::open(DgpConfig { root: root.display().to_string(), ..Default::default() }).unwrap());
        let lidar = PointCloud::decode(&ds.load_source("lidar", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        let lidar_calib = Calibration::decode(&ds.load_source("lidar_calib", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        let lidar_pose = Pose::decode(&ds.load_source("lidar_pose", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        for c in 0..6u32 {
            let item = ItemKey::new(&[0, 0, c]);
            let cal = Calibration::decode(&ds.load_source("camera_calib", &item).unwrap()).unwrap();
            let pose = Pose::decode(&ds.load_source("camera_pose", &item).unwrap()).unwrap();
            let (depth, uvz) = project(&Params::default(), &lidar, &lidar_calib, &lidar_pose, &cal, &pose).unwrap();
            let h = depth.height as f32;
            // Every camera sees a few thousand points, all in front of it and within LiDAR range.
            assert!(uvz.rows.len() > 2000, "camera {c}: {} points", uvz.rows.len());
            assert!(uvz.rows.iter().all(|r| r[2] > 1.0 && r[2] < 250.0));
            // The top fifth of the image (sky, tree tops) gets almost nothing.
            let top = uvz.rows.iter().filter(|r| r[1] < h * 0.2).count();
            assert!(top * 20 < uvz.rows.len(), "camera {c}: {top} of {} points in the top fifth", uvz.rows.len());
            // Lower rows are nearer than rows close to the horizon (ground seen at growing range).
            let median = |lo: f32, hi: f32| {
                let mut z: Vec<f32> =
                    uvz.rows.iter().filter(|r| r[1] >= lo * h && r[1] < hi * h).map(|r| r[2]).collect();
                z.sort_by(f32::total_cmp);
                z.get(z.len() / 2).copied().unwrap_or(f32::NAN)
            };
            let (low, mid) = (median(0.8, 1.0), median(0.5, 0.6));
            assert!(low < mid, "camera {c}: bottom rows median {low} m, middle rows {mid} m");
            if c == 0 {
                // Front camera, checked by hand on an overlay of the points on the image: the
                // road at the bottom centre is 6.5 m away, the road near the horizon 29 m, the
                // trees and grass at the left and right edges 15-16 m.
                let near = |u: f32, v: f32| {
                    uvz.rows
                        .iter()
                        .min_by(|a, b| (a[0] - u).hypot(a[1] - v).total_cmp(&(b[0] - u).hypot(b[1] - v)))
                        .unwrap()[2]
                };
                assert!((5.5..7.5).contains(&near(968.0, 1100.0)), "{}", near(968.0, 1100.0));
                assert!((25.0..33.0).contains(&near(968.0, 700.0)), "{}", near(968.0, 700.0));
                assert!((13.0..19.0).contains(&near(300.0, 800.0)), "{}", near(300.0, 800.0));
                assert!((13.0..19.0).contains(&near(1600.0, 800.0)), "{}", near(1600.0, 800.0));
            }
        }
    }
}
