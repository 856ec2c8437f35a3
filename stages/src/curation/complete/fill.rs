//! The scanline fill: samples grown into bands, samples seen through a nearer object dropped,
//! gaps bridged along rows and then down columns in inverse depth (split at an image edge where
//! the two ends disagree), and how each pixel was filled, which the 2D fill reads.

use super::Params;

/// Row pass: bridge short gaps between samples of each row, in inverse depth.
#[inline(always)]
pub(super) fn fill_rows(p: &Params, w: usize, h: usize, inv: &mut [f32], lum: &[f32]) {
    for y in 0..h {
        let row = &mut inv[y * w..(y + 1) * w];
        let lrow = &lum[y * w..(y + 1) * w];
        let mut last: Option<usize> = None;
        for x in 0..w {
            if row[x] <= 0.0 {
                continue;
            }
            if let Some(x0) = last {
                if x - x0 > 1 && x - x0 <= p.row_gap as usize {
                    bridge(row, 1, x0, x, p.tolerance, lrow);
                }
            }
            last = Some(x);
        }
    }
}

/// Fills `v[a+1..b]` (stride `s`) between the samples at `a` and `b`: linear when they agree,
/// otherwise split at the strongest edge of `guide` between them. Returns the split, the first
/// index taking `b`'s value (None when they agreed).
#[inline(always)]
pub(super) fn bridge(v: &mut [f32], s: usize, a: usize, b: usize, tol: f32, guide: &[f32]) -> Option<usize> {
    let (ia, ib) = (v[a * s], v[b * s]);
    let agree = (ia - ib).abs() <= tol * ia.min(ib);
    if agree {
        let n = (b - a) as f32;
        for k in a + 1..b {
            let t = (k - a) as f32 / n;
            v[k * s] = ia + (ib - ia) * t;
        }
    } else {
        let mut split = (a + b).div_ceil(2);
        let mut best = -1.0f32;
        for k in a + 1..=b {
            let g = (guide[k * s] - guide[(k - 1) * s]).abs();
            if g > best {
                best = g;
                split = k;
            }
        }
        for k in a + 1..b {
            v[k * s] = if k < split { ia } else { ib };
        }
        return Some(split);
    }
    None
}

/// The gain in inverse depth per row down the image when a sample `rows` below one of inverse
/// depth `upper` has `lower` and the two look like ground: the lower one nearer, by no more
/// than `tol` (relative) per row.
#[inline(always)]
pub(super) fn ground_slope(upper: f32, lower: f32, rows: usize, tol: f32) -> Option<f32> {
    (lower > upper && lower - upper <= tol * upper * rows as f32).then(|| (lower - upper) / rows as f32)
}

/// Whether the inverse-depth slope over samples `j..j+1` matches the slope of the interval
/// before or after it: a plane seen at a grazing angle (the road) changes depth fast but keeps
/// its inverse-depth slope. `c` holds the column at stride `s`.
#[inline(always)]
pub(super) fn continues_a_plane(c: &[f32], s: usize, samples: &[u32], j: usize, tol: f32) -> bool {
    let at = |k: usize| samples[k] as usize;
    let slope = |k: usize| (c[at(k + 1) * s] - c[at(k) * s]) / (at(k + 1) - at(k)) as f32;
    let sl = slope(j);
    let close = |t: f32| (t - sl).abs() <= tol * sl.abs().max(t.abs()) && t * sl > 0.0;
    (j > 0 && close(slope(j - 1))) || (j + 2 < samples.len() && close(slope(j + 1)))
}

/// `grow` (in mean sample spacings) in whole pixels for `samples` samples in a `w` x `h` image.
pub(super) fn grow_radius(grow: f32, w: usize, h: usize, samples: usize) -> usize {
    let spacing = ((w * h) as f32 / samples.max(1) as f32).sqrt();
    (grow * spacing).round() as usize
}

