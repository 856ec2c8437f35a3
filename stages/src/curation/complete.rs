//! `CompleteDepth`: dense metric depth from an image and a sparse depth (DiST-4D's last curation
//! step; the paper uses a learned completer, DepthLab, and sets sky to a fixed far depth).
//!
//! The built-in completer ([`ScanlineCompleter`]) interpolates *inverse* depth, which is linear
//! in image coordinates on any plane (road, facades), so between two samples of one surface it is
//! exact. First along rows (gaps up to `row_gap` px), then along columns (up to `column_gap`).
//! Where the two ends of a gap disagree by more than `tolerance` (relative), the gap spans a depth
//! edge: it is split at the strongest luminance edge of the image inside the gap, each side taking
//! its end's depth (the image guides where the object ends); when the lower end is ground (the
//! samples below it keep its inverse-depth slope) and the upper end farther, the ground below the
//! split keeps its slope until it meets the upper surface's depth. Below a column's lowest sample
//! the ground continues (inverse depth extrapolated from a sample a grown ring's width up); above
//! its highest sample a vertical surface continues (constant depth). Pixels of the `sky` mask
//! (from `EstimateSky`, or a segmentation through it) get
//! `sky_depth` (paper: 100 m). Columns with no sample take their nearest filled column.
//! Pixels more than `smooth_from` px from every sample then take the edge-aware 2D average of the
//! measured depths around them, corrected towards their surface's continuation where the two
//! agree (`smooth_unsupported`), and the pixels near the result's depth
//! edges are refined towards Levin et al.'s colour-affinity least squares (`refine`).
//!
//! Other completers (e.g. a learned one behind a worker) implement [`DepthCompleter`].

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{bail, ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, Image, Mask};
use dist4d_types::formats::to_16_significant_bits;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Longest horizontal gap (px) bridged between two samples of a row.
    pub row_gap: u32,
    /// Longest vertical gap (px) interpolated between two samples of a column (longer ones are
    /// split at an edge, as when the two disagree).
    pub column_gap: u32,
    /// Two samples belong to one surface when their depths differ by less than this fraction.
    pub tolerance: f32,
    /// Depth given to sky pixels (m), rounded to 16 significant bits as every output depth is; the
    /// paper uses 100 m.
    pub sky_depth: f32,
    /// Empty pixels within this distance (square window) of samples first take the nearest
    /// depth among them, so that 1-px LiDAR rings become bands the row pass can follow. In mean
    /// sample spacings (sqrt(image area / samples)), rounded to whole pixels: sparse input (one
    /// 32-beam sweep) needs wider bands than three aggregated keyframes, where wide bands only
    /// smear depth edges.
    pub grow: f32,
    /// A sample is dropped as seen through a nearer object when, within this many mean sample
    /// spacings straight up and straight down (give or take 0.3 spacings sideways), the nearest
    /// sample of its own image region is nearer than it by more than `tolerance` on both sides;
    /// a region ends at a colour step of `enclosed_edge` between two rows. 0 = off (16 takes
    /// 0.02-0.05 points off the pixels off by more than 10% on the synthetic seeds, for ~2 ms per
    /// 1600x900 image; docs/stages.md).
    pub enclosed_reach: f32,
    /// The colour step (sum of |dR| + |dG| + |dB| between 3x3 means of two neighbouring rows,
    /// 0-765) that ends an image region for `enclosed_reach`.
    pub enclosed_edge: f32,
    /// Pixels farther than this (px) from every sample take the edge-aware average of the pixels
    /// within it, spread over the image, instead of their column's extrapolation (no vertical
    /// streaks, no crown's depth on the facade above it), corrected as `keep_planes` says; the
    /// ground below a column's lowest sample keeps its extrapolation.
    pub smooth_from: f32,
    /// Spatial reach (px) of that average (the domain transform's sigma_s); 0 = off.
    pub smooth_sigma: f32,
    /// A colour step (sum of |dR| + |dG| + |dB|, 0-765) between the texture-evened colours of two
    /// neighbouring blocks (`smooth_texture`) that cuts the average as much as `smooth_sigma`
    /// pixels of distance (the domain transform's sigma_r, in these units) at full resolution; the
    /// average is taken over 2x2 blocks, where it cuts as much as 2 `smooth_sigma` (see
    /// `smooth_unsupported`).
    pub smooth_edge: f32,
    /// The average's links compare the blocks' colours averaged over a square of this radius, in
    /// blocks (2: 5 x 5 blocks, 10 x 10 px; 0: each block's own colour). A facade's or a crown's
    /// texture then counts as one colour and their outlines still as steps: with the blocks' own
    /// colours the texture's steps added up along every path, so that a facade's samples 200 px
    /// away reached the pixels above a tree crown less than the crown's samples across its outline.
    pub smooth_texture: u32,
    /// A colour step (as `smooth_edge`, between a pixel's own colour and a block's own mean) that
    /// weighs a block as much as 2 `smooth_sigma` px of distance when the average is brought back
    /// from the blocks to the pixels (`likeness` counts the colour twice).
    pub spread_edge: f32,
    /// Row-then-column passes of that average (Gastal and Oliveira use 3; over 2x2 blocks 2 gave
    /// the same accuracy).
    pub smooth_iterations: u32,
    /// Pixels the row and column passes filled by continuing a surface (a bridged row gap,
    /// linear between two agreeing samples of a column, a vertical surface above the highest
    /// sample of a column; not a column gap split at an image edge) keep that value where the 2D
    /// average agrees with it, and take the average more the more it disagrees: wholly at this
    /// relative difference. The correction is averaged over 8 px along the row. 0 = always the
    /// average.
    pub keep_planes: f32,
    /// Conjugate-gradient iterations refining the result towards the colour-affinity least
    /// squares of Levin et al. 2004 (every pixel like its like-coloured neighbours, samples held);
    /// 0 = off.
    pub refine_iterations: u32,
    /// Colour distance (Euclidean RGB, 0-441) at which a link's affinity falls to exp(-1/2).
    pub refine_sigma: f32,
    /// How hard a sample holds its own pixel, against a neighbour's affinity of at most 1.
    pub refine_weight: f32,
    /// Only pixels within this distance (px) of a depth edge of the filled map are refined.
    pub refine_band: u32,
    /// A learned completer as an external worker (DepthLab-style: RGB + the prompt in, dense depth
    /// out; docs/workers.md) in place of the built-in one: `Some((program: "python3", args:
    /// ["my_completer.py"]))`. Its name, version and weights enter the task keys. The sky and the
    /// support map are the engine's, as with the built-in completer.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worker: Option<crate::model_worker::WorkerSpec>,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            row_gap: 12,
            column_gap: 120,
            tolerance: 0.1,
            sky_depth: 100.0,
            grow: 0.13,
            enclosed_reach: 16.0,
            enclosed_edge: 20.0,
            smooth_from: 1.0,
            smooth_sigma: 30.0,
            smooth_edge: 15.0,
            smooth_texture: 2,
            spread_edge: 40.0,
            smooth_iterations: 2,
            keep_planes: 0.5,
            refine_iterations: 40,
            refine_sigma: 5.0,
            refine_weight: 100.0,
            refine_band: 5,
            worker: None,
        }
    }
}

/// Longest gap (px) worth bridging: wider than any camera image.
const MAX_GAP_PX: u64 = 100_000;

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .count("row_gap", self.row_gap as u64, 0, MAX_GAP_PX)
            .count("column_gap", self.column_gap as u64, 0, MAX_GAP_PX)
            .within("tolerance", self.tolerance as f64, 0.0, 100.0)
            .above("sky_depth", self.sky_depth as f64, 0.0, 1e6)
            // The growing window's work is image area x radius; 16 spacings is already coarse.
            .within("grow", self.grow as f64, 0.0, 16.0)
            // The search is one pass down and one up whatever the reach; past the image it is moot.
            .within("enclosed_reach", self.enclosed_reach as f64, 0.0, MAX_GAP_PX as f64)
            .within("enclosed_edge", self.enclosed_edge as f64, 0.0, 765.0)
            .within("smooth_from", self.smooth_from as f64, 0.0, MAX_GAP_PX as f64)
            .within("smooth_sigma", self.smooth_sigma as f64, 0.0, MAX_GAP_PX as f64)
            .above("smooth_edge", self.smooth_edge as f64, 0.0, 765.0)
            // Its cost grows with the radius; 16 blocks is a 66 px square, past any texture.
            .count("smooth_texture", self.smooth_texture as u64, 0, 16)
            .above("spread_edge", self.spread_edge as f64, 0.0, 765.0)
            // Each pass costs a few ms; more than a handful changes nothing (the sigmas halve).
            .count("smooth_iterations", self.smooth_iterations as u64, 0, 8)
            .within("keep_planes", self.keep_planes as f64, 0.0, 100.0)
            // Each iteration costs a few ms per megapixel.
            .count("refine_iterations", self.refine_iterations as u64, 0, 10_000)
            .above("refine_sigma", self.refine_sigma as f64, 0.0, 1e4)
            .above("refine_weight", self.refine_weight as f64, 0.0, 1e9)
            .count("refine_band", self.refine_band as u64, 0, MAX_GAP_PX)
            .done()
            .into_iter()
            .chain(crate::model_worker::WorkerSpec::problems_of(self.worker.as_ref()))
            .collect()
    }
}

