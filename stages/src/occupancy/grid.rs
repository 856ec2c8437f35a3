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
        use dist4d_types::occ3d::{LIFT, RANGE, VOXEL};
        GridParams { range: RANGE, voxel: VOXEL, lift: LIFT }
    }
}

impl GridParams {
    pub fn check(&self, c: &mut ParamChecks) {
        c.above("voxel", self.voxel, 0.0, 100.0).within("lift", self.lift, -100.0, 100.0);
        let [x0, y0, z0, x1, y1, z1] = self.range;
        let range_ok = self.range.iter().all(|v| v.is_finite() && v.abs() <= 1000.0) && x0 < x1 && y0 < y1 && z0 < z1;
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
        Grid { min: DVec3::new(self.range[0], self.range[1], self.range[2] + self.lift), voxel: self.voxel, dims }
    }
}

pub use dist4d_types::voxels::Grid;

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
}
