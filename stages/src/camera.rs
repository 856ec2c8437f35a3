//! A pinhole camera seen from a point cloud's frame: the composed transform every curation stage
//! needs to move points between a sensor frame and a camera image.

use anyhow::{anyhow, Result};
use dist4d_types::artifact::{Calibration, Pose};
use dist4d_types::geometry::Se3;
use glam::{DMat3, DVec3};

/// Maps points of one sensor frame (at one ego pose) into one camera (at its own ego pose).
#[derive(Clone, Debug)]
pub struct CameraView {
    /// Cloud frame -> camera frame.
    pub cam_from_cloud: Se3,
    rotation: DMat3,
    pub k: [[f64; 3]; 3],
    pub width: u32,
    pub height: u32,
}

impl CameraView {
    /// `cloud`/`cloud_pose`: the sensor the points are in (e.g. the target frame's LiDAR);
    /// `camera`/`camera_pose`: the camera. Same chain as the nuScenes devkit, composed once.
    pub fn new(cloud: &Calibration, cloud_pose: &Pose, camera: &Calibration, camera_pose: &Pose) -> Result<CameraView> {
        let k = camera.intrinsics.ok_or_else(|| anyhow!("camera calibration has no intrinsics"))?;
        let world_from_cloud = cloud_pose.ego_to_world.then_from(&cloud.sensor_to_ego);
        let world_from_cam = camera_pose.ego_to_world.then_from(&camera.sensor_to_ego);
        let cam_from_cloud = world_from_cam.inverse().then_from(&world_from_cloud);
        Ok(CameraView {
            rotation: cam_from_cloud.matrix(),
            cam_from_cloud,
            k,
            width: camera.width,
            height: camera.height,
        })
    }

    /// A point of the cloud frame in the camera frame (z = depth along the optical axis).
    #[inline]
    pub fn to_camera(&self, p: DVec3) -> DVec3 {
        self.rotation * p + self.cam_from_cloud.translation
    }

    /// Pixel coordinates (continuous; pixel (i, j) covers [i, i+1) x [j, j+1)) of a camera-frame point.
    #[inline]
    pub fn pixel(&self, c: DVec3) -> (f64, f64) {
        let k = &self.k;
        let kz = k[2][0] * c.x + k[2][1] * c.y + k[2][2] * c.z;
        ((k[0][0] * c.x + k[0][1] * c.y + k[0][2] * c.z) / kz, (k[1][0] * c.x + k[1][1] * c.y + k[1][2] * c.z) / kz)
    }

    /// The camera-frame point at pixel (u, v) and depth z (pinhole K with zero skew).
    #[inline]
    pub fn unproject(&self, u: f64, v: f64, z: f64) -> DVec3 {
        let k = &self.k;
        let y = (v - k[1][2]) / k[1][1];
        let x = (u - k[0][2] - k[0][1] * y) / k[0][0];
        DVec3::new(x * z, y * z, z)
    }

    /// The camera centre in the cloud frame.
    pub fn center(&self) -> DVec3 {
        self.cam_from_cloud.inverse().translation
    }

    /// Camera frame -> cloud frame.
    pub fn cloud_from_cam(&self) -> Se3 {
        self.cam_from_cloud.inverse()
    }
}

#[cfg(test)]
impl CameraView {
    /// A `w` x `h` pinhole camera with focal length `f` (px) and the principal point at the image
    /// centre, placed at the cloud frame's origin and looking along its +z: cloud frame = camera
    /// frame, which keeps test geometry readable.
    pub fn looking_along_z(w: u32, h: u32, f: f64) -> CameraView {
        use dist4d_types::geometry::Se3;
        let cam = Calibration {
            sensor_to_ego: Se3::from_yaw(0.0, DVec3::ZERO),
            intrinsics: Some([[f, 0.0, w as f64 / 2.0], [0.0, f, h as f64 / 2.0], [0.0, 0.0, 1.0]]),
            width: w,
            height: h,
        };
        let cloud = Calibration { intrinsics: None, width: 0, height: 0, ..cam.clone() };
        let pose = Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::ZERO), timestamp_us: 0 };
        CameraView::new(&cloud, &pose, &cam, &pose).expect("intrinsics are set")
    }
}