/// A depth completer: image + sparse metric depth (0 = unknown) -> dense metric depth.
pub trait DepthCompleter {
    /// `support`: also make the support map (a confidence a caller may not need).
    fn complete(&self, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Result<Completion>;
}

/// The built-in, image-guided inverse-depth interpolation described in the module docs.
pub struct ScanlineCompleter(pub Params);

impl DepthCompleter for ScanlineCompleter {
    fn complete(&self, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Result<Completion> {
        ensure!(
            image.width == sparse.width && image.height == sparse.height,
            "the image is {}x{} but the sparse depth is {}x{}",
            image.width,
            image.height,
            sparse.width,
            sparse.height
        );
        if let Some(s) = sky {
            ensure!(
                s.width == image.width && s.height == image.height,
                "the sky mask is {}x{} but the image is {}x{}",
                s.width,
                s.height,
                image.width,
                image.height
            );
        }
        // A sample nearer than a millimetre is no depth a sensor gives, and its inverse (up to +inf
        // for a subnormal one) spreads through the fill: one such sample left 80% of a map
        // without depth. (A fold, not `position`: it vectorises; the pixel is looked for only then.)
        if sparse.data.iter().fold(false, |any, &z| any | ((z > 0.0) & (z < MIN_SAMPLE_DEPTH))) {
            let i = sparse.data.iter().position(|&z| z > 0.0 && z < MIN_SAMPLE_DEPTH).unwrap_or(0);
            let w = sparse.width.max(1) as usize;
            bail!(
                "the sparse depth has a sample of {:e} m at pixel ({}, {}): nearer than {} m, not a depth in metres (0 = no sample)",
                sparse.data[i],
                i % w,
                i / w,
                MIN_SAMPLE_DEPTH
            );
        }
        Ok(complete(&self.0, image, sparse, sky, support))
    }
}

/// The nearest depth (m) a sparse sample may have.
pub const MIN_SAMPLE_DEPTH: f32 = 1e-3;

/// Luma (ITU-R BT.601 weights, 0-255) of every pixel.
#[inline(always)]
pub(crate) fn luminance(image: &Image) -> Vec<f32> {
    // Collected, not written into a zeroed map: the zeroing was a pass of its own.
    image.rgb.chunks_exact(3).map(|p| 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32).collect()
}

/// Row pass: bridge short gaps between samples of each row, in inverse depth.
#[inline(always)]
fn fill_rows(p: &Params, w: usize, h: usize, inv: &mut [f32], lum: &[f32]) {
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
fn bridge(v: &mut [f32], s: usize, a: usize, b: usize, tol: f32, guide: &[f32]) -> Option<usize> {
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
fn ground_slope(upper: f32, lower: f32, rows: usize, tol: f32) -> Option<f32> {
    (lower > upper && lower - upper <= tol * upper * rows as f32).then(|| (lower - upper) / rows as f32)
}

/// Whether the inverse-depth slope over samples `j..j+1` matches the slope of the interval
/// before or after it: a plane seen at a grazing angle (the road) changes depth fast but keeps
/// its inverse-depth slope. `c` holds the column at stride `s`.
#[inline(always)]
fn continues_a_plane(c: &[f32], s: usize, samples: &[u32], j: usize, tol: f32) -> bool {
    let at = |k: usize| samples[k] as usize;
    let slope = |k: usize| (c[at(k + 1) * s] - c[at(k) * s]) / (at(k + 1) - at(k)) as f32;
    let sl = slope(j);
    let close = |t: f32| (t - sl).abs() <= tol * sl.abs().max(t.abs()) && t * sl > 0.0;
    (j > 0 && close(slope(j - 1))) || (j + 2 < samples.len() && close(slope(j + 1)))
}

/// `grow` (in mean sample spacings) in whole pixels for `samples` samples in a `w` x `h` image.
fn grow_radius(grow: f32, w: usize, h: usize, samples: usize) -> usize {
    let spacing = ((w * h) as f32 / samples.max(1) as f32).sqrt();
    (grow * spacing).round() as usize
}

/// Fills empty pixels (0) with the largest inverse depth (the nearest sample) within a square
/// window of radius `r`; samples stay. The window maximum is separable: along rows into a
/// buffer, then down columns, a row of the image at a time (both passes vectorise).
#[inline(always)]
fn grow_samples<T: WindowMax>(inv: &mut [T], w: usize, h: usize, r: usize) {
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
fn drop_enclosed(p: &Params, inv: &mut [f32], planes: &[u8], w: usize, h: usize) -> Vec<usize> {
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

/// What `grow_samples` grows: inverse depths, and the refinement's edge mask (0 = empty).
trait WindowMax: Copy + Default + PartialEq {
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

/// How a pixel was filled before the 2D average (`complete`): continuing its neighbours (a
/// sample, a grown or bridged row, a plane along its column, a copied column), split at an image
/// edge between two disagreeing samples of its column, or continuing the ground below the lowest.
const CONTINUED: u8 = 0;
const SPLIT: u8 = 1;
const GROUND: u8 = 2;

/// The rows holding a sample, column by column (compressed: column `x`'s rows are
/// `rows[start[x]..start[x + 1]]`, top to bottom), found in one row-major scan.
struct ColumnSamples {
    start: Vec<usize>,
    rows: Vec<u32>,
}

#[inline(always)]
fn column_samples(inv: &[f32], w: usize) -> ColumnSamples {
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

/// The completion of `sparse` guided by `image`, with the support map when `support` asks for it.
pub fn complete(p: &Params, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Completion {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512bw") {
        // SAFETY: the CPU has AVX-512 F and BW, checked just above.
        return unsafe { complete_avx512(p, image, sparse, sky, support) };
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, checked just above.
        return unsafe { complete_avx2(p, image, sparse, sky, support) };
    }
    complete_portable(p, image, sparse, sky, support)
}

/// The same code compiled for AVX2: its element-wise loops and eight-lane sums run in 256-bit
/// vectors instead of two 128-bit ones, ~8% less time per image (docs/BENCHMARKS.md). Without FMA,
/// every operation rounds as in the portable build, so the outputs are bit-identical (a test
/// checks it): which machine of a cluster computed a cached map does not change it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn complete_avx2(p: &Params, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Completion {
    complete_portable(p, image, sparse, sky, support)
}

/// The same code for AVX-512 (F, BW, VL): ~13% less time per image than the AVX2 build on this
/// project's machine (docs/BENCHMARKS.md); bit-identical for the same reason (a test checks it).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
unsafe fn complete_avx512(p: &Params, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Completion {
    complete_portable(p, image, sparse, sky, support)
}

/// The completion; its helpers are inlined into it, so that each build of it (portable, AVX2)
/// compiles them for its own instruction set.
#[inline(always)]
fn complete_portable(p: &Params, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Completion {
    let (w, h) = (sparse.width as usize, sparse.height as usize);
    let mut inv = map(&sparse.data, |z| if z > 0.0 && z.is_finite() { 1.0 / z } else { 0.0 });
    let planes = colour_planes(&image.rgb);
    let lum = luma_of_planes(&planes);
    // From here on the prompt is the one without the samples seen through nearer objects.
    let dropped = drop_enclosed(p, &mut inv, &planes, w, h);
    // (No closure around work here, `then(|| ...)` or otherwise: a closure the compiler does not
    // inline is compiled apart, for the portable build only, and runs without AVX-512 inside its
    // build. `nm` on the binary lists no closure of this module.)
    let kept = if dropped.is_empty() {
        None
    } else {
        let mut kept = sparse.data.clone();
        for i in dropped {
            kept[i] = 0.0;
        }
        Some(kept)
    };
    let sparse_data: &[f32] = kept.as_deref().unwrap_or(&sparse.data);
    let samples = inv.iter().filter(|&&v| v > 0.0).count();
    let grow = grow_radius(p.grow, w, h, samples);
    grow_samples(&mut inv, w, h, grow);
    // Rows between the two samples that give a ground slope: a ring grown by `grow` rows up and
    // down is a band of equal samples, which would give none.
    let slope_rows = 2 * grow + 2;
    fill_rows(p, w, h, &mut inv, &lum);
    // Column pass, in place: each column is a stride-`w` view of the row-major maps. (Columns
    // taken in order share cache lines, so this costs less than transposing there and back.)
    let samples = column_samples(&inv, w);
    let mut has = vec![false; w];
    // How each pixel was filled (see `smooth_unsupported`).
    let mut continued = vec![CONTINUED; w * h];
    for x in 0..w {
        let c = &mut inv[x..];
        let g = &lum[x..];
        let samples = &samples.rows[samples.start[x]..samples.start[x + 1]];
        let (Some(&first), Some(&last)) = (samples.first(), samples.last()) else { continue };
        let (first, last) = (first as usize, last as usize);
        has[x] = true;
        let mut mark = |from: usize, to: usize, how: u8| {
            for y in from..to {
                continued[y * w + x] = how;
            }
        };
        for (j, pair) in samples.windows(2).enumerate() {
            let (a, b) = (pair[0] as usize, pair[1] as usize);
            if b - a <= 1 {
                continue;
            }
            let tol = if b - a > p.column_gap as usize {
                -1.0
            } else if continues_a_plane(c, w, samples, j, p.tolerance) {
                f32::INFINITY
            } else {
                p.tolerance
            };
            if let Some(split) = bridge(c, w, a, b, tol, g) {
                // Two surfaces. When the lower one is the ground (its samples below say so) and
                // the upper one is farther, the ground's inverse depth keeps falling up to the
                // split, not flat at its last sample's (a street's far end), and stops where it
                // meets the upper surface. The split stays at the image's edge: an object
                // without samples standing on the ground keeps it from taking the ground's depth.
                let (ia, ib) = (c[a * w], c[b * w]);
                let below = samples[j + 2..].iter().find(|&&s| s as usize >= b + slope_rows);
                let ground = below.and_then(|&n| ground_slope(ib, c[n as usize * w], n as usize - b, p.tolerance));
                let from = split.max(a + 1);
                match ground {
                    Some(slope) if ia < ib => {
                        for y in from..b {
                            c[y * w] = (ib - slope * (b - y) as f32).max(ia);
                        }
                        mark(a + 1, from, SPLIT);
                    }
                    _ => mark(a + 1, b, SPLIT),
                }
            }
        }
        // Below the lowest sample: the ground continues.
        let above = samples.iter().rev().find(|&&s| last - s as usize >= slope_rows);
        let slope = above.and_then(|&s| ground_slope(c[s as usize * w], c[last * w], last - s as usize, p.tolerance));
        let slope = slope.unwrap_or(0.0);
        let bottom = c[last * w];
        for y in last + 1..h {
            c[y * w] = (bottom + slope * (y - last) as f32).min(bottom * 5.0);
        }
        if slope > 0.0 {
            mark(last + 1, h, GROUND);
        }
        // Above the highest sample: a vertical surface continues (sky is decided below).
        let up = c[first * w];
        for y in 0..first {
            c[y * w] = up;
        }
    }
    // Columns with no sample take their nearest filled column.
    if has.iter().any(|&b| b) {
        let filled: Vec<usize> = (0..w).filter(|&x| has[x]).collect();
        for x in (0..w).filter(|&x| !has[x]) {
            let j = filled.partition_point(|&f| f < x);
            let near = match (j.checked_sub(1).map(|k| filled[k]), filled.get(j)) {
                (Some(a), Some(&b)) => {
                    if x - a <= b - x {
                        a
                    } else {
                        b
                    }
                }
                (Some(a), None) => a,
                (None, Some(&b)) => b,
                (None, None) => unreachable!(),
            };
            for y in 0..h {
                inv[y * w + x] = inv[y * w + near];
                continued[y * w + x] = continued[y * w + near];
            }
        }
    }
    let distance = if support { Some(support_distance(sparse_data, w, h)) } else { None };
    let near = near_samples(sparse_data, distance.as_deref(), p.smooth_from, w, h);
    let sky = sky.map(|s| s.data.as_slice());
    let no_sky;
    let sky_or_none = match sky {
        Some(s) => s,
        None => {
            no_sky = vec![0u8; w * h];
            &no_sky
        }
    };
    smooth_unsupported(p, &mut inv, &planes, &near, &continued, sky_or_none, w, h);
    refine(p, &mut inv, &planes, sparse_data, sky_or_none, w, h);
    // No depth farther than the farthest sample: where the far end of a road meets the sky between
    // tree crowns, the 2D fill and the refinement could bring an inverse depth down to nearly 0
    // (26-53 km on three pixels of the shared DGP scene's CAMERA_09). Nearer is left alone: a
    // surface continued past its samples (a road below its last ring) rightly comes nearer.
    let farthest = farthest_sample(sparse_data);
    // (A subnormal farthest sample has 1 / z = inf; the least of f32::MAX and 1 / z was MAX.)
    let far_inv = if farthest > 0.0 { (1.0 / farthest).min(f32::MAX) } else { f32::MAX };
    let mut depth = inv;
    for v in depth.iter_mut() {
        let inv = if far_inv < f32::MAX { v.max(far_inv) } else { *v };
        *v = if *v > 0.0 { to_16_significant_bits(1.0 / inv) } else { 0.0 };
    }
    if let Some(sky) = sky {
        for (d, &s) in depth.iter_mut().zip(sky) {
            if s != 0 {
                *d = to_16_significant_bits(p.sky_depth);
            }
        }
    }
    // Without any sample, only sky is known.
    Completion {
        depth: DepthMap { width: sparse.width, height: sparse.height, data: depth },
        support: distance.map(|data| DepthMap { width: sparse.width, height: sparse.height, data }),
    }
}

/// The largest positive depth of `depth` (+inf counts, NaN does not), 0 without any. Taken as
/// the largest bit pattern, positive floats ordering as their bits do, in sixteen lanes: an integer
/// maximum that vectorises, where a division per sample into a chained `min` of 1 / z took 7% of
/// the completion's time (1 / the farthest is that least 1 / z to the bit, division being
/// correctly rounded and so monotonic; overflowing to inf where the least was f32::MAX, for a
/// subnormal farthest sample, hence the caller's `min`).
#[inline(always)]
fn farthest_sample(depth: &[f32]) -> f32 {
    // Bits of a positive float, subnormal to +inf: 1..=0x7f80_0000; 0 for the rest.
    let key = |z: f32| {
        let b = z.to_bits();
        if b.wrapping_sub(1) < 0x7f80_0000 {
            b
        } else {
            0
        }
    };
    let mut lanes = [0u32; 16];
    let chunks = depth.chunks_exact(16);
    let tail = chunks.remainder().iter().fold(0, |m, &z| key(z).max(m));
    for chunk in chunks {
        for (l, &z) in lanes.iter_mut().zip(chunk) {
            *l = key(z).max(*l);
        }
    }
    f32::from_bits(lanes.iter().fold(tail, |m, &l| m.max(l)))
}

/// A dense depth and how far each of its pixels is from a measurement.
pub struct Completion {
    pub depth: DepthMap,
    /// Distance (px) from each pixel to the nearest sample of the sparse input: 0 on a sample;
    /// made only when asked for.
    pub support: Option<DepthMap>,
}

/// The chamfer distance of a pixel without a sample in reach (x3, as the transform counts).
const FAR: u32 = u32::MAX / 2;

/// 1 where a pixel is within `reach` px of a sample by the support distance (`distance`, or made
/// here). The 2D fill asks only this of the support distance, and at its reach of 1 px (the
/// default) that is a sample or a 4-neighbour of one: the chamfer's 3 / 3 = 1 for those, 4 / 3 and
/// more for the rest. Without the support map wanted, that costs a pass over the samples instead
/// of the chamfer's four.
#[inline(always)]
fn near_samples(sparse: &[f32], distance: Option<&[f32]>, reach: f32, w: usize, h: usize) -> Vec<u8> {
    const DIAGONAL: f32 = 4.0 / 3.0;
    if distance.is_some() || reach >= DIAGONAL {
        let made;
        let distance = match distance {
            Some(d) => d,
            None => {
                made = support_distance(sparse, w, h);
                &made
            }
        };
        return map(distance, |d| (d <= reach) as u8);
    }
    let sample = map(sparse, |z| (z > 0.0 && z.is_finite()) as u8);
    if reach < 1.0 || w == 0 {
        return sample;
    }
    let mut near = sample.clone();
    for (y, row) in near.chunks_exact_mut(w).enumerate() {
        let here = &sample[y * w..(y + 1) * w];
        for (n, s) in row[1..].iter_mut().zip(here) {
            *n |= s;
        }
        for (n, s) in row.iter_mut().zip(&here[1..]) {
            *n |= s;
        }
        if y > 0 {
            for (n, s) in row.iter_mut().zip(&sample[(y - 1) * w..y * w]) {
                *n |= s;
            }
        }
        if y + 1 < h {
            for (n, s) in row.iter_mut().zip(&sample[(y + 1) * w..(y + 2) * w]) {
                *n |= s;
            }
        }
    }
    near
}

/// Distance (px) from every pixel to the nearest valid sample: the 3-4 chamfer distance
/// (Borgefors 1986) divided by 3, within 8% of the Euclidean one; `f32::MAX` with no sample.
/// (NearestFill's exact transform costs about 40 ms per 1600x900 image, nearly this whole
/// completion's time; a confidence needs no better than 8%.)
#[inline(always)]
fn support_distance(sparse: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut d = map(sparse, |z| if z > 0.0 && z.is_finite() { 0 } else { FAR });
    if w == 0 {
        return Vec::new();
    }
    // Each pass takes a row at a time: the links to the previous row first (element-wise, so
    // they vectorise), then the row's own chain along it.
    for y in 0..h {
        let (done, rest) = d.split_at_mut(y * w);
        let row = &mut rest[..w];
        if y > 0 {
            chamfer_from_row(row, &done[(y - 1) * w..]);
        }
        chain_along(row);
    }
    for y in (0..h).rev() {
        let (head, below) = d.split_at_mut((y + 1) * w);
        let row = &mut head[y * w..];
        if y + 1 < h {
            chamfer_from_row(row, &below[..w]);
        }
        row.reverse();
        chain_along(row);
        row.reverse();
    }
    map(&d, |v| if v >= FAR { f32::MAX } else { v as f32 / 3.0 })
}

/// The chamfer's links along a row, left to right: row[x] = min(row[x], row[x - 1] + 3), that is
/// the least row[j] + 3 (x - j) over j <= x. Done in one chain, each step waits on the one
/// before; so the row's four quarters run as four chains side by side, and then each quarter
/// takes the end of the one before it as one more candidate, up to where it stops winning: past
/// there it never wins again, as it grows by 3 per pixel and the row, chained, by at most 3 (within
/// a quarter; at the next quarter's start it may not be, so the candidate may run on into that
/// quarter, and every quarter gets its own candidate after).
#[inline(always)]
fn chain_along(row: &mut [u32]) {
    let (w, q) = (row.len(), row.len() / 4);
    if q < 2 {
        for x in 1..w {
            row[x] = row[x].min(row[x - 1] + 3);
        }
        return;
    }
    for x in 1..q {
        for c in 0..4 {
            let i = c * q + x;
            row[i] = row[i].min(row[i - 1] + 3);
        }
    }
    // The last quarter takes the pixels the division left over.
    for x in 4 * q..w {
        row[x] = row[x].min(row[x - 1] + 3);
    }
    for c in 1..4 {
        let mut carried = row[c * q - 1];
        for v in &mut row[c * q..] {
            carried += 3;
            if carried >= *v {
                break;
            }
            *v = carried;
        }
    }
}

/// The 3-4 chamfer links from a row to its neighbour row `other` (element-wise, so they vectorise).
#[inline(always)]
fn chamfer_from_row(row: &mut [u32], other: &[u32]) {
    let w = row.len();
    row[0] = row[0].min(other[0] + 3).min(other.get(1).map_or(FAR, |v| v + 4));
    if w > 1 {
        row[w - 1] = row[w - 1].min(other[w - 1] + 3).min(other[w - 2] + 4);
    }
    for (v, o) in row[1..].iter_mut().zip(other.windows(3)) {
        *v = (*v).min(o[1] + 3).min(o[0] + 4).min(o[2] + 4);
    }
}

/// The red, green and blue planes of an RGB8 image, one after the other: the colour differences
/// of the 2D fill and the refinement are then element-wise on contiguous slices, and vectorise.
#[inline(always)]
fn colour_planes(rgb: &[u8]) -> Vec<u8> {
    let n = rgb.len() / 3;
    let mut planes = vec![0u8; 3 * n];
    let (red, rest) = planes.split_at_mut(n);
    let (green, blue) = rest.split_at_mut(n);
    for (((px, r), g), b) in rgb.chunks_exact(3).zip(red).zip(green).zip(blue) {
        (*r, *g, *b) = (px[0], px[1], px[2]);
    }
    planes
}

/// Luma (ITU-R BT.601 weights, 0-255) of every pixel of `planes` (as `colour_planes` makes them):
/// what `luminance` gives, to the bit, from contiguous planes (a loop inlined into each build; the
/// iterator `luminance` collects is compiled once, for the portable build).
#[inline(always)]
fn luma_of_planes(planes: &[u8]) -> Vec<f32> {
    let n = planes.len() / 3;
    let (red, green, blue) = (&planes[..n], &planes[n..2 * n], &planes[2 * n..]);
    let mut luma = vec![0f32; n];
    for (l, ((&r, &g), &b)) in luma.iter_mut().zip(red.iter().zip(green).zip(blue)) {
        *l = 0.299 * r as f32 + 0.587 * g as f32 + 0.114 * b as f32;
    }
    luma
}

/// Pixels farther than `smooth_from` px from every sample got their inverse depth from one
/// column (its highest sample continued up, or a long gap split at an edge), so neighbouring
/// columns disagree (vertical streaks), and a facade above a tree crown took the crown's depth.
/// They take instead the edge-aware average of the pixels within `smooth_from` of a sample,
/// spread in two dimensions: normalised convolution with the recursive filter of the domain
/// transform (Gastal and Oliveira 2011, section 4 and its iterations: rows then columns,
/// `smooth_iterations` times, the i-th with a spatial sigma falling as in their eq. 14). Weights
/// fall by exp(-sqrt 2 / sigma_i) per pixel and faster across colour steps (a step of
/// `smooth_edge` in the summed RGB difference of colours averaged over `smooth_texture` blocks
/// counts as `smooth_sigma` pixels, so that texture is not taken for edges); sky pixels
/// neither give nor pass on depth. Only measured depths are spread (and the ground below a
/// column's lowest sample, exact on flat ground), so the facade seen around a crown reaches the
/// pixels above it while the crown's green stops it. But an average cannot extrapolate: a
/// receding facade above its samples is too near at one end and too far at the other, where its
/// column's continuation is exact. So the result is the average plus the continuation's
/// correction, weighted by how well the two agree (`keep_planes`; split gaps get none) and
/// averaged along the row (so that noisy top samples do not make streaks again).
#[inline(always)]
fn smooth_unsupported(p: &Params, inv: &mut [f32], planes: &[u8], near: &[u8], continued: &[u8], sky: &[u8], w: usize, h: usize) {
    if p.smooth_sigma <= 0.0 || p.smooth_iterations == 0 || w < 2 || h < 2 {
        return;
    }
    // Nothing to replace: every pixel is a source or sky.
    if !inv.iter().zip(near).zip(sky.iter().zip(continued)).any(|((&v, &d), (&s, &c))| !is_source(v, d, s, c) & (s == 0)) {
        return;
    }
    // The average reaches tens of px and changes slowly, so it is taken over 2x2 blocks (a quarter
    // of the pixels, the filter's passes being most of its time), then brought back to each pixel
    // from the blocks around it, weighed by colour likeness so that it does not cross the edges the
    // blocks blur.
    let ratio = p.smooth_sigma / p.smooth_edge.max(1e-3);
    let mut blocks = Blocks::of(inv, near, continued, planes, sky, w, h);
    // A block is 2 px, so the spatial sigma halves in its units. The colour ratio is kept, which
    // makes each colour step cut twice as hard as at full resolution: the units alone would halve
    // it too, and that measured worse (2.00% of seed 0's 8 keyframes off by more than 10% against
    // 1.95%, with the blocks' own colours).
    // The links compare texture-evened colours (`smooth_texture`): a 2x2 block's mean keeps most
    // of a facade's or a crown's texture, whose steps added up along every path. On seed 0's 40
    // keyframes this took the pixels off by more than 10% from 1.74% to 1.48% (docs/BENCHMARKS.md,
    // "Curation accuracy on synthetic scenes"). The spread back to the pixels keeps the blocks' own
    // colours.
    // (An `if`, not `then(|| ...)`: a closure is compiled apart, without this build's instructions.)
    let evened;
    let link_planes = if p.smooth_texture > 0 {
        evened = box_mean(&blocks.planes, blocks.w, blocks.h, p.smooth_texture as usize);
        &evened
    } else {
        &blocks.planes
    };
    domain_filter(p, &mut blocks.num, &mut blocks.den, link_planes, &blocks.sky, blocks.w, blocks.h, p.smooth_sigma / 2.0, ratio);
    let like = likeness(p, p.smooth_sigma / p.spread_edge.max(1e-3));
    let mut spread = Spread::new(w);
    let keep = p.keep_planes;
    // A pixel takes the average plus the continuation's correction to it (0 where not trusted)
    // averaged over the replaced pixels within this many px along its row: a receding facade's
    // correction changes smoothly along the row and survives; noisy top samples would give each
    // column its own correction, vertical streaks again, and average out (4 / 8 / 16 px: 2.11 /
    // 2.11 / 2.12% of seed 0's 8 keyframes off by more than 10%).
    const RADIUS: usize = 8;
    // Per row: what each pixel becomes and its correction, then the correction's mean over the
    // window from running sums. The sums run in registers: read back from the previous entry,
    // each addition waited on a store (3.9 ms of the completion's then ~58, now 0.7).
    let mut correction = vec![0f32; w];
    let mut replaced = vec![0f32; w];
    // Running sums of the correction and of the replaced pixels, 0 before the row's first.
    let (mut correction_sums, mut replaced_sums) = (vec![0f32; w + 1], vec![0f32; w + 1]);
    for y in 0..h {
        spread.row(&blocks, y, planes, w, h, &like);
        let row = y * w..(y + 1) * w;
        let (inv, num, den, near) = (&mut inv[row.clone()], &spread.num[..], &spread.den[..], &near[row.clone()]);
        let (sky, continued) = (&sky[row.clone()], &continued[row]);
        for x in 0..w {
            let (v, s, c) = (inv[x], sky[x], continued[x]);
            let replace = !is_source(v, near[x], s, c) & (s == 0) & (den[x] > 1e-8);
            let smooth = num[x] / den[x].max(1e-8);
            // NaN (no average, keep = 0) falls to 0 in `max`.
            let trust = (1.0 - (v - smooth).abs() / (keep * smooth)).max(0.0);
            let trusted = replace & (c == CONTINUED) & (v > 0.0) & (keep > 0.0);
            correction[x] = if trusted { trust * (v - smooth) } else { 0.0 };
            replaced[x] = replace as u8 as f32;
            inv[x] = if replace { smooth } else { v };
        }
        let (mut sum, mut n) = (0f32, 0f32);
        for ((s, k), (&c, &r)) in correction_sums[1..].iter_mut().zip(&mut replaced_sums[1..]).zip(correction.iter().zip(&replaced)) {
            sum += c;
            n += r;
            (*s, *k) = (sum, n);
        }
        let (sums, counts) = (&correction_sums[..], &replaced_sums[..]);
        // The pixels whose window lies inside the row, `inner`, as slices offset by the window
        // (a loop that vectorises; with the window's ends clipped for every pixel it did not);
        // the few at the row's ends with their windows clipped.
        let inner = if w > 2 * RADIUS { RADIUS..w - RADIUS } else { 0..0 };
        if !inner.is_empty() {
            let (lo, hi) = (inner.start - RADIUS..inner.end - RADIUS, inner.start + RADIUS + 1..inner.end + RADIUS + 1);
            let (sums_lo, sums_hi, counts_lo, counts_hi) = (&sums[lo.clone()], &sums[hi.clone()], &counts[lo], &counts[hi]);
            for (t, (v, &r)) in inv[inner.clone()].iter_mut().zip(&replaced[inner.clone()]).enumerate() {
                *v += r * ((sums_hi[t] - sums_lo[t]) / (counts_hi[t] - counts_lo[t]).max(1.0));
            }
        }
        for x in (0..inner.start).chain(inner.end..w) {
            let (lo, hi) = (x.saturating_sub(RADIUS), (x + RADIUS + 1).min(w));
            inv[x] += replaced[x] * ((sums[hi] - sums[lo]) / (counts[hi] - counts[lo]).max(1.0));
        }
    }
}

/// Each of the three `w` x `h` planes of `planes` averaged over the square of radius `r` around
/// each cell (cut at the borders), rounded to the nearest (as f32: sum x (1 / cells) + 0.5,
/// truncated; every build rounds it alike). Separable integer sums: a running sum down the
/// columns (a row added, a row taken off), then along each row the sum of the 2r + 1 shifted
/// copies of it; every loop is element-wise and vectorises.
#[inline(always)]
fn box_mean(planes: &[u8], w: usize, h: usize, r: usize) -> Vec<u8> {
    let n = w * h;
    if r == 0 || n == 0 {
        return planes.to_vec();
    }
    let mut out = vec![0u8; 3 * n];
    let (mut column, mut sum) = (vec![0u32; w], vec![0u32; w]);
    for (plane, out) in planes.chunks_exact(n).zip(out.chunks_exact_mut(n)) {
        column.fill(0);
        for row in plane[..(r + 1).min(h) * w].chunks_exact(w) {
            add_row(&mut column, row);
        }
        for y in 0..h {
            // `column` holds rows y - r ..= y + r (cut at the borders).
            sum.copy_from_slice(&column);
            for d in 1..=r.min(w - 1) {
                for (s, &c) in sum[..w - d].iter_mut().zip(&column[d..]) {
                    *s += c;
                }
                for (s, &c) in sum[d..].iter_mut().zip(&column[..w - d]) {
                    *s += c;
                }
            }
            let rows = ((y + r + 1).min(h) - y.saturating_sub(r)) as f32;
            let out = &mut out[y * w..(y + 1) * w];
            let inner = if w > 2 * r { r..w - r } else { 0..0 };
            let whole = 1.0 / (rows * (2 * r + 1) as f32);
            for (o, &s) in out[inner.clone()].iter_mut().zip(&sum[inner.clone()]) {
                *o = (s as f32 * whole + 0.5) as u8;
            }
            for x in (0..inner.start).chain(inner.end..w) {
                let cells = rows * ((x + r + 1).min(w) - x.saturating_sub(r)) as f32;
                out[x] = (sum[x] as f32 * (1.0 / cells) + 0.5) as u8;
            }
            if y + r + 1 < h {
                add_row(&mut column, &plane[(y + r + 1) * w..(y + r + 2) * w]);
            }
            if y >= r {
                for (c, &v) in column.iter_mut().zip(&plane[(y - r) * w..(y - r + 1) * w]) {
                    *c -= v as u32;
                }
            }
        }
    }
    out
}

#[inline(always)]
fn add_row(sums: &mut [u32], row: &[u8]) {
    for (s, &v) in sums.iter_mut().zip(row) {
        *s += v as u32;
    }
}

/// The 2D fill's sources: pixels beside a sample (within `smooth_from`), or on the ground below a
/// column's lowest one (inverse depth, near a sample, sky, how it was filled); not sky.
#[inline(always)]
fn is_source(v: f32, near: u8, sky: u8, continued: u8) -> bool {
    ((near != 0) | (continued == GROUND)) & (sky == 0) & (v > 0.0)
}

/// The 2D fill's filter over (`num`, `den`) on a `w` x `h` grid whose colours are `planes` and sky
/// `sky`: `smooth_iterations` passes along rows and then columns, the first with spatial sigma
/// derived from `sigma_s` (px of this grid), a colour step of s counting as `ratio` s px.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn domain_filter(p: &Params, num: &mut [f32], den: &mut [f32], planes: &[u8], sky: &[u8], w: usize, h: usize, sigma_s: f32, ratio: f32) {
    let n = w * h;
    let iterations = p.smooth_iterations as i32;
    // The i-th iteration's spatial sigma (Gastal and Oliveira's eq. 14) halves from one iteration
    // to the next, so its link weights exp(-(sqrt 2 / sigma_i) (1 + ratio step)) are the previous
    // iteration's squared: the weights are looked up once, for the first iteration, and squared
    // in place after each use.
    let sigma = first_sigma(sigma_s, iterations);
    // Colour steps (summed RGB difference, 0-765) -> weight; the last entry, 0, is a link that
    // sky or the border cuts, so the passes below need no branch.
    let mut weight = [0f32; CUT + 1];
    for (s, c) in weight.iter_mut().enumerate().take(CUT) {
        *c = (-(2f32.sqrt() / sigma) * (1.0 + ratio * s as f32)).exp();
    }
    // Link weights to the left and to the upper neighbour.
    let mut left = vec![0f32; n];
    let mut up = vec![0f32; n];
    for y in 0..h {
        link_weights(&mut left[y * w + 1..(y + 1) * w], planes, sky, &weight, y * w + 1, 1);
        if y > 0 {
            link_weights(&mut up[y * w..(y + 1) * w], planes, sky, &weight, y * w, w);
        }
    }
    for k in 0..iterations {
        let last = k + 1 == iterations;
        // Along rows: causal, then anti-causal over the causal result. Each row is a chain of
        // dependent multiply-adds; four rows at a time, their running values in registers, keep
        // the core busy while one waits.
        for ((nums, dens), links) in num.chunks_mut(4 * w).zip(den.chunks_mut(4 * w)).zip(left.chunks_mut(4 * w)) {
            if nums.len() == 4 * w {
                filter_rows::<4>(nums, dens, links, w);
            } else {
                for ((nums, dens), links) in nums.chunks_mut(w).zip(dens.chunks_mut(w)).zip(links.chunks(w)) {
                    filter_rows::<1>(nums, dens, links, w);
                }
            }
            if !last {
                square(links);
            }
        }
        // Along columns, a whole row at a time (rows are contiguous, columns are not).
        for y in 1..h {
            let (nd, nr) = num.split_at_mut(y * w);
            let (dd, dr) = den.split_at_mut(y * w);
            let (np, dp) = (&nd[(y - 1) * w..], &dd[(y - 1) * w..]);
            let links = &up[y * w..(y + 1) * w];
            for x in 0..w {
                nr[x] += links[x] * np[x];
                dr[x] += links[x] * dp[x];
            }
        }
        for y in (0..h - 1).rev() {
            let (nh, nb) = num.split_at_mut((y + 1) * w);
            let (dh, db) = den.split_at_mut((y + 1) * w);
            let (nr, dr) = (&mut nh[y * w..], &mut dh[y * w..]);
            let links = &mut up[(y + 1) * w..(y + 2) * w];
            for x in 0..w {
                nr[x] += links[x] * nb[x];
                dr[x] += links[x] * db[x];
            }
            if !last {
                square(links);
            }
        }
    }
}

/// The spatial sigma of the first of `iterations` passes of a domain transform of sigma `sigma_s`
/// (Gastal and Oliveira's eq. 14; each later one is half the one before).
fn first_sigma(sigma_s: f32, iterations: i32) -> f32 {
    sigma_s * 3f32.sqrt() * 2f32.powi(iterations - 1) / (4f32.powi(iterations) - 1.0).sqrt()
}

/// How much a pixel takes of a block's average by their summed RGB difference (0-765; the pixel's
/// own colour against the block's own mean, not the texture-evened one, with `ratio` from
/// `spread_edge`): the full-resolution filter's first link weight, with the colour counting twice
/// as much (a pixel beside an edge, weighed against a block across it, should take nearly nothing;
/// once as much measured 1.96% of seed 0's 8 keyframes off by more than 10% against 1.95%). A pixel unlike
/// all four of its blocks (a 1 px pole or wire, which the blocks' means average away; a summed
/// difference over ~300) gets weights below the replacement's threshold and keeps its column's
/// value, which its own samples gave. Giving it the blocks' plain average instead (a floor of 1e-6
/// on the likeness) measured the same on the real hold-outs and 2.64 against 2.62 px boundary
/// accuracy on seed 0's 8 keyframes.
fn likeness(p: &Params, ratio: f32) -> [f32; CUT] {
    let sigma = first_sigma(p.smooth_sigma, p.smooth_iterations as i32);
    let mut like = [0f32; CUT];
    for (s, c) in like.iter_mut().enumerate() {
        *c = (-(2f32.sqrt() / sigma) * (1.0 + 2.0 * ratio * s as f32)).exp();
    }
    like
}

/// The 2D fill's grid: blocks of 2x2 pixels (fewer at an odd image's last row or column).
struct Blocks {
    w: usize,
    h: usize,
    /// Sums of the pixels' (num, den).
    num: Vec<f32>,
    den: Vec<f32>,
    /// Mean colours (red, green, blue planes, rounded).
    planes: Vec<u8>,
    /// 1 where every pixel of the block is sky.
    sky: Vec<u8>,
}

impl Blocks {
    /// The blocks of the filter's input: (inverse depth, 1) at sources, (0, 0) elsewhere.
    #[inline(always)]
    fn of(inv: &[f32], near: &[u8], continued: &[u8], planes: &[u8], sky: &[u8], w: usize, h: usize) -> Blocks {
        let (bw, bh) = (w.div_ceil(2), h.div_ceil(2));
        let (n, nb) = (w * h, bw * bh);
        let mut b = Blocks { w: bw, h: bh, num: vec![0f32; nb], den: vec![0f32; nb], planes: vec![0u8; 3 * nb], sky: vec![0u8; nb] };
        let pairs = w / 2;
        // A row's (num, den) of the filter's input.
        let (mut num, mut den) = ([vec![0f32; w], vec![0f32; w]], [vec![0f32; w], vec![0f32; w]]);
        for by in 0..bh {
            // The block's rows; an odd image's last block row has one, counted once.
            let (ya, yb) = (2 * by, (2 * by + 1).min(h - 1));
            let second = (yb != ya) as u8;
            let (rows, pixels) = (1 + second as u16, (1 + second as u16) * 2);
            let at = |y: usize| y * w..(y + 1) * w;
            let out = by * bw..(by + 1) * bw;
            // Sums of the two rows' pixel pairs (the second row weighed 0 when it is the first).
            for (k, y) in [ya, yb].into_iter().enumerate() {
                let row = at(y);
                let (v, d, s, c) = (&inv[row.clone()], &near[row.clone()], &sky[row.clone()], &continued[row]);
                for (x, (nu, de)) in num[k].iter_mut().zip(den[k].iter_mut()).enumerate() {
                    let source = is_source(v[x], d[x], s[x], c[x]) as u8 as f32;
                    *nu = v[x] * source;
                    *de = source;
                }
            }
            pair_sums(&mut b.num[out.clone()], &num, second);
            pair_sums(&mut b.den[out.clone()], &den, second);
            for c in 0..3 {
                let plane = &planes[c * n..(c + 1) * n];
                let (a, d) = (&plane[at(ya)], &plane[at(yb)]);
                let o = &mut b.planes[c * nb + out.start..c * nb + out.end];
                let s = second as u16;
                for (o, (p, q)) in o[..pairs].iter_mut().zip(a.chunks_exact(2).zip(d.chunks_exact(2))) {
                    let sum = p[0] as u16 + p[1] as u16 + s * (q[0] as u16 + q[1] as u16);
                    *o = ((sum + pixels / 2) / pixels) as u8;
                }
                if w % 2 == 1 {
                    o[pairs] = ((a[w - 1] as u16 + s * d[w - 1] as u16 + rows / 2) / rows) as u8;
                }
            }
            let (a, d) = (&sky[at(ya)], &sky[at(yb)]);
            let o = &mut b.sky[out];
            for (o, (p, q)) in o[..pairs].iter_mut().zip(a.chunks_exact(2).zip(d.chunks_exact(2))) {
                *o = ((p[0] != 0) & (p[1] != 0) & (q[0] != 0) & (q[1] != 0)) as u8;
            }
            if w % 2 == 1 {
                o[pairs] = ((a[w - 1] != 0) & (d[w - 1] != 0)) as u8;
            }
        }
        b
    }
}

/// Sums of the pixel pairs of two rows `v` into `out` (an odd row's last pixel alone), the second
/// row weighed 0 when `second` is 0 (an odd image's last block row is its first row counted once).
/// A function inlined into the completion: a closure was compiled apart, for the portable build.
#[inline(always)]
fn pair_sums(out: &mut [f32], v: &[Vec<f32>; 2], second: u8) {
    let (a, c) = (&v[0][..], &v[1][..]);
    let (w, pairs) = (a.len(), a.len() / 2);
    let f = second as f32;
    for (o, (p, q)) in out[..pairs].iter_mut().zip(a.chunks_exact(2).zip(c.chunks_exact(2))) {
        *o = (p[0] + p[1]) + f * (q[0] + q[1]);
    }
    if w % 2 == 1 {
        out[pairs] = a[w - 1] + f * c[w - 1];
    }
}

/// The filtered blocks brought back to a row of pixels at a time: each pixel's (num, den) from
/// the four blocks nearest it, bilinear weights between the blocks' centres (a pixel is a quarter
/// of a block from the nearest centre: 3/4 and 1/4 each way) times the likeness of the pixel's
/// colour and each block's.
struct Spread {
    /// Block rows spread to the image's width: block row j in slot j % 2 (a pixel row uses block
    /// rows j and j + 1).
    slots: [WideRow; 2],
    held: [usize; 2],
    /// The row's (num, den).
    num: Vec<f32>,
    den: Vec<f32>,
}

impl Spread {
    fn new(w: usize) -> Spread {
        Spread { slots: [WideRow::new(w), WideRow::new(w)], held: [usize::MAX; 2], num: vec![0f32; w], den: vec![0f32; w] }
    }

    /// (num, den) of pixel row `y`.
    #[inline(always)]
    fn row(&mut self, blocks: &Blocks, y: usize, planes: &[u8], w: usize, h: usize, like: &[f32; CUT]) {
        let n = w * h;
        // The block rows above and below the pixels' centres, and the first one's weight.
        let (a, wa) = if y.is_multiple_of(2) { (y as isize / 2 - 1, 0.25f32) } else { (y as isize / 2, 0.75) };
        let last = blocks.h as isize - 1;
        let (a, b) = (a.clamp(0, last) as usize, (a + 1).clamp(0, last) as usize);
        for by in [a, b] {
            if self.held[by % 2] != by {
                self.slots[by % 2].fill(blocks, by);
                self.held[by % 2] = by;
            }
        }
        let (top, bottom) = (&self.slots[a % 2], &self.slots[b % 2]);
        let row = y * w..(y + 1) * w;
        let (r, g, bl) = (&planes[row.clone()], &planes[n + row.start..n + row.end], &planes[2 * n + row.start..2 * n + row.end]);
        // The four blocks' terms over slices of the row's length (no bounds checks and no
        // closure, so that the loop vectorises, the likeness lookups as gathers).
        let (r, g, bl) = (&r[..w], &g[..w], &bl[..w]);
        let ([tr0, tg0, tb0], [tr2, tg2, tb2]) = (top.colour.each_ref().map(|c| &c[..w]), top.colour.each_ref().map(|c| &c[2..w + 2]));
        let ([br0, bg0, bb0], [br2, bg2, bb2]) = (bottom.colour.each_ref().map(|c| &c[..w]), bottom.colour.each_ref().map(|c| &c[2..w + 2]));
        let (tn0, tn2, td0, td2) = (&top.num[..w], &top.num[2..w + 2], &top.den[..w], &top.den[2..w + 2]);
        let (bn0, bn2, bd0, bd2) = (&bottom.num[..w], &bottom.num[2..w + 2], &bottom.den[..w], &bottom.den[2..w + 2]);
        let (num, den) = (&mut self.num[..w], &mut self.den[..w]);
        for x in 0..w {
            // x even: its farther block column at x (1/4), the nearer at x + 2 (3/4); odd:
            // the other way round.
            let wx = 0.25 + 0.5 * (x & 1) as f32;
            let s_tl = r[x].abs_diff(tr0[x]) as usize + g[x].abs_diff(tg0[x]) as usize + bl[x].abs_diff(tb0[x]) as usize;
            let s_tr = r[x].abs_diff(tr2[x]) as usize + g[x].abs_diff(tg2[x]) as usize + bl[x].abs_diff(tb2[x]) as usize;
            let s_bl = r[x].abs_diff(br0[x]) as usize + g[x].abs_diff(bg0[x]) as usize + bl[x].abs_diff(bb0[x]) as usize;
            let s_br = r[x].abs_diff(br2[x]) as usize + g[x].abs_diff(bg2[x]) as usize + bl[x].abs_diff(bb2[x]) as usize;
            let tl = (wa * wx) * like[s_tl];
            let tr = (wa * (1.0 - wx)) * like[s_tr];
            let bo = ((1.0 - wa) * wx) * like[s_bl];
            let br = ((1.0 - wa) * (1.0 - wx)) * like[s_br];
            num[x] = ((tl * tn0[x] + tr * tn2[x]) + bo * bn0[x]) + br * bn2[x];
            den[x] = ((tl * td0[x] + tr * td2[x]) + bo * bd0[x]) + br * bd2[x];
        }
    }
}

/// A row of blocks spread to the image's width `w`, padded: block k at indices 2k + 1 and 2k + 2,
/// block 0 at index 0 too and the last block to the end; a pixel x's two nearest block columns are
/// then at x and x + 2.
struct WideRow {
    num: Vec<f32>,
    den: Vec<f32>,
    colour: [Vec<u8>; 3],
}

impl WideRow {
    fn new(w: usize) -> WideRow {
        WideRow { num: vec![0f32; w + 2], den: vec![0f32; w + 2], colour: std::array::from_fn(|_| vec![0u8; w + 2]) }
    }

    /// Block row `by` of `blocks`.
    #[inline(always)]
    fn fill(&mut self, blocks: &Blocks, by: usize) {
        let (bw, at) = (blocks.w, by * blocks.w);
        spread_pairs(&mut self.num, &blocks.num[at..at + bw]);
        spread_pairs(&mut self.den, &blocks.den[at..at + bw]);
        for (c, out) in self.colour.iter_mut().enumerate() {
            let plane = c * blocks.w * blocks.h + at;
            spread_pairs(out, &blocks.planes[plane..plane + bw]);
        }
    }
}

/// `out[0]` = v[0], v[k] at 2k + 1 and 2k + 2, the last of `v` to the end of `out`.
#[inline(always)]
fn spread_pairs<T: Copy>(out: &mut [T], v: &[T]) {
    out[0] = v[0];
    // Whole pairs written as two stores: `fill` on a chunk of unknown length called memset once
    // per pair (1% of the chain's CPU). An odd last slot is the end's, set below.
    for (o, &x) in out[1..].chunks_exact_mut(2).zip(v) {
        o[0] = x;
        o[1] = x;
    }
    let end = out.len() - 1;
    out[end] = v[v.len() - 1];
}

/// The weights of the links from the pixels `from..from + out.len()` to the pixels `back` before
/// them: `weight` of their summed RGB difference (`planes`: red, green, blue planes of one image),
/// 0 where either pixel is sky.
#[inline(always)]
fn link_weights(out: &mut [f32], planes: &[u8], sky: &[u8], weight: &[f32; CUT + 1], from: usize, back: usize) {
    let (n, len) = (sky.len(), out.len());
    let plane = |c: usize, from: usize| &planes[c * n + from..c * n + from + len];
    let (r, g, b, s) = (plane(0, from), plane(1, from), plane(2, from), &sky[from..from + len]);
    let at = from - back;
    let (r0, g0, b0, s0) = (plane(0, at), plane(1, at), plane(2, at), &sky[at..at + len]);
    for (i, o) in out.iter_mut().enumerate() {
        let d = r[i].abs_diff(r0[i]) as usize + g[i].abs_diff(g0[i]) as usize + b[i].abs_diff(b0[i]) as usize;
        // A select, not a branch, so that the loop vectorises (with AVX2, the lookup too).
        *o = weight[if (s[i] | s0[i]) != 0 { CUT } else { d }];
    }
}

/// The slot of a cut link (sky, or the image's border) in the 2D fill's weight table, after the
/// 766 colour steps (summed RGB differences 0-765).
const CUT: usize = 766;

/// Each weight squared, in place: the next iteration's (see `smooth_unsupported`).
#[inline(always)]
fn square(weights: &mut [f32]) {
    weights.iter_mut().for_each(|c| *c *= *c);
}

/// `f` of each element, as a loop inlined into the caller: `collect` would run code compiled once,
/// for the portable build, inside the AVX2 build of the completion too.
#[inline(always)]
fn map<T: Copy, U: Copy + Default>(from: &[T], f: impl Fn(T) -> U) -> Vec<U> {
    let mut out = vec![U::default(); from.len()];
    for (o, &x) in out.iter_mut().zip(from) {
        *o = f(x);
    }
    out
}

/// The recursive filter along `R` rows of `w` pixels (row-major in `nums`, `dens`, `links`): causal
/// (x_i += c_i x_{i-1}, c_i the link to the left), then anti-causal over its result (x_i += c_{i+1}
/// x_{i+1}). The `R` chains run side by side with their last values in registers: read back from
/// memory, each step would wait on the store before it.
#[inline(always)]
fn filter_rows<const R: usize>(nums: &mut [f32], dens: &mut [f32], links: &[f32], w: usize) {
    let (nums, dens, links) = (&mut nums[..R * w], &mut dens[..R * w], &links[..R * w]);
    let (mut n, mut d) = ([0f32; R], [0f32; R]);
    for r in 0..R {
        (n[r], d[r]) = (nums[r * w], dens[r * w]);
    }
    for x in 1..w {
        for r in 0..R {
            let (i, c) = (r * w + x, links[r * w + x]);
            n[r] = nums[i] + c * n[r];
            d[r] = dens[i] + c * d[r];
            nums[i] = n[r];
            dens[i] = d[r];
        }
    }
    for x in (0..w - 1).rev() {
        for r in 0..R {
            let (i, c) = (r * w + x, links[r * w + x + 1]);
            n[r] = nums[i] + c * n[r];
            d[r] = dens[i] + c * d[r];
            nums[i] = n[r];
            dens[i] = d[r];
        }
    }
}

/// A few conjugate-gradient steps on the colour-affinity least squares of Levin, Lischinski and
/// Weiss 2004 (the NYU Depth v2 toolbox's fill), in inverse depth x, near the filled map's depth
/// edges: minimise, over the pixels within `refine_band` px of a depth step of more than
/// `EDGE_STEP`, sum over 4-neighbour links of w_ij (x_i - x_j)^2 + `refine_weight` * sum over
/// samples of (x_i - 1/z_i)^2, with w_ij = exp(-|rgb_i - rgb_j|^2 / 2 `refine_sigma`^2) + 1e-4;
/// every other pixel keeps its value and holds its neighbours in the band (sky neither gives nor
/// takes). Started from the filled map, tens of steps (Jacobi-preconditioned) move depth edges
/// onto colour edges; solved to the end over the whole image it takes thousands and blurs real
/// images across like-coloured surfaces. Figures: docs/BENCHMARKS.md, "What the completion can
/// reach".
#[inline(always)]
fn refine(p: &Params, x: &mut [f32], planes: &[u8], sparse: &[f32], sky: &[u8], w: usize, h: usize) {
    /// A depth step (ratio) that marks a depth edge of the filled map.
    const EDGE_STEP: f32 = 1.05;
    if p.refine_iterations == 0 || w < 2 || h < 2 {
        return;
    }
    let n = w * h;
    // Depth edges of the filled map (1 on both sides of a step), grown by the band (a
    // square-window maximum) into the active set.
    let (lo, hi) = (1.0 / EDGE_STEP, EDGE_STEP);
    // 1 where two neighbours (neither sky, both filled) differ by more than the step; no
    // branch, so that the passes below vectorise.
    let step = |a: f32, b: f32, sa: u8, sb: u8| -> u8 {
        ((sa | sb) == 0) as u8 & (a > 0.0) as u8 & (b > 0.0) as u8 & ((a > hi * b) | (a < lo * b)) as u8
    };
    let mut edge = vec![0u8; n];
    let mut flags = vec![0u8; w];
    for y in 0..h {
        let row = y * w;
        let (xr, sr) = (&x[row..row + w], &sky[row..row + w]);
        for (f, (xp, sp)) in flags.iter_mut().zip(xr.windows(2).zip(sr.windows(2))) {
            *f = step(xp[0], xp[1], sp[0], sp[1]);
        }
        flags[w - 1] = 0;
        let er = &mut edge[row..row + w];
        er[0] |= flags[0];
        for (e, f) in er[1..].iter_mut().zip(flags.windows(2)) {
            *e |= f[0] | f[1];
        }
        if y + 1 < h {
            let (xb, sb) = (&x[row + w..row + 2 * w], &sky[row + w..row + 2 * w]);
            for (f, ((&a, &b), (&sa, &sb))) in flags.iter_mut().zip(xr.iter().zip(xb).zip(sr.iter().zip(sb))) {
                *f = step(a, b, sa, sb);
            }
            let (top, bottom) = edge[row..row + 2 * w].split_at_mut(w);
            for ((t, b), &f) in top.iter_mut().zip(bottom.iter_mut()).zip(&flags) {
                *t |= f;
                *b |= f;
            }
        }
    }
    grow_samples(&mut edge, w, h, p.refine_band as usize);
    // Compact numbering of the active pixels, from 1; slot 0 and slot m + 1 hold 0 so that a
    // link leaving the band (or the image) reads a 0 weight and a 0 value without a branch.
    const OUT: u32 = 0;
    let mut at = vec![OUT; n];
    let mut index = Vec::new();
    // A stretch of pixels none of which is in the band is passed over with one test: most are
    // not in it, and the test per pixel, a branch on three maps, was 3% of the completion's time.
    const STRETCH: usize = 64;
    for (c, edges) in edge.chunks(STRETCH).enumerate() {
        if edges.iter().fold(0, |any, &e| any | e) == 0 {
            continue;
        }
        let first = c * STRETCH;
        let pixels = first..first + edges.len();
        let (at, sky, x) = (&mut at[pixels.clone()], &sky[pixels.clone()], &x[pixels]);
        for (t, &e) in edges.iter().enumerate() {
            if e != 0 && sky[t] == 0 && x[t] > 0.0 {
                index.push((first + t) as u32);
                at[t] = index.len() as u32;
            }
        }
    }
    let m = index.len();
    if m == 0 {
        return;
    }
    drop(edge);
    let mut factor = [0f32; 256];
    for (d, f) in factor.iter_mut().enumerate() {
        *f = (-((d * d) as f32) / (2.0 * p.refine_sigma * p.refine_sigma)).exp();
    }
    // The system A u = b over slots 1..=m, with a weight per link direction (0 where the
    // neighbour is outside the band: fixed, its value on the right-hand side). The diagonal holds
    // every link's weight and the sample's hold. Slots run in row-major order, so a run of
    // active pixels whose upper neighbours are all active has those neighbours in consecutive
    // slots too, and A v along such a run is arithmetic on contiguous slices (it vectorises).
    let len = m + 2;
    let [mut left, mut up] = [(); 2].map(|_| vec![0f32; len]);
    let mut diag = vec![1f32; len];
    let mut rhs = vec![0f32; len];
    let mut u = vec![0f32; len];
    // Runs of consecutive slots whose upper neighbours are active and consecutive too: (first
    // slot, length, first upper slot).
    let mut up_runs: Vec<[u32; 3]> = Vec::new();
    // The system is set up a segment at a time: a maximal run of active pixels along a row
    // (consecutive pixels, consecutive slots), whose links are arrays over it, so that the loops
    // are element-wise on contiguous slices and vectorise. `across[t]` joins its pixels t - 1 and
    // t (at both ends, to the fixed pixels beside it), `above` and `below` join each to the rows
    // above and below; 0 where there is no neighbour, which adds nothing to a sum.
    let (mut across, mut above, mut below) = (vec![0f32; w + 1], vec![0f32; w], vec![0f32; w]);
    let mut k = 1;
    while k <= m {
        let first = index[k - 1] as usize;
        let (y, c) = (first / w, first % w);
        let mut n = 1;
        while k + n <= m && index[k + n - 1] as usize == first + n && c + n < w {
            n += 1;
        }
        let (pixels, slots) = (first..first + n, k..k + n);
        let across = &mut across[..n + 1];
        across.fill(0.0);
        let (from, to) = (first - (c > 0) as usize, first + n - (c + n == w) as usize);
        link_affinities(&mut across[(c == 0) as usize..(to - from + (c == 0) as usize)], planes, sky, &factor, from, from + 1);
        let (above, below) = (&mut above[..n], &mut below[..n]);
        above.fill(0.0);
        below.fill(0.0);
        if y > 0 {
            link_affinities(above, planes, sky, &factor, first, first - w);
        }
        if y + 1 < h {
            link_affinities(below, planes, sky, &factor, first, first + w);
        }
        let (samples, start) = (&sparse[pixels.clone()], &x[pixels]);
        let (diag, rhs) = (&mut diag[slots.clone()], &mut rhs[slots.clone()]);
        u[slots.clone()].copy_from_slice(start);
        for t in 0..n {
            let z = samples[t];
            let held = if z > 0.0 && z.is_finite() { p.refine_weight } else { 0.0 };
            let d = held + across[t] + across[t + 1] + above[t] + below[t];
            diag[t] = if d > 0.0 { d } else { 1.0 };
            rhs[t] = if held > 0.0 { held / z } else { 0.0 };
        }
        // Fixed neighbours: a link's weight times their value goes to the right-hand side, in
        // the order left, right, up, down. Along the row only the segment's ends have them (it is
        // a maximal run of active pixels). A sky neighbour's weight is 0, but its value is not
        // read: 0 times a value that is not finite would be NaN.
        if c > 0 && sky[first - 1] == 0 {
            rhs[0] += across[0] * x[first - 1];
        }
        if c + n < w && sky[first + n] == 0 {
            rhs[n - 1] += across[n] * x[first + n];
        }
        if y > 0 {
            add_fixed(rhs, above, &at, sky, x, first - w);
        }
        if y + 1 < h {
            add_fixed(rhs, below, &at, sky, x, first + w);
        }
        left[k] = 0.0;
        left[k + 1..k + n].copy_from_slice(&across[1..n]);
        if y > 0 {
            let ats = &at[first - w..first - w + n];
            for (t, (o, &up_slot)) in up[slots].iter_mut().zip(ats).enumerate() {
                *o = if up_slot != OUT { above[t] } else { 0.0 };
                if up_slot != OUT {
                    let kt = (k + t) as u32;
                    match up_runs.last_mut() {
                        Some([first, n, above]) if *first + *n == kt && *above + *n == up_slot => *n += 1,
                        _ => up_runs.push([kt, 1, up_slot]),
                    }
                }
            }
        }
        k += n;
    }
    drop(at);
    // Conjugate gradients on the system scaled to a unit diagonal, S A S u' = S b with u = S u'
    // and S = diag^-1/2: the same iterates as the Jacobi-preconditioned system's, and no diagonal or
    // preconditioner to stream through every step. A link's weight in one direction is its
    // neighbour's in the other (the right link of a slot is the left one of the next slot, the
    // lower link the upper one of the slot below), so only two directions are stored. The loops
    // below are element-wise or sums in eight f32 lanes, so that they vectorise.
    let scale = map(&diag, |d| 1.0 / d.sqrt());
    drop(diag);
    // (0 where the neighbour is not active, whatever it is multiplied by.)
    for k in 1..=m {
        left[k] *= scale[k] * scale[k - 1];
    }
    for &[k, n, above] in &up_runs {
        let (k, n, above) = (k as usize, n as usize, above as usize);
        for t in 0..n {
            up[k + t] *= scale[k + t] * scale[above + t];
        }
    }
    for ((b, u), &s) in rhs.iter_mut().zip(u.iter_mut()).zip(&scale) {
        *b *= s;
        *u /= s;
    }
    let system = Stencil { up_runs: &up_runs, left: &left, up: &up };
    let mut r = vec![0f32; len];
    system.apply(&u, &mut r);
    for (r, &b) in r.iter_mut().zip(&rhs) {
        *r = b - *r;
    }
    r[0] = 0.0;
    r[m + 1] = 0.0;
    let mut rr = dot(&r, &r);
    let (mut dir, mut q) = (vec![0f32; len], vec![0f32; len]);
    let mut beta = 0f32;
    // A step's u += alpha dir is made in the next step's pass over dir, before dir is replaced
    // (one pass over dir fewer per step); `moved` is the alpha of the step not yet added to u.
    // After a break there is none: the direction made in the pass that broke may hold NaN or inf
    // (a subnormal sample's 1 / z), and 0 times it is NaN.
    let mut moved = None;
    for _ in 0..p.refine_iterations {
        // A cancellation point: the caller turns the stop into an error (see `dist4d_types::cancel`).
        if dist4d_types::cancel::requested() {
            break;
        }
        let pq = system.next_direction(&mut dir, &r, beta, &mut q, (&mut u, moved.unwrap_or(0.0)));
        moved = None;
        if !(pq > 0.0) || rr <= 0.0 {
            break;
        }
        let alpha = (rr / pq) as f32;
        let next = cg_residual(&mut r, &q, alpha);
        moved = Some(alpha);
        beta = (next / rr) as f32;
        rr = next;
    }
    if let Some(alpha) = moved {
        for (u, &d) in u.iter_mut().zip(&dir) {
            *u += alpha * d;
        }
    }
    for (k0, &i) in index.iter().enumerate() {
        x[i as usize] = u[k0 + 1] * scale[k0 + 1];
    }
}

/// The refinement's weights of the links from the pixels `from..from + out.len()` to the pixels
/// `to..` (`planes`: red, green, blue planes of one image): the product of `factor` of each
/// plane's difference, + 1e-4; 0 where either pixel is sky (a link's weight does not depend on its
/// direction). A function inlined into the completion, not a closure: a closure was compiled
/// apart, for the portable build only, and ran without AVX-512 inside its build.
#[inline(always)]
fn link_affinities(out: &mut [f32], planes: &[u8], sky: &[u8], factor: &[f32; 256], from: usize, to: usize) {
    let (n, len) = (sky.len(), out.len());
    let plane = |c: usize, at: usize| &planes[c * n + at..c * n + at + len];
    let (r, g, b, s) = (plane(0, from), plane(1, from), plane(2, from), &sky[from..from + len]);
    let (r1, g1, b1, s1) = (plane(0, to), plane(1, to), plane(2, to), &sky[to..to + len]);
    for (t, o) in out.iter_mut().enumerate() {
        let a = factor[r[t].abs_diff(r1[t]) as usize] * factor[g[t].abs_diff(g1[t]) as usize] * factor[b[t].abs_diff(b1[t]) as usize]
            + 1e-4;
        *o = if (s[t] | s1[t]) != 0 { 0.0 } else { a };
    }
}

/// Adds to `rhs` each link's weight (`weights`) times the value in `x` of its neighbour, the pixels
/// `neighbours..neighbours + rhs.len()`, where that neighbour is fixed: outside the refinement's
/// band (`at` 0) and not sky. (Inlined, as `link_affinities`.)
#[inline(always)]
fn add_fixed(rhs: &mut [f32], weights: &[f32], at: &[u32], sky: &[u8], x: &[f32], neighbours: usize) {
    let n = rhs.len();
    let (ats, skies, values) = (&at[neighbours..neighbours + n], &sky[neighbours..neighbours + n], &x[neighbours..neighbours + n]);
    for t in 0..n {
        let fixed = (ats[t] == 0) & (skies[t] == 0);
        rhs[t] += if fixed { weights[t] * values[t] } else { 0.0 };
    }
}

/// The refinement's matrix scaled to a unit diagonal, by link direction (see `refine`).
struct Stencil<'a> {
    /// (first slot, length, first upper slot) of the runs of slots with active upper neighbours.
    up_runs: &'a [[u32; 3]],
    /// Scaled weight of each slot's link to its left neighbour, 0 where that one is not active.
    left: &'a [f32],
    /// Scaled weight of each slot's link to its upper neighbour, 0 where that one is not active.
    up: &'a [f32],
}

impl Stencil<'_> {
    /// out = A v over the active slots (the pads stay 0): the links along rows over all slots at
    /// once, then each vertical link, to both of its slots, a run at a time.
    #[inline(always)]
    fn apply(&self, v: &[f32], out: &mut [f32]) {
        self.along_rows(v, out, 1..out.len() - 1);
        for &run in self.up_runs {
            self.vertical(run, v, out);
        }
    }

    /// out = v - the links along rows times v, over the slots `slots` (a slot's right link is the
    /// next slot's left one, 0 where they are not neighbours).
    #[inline(always)]
    fn along_rows(&self, v: &[f32], out: &mut [f32], slots: std::ops::Range<usize>) {
        let (start, end) = (slots.start, slots.end);
        let (centre, east, west) = (&v[start..end], &v[start + 1..end + 1], &v[start - 1..end - 1]);
        let (wl, wr) = (&self.left[start..end], &self.left[start + 1..end + 1]);
        for (t, o) in out[slots].iter_mut().enumerate() {
            *o = centre[t] - wl[t] * west[t] - wr[t] * east[t];
        }
    }

    /// Takes one run's vertical links times v off both of their slots.
    #[inline(always)]
    fn vertical(&self, [k, n, above]: [u32; 3], v: &[f32], out: &mut [f32]) {
        let (k, n, above) = (k as usize, n as usize, above as usize);
        let (links, here, up) = (&self.up[k..k + n], &v[k..k + n], &v[above..above + n]);
        for (t, o) in out[k..k + n].iter_mut().enumerate() {
            *o -= links[t] * up[t];
        }
        for (t, o) in out[above..above + n].iter_mut().enumerate() {
            *o -= links[t] * here[t];
        }
    }

    /// A step's first pass over the slots, a block at a time so that each block is worked on
    /// while it is in cache: the last step's move u += alpha dir (`moved`: (u, alpha)), the search
    /// direction dir = r + beta dir, q = A dir (as `apply`), and returns dir . q, summed by
    /// `BlockSum` where q is final: a run of vertical links writes to its own slots and to the row
    /// above's, so q is final before the next run's upper slots (at lower slot numbers: rows above
    /// in the image).
    #[inline(always)]
    fn next_direction(&self, dir: &mut [f32], r: &[f32], beta: f32, q: &mut [f32], moved: (&mut [f32], f32)) -> f64 {
        let (u, alpha) = moved;
        const BLOCK: usize = 2048;
        let m = q.len() - 2;
        let (mut run, mut updated, mut sum) = (0, 1, BlockSum::default());
        let mut start = 1;
        while start <= m {
            let end = (start + BLOCK).min(m + 1);
            // The direction one slot ahead of the block, its east neighbour.
            let ahead = (end + 1).min(m + 1);
            for ((d, u), &r) in dir[updated..ahead].iter_mut().zip(&mut u[updated..ahead]).zip(&r[updated..ahead]) {
                *u += alpha * *d;
                *d = r + beta * *d;
            }
            updated = ahead;
            self.along_rows(dir, q, start..end);
            while let Some(&[k, n, above]) = self.up_runs.get(run) {
                if (k + n) as usize > end {
                    break;
                }
                self.vertical([k, n, above], dir, q);
                run += 1;
            }
            let done = match self.up_runs.get(run) {
                _ if end == m + 1 => q.len(),
                Some(&[_, _, above]) => (above as usize).min(end) / 8 * 8,
                None => end / 8 * 8,
            };
            sum.add(dir, q, done);
            start = end;
        }
        sum.total
    }
}

/// A conjugate-gradient step's residual update r -= alpha q, returning the new r . r (summed as
/// `dot` sums), in one pass over r.
#[inline(always)]
fn cg_residual(r: &mut [f32], q: &[f32], alpha: f32) -> f64 {
    const BLOCK: usize = 4096;
    let mut total = 0f64;
    for (r, q) in r.chunks_mut(BLOCK).zip(q.chunks(BLOCK)) {
        let mut lanes = [0f32; 8];
        let mut tail = 0f32;
        let (mut rc, mut qc) = (r.chunks_exact_mut(8), q.chunks_exact(8));
        for (r, q) in (&mut rc).zip(&mut qc) {
            for l in 0..8 {
                r[l] -= alpha * q[l];
                lanes[l] += r[l] * r[l];
            }
        }
        for (r, &q) in rc.into_remainder().iter_mut().zip(qc.remainder()) {
            *r -= alpha * q;
            tail += *r * *r;
        }
        total += lanes.iter().map(|&l| l as f64).sum::<f64>() + tail as f64;
    }
    total
}

/// sum a_k b_k, in eight f32 lanes per block of 4096, blocks summed in f64: it vectorises, and no
/// lane sums more than 512 terms.
#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f64 {
    let mut sum = BlockSum::default();
    sum.add(a, b, a.len());
    sum.total
}

/// `dot` taken a stretch at a time, in order: each lane and block sums the same terms in the
/// same order as over the whole, so the total is the same to the bit (stretches end on
/// multiples of 8, but the last).
#[derive(Default)]
struct BlockSum {
    lanes: [f32; 8],
    total: f64,
    /// The next index to add.
    next: usize,
}

impl BlockSum {
    /// Adds a_k b_k over `self.next..to` (a multiple of 8, or the slices' end).
    #[inline(always)]
    fn add(&mut self, a: &[f32], b: &[f32], to: usize) {
        debug_assert!(to.is_multiple_of(8) || to == a.len(), "a stretch ends on a multiple of 8 or at the end");
        const BLOCK: usize = 4096;
        while self.next < to {
            let block_end = (self.next / BLOCK + 1) * BLOCK;
            let end = to.min(block_end);
            let whole = self.next + (end - self.next) / 8 * 8;
            let (ca, cb) = (a[self.next..whole].chunks_exact(8), b[self.next..whole].chunks_exact(8));
            for (x, y) in ca.zip(cb) {
                for l in 0..8 {
                    self.lanes[l] += x[l] * y[l];
                }
            }
            // What is left of the last block, summed on its own.
            let tail = a[whole..end].iter().zip(&b[whole..end]).map(|(x, y)| x * y).sum::<f32>();
            if end == block_end || end == a.len() {
                self.total += self.lanes.iter().map(|&l| l as f64).sum::<f64>() + tail as f64;
                self.lanes = [0.0; 8];
            }
            self.next = end;
        }
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the camera image
        image: One<Image>,
        /// sparse metric depth (the z-buffered prompt)
        sparse: One<DepthMap>,
        /// sky pixels (e.g. from EstimateSky), set to sky_depth
        sky: Optional<Mask>,
        /// the ego vehicle's body (EgoMask.mask): no sample is read there, and depth and support
        /// are 0 (invalid) there
        ego: Optional<Mask>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// dense metric depth, sky at sky_depth, 0 on the ego body
        depth: One<DepthMap>,
        /// per-pixel confidence: distance (px) to the nearest sample of the sparse input, 0 on a
        /// sample (a training loader masks pixels above its own threshold); kept only when the
        /// run reads it (the training-pair pipelines do not)
        support: OnDemand<DepthMap>,
    }
}

pub struct CompleteDepth(Params, crate::model_worker::ModelWorker);

impl Stage for CompleteDepth {
    const KIND: &'static str = "CompleteDepth";
    // 9: the 2D fill's weights squared from one iteration to the next instead of looked up
    //    again (outputs within 1e-4, relative, of 8's).
    // 10: the refinement's CG on the system scaled to a unit diagonal (the same iterates as the
    //    Jacobi-preconditioned one; outputs within 3e-4 of 9's).
    // 11: the 2D fill over 2x2 blocks, spread back by colour likeness, in 2 passes; the refinement
    //    40 steps in a 5 px band (docs/BENCHMARKS.md, "Completion time vs IP-Basic").
    // 12: depths rounded to 16 significant bits (`to_16_significant_bits`; within 1.5e-5 of 11's),
    //    the sky's and a worker's too.
    // 13: no depth farther than the farthest sample (a few pixels of 26-53 km on the shared DGP
    //    scene).
    // 14: samples seen through a nearer object dropped first (`enclosed_reach`; facade returns on a
    //    tree crown between its rings).
    // 15: the 2D fill's links compare colours averaged over 10 x 10 px (`smooth_texture`), its
    //    colour step 40 -> 15 (`smooth_edge`); the spread back keeps 40 (`spread_edge`).
    const VERSION: u32 = 15;
    const SUMMARY: &'static str =
        "Image + sparse depth -> dense metric depth (image-guided inverse-depth interpolation; sky = 100 m)";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        let worker = crate::model_worker::ModelWorker::new(params.worker.clone());
        Ok(CompleteDepth(params, worker))
    }
    fn identity(&self) -> Result<Option<String>> {
        self.1.identity()
    }
    fn resource(&self) -> Option<dist4d_runtime::Resource> {
        self.1.resource()
    }
    fn run(&self, ctx: &TaskContext, mut i: Inputs) -> Result<Made<Outputs>> {
        let ego_mask = i.ego.take();
        let ego = super::ego_mask::wired(ego_mask.as_ref(), i.sparse.width, i.sparse.height, "prompt")?;
        if let Some(ego) = ego {
            // A prompt made without the mask still has the road behind the hood on it.
            super::ego_mask::set_where(&mut i.sparse.data, ego, 0.0);
        }
        let mut out = if self.1.is_set() {
            worker_completion(ctx, &self.0, &self.1, &i)?
        } else {
            let c = ScanlineCompleter(self.0.clone()).complete(&i.image, &i.sparse, i.sky.as_ref(), ctx.wants("support"))?;
            // The refinement stops early on a stop request: its partial result is not kept.
            dist4d_types::cancel::check()?;
            Outputs { depth: c.depth, support: c.support }
        };
        if let Some(ego) = ego {
            for map in std::iter::once(&mut out.depth).chain(out.support.as_mut()) {
                super::ego_mask::set_where(&mut map.data, ego, 0.0);
            }
        }
        Ok(out.into())
    }
}

/// The completion by the stage's worker (op `complete_depth`: inputs `image`, NPY uint8 H x W x 3,
/// and `prompt`, NPY float32 H x W, 0 = none; output `depth`, NPY float32 H x W), checked (shape,
/// finite, not negative), then the sky and the support map as the built-in completer makes them.
fn worker_completion(
    ctx: &TaskContext,
    p: &Params,
    worker: &crate::model_worker::ModelWorker,
    i: &Inputs,
) -> Result<Outputs> {
    use crate::model_worker::{npy_rgb8, Exchange};
    let (w, h) = (i.sparse.width, i.sparse.height);
    ensure!(
        (i.image.width, i.image.height) == (w, h),
        "the image is {}x{}, the prompt {w}x{h}",
        i.image.width,
        i.image.height
    );
    let ex = Exchange::new()?;
    let inputs = vec![
        ex.put("image", "image.npy", &npy_rgb8(w, h, &i.image.rgb))?,
        ex.put("prompt", "prompt.npy", &dist4d_types::formats::npy_f32(&[h as usize, w as usize], &i.sparse.data))?,
    ];
    let outputs = worker.call(ctx, &ex, "complete_depth", inputs, serde_json::json!({}))?;
    let mut data = crate::model_worker::worker_depth(&ex, &outputs, "depth", w, h)?;
    // 16 significant bits, as the built-in completer gives (`to_16_significant_bits`); 0 stays 0.
    for z in data.iter_mut().filter(|z| **z > 0.0) {
        *z = to_16_significant_bits(*z);
    }
    if let Some(sky) = &i.sky {
        ensure!(sky.data.len() == data.len(), "the sky mask is not {w}x{h}");
        for (z, &s) in data.iter_mut().zip(&sky.data) {
            if s != 0 {
                *z = to_16_significant_bits(p.sky_depth);
            }
        }
    }
    let support = ctx.wants("support").then(|| DepthMap {
        width: w,
        height: h,
        data: support_distance(&i.sparse.data, w as usize, h as usize),
    });
    Ok(Outputs { depth: DepthMap { width: w, height: h, data }, support })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depths_keep_16_significant_bits_rounded_to_the_nearest() {
        let mut rng = dist4d_types::rng::Rng::new(3);
        for _ in 0..10_000 {
            let v = rng.range(0.05, 300.0) as f32;
            let r = to_16_significant_bits(v);
            assert_eq!(r.to_bits() & 0xFF, 0, "{v}: low byte not zero");
            assert!(((r - v) / v).abs() <= 1.0 / 65536.0, "{v} -> {r}");
            // Nearest: neither neighbour with 16 significant bits is closer.
            let step = f32::from_bits(r.to_bits() + 0x100) - r;
            assert!((r - v).abs() <= step / 2.0 + f32::EPSILON * v, "{v} -> {r}");
            assert_eq!(to_16_significant_bits(r), r, "not idempotent at {v}");
        }
        // Depths the pipeline sets exactly stay exact; a mantissa of all ones carries into 2^k.
        assert_eq!(to_16_significant_bits(100.0), 100.0);
        assert_eq!(to_16_significant_bits(f32::from_bits(0x427F_FFFF)), 64.0);
    }

    #[test]
    fn the_farthest_sample_gives_the_least_inverse_depth_to_the_bit() {
        // What it replaced: the least 1 / z over the positive depths (f32::MAX without any).
        let least_inverse = |depth: &[f32]| depth.iter().filter(|&&z| z > 0.0).fold(f32::MAX, |m, &z| m.min(1.0 / z));
        // As `complete_portable` takes it.
        let of = |depth: &[f32]| {
            let z = farthest_sample(depth);
            if z > 0.0 {
                (1.0 / z).min(f32::MAX)
            } else {
                f32::MAX
            }
        };
        let mut rng = dist4d_types::rng::Rng::new(11);
        let odd = [0.0, -0.0, -3.0, f32::NAN, -f32::NAN, f32::NEG_INFINITY, 1e-42, f32::MAX];
        for len in [0, 1, 15, 16, 17, 100, 1_000] {
            let mut depth: Vec<f32> = (0..len).map(|_| rng.range(0.5, 120.0) as f32).collect();
            for (k, &v) in odd.iter().enumerate() {
                if k < len {
                    depth[(k * 7) % len] = v;
                }
            }
            assert_eq!(of(&depth).to_bits(), least_inverse(&depth).to_bits(), "{len} depths");
            if len > 3 {
                depth[len - 2] = f32::INFINITY;
                assert_eq!(of(&depth), 0.0);
                assert_eq!(of(&depth).to_bits(), least_inverse(&depth).to_bits(), "{len} depths, one +inf");
            }
        }
        assert_eq!(farthest_sample(&[0.0, -1.0, f32::NAN]), 0.0);
        // Only subnormal samples: 1 / z overflows; the old least was f32::MAX.
        for depth in [&[1e-42f32][..], &[1e-42, 0.0, 3e-39][..]] {
            assert_eq!(of(depth).to_bits(), least_inverse(depth).to_bits(), "{depth:?}");
        }
    }

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

    use crate::curation::sky::{estimate_sky, Params as SkyParams};

    fn grey(w: u32, h: u32, f: impl Fn(usize, usize) -> [u8; 3]) -> Image {
        let mut rgb = Vec::new();
        for y in 0..h as usize {
            for x in 0..w as usize {
                rgb.extend_from_slice(&f(x, y));
            }
        }
        Image { width: w, height: h, rgb }
    }

    #[test]
    fn a_ground_plane_sampled_on_sparse_rows_is_recovered_exactly() {
        // Camera 1.5 m above a flat road, f = 100, horizon at row 20: z = 150 / (v - 20).
        let (w, h) = (40u32, 60u32);
        let truth = |y: usize| 150.0 / (y as f32 + 0.5 - 20.0);
        let mut sparse = DepthMap::new(w, h);
        for y in (24..h as usize).step_by(7) {
            for x in (0..w as usize).step_by(5) {
                sparse.data[y * w as usize + x] = truth(y);
            }
        }
        let image = grey(w, h, |_, _| [90, 90, 90]);
        // Without growth (which copies a sample's depth to its neighbours, a small error on a
        // slanted surface) and without the average of unsupported pixels (which mixes rows, so
        // it is not exact on the ground: the price of no streaks), interpolation in inverse
        // depth is exact on a plane.
        let p = Params { grow: 0.0, smooth_sigma: 0.0, refine_iterations: 0, ..Params::default() };
        let d = complete(&p, &image, &sparse, None, false).depth;
        for y in 24..h as usize {
            for x in 0..w as usize {
                let z = d.data[y * w as usize + x];
                assert!((z - truth(y)).abs() / truth(y) < 1e-4, "({x}, {y}): {z} vs {}", truth(y));
            }
        }
    }

    #[test]
    fn the_ground_keeps_its_slope_up_to_the_farther_wall_it_meets() {
        // A street's far end: a wall 30 m away over rows 0..=12, sampled on rows 2 and 6; the
        // road below (horizon at row 8, camera 1.5 m up, f = 100: z = 150 / (v - 8)) meets it
        // between rows 12 and 13 and is sampled from row 26 down. The gap 7..26 splits at the
        // wall's edge; below it the road's depth must keep falling towards the wall (it used to
        // stay at the depth of its highest sample, 8 m, up to the wall), and a painted line in
        // the road (rows 21-22, a weaker edge) must not stop it.
        let (w, h) = (30u32, 60u32);
        let road = |y: usize| 150.0 / (y as f32 + 0.5 - 8.0);
        let mut sparse = DepthMap::new(w, h);
        for x in 0..w as usize {
            for y in [2, 6] {
                sparse.data[y * w as usize + x] = 30.0;
            }
            for y in (26..h as usize).step_by(7) {
                sparse.data[y * w as usize + x] = road(y);
            }
        }
        let image = grey(w, h, |_, y| match y {
            0..=12 => [200, 200, 200],
            21 | 22 => [130, 130, 130],
            _ => [60, 60, 60],
        });
        let p = Params { grow: 0.0, smooth_sigma: 0.0, refine_iterations: 0, ..Params::default() };
        let d = complete(&p, &image, &sparse, None, false).depth;
        for y in 0..26 {
            let (z, truth) = (d.data[y * w as usize + 5], if y <= 12 { 30.0 } else { road(y) });
            assert!((z - truth).abs() < 0.01 * truth, "row {y}: {z} vs {truth}");
        }
    }

    #[test]
    fn surfaces_continue_beyond_their_samples_where_the_average_agrees() {
        // A facade at a grazing angle (inverse depth linear along rows: 1/z = 0.05 + 0.0006 x,
        // 20 m to 10 m) over rows 0..70, sampled on rows 45..70 only; below it a road sampled
        // down to row 84 (inverse depth linear down the rows), its last rows unsampled. One
        // colour on each, so the 2D average of measured depths reaches the unsampled pixels
        // unhindered: it cannot extrapolate (its values lie between the samples'), the
        // continuation of the column can.
        let (w, h) = (80u32, 100u32);
        let truth = |x: usize, y: usize| {
            if y < 70 {
                1.0 / (0.05 + 0.0006 * x as f32)
            } else {
                1.0 / (0.05 + 0.01 * (y as f32 - 69.0))
            }
        };
        let mut sparse = DepthMap::new(w, h);
        for y in (45..85).step_by(3) {
            for x in (0..w as usize).step_by(2) {
                sparse.data[y * w as usize + x] = truth(x, y);
            }
        }
        let image = grey(w, h, |_, y| if y < 70 { [100, 100, 100] } else { [60, 60, 60] });
        // The mean and the worst relative error over `rows`.
        let error = |keep_planes: f32, rows: std::ops::Range<usize>| {
            let p = Params { keep_planes, refine_iterations: 0, ..Params::default() };
            let d = complete(&p, &image, &sparse, None, false).depth;
            let (mut sum, mut worst, mut n) = (0f32, 0f32, 0);
            for y in rows {
                for x in 0..w as usize {
                    let e = (d.data[y * w as usize + x] - truth(x, y)).abs() / truth(x, y);
                    (sum, worst, n) = (sum + e, worst.max(e), n + 1);
                }
            }
            (sum / n as f32, worst)
        };
        let worst = |keep_planes, rows| error(keep_planes, rows).1;
        // The continuation is taken wholly only where the average agrees exactly (the weight
        // falls linearly with their difference, and the correction is averaged along rows), so
        // the facade's ends are not exact; but the error at least halves on the mean.
        let (kept, averaged) = (error(0.5, 0..40).0, error(0.0, 0..40).0);
        assert!(kept < 0.5 * averaged && averaged > 0.05, "facade above its samples: {kept} against {averaged}");
        assert!(worst(0.5, 88..100) < 1e-4, "road below its samples: {}", worst(0.5, 88..100));
    }

    #[test]
    fn the_facade_above_a_crown_takes_the_facade_s_depth_through_its_texture() {
        // A textured facade 20 m away (grey, each pixel +-30 per channel) behind a smooth green
        // crown 8 m away (a disc of radius 40 px centred at (120, 110)); LiDAR rings every 4 rows
        // from row 100 down, none above (the crown's top, row 70, is above the LiDAR), and two
        // patches of stereo depth on the facade beside the crown. A column through the crown
        // continues the crown's depth up to the image's top; only the 2D fill can give the
        // facade above the crown the facade's depth, from the patches 35-50 px away through the
        // facade's texture. Comparing raw block colours, the texture's steps along the way bring
        // the patches' weight under the fill's cut-off, and the crown's continuation stays (with
        // a flat grey facade, or without the patches, the two settings agree: a reviewer checked).
        let (w, h) = (240u32, 160u32);
        let crown = |x: usize, y: usize| (x as f32 - 120.0).powi(2) + (y as f32 - 110.0).powi(2) < 40.0 * 40.0;
        let mut rng = dist4d_types::rng::Rng::new(23);
        let noise: Vec<i32> = (0..w * h * 3).map(|_| rng.below(61) as i32 - 30).collect();
        let image = grey(w, h, |x, y| {
            if crown(x, y) {
                [40, 90, 40]
            } else {
                let i = 3 * (y * w as usize + x);
                [0, 1, 2].map(|k| (120 + noise[i + k]) as u8)
            }
        });
        let mut sparse = DepthMap::new(w, h);
        for y in (100..h as usize).step_by(4) {
            for x in (0..w as usize).step_by(2) {
                sparse.data[y * w as usize + x] = if crown(x, y) { 8.0 } else { 20.0 };
            }
        }
        // Stereo found the facade in two patches beside the crown, 35-50 px from it.
        for y in (10..60).step_by(3) {
            for x in (66..72).chain(168..174).step_by(2) {
                sparse.data[y * w as usize + x] = 20.0;
            }
        }
        // The mean relative error above the crown (rows 5..60, columns 105..135).
        let above = |p: &Params| {
            let d = complete(p, &image, &sparse, None, false).depth;
            let (mut sum, mut n) = (0f32, 0);
            for y in 5..60 {
                for x in 105..135 {
                    sum += (d.data[y * w as usize + x] - 20.0).abs() / 20.0;
                    n += 1;
                }
            }
            sum / n as f32
        };
        let evened = above(&Params::default());
        // CompleteDepth 14's fill: the blocks' own colours, a step of 40.
        let raw = above(&Params { smooth_texture: 0, smooth_edge: 40.0, ..Params::default() });
        assert!(evened < 0.05, "the facade above the crown is off by {evened} on average");
        assert!(raw > 0.3, "the test no longer tells: the fill without evened colours is off by {raw} only");
    }

    #[test]
    fn a_box_mean_is_the_mean_of_the_square_cut_at_the_borders() {
        let mut rng = dist4d_types::rng::Rng::new(29);
        for (w, h, r) in [(9usize, 7usize, 2usize), (1, 5, 1), (6, 1, 3), (4, 4, 0), (5, 6, 9)] {
            let planes: Vec<u8> = (0..3 * w * h).map(|_| rng.below(256) as u8).collect();
            let got = box_mean(&planes, w, h, r);
            for k in 0..3 {
                for y in 0..h {
                    for x in 0..w {
                        let (mut sum, mut cells) = (0u32, 0u32);
                        for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                            for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                                sum += planes[k * w * h + yy * w + xx] as u32;
                                cells += 1;
                            }
                        }
                        let expected = (sum as f32 * (1.0 / cells as f32) + 0.5) as u8;
                        assert_eq!(got[k * w * h + y * w + x], expected, "{w}x{h}, r {r}, plane {k}, ({x}, {y})");
                    }
                }
            }
        }
    }

    #[test]
    fn a_depth_edge_follows_the_image_edge_and_sky_gets_its_depth() {
        // A wall 5 m away covers rows 0..30 of columns 10..20 and sits on a road 20 m away;
        // LiDAR samples rows 25 and 40 only. The image is dark on the wall, mid-grey elsewhere;
        // the top rows outside the wall are bright blue sky.
        let (w, h) = (30u32, 50u32);
        let mut sparse = DepthMap::new(w, h);
        for x in 0..w as usize {
            let wall = (10..20).contains(&x);
            sparse.data[25 * w as usize + x] = if wall { 5.0 } else { 20.0 };
            sparse.data[40 * w as usize + x] = 20.0;
        }
        let image = grey(w, h, |x, y| {
            if (10..20).contains(&x) && y < 33 {
                [30, 30, 30]
            } else if y < 10 {
                [150, 190, 240]
            } else {
                [120, 110, 100]
            }
        });
        let sky = estimate_sky(&SkyParams::default(), &image, Some(&sparse));
        let sky = Mask { width: w, height: h, data: sky.into_iter().map(u8::from).collect() };
        let d = complete(&Params::default(), &image, &sparse, Some(&sky), false).depth;
        let at = |x: usize, y: usize| d.data[y * w as usize + x];
        // Pixels between the rows take the edge-aware average of the sampled ones, which the
        // grown samples beside the wall's edges (one column of road-coloured pixels at 5 m)
        // nudge by a few centimetres.
        let near = |z: f32, truth: f32| (z - truth).abs() < 0.02 * truth;
        assert!(near(at(15, 32), 5.0), "{}", at(15, 32));
        assert!(near(at(15, 33), 20.0), "{}", at(15, 33));
        assert!(near(at(15, 5), 5.0), "the wall continues up: {}", at(15, 5));
        assert_eq!(at(3, 5), 100.0, "sky");
        // Not sky (below the sky colour) and the road's depth, not the wall's. (Sample growth
        // puts the wall's depth one column beyond its edge, which the row average spreads a
        // little, so not exactly 20 m.)
        assert!(at(3, 15) > 15.0, "{}", at(3, 15));
        // Without a sky mask, nothing is sky.
        let d = complete(&Params::default(), &image, &sparse, None, false).depth;
        assert!(d.data[5 * w as usize + 3] < 25.0);
    }

    #[test]
    fn the_avx2_and_avx512_builds_compute_bit_for_bit_what_the_portable_one_does() {
        #[cfg(target_arch = "x86_64")]
        {
            if !std::arch::is_x86_feature_detected!("avx2") {
                eprintln!("skipped: this CPU has no AVX2");
                return;
            }
            // A textured scene with a near box, far ground, sky at the top and LiDAR-like rows,
            // large enough for every phase (fill, 2D fill, refinement) to run its vector loops.
            let (w, h) = (160u32, 120u32);
            let mut sparse = DepthMap::new(w, h);
            for y in (40..h as usize).step_by(6) {
                for x in (y % 3..w as usize).step_by(2) {
                    let near = (50..90).contains(&x) && y < 80;
                    sparse.data[y * w as usize + x] = if near { 6.0 + 0.01 * x as f32 } else { 30.0 - 0.1 * y as f32 };
                }
            }
            let image = grey(w, h, |x, y| {
                if y < 20 {
                    [150, 190, 240]
                } else if (50..90).contains(&x) && y < 80 {
                    [40 + (x % 7) as u8, 30, 30 + (y % 5) as u8]
                } else {
                    [120 + ((x * 7 + y * 3) % 23) as u8, 110, 100]
                }
            });
            let sky = Mask { width: w, height: h, data: (0..w * h).map(|i| u8::from(i < 20 * w)).collect() };
            let p = Params::default();
            let portable = complete_portable(&p, &image, &sparse, Some(&sky), true);
            // SAFETY: AVX2 is present, checked above.
            let avx2 = unsafe { complete_avx2(&p, &image, &sparse, Some(&sky), true) };
            let bits = |m: &DepthMap| m.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            let support = |c: &Completion| bits(c.support.as_ref().expect("asked for"));
            assert_eq!(bits(&portable.depth), bits(&avx2.depth));
            assert_eq!(support(&portable), support(&avx2));
            assert!(portable.depth.data.iter().all(|z| z.is_finite() && *z > 0.0));
            if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512bw") {
                // SAFETY: AVX-512 F and BW are present, checked just above.
                let avx512 = unsafe { complete_avx512(&p, &image, &sparse, Some(&sky), true) };
                assert_eq!(bits(&portable.depth), bits(&avx512.depth));
                assert_eq!(support(&portable), support(&avx512));
            } else {
                eprintln!("AVX-512 part skipped: this CPU has no AVX-512");
            }
        }
    }