/// Fills empty pixels (0) with the largest inverse depth (the nearest sample) within a square
/// window of radius `r`; samples stay. The window maximum is separable: along rows into a
/// buffer, then down columns, a row of the image at a time (both passes vectorise).
#[inline(always)]
pub(super) fn grow_samples<T: WindowMax>(inv: &mut [T], w: usize, h: usize, r: usize) {
    if r == 0 || w == 0 {
        return;
    }
    let mut across = inv.to_vec();
    for (src, dst) in inv.chunks_exact(w).zip(across.chunks_exact_mut(w)) {
        for d in 1..=r.min(w - 1) {
            for (o, &v) in dst[..w - d].iter_mut().zip(&src[d..]) {
                *o = o.max(v);
            }
            for (o, &v) in dst[d..].iter_mut().zip(&src[..w - d]) {
                *o = o.max(v);
            }
        }
    }
    let mut grown = vec![T::default(); w];
    for y in 0..h {
        let row = &mut inv[y * w..(y + 1) * w];
        grown.copy_from_slice(&across[y * w..(y + 1) * w]);
        for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
            for (g, &v) in grown.iter_mut().zip(&across[yy * w..(yy + 1) * w]) {
                *g = g.max(v);
            }
        }
        for (i, &g) in row.iter_mut().zip(&grown) {
            if *i == T::default() {
                *i = g;
            }
        }
    }
}

/// What `grow_samples` grows: inverse depths, and the refinement's edge mask (0 = empty).
pub(super) trait WindowMax: Copy + Default + PartialEq {
    fn max(self, other: Self) -> Self;
}

impl WindowMax for f32 {
    #[inline(always)]
    fn max(self, other: f32) -> f32 {
        f32::max(self, other)
    }
}

impl WindowMax for u8 {
    #[inline(always)]
    fn max(self, other: u8) -> u8 {
        Ord::max(self, other)
    }
}

/// Sideways slack of `enclosed_reach`'s search (mean sample spacings): the rings of the nearer
/// object above and below are not in the sample's own column (DepthPrompt's occlusion window uses
/// the same).
const ENCLOSED_SIDE: f32 = 0.3;

