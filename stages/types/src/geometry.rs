//! Rigid transforms (SE(3)) in f64, as the nuScenes devkit computes them.

use anyhow::Result;
use glam::{DMat3, DQuat, DVec3};

/// A rigid transform `p -> R p + t` (the default is the identity).
#[derive(Clone, Copy, Debug, PartialEq, Default)]
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

    /// `p` in the box's own axes: x along its length, z up, origin at its centre; the box spans
    /// [`BoxTest::corners`].
    #[inline]
    pub fn local(&self, p: DVec3) -> DVec3 {
        self.to_box.apply(p)
    }

    /// The lowest and highest corners of the box in its own axes (see [`BoxTest::local`]).
    pub fn corners(&self) -> (DVec3, DVec3) {
        (DVec3::new(-self.half.x, -self.half.y, self.z_min), self.half)
    }

    /// The part of the segment from `a` to `b` inside the box, in the box's own axes; `None`
    /// when the segment misses it (the slab test of Kay and Kajiya 1986).
    pub fn clip(&self, a: DVec3, b: DVec3) -> Option<(DVec3, DVec3)> {
        // Bounding sphere first: most segments pass nowhere near a given box.
        let d = b - a;
        let t = if d.length_squared() > 0.0 {
            ((self.center - a).dot(d) / d.length_squared()).clamp(0.0, 1.0)
        } else {
            0.0
        };
        if (a + d * t - self.center).length_squared() > self.radius2 {
            return None;
        }
        let (qa, qb) = (self.to_box.apply(a), self.to_box.apply(b));
        let dir = qb - qa;
        let (lo, hi) = self.corners();
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        for axis in 0..3 {
            let (o, v) = (qa[axis], dir[axis]);
            if v.abs() < 1e-12 {
                if o < lo[axis] || o > hi[axis] {
                    return None;
                }
                continue;
            }
            let (mut near, mut far) = ((lo[axis] - o) / v, (hi[axis] - o) / v);
            if near > far {
                std::mem::swap(&mut near, &mut far);
            }
            t0 = t0.max(near);
            t1 = t1.min(far);
            if t0 > t1 {
                return None;
            }
        }
        Some((qa + dir * t0, qa + dir * t1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whether the segment from `a` to `b` passes through `b`'s box.
    fn crosses(b: &BoxTest, from: DVec3, to: DVec3) -> bool {
        b.clip(from, to).is_some()
    }

    /// A 4 x 2 x 1.5 m box (length along world x) centred at (10, 0, 0.75), yawed by `yaw`.
    fn car(yaw: f64) -> BoxTest {
        BoxTest::new(
            [2.0, 4.0, 1.5],
            &Se3::from_yaw(yaw, DVec3::new(10.0, 0.0, 0.75)),
            &Se3::from_yaw(0.0, DVec3::ZERO),
            0.0,
            0.0,
        )
    }

    #[test]
    fn a_segment_crosses_a_box_only_when_it_passes_through_it() {
        let eye = DVec3::new(0.0, 0.0, 1.0);
        for yaw in [0.0, 0.4, 1.3] {
            let b = car(yaw);
            // Through the middle, to a point behind the box.
            assert!(crosses(&b, eye, DVec3::new(20.0, 0.0, 0.5)), "yaw {yaw}");
            // Ending in front of the box, passing beside it, or over its roof.
            assert!(!crosses(&b, eye, DVec3::new(7.0, 0.0, 0.8)), "yaw {yaw}");
            assert!(!crosses(&b, eye, DVec3::new(20.0, 6.0, 0.5)), "yaw {yaw}");
            assert!(!crosses(&b, eye, DVec3::new(20.0, 0.0, 3.5)), "yaw {yaw}");
            // Ending inside the box.
            assert!(crosses(&b, eye, DVec3::new(10.0, 0.0, 0.5)), "yaw {yaw}");
        }
        // y = x / 5 passes beside the box along x (|y| <= 1 for x in [8, 12]) but through it
        // turned by 90 degrees (|y| <= 2 for x in [9, 11]).
        assert!(!crosses(&car(0.0), eye, DVec3::new(20.0, 4.0, 1.0)));
        assert!(crosses(&car(std::f64::consts::FRAC_PI_2), eye, DVec3::new(20.0, 4.0, 1.0)));
        // A zero-length segment crosses only when it lies inside.
        assert!(crosses(&car(0.0), DVec3::new(10.0, 0.0, 0.5), DVec3::new(10.0, 0.0, 0.5)));
        assert!(!crosses(&car(0.0), eye, eye));
    }
}

/// The recording cars' boxes in their ego frames (min and max corners; x forward, y left, z up;
/// metres): a LiDAR's returns inside are the car itself, which the dataset readers drop
/// (docs/datasets.md).
pub mod ego_box {
    /// nuScenes' Renault Zoe (4.08 x 1.73 m, the ego frame at the rear axle on the ground) with
    /// room for the roof LiDAR's mount (1.84 m up). The synthetic world's hatchback lies inside.
    pub const NUSCENES: ([f64; 3], [f64; 3]) = ([-1.0, -1.0, -1.0], [3.4, 1.0, 2.0]);
    /// DDAD's Ford Fusion (4.87 x 1.85 m; the ego frame on the ground) with a margin.
    pub const DDAD: ([f64; 3], [f64; 3]) = ([-1.3, -1.0, -0.5], [3.9, 1.0, 2.0]);

    /// Whether the ego-frame point `p` lies in `b`.
    pub fn contains(b: &([f64; 3], [f64; 3]), p: glam::DVec3) -> bool {
        (0..3).all(|k| p[k] >= b.0[k] && p[k] <= b.1[k])
    }
}