    #[test]
    fn a_smooth_bright_facade_fading_into_its_samples_is_not_sky() {
        // Columns 0..10: a bright bluish facade whose luminance falls 1 per row from 110, so it
        // is smooth and sky-coloured at the top but meets its LiDAR samples (row 30, 10 m)
        // without an edge. Columns 10..20: sky down to row 12, then a dark wall at an edge.
        let (w, h) = (20u32, 40u32);
        let mut sparse = DepthMap::new(w, h);
        for x in 0..w as usize {
            sparse.data[30 * w as usize + x] = 10.0;
        }
        let image = grey(w, h, |x, y| {
            if x < 10 {
                let v = 110 - y as u8;
                [v - 6, v, v + 20]
            } else if y < 12 {
                [150, 190, 240]
            } else {
                [60, 60, 60]
            }
        });
        let sky = estimate_sky(&SkyParams { min_area: 0.0, ..SkyParams::default() }, &image, Some(&sparse));
        let at = |x: usize, y: usize| sky[y * w as usize + x];
        assert!(!at(5, 2), "facade, not sky");
        assert!(at(15, 2), "sky above an edge");
        assert!(!at(15, 12), "the wall below the edge");
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
    fn support_distance_is_the_chamfer_distance_to_the_nearest_sample() {
        let (w, h) = (11, 9);
        let mut sparse = vec![0f32; w * h];
        sparse[4 * w + 5] = 7.0;
        let d = support_distance(&sparse, w, h);
        assert_eq!(d[4 * w + 5], 0.0);
        assert_eq!(d[4 * w + 8], 3.0);
        assert_eq!(d[7 * w + 8], 4.0, "three diagonal steps: 3 x 4/3");
        assert!(support_distance(&[0.0; 4], 2, 2).iter().all(|&v| v == f32::MAX));
    }

    /// Red, green and blue planes of a `w` x `h` image from a colour per pixel.
    fn planes_of(w: usize, h: usize, f: impl Fn(usize, usize) -> [u8; 3]) -> Vec<u8> {
        let mut planes = vec![0u8; 3 * w * h];
        for y in 0..h {
            for x in 0..w {
                let c = f(x, y);
                for k in 0..3 {
                    planes[k * w * h + y * w + x] = c[k];
                }
            }
        }
        planes
    }

    #[test]
    fn blocks_sum_the_sources_and_average_the_colours_of_their_pixels() {
        // Odd sizes: the last block row and column hold 2 or 1 pixels.
        let (w, h) = (5usize, 3usize);
        let inv: Vec<f32> = (0..w * h).map(|i| 0.1 * (i + 1) as f32).collect();
        // Sources: near a sample (every other pixel), or ground (pixel 7); the last column is sky.
        let near: Vec<u8> = (0..w * h).map(|i| (i % 2 == 0) as u8).collect();
        let continued: Vec<u8> = (0..w * h).map(|i| if i == 7 { GROUND } else { CONTINUED }).collect();
        let sky: Vec<u8> = (0..w * h).map(|i| (i == 4 || i == 9 || i == 14) as u8).collect();
        let planes = planes_of(w, h, |x, y| [(10 * x + y) as u8, 7, (x * y) as u8]);
        let b = Blocks::of(&inv, &near, &continued, &planes, &sky, w, h);
        assert_eq!((b.w, b.h), (3, 2));
        for (by, bx) in (0..2).flat_map(|by| (0..3).map(move |bx| (by, bx))) {
            let pixels: Vec<usize> =
                [(2 * by, 2 * bx), (2 * by, 2 * bx + 1), (2 * by + 1, 2 * bx), (2 * by + 1, 2 * bx + 1)]
                    .into_iter()
                    .filter(|&(y, x)| y < h && x < w)
                    .map(|(y, x)| y * w + x)
                    .collect();
            let source = |i: usize| is_source(inv[i], near[i], sky[i], continued[i]);
            let j = by * 3 + bx;
            let num: f32 = pixels.iter().filter(|&&i| source(i)).map(|&i| inv[i]).sum();
            let den = pixels.iter().filter(|&&i| source(i)).count() as f32;
            assert!((b.num[j] - num).abs() < 1e-6 && b.den[j] == den, "block {j}: {} {} against {num} {den}", b.num[j], b.den[j]);
            for k in 0..3 {
                let sum: u32 = pixels.iter().map(|&i| planes[k * w * h + i] as u32).sum();
                let n = pixels.len() as u32;
                assert_eq!(b.planes[k * 6 + j] as u32, (sum + n / 2) / n, "block {j}, colour {k}");
            }
            assert_eq!(b.sky[j], pixels.iter().all(|&i| sky[i] != 0) as u8, "block {j}");
        }
    }

    #[test]
    fn spreading_blocks_keeps_their_value_on_each_side_of_a_colour_edge() {
        // Blocks left of x = 10 red with inverse depth 0.5, right of it blue with 0.1; a pixel
        // row spread from them takes its own side's value, up to the edge, and a uniform region
        // exactly its value.
        let (w, h) = (20usize, 8usize);
        let planes = planes_of(w, h, |x, _| if x < 10 { [200, 30, 30] } else { [30, 30, 200] });
        let (bw, bh) = (10usize, 4usize);
        let mut blocks = Blocks { w: bw, h: bh, num: vec![0.0; bw * bh], den: vec![4.0; bw * bh], planes: vec![0; 3 * bw * bh], sky: vec![0; bw * bh] };
        for by in 0..bh {
            for bx in 0..bw {
                let j = by * bw + bx;
                blocks.num[j] = 4.0 * if bx < 5 { 0.5 } else { 0.1 };
                let c: [u8; 3] = if bx < 5 { [200, 30, 30] } else { [30, 30, 200] };
                for k in 0..3 {
                    blocks.planes[k * bw * bh + j] = c[k];
                }
            }
        }
        let p = Params::default();
        let like = likeness(&p, p.smooth_sigma / p.spread_edge);
        let mut spread = Spread::new(w);
        for y in 0..h {
            spread.row(&blocks, y, &planes, w, h, &like);
            for x in 0..w {
                let v = spread.num[x] / spread.den[x];
                let expected = if x < 10 { 0.5 } else { 0.1 };
                assert!((v - expected).abs() < 1e-4 * expected, "row {y}, pixel {x}: {v}");
            }
        }
        // Without the colour likeness (a grey image), the pixels beside the edge mix both sides.
        let grey = planes_of(w, h, |_, _| [100, 100, 100]);
        let flat = Blocks { planes: vec![100; 3 * bw * bh], ..blocks };
        let mut spread = Spread::new(w);
        spread.row(&flat, 3, &grey, w, h, &like);
        // Pixel 9 is 3/4 on block 4 (0.5) and 1/4 on block 5 (0.1), pixel 10 the other way.
        assert!((spread.num[9] / spread.den[9] - 0.4).abs() < 1e-6);
        assert!((spread.num[10] / spread.den[10] - 0.2).abs() < 1e-6);
    }

    #[test]
    fn spreading_blocks_is_bilinear_between_block_centres_and_clamped_at_the_borders() {
        // One colour, block values a ramp in both directions; odd sizes, so that the last block
        // row and column are half blocks.
        for (w, h) in [(9usize, 7usize), (10, 8), (2, 5), (5, 2)] {
            let (bw, bh) = (w.div_ceil(2), h.div_ceil(2));
            let value = |bx: usize, by: usize| bx as f32 + 10.0 * by as f32;
            let blocks = Blocks {
                w: bw,
                h: bh,
                num: (0..bw * bh).map(|j| 4.0 * value(j % bw, j / bw)).collect(),
                den: vec![4.0; bw * bh],
                planes: vec![90; 3 * bw * bh],
                sky: vec![0; bw * bh],
            };
            let planes = planes_of(w, h, |_, _| [90, 90, 90]);
            let p = Params::default();
            let like = likeness(&p, p.smooth_sigma / p.spread_edge);
            let mut spread = Spread::new(w);
            // A pixel's centre in block units is (x - 0.5) / 2, clamped to the first and last
            // block centres.
            let at = |x: usize, n: usize| ((x as f32 - 0.5) / 2.0).clamp(0.0, (n - 1) as f32);
            for y in 0..h {
                spread.row(&blocks, y, &planes, w, h, &like);
                for x in 0..w {
                    let expected = at(x, bw) + 10.0 * at(y, bh);
                    let v = spread.num[x] / spread.den[x];
                    assert!((v - expected).abs() < 1e-4, "{w}x{h}, pixel ({x}, {y}): {v} against {expected}");
                }
            }
        }
    }

    #[test]
    fn odd_and_tiny_images_complete_to_finite_depths() {
        for (w, h) in [(31u32, 17u32), (3, 3), (2, 9), (9, 2), (1, 5), (5, 1)] {
            let mut sparse = DepthMap::new(w, h);
            for (i, z) in sparse.data.iter_mut().enumerate() {
                if i % 5 == 0 {
                    *z = 4.0 + (i % 7) as f32;
                }
            }
            let image = grey(w, h, |x, y| [(x * 40 % 256) as u8, (y * 30 % 256) as u8, 100]);
            let c = complete(&Params::default(), &image, &sparse, None, true);
            assert_eq!(c.depth.data.len(), (w * h) as usize);
            assert!(c.depth.data.iter().all(|z| z.is_finite() && *z > 0.0), "{w}x{h}: {:?}", c.depth.data);
        }
    }

    #[test]
    fn pixels_near_a_sample_are_those_the_support_distance_puts_within_reach() {
        let mut rng = dist4d_types::rng::Rng::new(17);
        for (w, h) in [(1, 1), (1, 7), (9, 1), (2, 2), (31, 17), (64, 40)] {
            for density in [0.0, 0.02, 0.3, 1.0] {
                let sparse: Vec<f32> = (0..w * h)
                    .map(|_| if rng.next_f64() < density { 1.0 + rng.next_f64() as f32 } else { 0.0 })
                    .collect();
                let distance = support_distance(&sparse, w, h);
                for reach in [0.0, 0.5, 1.0, 1.2, 4.0 / 3.0, 2.5] {
                    let from_distance = near_samples(&sparse, Some(&distance), reach, w, h);
                    let expected: Vec<u8> = distance.iter().map(|&d| (d <= reach) as u8).collect();
                    assert_eq!(from_distance, expected);
                    assert_eq!(near_samples(&sparse, None, reach, w, h), expected, "{w}x{h}, density {density}, reach {reach}");
                }
            }
        }
    }

    #[test]
    fn the_depth_is_the_same_with_and_without_the_support_map() {
        let (w, h) = (80u32, 60u32);
        let mut sparse = DepthMap::new(w, h);
        for y in (20..h as usize).step_by(5) {
            for x in (y % 2..w as usize).step_by(3) {
                sparse.data[y * w as usize + x] = if x < 30 { 5.0 } else { 20.0 - 0.1 * y as f32 };
            }
        }
        let image = grey(w, h, |x, y| if x < 30 { [200, 40, 40] } else { [90 + (y % 9) as u8, 100, 110] });
        let with = complete(&Params::default(), &image, &sparse, None, true);
        let without = complete(&Params::default(), &image, &sparse, None, false);
        let bits = |m: &DepthMap| m.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&with.depth), bits(&without.depth));
        assert!(with.support.is_some() && without.support.is_none());
    }

