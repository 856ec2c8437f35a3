//! Hole filling, background first: what the built-in generators (`FillViewBaseline`,
//! `GenerateFuture`) make of a reprojected condition's holes.
//!
//! The holes of a reprojection are mostly disocclusions: background that a nearer object hid
//! from the source camera. Filling them from the nearer side would grow the object; here each
//! hole pixel looks for the nearest valid pixel along its row and column (four directions) and
//! takes, of those found, the ones on the farthest surface (within `tolerance` of the farthest
//! depth), averaged with weights 1 / distance. Holes with no valid pixel on any of the four
//! lines (a corner the source never saw) take the nearest filled value the same way in a second
//! pass. The result is blurry and streaky inside large holes: it is a baseline, not a generator,
//! and its scores (docs/BENCHMARKS.md) are what a learned model must beat.

/// Per pixel, the index of the nearest valid pixel in each of the four directions (or none).
fn nearest_valid(valid: &[bool], w: usize, h: usize) -> [Vec<u32>; 4] {
    const NONE: u32 = u32::MAX;
    let mut left = vec![NONE; w * h];
    let mut right = vec![NONE; w * h];
    let mut up = vec![NONE; w * h];
    let mut down = vec![NONE; w * h];
    for y in 0..h {
        let mut last = NONE;
        for x in 0..w {
            let i = y * w + x;
            left[i] = last;
            if valid[i] {
                last = i as u32;
            }
        }
        last = NONE;
        for x in (0..w).rev() {
            let i = y * w + x;
            right[i] = last;
            if valid[i] {
                last = i as u32;
            }
        }
    }
    // Per column, the last valid pixel seen going down (then up) the image.
    let mut last = vec![NONE; w];
    for y in 0..h {
        for (x, l) in last.iter_mut().enumerate() {
            let i = y * w + x;
            up[i] = *l;
            if valid[i] {
                *l = i as u32;
            }
        }
    }
    last.iter_mut().for_each(|l| *l = NONE);
    for y in (0..h).rev() {
        for (x, l) in last.iter_mut().enumerate() {
            let i = y * w + x;
            down[i] = *l;
            if valid[i] {
                *l = i as u32;
            }
        }
    }
    [left, right, up, down]
}

/// The hole filling of the module doc: returns the filled RGB and depth.
pub fn fill(rgb: &[u8], depth: &[f32], valid: &[bool], w: usize, h: usize, tolerance: f32) -> (Vec<u8>, Vec<f32>) {
    let mut out_rgb = rgb.to_vec();
    let mut out_depth: Vec<f32> = depth.iter().zip(valid).map(|(&z, &v)| if v { z } else { 0.0 }).collect();
    let mut filled = valid.to_vec();
    // Two passes: the second reaches holes whose lines held no valid pixel, from the first's fill.
    for _ in 0..2 {
        let near = nearest_valid(&filled, w, h);
        let (src_rgb, src_depth, src_filled) = (out_rgb.clone(), out_depth.clone(), filled.clone());
        for i in 0..w * h {
            if src_filled[i] {
                continue;
            }
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            let mut cand: [(f32, usize); 4] = [(0.0, 0); 4];
            let mut n = 0;
            let mut far = 0f32;
            for dir in &near {
                let j = dir[i];
                if j != u32::MAX {
                    let j = j as usize;
                    let dist = ((j % w) as i64 - x).abs() + ((j / w) as i64 - y).abs();
                    cand[n] = (dist as f32, j);
                    n += 1;
                    far = far.max(src_depth[j]);
                }
            }
            if n == 0 {
                continue;
            }
            let (mut wsum, mut acc, mut zacc) = (0f32, [0f32; 3], 0f32);
            for &(dist, j) in &cand[..n] {
                if src_depth[j] >= far * (1.0 - tolerance) {
                    let wt = 1.0 / dist.max(1.0);
                    wsum += wt;
                    zacc += wt * src_depth[j];
                    for k in 0..3 {
                        acc[k] += wt * src_rgb[3 * j + k] as f32;
                    }
                }
            }
            out_depth[i] = zacc / wsum;
            for k in 0..3 {
                out_rgb[3 * i + k] = (acc[k] / wsum).round() as u8;
            }
            filled[i] = true;
        }
    }
    (out_rgb, out_depth)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_disocclusion_is_filled_from_the_background_not_the_object() {
        // A row: object (5 m, red) | hole | wall (20 m, grey).
        let w = 10;
        let depth = [5.0, 5.0, 5.0, 0.0, 0.0, 0.0, 20.0, 20.0, 20.0, 20.0];
        let valid: Vec<bool> = depth.iter().map(|&z| z > 0.0).collect();
        let rgb: Vec<u8> = depth.iter().flat_map(|&z| if z == 5.0 { [250, 0, 0] } else { [100, 100, 100] }).collect();
        let (rgb, depth) = fill(&rgb, &depth, &valid, w, 1, 0.1);
        for x in 3..6 {
            assert_eq!(depth[x], 20.0, "{x}");
            assert_eq!(&rgb[3 * x..3 * x + 3], &[100, 100, 100]);
        }
    }

    #[test]
    fn every_pixel_is_filled_when_anything_is_valid() {
        let (w, h) = (7, 5);
        let mut depth = vec![0.0f32; w * h];
        depth[w * 2 + 3] = 10.0;
        let valid: Vec<bool> = depth.iter().map(|&z| z > 0.0).collect();
        let (_, out) = fill(&vec![9; 3 * w * h], &depth, &valid, w, h, 0.1);
        assert!(out.iter().all(|&z| z == 10.0), "{out:?}");
    }
}