/// Sets to 0 the samples of `inv` (inverse depth, 0 = none) seen through a nearer object, and
/// returns where they were. A facade's LiDAR return between the rings of a tree crown in front of it
/// (the LiDAR sat elsewhere, or another keyframe's sweep saw past the crown) lands on the crown's
/// pixels, and the completion spreads it over the crown around it. DepthPrompt drops such samples
/// when nearer samples lie within 2 spacings above and below, but a crown near the camera has its
/// rings farther apart than that, and a longer reach would also drop the facade seen between a
/// crown and a car. Here the reach is long but stays inside the sample's image region: the nearer
/// sample above and the one below must both be reached without crossing a colour step. A facade
/// between a crown and a car has the crown's and the car's outlines between it and them.
#[inline(always)]
pub(super) fn drop_enclosed(p: &Params, inv: &mut [f32], planes: &[u8], w: usize, h: usize) -> Vec<usize> {
    if p.enclosed_reach <= 0.0 || w < 3 || h < 3 {
        return Vec::new();
    }
    // The samples in row-major order, and where each row's samples begin.
    // (Blocks of 16 pixels with no sample, most of them, are passed over by one vectorised test.)
    let mut at: Vec<u32> = Vec::new();
    for (b, block) in inv.chunks(16).enumerate() {
        if block.iter().fold(false, |any, &v| any | (v > 0.0)) {
            at.extend(block.iter().enumerate().filter(|(_, &v)| v > 0.0).map(|(k, _)| (b * 16 + k) as u32));
        }
    }
    if at.is_empty() {
        return Vec::new();
    }
    let rows: Vec<usize> = (0..=h).map(|y| at.partition_point(|&i| (i as usize) < y * w)).collect();
    let spacing = ((w * h) as f32 / at.len() as f32).sqrt();
    let reach = ((p.enclosed_reach * spacing).round() as usize).max(1);
    // At most 31 columns to each side: one bit each in a u64.
    let side = ((ENCLOSED_SIDE * spacing).round() as usize).min(31);
    let keep = 1.0 - p.tolerance.min(1.0);
    // 9x: the steps are compared between sums of 3x3 pixels.
    let limit = (9.0 * p.enclosed_edge) as i32;
    let n = w * h;
    let px = |c: usize, y: usize, x: usize| planes[c * n + y * w + x] as i32;
    // Whether pixels (x, y) and (c, y) have alike colours: beside a crown's outline, the crown's
    // columns do not count.
    let like = |y: usize, x: usize, c: usize| {
        c == x || (0..3).map(|k| (px(k, y, x) - px(k, y, c)).abs()).sum::<i32>() as f32 <= p.enclosed_edge
    };
    // Whether rows a..=b of column x lie in one region: no colour step of `enclosed_edge` between
    // the 3x3 means of two neighbouring rows. (Row r's mean less row r - 1's is, 9x, the sum of 3
    // pixels of row r + 1 less that of row r - 2, rows clamped to the image.)
    let across = |c: usize, y: usize, x: usize| px(c, y, x.saturating_sub(1)) + px(c, y, x) + px(c, y, (x + 1).min(w - 1));
    let one_region = |x: usize, a: usize, b: usize| {
        (a + 1..=b).all(|r| {
            let (lo, hi) = (r.saturating_sub(2), (r + 1).min(h - 1));
            (0..3).map(|c| (across(c, hi, x) - across(c, lo, x)).abs()).sum::<i32>() <= limit
        })
    };
    // Per column, the last sample passed (its row and inverse depth). At a sample, the columns
    // x +- side (bit c - x + side) whose last sample is nearer by more than `tolerance`, within
    // reach and of a pixel like the sample's on its row: candidates, before the region is asked.
    let none = usize::MAX;
    let candidates = |last: &[(usize, f32)], y: usize, x: usize, v: f32| {
        let (a, b) = (x.saturating_sub(side), (x + side).min(w - 1));
        (a..=b).fold(0u64, |m, c| {
            let (r, u) = last[c];
            let hit = r != none && r.abs_diff(y) <= reach && v < u * keep && like(y, x, c);
            m | ((hit as u64) << (c + side - x))
        })
    };
    // Up first: each sample's candidates below, and the rows of their samples.
    let width = 2 * side + 1;
    let mut below = vec![0u64; at.len()];
    let mut below_rows = vec![0u32; at.len() * width];
    let mut last = vec![(none, 0f32); w];
    for y in (0..h).rev() {
        for k in rows[y]..rows[y + 1] {
            let x = at[k] as usize - y * w;
            below[k] = candidates(&last, y, x, inv[at[k] as usize]);
            let mut bits = below[k];
            while bits != 0 {
                let j = bits.trailing_zeros() as usize;
                below_rows[k * width + j] = last[x + j - side].0 as u32;
                bits &= bits - 1;
            }
        }
        for &i in &at[rows[y]..rows[y + 1]] {
            last[i as usize - y * w] = (y, inv[i as usize]);
        }
    }
    // Then down: a sample with candidates on both sides is dropped when one of each is in its
    // region.
    last.fill((none, 0.0));
    let mut dropped = Vec::new();
    for y in 0..h {
        for k in rows[y]..rows[y + 1] {
            if below[k] == 0 {
                continue;
            }
            let i = at[k] as usize;
            let x = i - y * w;
            let mut up = candidates(&last, y, x, inv[i]);
            let mut seen_above = false;
            while up != 0 && !seen_above {
                let c = x + up.trailing_zeros() as usize - side;
                seen_above = one_region(c, last[c].0, y);
                up &= up - 1;
            }
            let mut down = if seen_above { below[k] } else { 0 };
            while down != 0 {
                let j = down.trailing_zeros() as usize;
                if one_region(x + j - side, y, below_rows[k * width + j] as usize) {
                    dropped.push(i);
                    break;
                }
                down &= down - 1;
            }
        }
        for &i in &at[rows[y]..rows[y + 1]] {
            last[i as usize - y * w] = (y, inv[i as usize]);
        }
    }
    // Decided on the map as it came, whatever the order.
    for &i in &dropped {
        inv[i] = 0.0;
    }
    dropped
}