    #[test]
    fn chaining_a_row_in_quarters_gives_what_one_chain_gives() {
        let mut rng = dist4d_types::rng::Rng::new(3);
        for len in (0..40).chain([97, 1600, 1601, 1603]) {
            for density in [0.0, 0.01, 0.2, 0.9] {
                let row: Vec<u32> = (0..len)
                    .map(|_| if rng.next_f64() < density { rng.below(12) as u32 } else { FAR })
                    .collect();
                let mut one = row.clone();
                for x in 1..len {
                    one[x] = one[x].min(one[x - 1] + 3);
                }
                let mut quarters = row;
                chain_along(&mut quarters);
                assert_eq!(quarters, one, "{len} px, density {density}");
            }
        }
    }

    #[test]
    fn the_fused_cg_pass_gives_the_move_direction_product_and_sum_to_the_bit() {
        // 9 000 slots (blocks of 2 048 from slot 1), rows of 300 slots. Vertical runs: short
        // random ones, one across the first block boundary, and one longer than a block and than
        // a row (a band over whole rows: it overlaps its own upper slots); none in the last third,
        // where the product is final at each block's end.
        let mut rng = dist4d_types::rng::Rng::new(5);
        let (m, row) = (9_000usize, 300usize);
        let len = m + 2;
        let mut left: Vec<f32> = (0..len).map(|k| if k > 1 && k <= m && k % row != 1 { rng.range(0.0, 0.25) as f32 } else { 0.0 }).collect();
        left[0] = 0.0;
        let mut starts = Vec::new();
        let mut k = row + 1;
        while k + 40 <= 2_000 {
            let n = 1 + rng.below(40) as usize;
            starts.push((k, n));
            k += n + rng.below(20) as usize;
        }
        starts.extend([(2_040, 20), (2_100, 30), (4_000, 2_500)]);
        let mut up = vec![0f32; len];
        let mut up_runs = Vec::new();
        for (k, n) in starts {
            up_runs.push([k as u32, n as u32, (k - row) as u32]);
            for t in 0..n {
                up[k + t] = rng.range(0.0, 0.25) as f32;
            }
        }
        let system = Stencil { up_runs: &up_runs, left: &left, up: &up };
        let vector = |rng: &mut dist4d_types::rng::Rng| -> Vec<f32> {
            (0..len).map(|k| if k == 0 || k == m + 1 { 0.0 } else { rng.range(-1.0, 1.0) as f32 }).collect()
        };
        let (r, old) = (vector(&mut rng), vector(&mut rng));
        let beta = 0.37f32;
        let mut dir = old.clone();
        let mut q = vec![0f32; len];
        // The previous step's move along the old direction is made in the same pass.
        let (solution, alpha) = (vector(&mut rng), -0.61f32);
        let mut u = solution.clone();
        let pq = system.next_direction(&mut dir, &r, beta, &mut q, (&mut u, alpha));
        let moved: Vec<f32> = solution.iter().zip(&old).map(|(&u, &d)| u + alpha * d).collect();
        assert_eq!(u[1..=m], moved[1..=m]);
        let expected: Vec<f32> = r.iter().zip(&old).map(|(&r, &d)| r + beta * d).collect();
        let mut product = vec![0f32; len];
        system.apply(&expected, &mut product);
        assert_eq!(dir, expected);
        assert_eq!(q, product);
        assert_eq!(pq.to_bits(), dot(&expected, &product).to_bits());
        // And `dot` sums as the per-block dot product it replaced: eight f32 lanes over each
        // block of 4 096, the block's remainder on its own, blocks summed in f64.
        let mut blocks = 0f64;
        for (a, b) in expected.chunks(4096).zip(product.chunks(4096)) {
            let mut lanes = [0f32; 8];
            let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
            let tail: f32 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
            for (x, y) in ca.zip(cb) {
                for l in 0..8 {
                    lanes[l] += x[l] * y[l];
                }
            }
            blocks += lanes.iter().map(|&l| l as f64).sum::<f64>() + tail as f64;
        }
        assert_eq!(dot(&expected, &product).to_bits(), blocks.to_bits());
    }

