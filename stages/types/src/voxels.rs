//! A voxel grid in a vehicle's frame, rays through it (Amanatides and Woo 1987), and the
//! visibility masks of an occupancy frame cast with them: shared by the occupancy stages and the
//! synthetic world's exact occupancy, so both are cast the same way.

use crate::geometry::Se3;
use glam::DVec3;

/// A grid in the ego frame (its lower corner already lifted).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    pub min: DVec3,
    pub voxel: f64,
    pub dims: [usize; 3],
}

impl Grid {
    pub fn len(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn linear(&self, c: [i64; 3]) -> usize {
        (c[0] as usize * self.dims[1] + c[1] as usize) * self.dims[2] + c[2] as usize
    }

    /// The voxel of an ego-frame point, if inside.
    pub fn index(&self, p: DVec3) -> Option<usize> {
        let q = (p - self.min) / self.voxel;
        let c = [q.x.floor(), q.y.floor(), q.z.floor()];
        if (0..3).all(|a| c[a] >= 0.0 && c[a] < self.dims[a] as f64) {
            Some(self.linear([c[0] as i64, c[1] as i64, c[2] as i64]))
        } else {
            None
        }
    }

    /// The centre of voxel `i` in the ego frame.
    pub fn centre(&self, i: usize) -> DVec3 {
        let k = i % self.dims[2];
        let j = (i / self.dims[2]) % self.dims[1];
        let x = i / (self.dims[1] * self.dims[2]);
        self.min + (DVec3::new(x as f64, j as f64, k as f64) + 0.5) * self.voxel
    }

    /// Visits the voxels the segment `from` -> `to` (ego frame) passes through, in order, until
    /// `visit` returns false (Amanatides and Woo 1987, on the part of the segment inside the grid).
    pub fn trace(&self, from: DVec3, to: DVec3, mut visit: impl FnMut(usize) -> bool) {
        let a = (from - self.min) / self.voxel;
        let dir = (to - self.min) / self.voxel - a;
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        for ax in 0..3 {
            let (o, v, hi) = (a[ax], dir[ax], self.dims[ax] as f64);
            if v.abs() < 1e-12 {
                if o < 0.0 || o >= hi {
                    return;
                }
                continue;
            }
            let (ta, tb) = ((0.0 - o) / v, (hi - o) / v);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
            if t0 > t1 {
                return;
            }
        }
        let start = a + dir * t0;
        let mut cell = [0i64; 3];
        let mut step = [0i64; 3];
        let mut t_max = [f64::INFINITY; 3];
        let mut t_delta = [f64::INFINITY; 3];
        for ax in 0..3 {
            let c = (start[ax].floor() as i64).clamp(0, self.dims[ax] as i64 - 1);
            cell[ax] = c;
            if dir[ax] > 0.0 {
                step[ax] = 1;
                t_max[ax] = (c as f64 + 1.0 - a[ax]) / dir[ax];
                t_delta[ax] = 1.0 / dir[ax];
            } else if dir[ax] < 0.0 {
                step[ax] = -1;
                t_max[ax] = (c as f64 - a[ax]) / dir[ax];
                t_delta[ax] = -1.0 / dir[ax];
            }
        }
        loop {
            if !visit(self.linear(cell)) {
                return;
            }
            let ax = if t_max[0] <= t_max[1] && t_max[0] <= t_max[2] {
                0
            } else if t_max[1] <= t_max[2] {
                1
            } else {
                2
            };
            if t_max[ax] > t1 {
                return;
            }
            cell[ax] += step[ax];
            if cell[ax] < 0 || cell[ax] >= self.dims[ax] as i64 {
                return;
            }
            t_max[ax] += t_delta[ax];
        }
    }
}

/// A camera for [`cast_masks`]: where it is in the grid's frame, its intrinsics and image size.
pub struct MaskCamera {
    pub ego_from_camera: Se3,
    pub k: [[f64; 3]; 3],
    pub width: u32,
    pub height: u32,
    /// Pixels (row-major, non-zero) through which the camera sees nothing of the scene: the
    /// recording car's body. No ray is cast through them. Empty = none.
    pub blocked: Vec<u8>,
}

/// The visibility masks of an occupancy frame (C order over the grid, 0/1):
/// - `mask_lidar`: every voxel a ray from `lidar_origin` to one of `returns` (grid frame) passes
///   through or ends in (returns within 0.5 m of the origin, no-return points, are skipped);
/// - `mask_camera`: every voxel a camera ray reaches, one ray per `ray_step` pixels, stopping at
///   the first voxel that is not `free` in `semantics` (included) or after `max_distance`, that
///   the LiDAR also observed.
#[allow(clippy::too_many_arguments)]
pub fn cast_masks(
    grid: &Grid,
    semantics: &[u8],
    free: u8,
    lidar_origin: DVec3,
    returns: impl Iterator<Item = DVec3>,
    cameras: &[MaskCamera],
    ray_step: usize,
    max_distance: f64,
) -> (Vec<u8>, Vec<u8>) {
    let n = grid.len();
    let (mut lidar, mut camera) = (vec![0u8; n], vec![0u8; n]);
    for end in returns {
        if (end - lidar_origin).length() < 0.5 {
            continue;
        }
        grid.trace(lidar_origin, end, |v| {
            lidar[v] = 1;
            true
        });
    }
    let step = ray_step.max(1);
    for cam in cameras {
        let k = cam.k;
        let centre = cam.ego_from_camera.translation;
        for y in (step / 2..cam.height as usize).step_by(step) {
            for x in (step / 2..cam.width as usize).step_by(step) {
                if cam.blocked.get(y * cam.width as usize + x).is_some_and(|&b| b != 0) {
                    continue;
                }
                let yc = (y as f64 + 0.5 - k[1][2]) / k[1][1];
                let xc = (x as f64 + 0.5 - k[0][2] - k[0][1] * yc) / k[0][0];
                let dir = cam.ego_from_camera.rotation * DVec3::new(xc, yc, 1.0).normalize();
                grid.trace(centre, centre + dir * max_distance, |v| {
                    if lidar[v] != 0 {
                        camera[v] = 1;
                    }
                    semantics[v] == free
                });
            }
        }
    }
    (lidar, camera)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ray_visits_each_voxel_it_crosses_once_in_order_and_only_inside() {
        let g = Grid { min: DVec3::ZERO, voxel: 1.0, dims: [4, 3, 2] };
        let mut seen = Vec::new();
        g.trace(DVec3::new(-2.0, 0.5, 0.5), DVec3::new(10.0, 0.5, 0.5), |i| {
            seen.push(i);
            true
        });
        let cells: Vec<usize> = (0..4).map(|x| g.index(DVec3::new(x as f64 + 0.5, 0.5, 0.5)).unwrap()).collect();
        assert_eq!(seen, cells);
        // A diagonal: every step changes one coordinate by one.
        let mut last: Option<DVec3> = None;
        g.trace(DVec3::new(0.1, 0.2, 0.3), DVec3::new(3.9, 2.7, 1.8), |i| {
            let c = g.centre(i);
            if let Some(l) = last {
                assert!(((c - l).abs().element_sum() - 1.0).abs() < 1e-9, "{l} -> {c}");
            }
            last = Some(c);
            true
        });
        assert!((last.unwrap() - DVec3::new(3.5, 2.5, 1.5)).length() < 1e-9);
        let mut none = 0;
        g.trace(DVec3::new(-5.0, -5.0, 5.0), DVec3::new(-1.0, -1.0, 5.0), |_| {
            none += 1;
            true
        });
        assert_eq!(none, 0);
    }
}
