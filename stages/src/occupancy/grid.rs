//! The voxel grid of an occupancy frame, and rays through it.
//!
//! Convention (checked against a real Occ3D-nuScenes file, docs/occupancy.md): axes x forward, y
//! left, z up of the ego frame; index (i, j, k) in C order over [X, Y, Z]; voxel (i, j, k) covers
//! `min + (i, j, k) * voxel` to the next, with `min` = the range's lower corner in a frame `lift`
//! metres above the ego frame's origin. Occ3D-nuScenes states the range [-40, -40, -1, 40, 40,
//! 5.4] in the ego frame, which would put the road (ego z = 0) in z layer 2; its files have every
//! driveable-surface voxel in layer 0, as a lift of 0.8 m does (the road in the middle of layer 0).

use dist4d_graph::ParamChecks;
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct GridParams {
    /// [x_min, y_min, z_min, x_max, y_max, z_max], metres.
    pub range: [f64; 6],
    /// Voxel edge (m).
    pub voxel: f64,
    /// The grid's frame sits this far (m) above the ego frame's origin (see the module doc).
    pub lift: f64,
}

impl Default for GridParams {
    fn default() -> Self {
        GridParams { range: [-40.0, -40.0, -1.0, 40.0, 40.0, 5.4], voxel: 0.4, lift: 0.8 }
    }
}

impl GridParams {
    pub fn check(&self, c: &mut ParamChecks) {
        c.above("voxel", self.voxel, 0.0, 100.0).within("lift", self.lift, -100.0, 100.0);
        let [x0, y0, z0, x1, y1, z1] = self.range;
        let range_ok =
            self.range.iter().all(|v| v.is_finite() && v.abs() <= 1000.0) && x0 < x1 && y0 < y1 && z0 < z1;
        c.check(range_ok, "range", || {
            format!(
                "must be [x_min, y_min, z_min, x_max, y_max, z_max] within +-1000 m with min < max, found {:?}",
                self.range
            )
        });
        if range_ok && self.voxel > 0.0 && self.voxel <= 100.0 {
            let n: f64 = (0..3).map(|a| ((self.range[a + 3] - self.range[a]) / self.voxel).round()).product();
            c.check(n <= 64.0 * 1024.0 * 1024.0, "voxel", || {
                format!("makes a grid of {n} voxels; at most 64 Mi (a frame's three volumes are held in memory)")
            });
        }
    }

    pub fn grid(&self) -> Grid {
        let dims = [0, 1, 2].map(|a| (((self.range[a + 3] - self.range[a]) / self.voxel).round() as usize).max(1));
        Grid {
            min: DVec3::new(self.range[0], self.range[1], self.range[2] + self.lift),
            voxel: self.voxel,
            dims,
        }
    }
}

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_road_lands_in_layer_zero_and_indices_run_x_then_y_then_z() {
        let g = GridParams::default().grid();
        assert_eq!(g.dims, [200, 200, 16]);
        let road = g.index(DVec3::new(0.1, 0.1, 0.0)).unwrap();
        assert_eq!(road % 16, 0, "ego z = 0 is in z layer 0");
        assert_eq!(road, (100 * 200 + 100) * 16);
        assert_eq!(g.index(DVec3::new(-39.9, -39.9, -0.19)), Some(0));
        assert_eq!(g.index(DVec3::new(0.0, 0.0, -0.21)), None, "below the grid");
        let c = g.centre(road);
        assert!((c - DVec3::new(0.2, 0.2, 0.0)).length() < 1e-9, "{c}");
    }

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