    #[test]
    fn a_facade_above_a_tree_crown_takes_the_facade_depth_seen_beside_the_crown() {
        // A facade 20 m away (grey-blue) behind a crown 8 m away (green) covering columns
        // 12..28, rows 12..30. The LiDAR sees the crown and the facade beside it and below it,
        // but nothing above the crown: its column's highest sample is the crown's.
        let (w, h) = (40u32, 40u32);
        let crown = |x: usize, y: usize| (12..28).contains(&x) && (12..30).contains(&y);
        let image = grey(w, h, |x, y| if crown(x, y) { [30, 90, 30] } else { [100, 100, 120] });
        let mut sparse = DepthMap::new(w, h);
        for y in (2..h as usize).step_by(3) {
            for x in (0..w as usize).step_by(2) {
                let beside = !(10..30).contains(&x) || y >= 32;
                if crown(x, y) {
                    sparse.data[y * w as usize + x] = 8.0;
                } else if beside {
                    sparse.data[y * w as usize + x] = 20.0;
                }
            }
        }
        let at = |d: &DepthMap, x: usize, y: usize| d.data[y * w as usize + x];
        let d = complete(&Params::default(), &image, &sparse, None, false).depth;
        for x in 14..26 {
            let z = at(&d, x, 4);
            assert!((z - 20.0).abs() < 0.05 * 20.0, "({x}, 4): {z}");
        }
        assert!((at(&d, 20, 20) - 8.0).abs() < 0.05 * 8.0, "the crown keeps its depth: {}", at(&d, 20, 20));
        // The column alone (neither average nor refinement) would continue the crown up.
        let column = Params { smooth_sigma: 0.0, refine_iterations: 0, ..Params::default() };
        let column = complete(&column, &image, &sparse, None, false).depth;
        assert!((at(&column, 20, 4) - 8.0).abs() < 0.5, "{}", at(&column, 20, 4));
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

    #[test]
    fn refinement_moves_a_misplaced_depth_edge_onto_the_colour_edge() {
        // Columns 0..20 are dark (a pole 10 m away), 20..40 bright (a wall 20 m away); samples
        // every 6 px. The filled map starts with the edge 3 px too far left (columns 17..20 at
        // the wall's depth, as a grown band or a blurred fill leaves it).
        let (w, h) = (40usize, 30usize);
        let image = grey(w as u32, h as u32, |x, _| if x < 20 { [40, 40, 40] } else { [200, 190, 180] });
        let depth = |x: usize| if x < 20 { 10.0f32 } else { 20.0 };
        let mut sparse = vec![0f32; w * h];
        for y in (1..h).step_by(6) {
            for x in (1..w).step_by(6) {
                sparse[y * w + x] = depth(x);
            }
        }
        let start: Vec<f32> = (0..w * h).map(|i| 1.0 / if i % w < 17 { 10.0 } else { 20.0 }).collect();
        let mut inv = start.clone();
        let planes = colour_planes(&image.rgb);
        refine(&Params::default(), &mut inv, &planes, &sparse, &vec![0; w * h], w, h);
        for y in 0..h {
            for x in 15..25 {
                let z = 1.0 / inv[y * w + x];
                assert!((z - depth(x)).abs() < 0.05 * depth(x), "({x}, {y}): {z}");
            }
        }
        // Without iterations nothing moves.
        let mut same = start.clone();
        refine(
            &Params { refine_iterations: 0, ..Params::default() },
            &mut same,
            &planes,
            &sparse,
            &vec![0; w * h],
            w,
            h,
        );
        assert_eq!(same, start);
    }

    #[test]
    fn a_sample_nearer_than_a_millimetre_is_an_error_naming_its_pixel() {
        let (w, h) = (30u32, 20u32);
        let image = grey(w, h, |_, _| [90, 90, 90]);
        let mut sparse = DepthMap::new(w, h);
        for y in (1..h as usize).step_by(3) {
            for x in (0..w as usize).step_by(2) {
                sparse.data[y * w as usize + x] = 12.0;
            }
        }
        let completer = ScanlineCompleter(Params::default());
        let fine = completer.complete(&image, &sparse, None, false).unwrap();
        assert!(fine.depth.data.iter().all(|&d| d > 0.0));
        for bad in [1e-42f32, 1e-30, 5e-4] {
            let mut odd = sparse.clone();
            odd.data[7 * w as usize + 11] = bad;
            let err = completer.complete(&image, &odd, None, false).err().expect("an error").to_string();
            assert!(err.contains("pixel (11, 7)") && err.contains("nearer than"), "{err}");
        }
        // Negative, NaN and infinite values are no samples, as before.
        let mut odd = sparse.clone();
        odd.data[7 * w as usize + 11] = -3.0;
        odd.data[8 * w as usize + 11] = f32::NAN;
        assert!(completer.complete(&image, &odd, None, false).is_ok());
    }

    #[test]
    fn a_refinement_that_stops_at_once_leaves_its_band_as_it_was() {
        // One sample of a subnormal depth: its inverse depth is +inf, the residuals beside it
        // NaN, and the first step stops the refinement. The map stays as filled (a pending move
        // made after the stop, 0 times a direction holding NaN, made its neighbours NaN).
        let (w, h) = (40usize, 30usize);
        let image = grey(w as u32, h as u32, |x, _| if x < 20 { [40, 40, 40] } else { [200, 190, 180] });
        let mut sparse = vec![0f32; w * h];
        for y in (1..h).step_by(6) {
            for x in (1..w).step_by(6) {
                sparse[y * w + x] = if x < 20 { 10.0 } else { 20.0 };
            }
        }
        let odd = 13 * w + 19;
        sparse[odd] = 1e-42;
        let mut start: Vec<f32> = (0..w * h).map(|i| 1.0 / if i % w < 17 { 10.0 } else { 20.0 }).collect();
        start[odd] = 1.0 / sparse[odd];
        assert_eq!(start[odd], f32::INFINITY);
        let mut inv = start.clone();
        refine(&Params::default(), &mut inv, &colour_planes(&image.rgb), &sparse, &vec![0; w * h], w, h);
        // (To the rounding of the system's scaling, x / s * s.)
        for (i, (&v, &s)) in inv.iter().zip(&start).enumerate() {
            assert!((v - s).abs() <= 1e-6 * s || (i == odd && !v.is_finite()), "pixel {i}: {s} became {v}");
        }
    }

    #[test]
    fn a_facade_above_its_highest_samples_has_no_vertical_streaks() {
        // One uniform wall; the top samples alternate between 10 m and 12 m every 4 columns
        // (noisy MVS points), at row 40. Above them each column used to continue its own
        // sample upwards: stripes of 10 and 12 m. Far from the samples the row is now one
        // surface.
        let (w, h) = (64u32, 60u32);
        let mut sparse = DepthMap::new(w, h);
        for x in 0..w as usize {
            for y in (40..h as usize).step_by(3) {
                sparse.data[y * w as usize + x] = if (x / 4) % 2 == 0 || y > 40 { 10.0 } else { 12.0 };
            }
        }
        let image = grey(w, h, |_, _| [120, 110, 100]);
        let p = Params { grow: 0.0, ..Params::default() };
        // The depths of row 5 between columns 8 and 56: (least, greatest).
        let span = |p: &Params| {
            let d = complete(p, &image, &sparse, None, false).depth;
            (8..56).map(|x| d.data[5 * w as usize + x]).fold((f32::MAX, 0f32), |(a, b), v| (a.min(v), b.max(v)))
        };
        let (lo, hi) = span(&p);
        assert!(hi / lo < 1.02, "row 5 spans {lo}..{hi} m");
        // Kept continuations of noisy top samples would be streaks again: each column's
        // correction to the average is averaged along the row first (without the refinement,
        // which smooths steps over 5%, to see it).
        let (lo, hi) = span(&Params { refine_iterations: 0, ..p.clone() });
        assert!(hi / lo < 1.02, "without the refinement, row 5 spans {lo}..{hi} m");
        let streaky = complete(&Params { smooth_sigma: 0.0, refine_iterations: 0, ..p }, &image, &sparse, None, false).depth;
        assert_eq!(streaky.data[5 * w as usize + 5], 12.0, "without the row average: a streak");
    }
}
