//! `DepthPrompt`: points -> the sparse z-buffered depth of one camera and its nearest-neighbour
//! fill, the "initial depth prompt" DiST-4D hands to its depth completer (Sec. 3.2).
//!
//! The fill is exact: every pixel takes the depth of the nearest (Euclidean, in pixels) sparse
//! pixel, from a linear-time distance transform (Felzenszwalb and Huttenlocher 2012) that carries
//! the nearest seed along; ties go to the seed found first (smaller row, then column).

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

/// For every pixel, the index of the nearest pixel with depth > 0 (`u32::MAX` if there is none).
pub fn nearest_seed(depth: &DepthMap) -> Vec<u32> {
    let (w, h) = (depth.width as usize, depth.height as usize);
    const FAR: i64 = i64::MAX / 4;
    // Pass 1, columns: squared vertical distance to the nearest seed in the column, and its row.
    let mut col_d2 = vec![FAR; w * h];
    let mut col_row = vec![u32::MAX; w * h];
    for x in 0..w {
        let mut last: Option<usize> = None;
        for y in 0..h {
            if depth.data[y * w + x] > 0.0 {
                last = Some(y);
            }
            if let Some(r) = last {
                col_d2[y * w + x] = ((y - r) * (y - r)) as i64;
                col_row[y * w + x] = r as u32;
            }
        }
        let mut next: Option<usize> = None;
        for y in (0..h).rev() {
            if depth.data[y * w + x] > 0.0 {
                next = Some(y);
            }
            if let Some(r) = next {
                let d = ((r - y) * (r - y)) as i64;
                if d < col_d2[y * w + x] {
                    col_d2[y * w + x] = d;
                    col_row[y * w + x] = r as u32;
                }
            }
        }
    }
    // Pass 2, rows: lower envelope of the parabolas (x - q)^2 + col_d2[q].
    let mut out = vec![u32::MAX; w * h];
    let mut v = vec![0usize; w];
    let mut z = vec![0f64; w + 1];
    for y in 0..h {
        let f = &col_d2[y * w..(y + 1) * w];
        let mut k: isize = -1;
        for q in 0..w {
            if f[q] >= FAR {
                continue;
            }
            loop {
                if k < 0 {
                    k = 0;
                    v[0] = q;
                    z[0] = f64::NEG_INFINITY;
                    z[1] = f64::INFINITY;
                    break;
                }
                let p = v[k as usize];
                let s = ((f[q] + (q * q) as i64) - (f[p] + (p * p) as i64)) as f64 / (2.0 * (q as f64 - p as f64));
                if s <= z[k as usize] {
                    k -= 1;
                    continue;
                }
                k += 1;
                v[k as usize] = q;
                z[k as usize] = s;
                z[k as usize + 1] = f64::INFINITY;
                break;
            }
        }
        if k < 0 {
            continue;
        }
        let mut j = 0usize;
        for x in 0..w {
            while z[j + 1] < x as f64 {
                j += 1;
            }
            let q = v[j];
            out[y * w + x] = col_row[y * w + q] * w as u32 + q as u32;
        }
    }
    out
}

/// The nearest-neighbour fill of a sparse depth map (all zeros stay zeros).
pub fn nearest_fill(sparse: &DepthMap) -> DepthMap {
    let seeds = nearest_seed(sparse);
    let data = seeds.iter().map(|&s| if s == u32::MAX { 0.0 } else { sparse.data[s as usize] }).collect();
    DepthMap { width: sparse.width, height: sparse.height, data }
}

struct Op(Params);

impl TypedOp for Op {
    fn run(&self, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Vec<Vec<u8>>> {
        let view = CameraView::from_inputs(inputs)?;
        let sparse = project_points(&self.0, &one::<PointCloud>(inputs, 0)?, &view);
        let filled = nearest_fill(&sparse);
        use crate::artifact::Artifact;
        Ok(vec![sparse.encode(), filled.encode()])
    }
}

pub fn def() -> StageDef {
    StageDef::new::<Params>(
        "DepthPrompt",
        1,
        "Points -> sparse z-buffered depth of one camera and its nearest-neighbour fill (the depth prompt)",
        crate::camera::cloud_and_camera_ports("the cloud, in the frame of `cloud_calib` at `cloud_pose`"),
        vec![
            PortSpec::one("sparse", "DepthMap", "z-buffered projection, 0 = no point"),
            PortSpec::one("prompt", "DepthMap", "nearest-neighbour fill of `sparse`"),
        ],
        vec!["camera"],
        |p: Params| Ok(Box::new(Op(p))),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::rng::Rng;

    #[test]
    fn the_fill_takes_the_exactly_nearest_seed() {
        let (w, h) = (37usize, 23usize);
        let mut rng = Rng::new(9);
        let mut d = DepthMap::new(w as u32, h as u32);
        for _ in 0..12 {
            let i = rng.below((w * h) as u64) as usize;
            d.data[i] = 1.0 + i as f32;
        }
        let seeds: Vec<usize> = (0..w * h).filter(|&i| d.data[i] > 0.0).collect();
        let got = nearest_seed(&d);
        for i in 0..w * h {
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            let dist = |s: usize| {
                let (sx, sy) = ((s % w) as i64, (s / w) as i64);
                (sx - x).pow(2) + (sy - y).pow(2)
            };
            let best = seeds.iter().map(|&s| dist(s)).min().unwrap();
            assert_eq!(dist(got[i] as usize), best, "pixel ({x}, {y})");
        }
        let filled = nearest_fill(&d);
        assert!(filled.data.iter().all(|&z| z > 0.0));
        assert!(nearest_fill(&DepthMap::new(4, 3)).data.iter().all(|&z| z == 0.0));
    }
}
