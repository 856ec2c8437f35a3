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
//!
//! The code, a file per phase: `fill` (the scanline fill's pieces: samples grown into bands,
//! those seen through a nearer object dropped, gaps bridged along rows and columns), `smooth`
//! (the 2D fill), `refine` (the refinement), `support` (the support map), `kernels` (the builds
//! for each instruction set and the helpers they share). This file holds the parameters, the
//! stage, and the completion's steps in order (`complete_portable`).

mod fill;
mod kernels;
mod refine;
mod smooth;
mod support;

use crate::stage::Stage;
use anyhow::{bail, ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::{Made, TaskContext};
use dist4d_types::artifact::{DepthMap, Image, Mask};
use dist4d_types::formats::to_16_significant_bits;
use serde::{Deserialize, Serialize};

use fill::{
    bridge, column_samples, continues_a_plane, drop_enclosed, fill_rows, ground_slope, grow_radius, grow_samples, CONTINUED,
    GROUND, SPLIT,
};
use kernels::{colour_planes, farthest_sample, luma_of_planes, map};
use refine::refine;
use smooth::smooth_unsupported;
use support::{near_samples, support_distance};

pub use kernels::complete;
pub(crate) use kernels::luminance;

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

/// A dense depth and how far each of its pixels is from a measurement.
pub struct Completion {
    pub depth: DepthMap,
    /// Distance (px) from each pixel to the nearest sample of the sparse input: 0 on a sample;
    /// made only when asked for.
    pub support: Option<DepthMap>,
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

    use crate::curation::sky::{estimate_sky, Params as SkyParams};

    pub(super) fn grey(w: u32, h: u32, f: impl Fn(usize, usize) -> [u8; 3]) -> Image {
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
}