/// How a pixel was filled before the 2D average (`complete`): continuing its neighbours (a
/// sample, a grown or bridged row, a plane along its column, a copied column), split at an image
/// edge between two disagreeing samples of its column, or continuing the ground below the lowest.
pub(super) const CONTINUED: u8 = 0;
pub(super) const SPLIT: u8 = 1;
pub(super) const GROUND: u8 = 2;

/// The rows holding a sample, column by column (compressed: column `x`'s rows are
/// `rows[start[x]..start[x + 1]]`, top to bottom), found in one row-major scan.
pub(super) struct ColumnSamples {
    pub(super) start: Vec<usize>,
    pub(super) rows: Vec<u32>,
}

#[inline(always)]
pub(super) fn column_samples(inv: &[f32], w: usize) -> ColumnSamples {
    let mut start = vec![0usize; w + 1];
    for row in inv.chunks_exact(w) {
        for (x, &v) in row.iter().enumerate() {
            start[x + 1] += (v > 0.0) as usize;
        }
    }
    for x in 0..w {
        start[x + 1] += start[x];
    }
    let mut next = start.clone();
    let mut rows = vec![0u32; start[w]];
    for (y, row) in inv.chunks_exact(w).enumerate() {
        for (x, &v) in row.iter().enumerate() {
            if v > 0.0 {
                rows[next[x]] = y as u32;
                next[x] += 1;
            }
        }
    }
    ColumnSamples { start, rows }
}

#[cfg(test)]
mod tests {
    use super::super::{kernels::colour_planes, tests::grey};
    use super::*;

