//! Rigid transforms (SE(3)) in f64, as the nuScenes devkit computes them.

use anyhow::Result;
use glam::{DMat3, DQuat, DVec3};

/// A rigid transform `p -> R p + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Se3 {
    pub rotation: DQuat,
    pub translation: DVec3,
}

impl Se3 {
    /// From a nuScenes-style quaternion `[w, x, y, z]` and translation. The quaternion is
    /// normalised, as pyquaternion does.
    pub fn from_wxyz_t(q: [f64; 4], t: [f64; 3]) -> Se3 {
        Se3 { rotation: DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize(), translation: DVec3::from_array(t) }
    }

    /// A rotation about z by `yaw` radians, then a translation.
    pub fn from_yaw(yaw: f64, t: DVec3) -> Se3 {
        Se3 { rotation: DQuat::from_rotation_z(yaw), translation: t }
    }

    /// The quaternion as nuScenes writes it, `[w, x, y, z]`.
    pub fn wxyz(&self) -> [f64; 4] {
        let q = self.rotation;
        [q.w, q.x, q.y, q.z]
    }

    pub fn inverse(&self) -> Se3 {
        let r = self.rotation.inverse();
        Se3 { rotation: r, translation: -(r * self.translation) }
    }

    /// `self * other`: apply `other` first, then `self`.
    pub fn then_from(&self, other: &Se3) -> Se3 {
        Se3 { rotation: (self.rotation * other.rotation).normalize(), translation: self.apply(other.translation) }
    }

    pub fn matrix(&self) -> DMat3 {
        DMat3::from_quat(self.rotation)
    }

    pub fn apply(&self, p: DVec3) -> DVec3 {
        self.matrix() * p + self.translation
    }

    pub fn encode_into(&self, out: &mut Vec<u8>) {
        let q = self.rotation;
        for x in [q.w, q.x, q.y, q.z, self.translation.x, self.translation.y, self.translation.z] {
            out.extend_from_slice(&x.to_le_bytes());
        }
    }

    pub fn decode_from<'a>(take: &mut dyn FnMut(usize) -> Result<&'a [u8]>) -> Result<Se3> {
        let mut v = [0.0f64; 7];
        for x in v.iter_mut() {
            *x = f64::from_le_bytes(take(8)?.try_into()?);
        }
        Ok(Se3 { rotation: DQuat::from_xyzw(v[1], v[2], v[3], v[0]), translation: DVec3::new(v[4], v[5], v[6]) })
    }
}

/// A 3D box as a point test in some sensor frame: grown by `margin` sideways and on top, its
/// bottom raised by `ground_clearance` (so the ground under a car is not inside it).
pub struct BoxTest {
    to_box: Se3,
    half: DVec3,
    z_min: f64,
    radius2: f64,
    center: DVec3,
}

impl BoxTest {
    /// A box of `size` ([width, length, height], nuScenes order) at `box_to_world`;
    /// `frame_from_world`: the frame the tested points are in.
    pub fn new(
        size: [f64; 3],
        box_to_world: &Se3,
        frame_from_world: &Se3,
        margin: f64,
        ground_clearance: f64,
    ) -> BoxTest {
        let box_to_frame = frame_from_world.then_from(box_to_world);
        // nuScenes size is [width, length, height]; the box x axis runs along its length.
        let half = DVec3::new(size[1] / 2.0, size[0] / 2.0, size[2] / 2.0) + DVec3::splat(margin);
        BoxTest {
            to_box: box_to_frame.inverse(),
            z_min: -size[2] / 2.0 + ground_clearance,
            radius2: half.length_squared(),
            center: box_to_frame.translation,
            half,
        }
    }

    #[inline]
    pub fn contains(&self, p: DVec3) -> bool {
        if (p - self.center).length_squared() > self.radius2 {
            return false;
        }
        let q = self.to_box.apply(p);
        q.x.abs() <= self.half.x && q.y.abs() <= self.half.y && q.z >= self.z_min && q.z <= self.half.z
    }
}
