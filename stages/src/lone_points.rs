//! Which points of a fused cloud stand alone: the last rule a cloud made from depth maps
//! (`SurroundCloud`) applies, after [`crate::lift`] has dropped every pixel it can tell from one
//! image.
//!
//! A surface lifted from a camera is sampled every few centimetres near the ego and every few
//! decimetres at 100 m (a pixel's footprint), so on any surface a point has many others within
//! a metre. What a per-image rule lets through one pixel at a time (a speckle that has
//! neighbours in its image but not in depth, the one pixel of a ramp that passed every test)
//! lands alone in 3D. A point is **lone** when fewer than `min_neighbours` other points lie within
//! `radius` metres of it; lone points are dropped, and the test is repeated on the neighbours of
//! what was dropped until nothing changes, so that no point left depends on a dropped one for
//! its company (with `min_neighbours` 1, no point left is farther than `radius` from another).
//!
//! The params and what they do are in docs/stages.md (`SurroundCloud`) and docs/BENCHMARKS.md
//! ("Flying pixels (issue 42)").

use crate::voxel_hash::VoxelHasher;
use dist4d_graph::ParamChecks;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::hash::BuildHasherDefault;

/// The rule's params (see the module doc).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct LoneParams {
    /// Metres: the neighbourhood a point needs company in.
    pub radius: f32,
    /// Other points it needs within `radius`; 0 turns the rule off.
    pub min_neighbours: u32,
}

impl Default for LoneParams {
    fn default() -> Self {
        LoneParams { radius: 1.0, min_neighbours: 3 }
    }
}

impl LoneParams {
    /// Range checks, added to the stage's own.
    pub fn check(&self, c: &mut ParamChecks) {
        c.above("radius", self.radius as f64, 0.0, 1e3).count("min_neighbours", self.min_neighbours as u64, 0, 1000);
    }
}

type Cell = (i64, i64, i64);

/// Per point, whether it has company (see the module doc). The answer does not depend on the
/// points' order.
pub fn with_company(points: &[[f32; 3]], p: &LoneParams) -> Vec<bool> {
    let mut alive = vec![true; points.len()];
    if p.min_neighbours == 0 || points.is_empty() {
        return alive;
    }
    let r = p.radius as f64;
    let cell = |q: &[f32; 3]| -> Cell {
        ((q[0] as f64 / r).floor() as i64, (q[1] as f64 / r).floor() as i64, (q[2] as f64 / r).floor() as i64)
    };
    let mut grid: HashMap<Cell, Vec<u32>, BuildHasherDefault<VoxelHasher>> = HashMap::default();
    for (k, q) in points.iter().enumerate() {
        grid.entry(cell(q)).or_default().push(k as u32);
    }
    let r2 = (p.radius * p.radius) as f64;
    let d2 = |a: &[f32; 3], b: &[f32; 3]| {
        let (x, y, z) = ((a[0] - b[0]) as f64, (a[1] - b[1]) as f64, (a[2] - b[2]) as f64);
        x * x + y * y + z * z
    };
    // The living points within `radius` of point k, up to `cap` of them.
    let company = |k: usize, alive: &[bool], cap: usize, out: &mut Vec<u32>| {
        out.clear();
        let (cx, cy, cz) = cell(&points[k]);
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let Some(list) = grid.get(&(cx + dx, cy + dy, cz + dz)) else { continue };
                    for &m in list {
                        if m as usize != k && alive[m as usize] && d2(&points[m as usize], &points[k]) <= r2 {
                            out.push(m);
                            if out.len() >= cap {
                                return;
                            }
                        }
                    }
                }
            }
        }
    };
    let need = p.min_neighbours as usize;
    let mut candidates: Vec<u32> = (0..points.len() as u32).collect();
    let mut found = Vec::new();
    while !candidates.is_empty() {
        // One pass decides on every candidate against the same living set, then drops.
        let lone: Vec<u32> = candidates
            .iter()
            .copied()
            .filter(|&k| {
                company(k as usize, &alive, need, &mut found);
                found.len() < need
            })
            .collect();
        for &k in &lone {
            alive[k as usize] = false;
        }
        // Who kept company with a dropped point is tested again.
        let mut next = Vec::new();
        for &k in &lone {
            company(k as usize, &alive, usize::MAX, &mut found);
            next.extend_from_slice(&found);
        }
        next.sort_unstable();
        next.dedup();
        candidates = next;
    }
    alive
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 2 x 2 m wall at x = 10 sampled every 0.1 m.
    fn wall() -> Vec<[f32; 3]> {
        (0..400).map(|k| [10.0, (k % 20) as f32 * 0.1, (k / 20) as f32 * 0.1]).collect()
    }

    #[test]
    fn a_surface_stays_and_points_alone_in_the_air_go() {
        let mut pts = wall();
        // A flying pixel 5 m in front of the wall, and a pair of them 20 m behind it.
        pts.extend([[5.0, 1.0, 1.0], [30.0, 1.0, 1.0], [30.3, 1.0, 1.0]]);
        let keep = with_company(&pts, &LoneParams::default());
        assert!(keep[..400].iter().all(|&k| k), "the wall stays");
        assert!(!keep[400] && !keep[401] && !keep[402], "{:?}", &keep[400..]);
        // With the rule off every point stays.
        assert!(with_company(&pts, &LoneParams { min_neighbours: 0, ..LoneParams::default() }).iter().all(|&k| k));
    }

    #[test]
    fn a_chain_that_only_had_company_in_what_was_dropped_goes_too() {
        // Four points in a row 0.9 m apart: the ends have one neighbour, the middle two have
        // two. With 2 needed, the ends go first, then the middle has one each: all go.
        let pts = [[0.0, 0.0, 0.0], [0.9, 0.0, 0.0], [1.8, 0.0, 0.0], [2.7, 0.0, 0.0]];
        let keep = with_company(&pts, &LoneParams { radius: 1.0, min_neighbours: 2 });
        assert_eq!(keep, vec![false; 4]);
        // With one needed, the chain is its own company.
        let keep = with_company(&pts, &LoneParams { radius: 1.0, min_neighbours: 1 });
        assert_eq!(keep, vec![true; 4]);
    }
}