    #[test]
    fn growing_takes_the_nearest_sample_of_the_square_window() {
        // Against a direct scan of every window, for several radii, on a map with runs of
        // samples, lone ones and samples at the borders.
        let (w, h) = (23, 17);
        let mut rng = dist4d_types::rng::Rng::new(7);
        let sparse: Vec<f32> =
            (0..w * h).map(|_| if rng.range(0.0, 1.0) < 0.08 { rng.range(0.01, 1.0) as f32 } else { 0.0 }).collect();
        for r in [1usize, 2, 4] {
            let mut grown = sparse.clone();
            grow_samples(&mut grown, w, h, r);
            for y in 0..h {
                for x in 0..w {
                    let mut best = 0f32;
                    for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                        for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                            best = best.max(sparse[yy * w + xx]);
                        }
                    }
                    let want = if sparse[y * w + x] > 0.0 { sparse[y * w + x] } else { best };
                    assert_eq!(grown[y * w + x], want, "r {r}, ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn sparser_samples_grow_wider() {
        // 1600x900: three aggregated keyframes (~11,000 samples) vs one 32-beam sweep (~2,700).
        assert_eq!(grow_radius(0.13, 1600, 900, 11_000), 1);
        assert_eq!(grow_radius(0.13, 1600, 900, 2_700), 3);
        assert_eq!(grow_radius(0.0, 1600, 900, 10), 0);
        assert_eq!(grow_radius(0.13, 1600, 900, 0), 156, "no samples: nothing to grow, no panic");
    }

    #[test]
    fn growing_fills_near_empty_pixels_with_the_nearest_sample_only() {
        let (w, h) = (9, 7);
        let mut inv = vec![0f32; w * h];
        inv[3 * w + 4] = 1.0 / 10.0;
        inv[3 * w + 5] = 1.0 / 5.0;
        grow_samples(&mut inv, w, h, 1);
        // Samples stay; their 1-px neighbourhood takes the nearer (larger inverse) depth.
        assert_eq!(inv[3 * w + 4], 0.1);
        assert_eq!(inv[2 * w + 3], 0.1);
        assert_eq!(inv[4 * w + 4], 0.2);
        assert_eq!(inv[3 * w + 6], 0.2);
        assert_eq!(inv[3 * w + 2], 0.0);
        assert_eq!(inv[5 * w + 4], 0.0);
        assert_eq!(inv.iter().filter(|&&v| v > 0.0).count(), 3 * 4);
    }

    #[test]
    fn facade_samples_on_a_crown_are_dropped_but_not_the_facade_between_a_crown_and_a_car() {
        // A facade 8 m away (brown). Left: a crown 5 m away (green, rows 5..45, columns 10..30)
        // with its rings on rows 8 and 42, 34 rows apart, and a facade return between them (row
        // 25) that came through it. Right: a crown (rows 5..20) and a car (blue, rows 35..55),
        // 5 m away, and the facade between them on row 27, seen for real. Beside the crowns'
        // outlines the facade's samples stay.
        let (w, h) = (64usize, 60usize);
        let crown = |x: usize, y: usize| (10..30).contains(&x) && (5..45).contains(&y);
        let crown2 = |x: usize, y: usize| (40..56).contains(&x) && (5..20).contains(&y);
        let car = |x: usize, y: usize| (40..56).contains(&x) && (35..55).contains(&y);
        let image = grey(w as u32, h as u32, |x, y| {
            if crown(x, y) || crown2(x, y) {
                [30, 90, 30]
            } else if car(x, y) {
                [20, 30, 160]
            } else {
                [120, 90, 60]
            }
        });
        let mut inv = vec![0f32; w * h];
        let mut leaks = Vec::new();
        for x in 0..w {
            for y in [8, 10, 25, 27, 42, 45] {
                let near = crown(x, y) && (y == 8 || y == 42) || (crown2(x, y) && y == 10) || (car(x, y) && y == 45);
                let rows = if x < 35 { [8, 25, 42] } else { [8, 27, 42] };
                let facade = !crown(x, y) && !crown2(x, y) && !car(x, y) && rows.contains(&y);
                if near {
                    inv[y * w + x] = 1.0 / 5.0;
                } else if facade || crown(x, y) && y == 25 {
                    inv[y * w + x] = 1.0 / 8.0;
                    if crown(x, y) {
                        leaks.push(y * w + x);
                    }
                }
            }
        }
        let planes = colour_planes(&image.rgb);
        let before = inv.clone();
        let mut dropped = drop_enclosed(&Params::default(), &mut inv, &planes, w, h);
        dropped.sort();
        assert_eq!(dropped, leaks);
        assert!((0..w * h).all(|i| inv[i] == if leaks.contains(&i) { 0.0 } else { before[i] }));
        // Without the colour step, the facade between the crown and the car is dropped too.
        let mut flat = before.clone();
        let no_edges = Params { enclosed_edge: 765.0, ..Params::default() };
        let dropped = drop_enclosed(&no_edges, &mut flat, &planes, w, h);
        assert!(dropped.contains(&(27 * w + 48)), "{dropped:?}");
        // Off, nothing is dropped.
        let mut off = before.clone();
        assert!(drop_enclosed(&Params { enclosed_reach: 0.0, ..Params::default() }, &mut off, &planes, w, h).is_empty());
    }

    #[test]
    fn the_refined_band_is_a_square_window_around_each_edge_pixel() {
        let (w, h) = (9, 7);
        let mut mask = vec![0u8; w * h];
        mask[3 * w + 4] = 1;
        let mut grown = mask.clone();
        grow_samples(&mut grown, w, h, 2);
        for y in 0..h {
            for x in 0..w {
                let inside = x.abs_diff(4) <= 2 && y.abs_diff(3) <= 2;
                assert_eq!(grown[y * w + x] > 0, inside, "({x}, {y})");
            }
        }
        let mut same = mask.clone();
        grow_samples(&mut same, w, h, 0);
        assert_eq!(same, mask);
    }
}
