//! `NearestFill`: sparse depth -> every pixel takes the depth of its nearest sample, the "initial
//! depth prompt" DiST-4D hands to its learned depth completer (Sec. 3.2).
//!
//! The fill is exact: every pixel takes the depth of the nearest (Euclidean, in pixels) sparse
//! pixel, from a linear-time distance transform (Felzenszwalb and Huttenlocher 2012) that carries
//! the nearest seed along; ties go to the seed found first (smaller row, then column). About 40 ms
//! for 1600x900, which is why it is a stage of its own: pipelines run it only when a completer
//! reads it.

use dist4d_runtime::Made;
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use anyhow::Result;
use dist4d_graph::Validate;
use dist4d_types::artifact::{DepthMap};
use serde::{Deserialize, Serialize};

/// No parameters.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
#[serde(deny_unknown_fields)]
pub struct Params {}

impl Validate for Params {}

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

crate::inputs! {
    pub struct Inputs {
        /// sparse depth, 0 = none (e.g. DepthPrompt.sparse)
        sparse: One<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the nearest-neighbour fill (all 0 when there is no sample)
        prompt: One<DepthMap>,
    }
}

pub struct NearestFill;

impl Stage for NearestFill {
    const KIND: &'static str = "NearestFill";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "Sparse depth -> dense: each pixel takes its nearest sample's depth (DiST-4D's initial prompt)";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(_: Params) -> Result<Self> {
        Ok(NearestFill)
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        Ok(Outputs { prompt: nearest_fill(&i.sparse) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::rng::Rng;

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