/// Per pixel, the nearest of the given camera-frame depths (z-buffer); 0 where none.
pub struct ZBuffer {
    pub width: u32,
    pub height: u32,
    pub depth: Vec<f32>,
}

impl ZBuffer {
    pub fn new(width: u32, height: u32) -> ZBuffer {
        ZBuffer { width, height, depth: vec![0.0; width as usize * height as usize] }
    }

    /// Splats depth `z` at continuous pixel (u, v) when it is inside the image and nearer.
    #[inline]
    pub fn splat(&mut self, u: f64, v: f64, z: f32) -> bool {
        if !(u >= 0.0 && v >= 0.0 && u < self.width as f64 && v < self.height as f64 && z > 0.0) {
            return false;
        }
        let d = &mut self.depth[v as usize * self.width as usize + u as usize];
        if *d == 0.0 || z < *d {
            *d = z;
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn composes_the_devkit_chain_and_inverts_it() {
        let lidar = Calibration {
            sensor_to_ego: Se3::from_yaw(0.3, DVec3::new(1.0, 0.0, 1.8)),
            intrinsics: None,
            width: 0,
            height: 0,
        };
        let cam = Calibration {
            sensor_to_ego: Se3::from_wxyz_t([0.5, -0.5, 0.5, -0.5], [1.5, 0.0, 1.5]),
            intrinsics: Some([[1000.0, 0.0, 800.0], [0.0, 1000.0, 450.0], [0.0, 0.0, 1.0]]),
            width: 1600,
            height: 900,
        };
        let p1 = Pose { ego_to_world: Se3::from_yaw(1.0, DVec3::new(10.0, 5.0, 0.0)), timestamp_us: 0 };
        let p2 = Pose { ego_to_world: Se3::from_yaw(1.1, DVec3::new(11.0, 5.5, 0.1)), timestamp_us: 50_000 };
        let view = CameraView::new(&lidar, &p1, &cam, &p2).unwrap();
        let p = DVec3::new(20.0, -3.0, 0.5);
        // Step by step, as the devkit does.
        let w = p1.ego_to_world.apply(lidar.sensor_to_ego.apply(p));
        let c = cam.sensor_to_ego.inverse().apply(p2.ego_to_world.inverse().apply(w));
        assert!((view.to_camera(p) - c).length() < 1e-9);
        let (u, v) = view.pixel(c);
        let back = view.unproject(u, v, c.z);
        assert!((back - c).length() < 1e-9);
        assert!((view.cloud_from_cam().apply(c) - p).length() < 1e-9);
        let centre = view.center();
        assert!(view.to_camera(centre).length() < 1e-9);
    }
}

crate::inputs! {
    /// The inputs a [`CameraView`] is made from, shared by the stages that look at a point cloud
    /// from one camera (declare a field `view: Group<ViewPorts>` after the cloud).
    pub struct ViewPorts {
        /// the sensor the cloud is in (the target frame's LiDAR)
        cloud_calib: One<Calibration>,
        /// ego pose of that sensor's frame
        cloud_pose: One<Pose>,
        /// camera mounting and intrinsics
        camera_calib: One<Calibration>,
        /// ego pose at the camera time
        camera_pose: One<Pose>,
    }
}

impl ViewPorts {
    pub fn view(&self) -> Result<CameraView> {
        CameraView::new(&self.cloud_calib, &self.cloud_pose, &self.camera_calib, &self.camera_pose)
    }
}

crate::inputs! {
    /// The inputs of a stage that looks at a point cloud from one camera: the cloud and its view.
    pub struct CloudInView {
        /// the cloud, in the frame of `cloud_calib` at `cloud_pose`
        points: One<dist4d_types::artifact::PointCloud>,
        /// the cloud's sensor and pose, the camera's calibration and pose
        view: Group<ViewPorts>,
    }
}
