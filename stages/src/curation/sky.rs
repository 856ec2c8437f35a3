//! `EstimateSky`: which pixels of a camera image are sky, without a segmenter.
//!
//! DiST-4D sets sky to a fixed far depth and takes the sky from a segmentation. Without one, a
//! depth completer must still tell the sky from a structure it has no depth for (a facade above
//! the LiDAR's field of view), or the sky gets completed as walls. The estimate combines geometry
//! and colour, in the spirit of classical sky detection (border detection from the top of the
//! image through smooth pixels, then a colour test; Shen and Wang 2013, "Sky region detection in
//! a single image for autonomous ground robot navigation"):
//!
//! - **Regions**: pixels join their 4-neighbours while the colour of the 3x3-smoothed image
//!   changes by at most `step` (0-255, largest channel difference): the sky is smooth, and where
//!   it meets a building, a tree or a pole the colour jumps; clouds join because their edges are
//!   soft. Only pixels that are bright enough (luminance at least half `min_luminance`), not
//!   distinctly red or green (blue within `hue_slack` of both) and without a depth sample take
//!   part. Regions are found everywhere, not only from the top edge: sky seen under a tree crown
//!   or a lamp arm is sky too.
//! - **Geometry**: LiDAR gets no return from the sky. A region with more than `max_samples`
//!   depth samples per pixel inside it (samples whose four neighbours all belong to it; `support`,
//!   e.g. the aggregated LiDAR projection) is a measured structure (a bright facade between
//!   LiDAR rings), not sky. Samples on a silhouette against the sky do not count.
//! - **Appearance**: a sky region is bright (mean luminance >= `min_luminance`) and smooth (mean
//!   |dx| + |dy| of the unsmoothed luminance <= `max_texture`; a facade is textured) and not
//!   tiny (>= `min_area` of the image), and it reaches into the upper part of the image (above
//!   `max_first_row` of its height).
//! - **Skyline**: the pixels on each side of it are blends of sky and structure; each goes to the
//!   side whose colour it is nearer (twice: the smoothing leaves a band two pixels wide).
//! - **Holes**: non-sky specks enclosed by sky, without a depth sample and smaller than
//!   `max_hole` of the image (JPEG blocks, a distant bird), become sky.
//!
//! A semantic map, when wired, takes precedence (Cityscapes id 23 = sky).
//!
//! It fails on smooth, bright, untextured walls that no depth sample touches (a white facade far
//! above the LiDAR with no MVS support), on dark skies (dusk, night) and on red or green skies.
//! Figures are in docs/BENCHMARKS.md.

use dist4d_runtime::Made;
use crate::box_sum::box_sum;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, Image, Mask, Segmentation};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Largest colour step (0-255, largest channel difference of the 3x3-smoothed image) between
    /// neighbouring sky pixels.
    pub step: f32,
    /// Darkest mean luminance (0-255) of a sky region; no pixel of it is darker than half this.
    pub min_luminance: f32,
    /// Largest mean luminance texture (|dx| + |dy| of the unsmoothed image, 0-255) of a sky region.
    pub max_texture: f32,
    /// Most depth samples inside a sky region, per pixel of the region.
    pub max_samples: f32,
    /// How far (0-255) red or green may exceed blue in a sky pixel. Real sky is blue or neutral
    /// (on the hand-labelled real images 99.5% of sky pixels have blue >= red - 2), while
    /// concrete soffits and cream facades are warm grey (blue 8-12 below red): 12 let nuScenes
    /// CAM_FRONT_RIGHT's white soffit join the sky, 4 keeps 86% of it out.
    pub hue_slack: f32,
    /// A sky region reaches above this fraction of the image height (white road markings and
    /// kerbs low in the image are bright and smooth too).
    pub max_first_row: f32,
    /// Smallest sky region kept, as a fraction of the image area.
    pub min_area: f32,
    /// Largest enclosed non-sky speck without depth that becomes sky, as a fraction of the image area.
    pub max_hole: f32,
    /// A sky pixel darker than this fraction of the frame's mean sky luminance and textured
    /// (`structure_texture`) is structure the sky crept into; 0 turns the test off.
    pub structure_luminance: f32,
    /// Mean luminance texture (|dx| + |dy|, 0-255) over a 15 px box above which a dark sky pixel
    /// is structure.
    pub structure_texture: f32,
    /// A semantic segmenter as an external worker (op `segment`: the image in, Cityscapes ids
    /// out; docs/workers.md) in place of the estimate, when the dataset has no segmentation:
    /// `Some((program: "python3", args: ["my_segmenter.py"]))`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worker: Option<crate::model_worker::WorkerSpec>,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            step: 6.0,
            min_luminance: 150.0,
            max_texture: 2.0,
            max_samples: 0.0002,
            hue_slack: 4.0,
            max_first_row: 0.5,
            min_area: 0.0003,
            max_hole: 0.0005,
            structure_luminance: 0.85,
            structure_texture: 2.5,
            worker: None,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .within("step", self.step as f64, 0.0, 255.0)
            .within("min_luminance", self.min_luminance as f64, 0.0, 255.0)
            .within("max_texture", self.max_texture as f64, 0.0, 510.0)
            .within("max_samples", self.max_samples as f64, 0.0, 1.0)
            .within("hue_slack", self.hue_slack as f64, 0.0, 255.0)
            .within("max_first_row", self.max_first_row as f64, 0.0, 1.0)
            .within("min_area", self.min_area as f64, 0.0, 1.0)
            .within("max_hole", self.max_hole as f64, 0.0, 1.0)
            .within("structure_luminance", self.structure_luminance as f64, 0.0, 1.0)
            .within("structure_texture", self.structure_texture as f64, 0.0, 510.0)
            .done()
            .into_iter()
            .chain(crate::model_worker::WorkerSpec::problems_of(self.worker.as_ref()))
            .collect()
    }
}

/// The image smoothed by a 3x3 box (edges replicated), per channel.
fn smoothed(image: &Image) -> Vec<[u8; 3]> {
    let (w, h) = (image.width as usize, image.height as usize);
    let row = 3 * w;
    // Rows first into sums of three (at most 765: u16), then columns; on the interleaved
    // channels, where a pixel's neighbour is 3 values away, so that the loops vectorise.
    let mut across = vec![0u16; row * h];
    for (src, dst) in image.rgb.chunks_exact(row).zip(across.chunks_exact_mut(row)) {
        let at = |x: usize, c: usize| src[3 * x + c] as u16;
        for x in [0, w - 1] {
            let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
            for c in 0..3 {
                dst[3 * x + c] = at(l, c) + at(x, c) + at(r, c);
            }
        }
        if w > 2 {
            let (left, mid, right) = (&src[..row - 6], &src[3..row - 3], &src[6..]);
            for (k, d) in dst[3..row - 3].iter_mut().enumerate() {
                *d = left[k] as u16 + mid[k] as u16 + right[k] as u16;
            }
        }
    }
    let mut out = vec![[0u8; 3]; w * h];
    for (y, o) in out.as_flattened_mut().chunks_exact_mut(row).enumerate() {
        let (u, d) = (y.saturating_sub(1), (y + 1).min(h - 1));
        let (up, here, down) = (&across[u * row..(u + 1) * row], &across[y * row..(y + 1) * row], &across[d * row..(d + 1) * row]);
        for (k, o) in o.iter_mut().enumerate() {
            *o = ((up[k] + here[k] + down[k] + 4) / 9) as u8;
        }
    }
    out
}

/// The 4-neighbours of pixel `i` inside a `w` x `h` image.
fn neighbours(i: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (x, y) = (i % w, i / w);
    [(i.wrapping_sub(1), x > 0), (i + 1, x + 1 < w), (i.wrapping_sub(w), y > 0), (i + w, y + 1 < h)]
        .into_iter()
        .filter_map(|(j, inside)| inside.then_some(j))
}

/// Which pixels hold a depth sample.
fn samples(support: Option<&DepthMap>, n: usize) -> Vec<bool> {
    match support {
        Some(s) => s.data.iter().map(|&z| z > 0.0 && z.is_finite()).collect(),
        None => vec![false; n],
    }
}

/// The sky estimate described in the module docs. `support` (same size as the image, 0 = no
/// depth) bounds the sky from below in each column; without it the whole image may be sky.
pub fn estimate_sky(p: &Params, image: &Image, support: Option<&DepthMap>) -> Vec<bool> {
    let (w, h) = (image.width as usize, image.height as usize);
    if w == 0 || h == 0 {
        return Vec::new();
    }
    let rgb = smoothed(image);
    let sampled = samples(support, w * h);
    let plausible = |i: usize| {
        let [r, g, b] = rgb[i].map(|v| v as f32);
        0.299 * r + 0.587 * g + 0.114 * b >= 0.5 * p.min_luminance && b + p.hue_slack >= r && b + p.hue_slack >= g
    };
    let close = |a: usize, b: usize| {
        let (ca, cb) = (rgb[a], rgb[b]);
        (0..3).all(|c| (ca[c] as f32 - cb[c] as f32).abs() <= p.step)
    };
    // A candidate is smooth towards its right and lower neighbours (so, with theirs, in all four
    // directions): pixels beside an edge take no part, and a region cannot creep through a
    // gradual transition into a neighbouring surface.
    // Decided once per pixel, a row at a time: the regions below ask up to four times a pixel.
    let mut candidate = vec![false; w * h];
    for (y, row) in candidate.chunks_exact_mut(w).enumerate() {
        for (x, c) in row.iter_mut().enumerate() {
            let i = y * w + x;
            *c = !sampled[i] && plausible(i) && (x + 1 == w || close(i, i + 1)) && (y + 1 == h || close(i, i + w));
        }
    }

    // Luminance texture of the unsmoothed image: |dx| + |dy| (sky is smooth, walls are not).
    let lum = super::complete::luminance(image);
    let texture = |i: usize| {
        let (x, y) = (i % w, i / w);
        let dx = if x + 1 < w { (lum[i + 1] - lum[i]).abs() } else { 0.0 };
        let dy = if y + 1 < h { (lum[i + w] - lum[i]).abs() } else { 0.0 };
        dx + dy
    };

    // Regions of candidate pixels joined through small colour steps; each gathers what decides
    // whether it is sky.
    #[derive(Default, Clone)]
    struct Region {
        size: usize,
        first_row: usize,
        luminance: f64,
        texture: f64,
    }
    let mut label = vec![0u32; w * h];
    let mut regions = vec![Region::default()]; // label 0 = not a candidate
    let mut stack = Vec::new();
    for start in 0..w * h {
        if label[start] != 0 || !candidate[start] {
            continue;
        }
        let id = regions.len() as u32;
        let mut r = Region { first_row: h, ..Region::default() };
        label[start] = id;
        stack.push(start);
        while let Some(i) = stack.pop() {
            r.size += 1;
            r.first_row = r.first_row.min(i / w);
            r.luminance += lum[i] as f64;
            r.texture += texture(i) as f64;
            for j in neighbours(i, w, h) {
                if label[j] == 0 && candidate[j] {
                    label[j] = id;
                    stack.push(j);
                }
            }
        }
        regions.push(r);
    }
    // Depth samples inside a region (all four neighbours in it): sky has none, as LiDAR gets no
    // return from it; a facade between LiDAR rings or beside MVS points has many. (Samples on
    // a silhouette against the sky have a neighbour outside and do not count.)
    let mut inside = vec![0usize; regions.len()];
    for i in (0..w * h).filter(|&i| sampled[i]) {
        let (x, y) = (i % w, i / w);
        if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
            continue;
        }
        let l = label[i - 1];
        if l != 0 && label[i + 1] == l && label[i - w] == l && label[i + w] == l {
            inside[l as usize] += 1;
        }
    }
    let min_size = (p.min_area as f64 * (w * h) as f64).ceil().max(1.0) as usize;
    let keep: Vec<bool> = regions
        .iter()
        .enumerate()
        .map(|(l, r)| {
            l != 0
                && r.size >= min_size
                && (r.first_row as f32) < p.max_first_row * h as f32
                && r.luminance / r.size as f64 >= p.min_luminance as f64
                && r.texture / r.size as f64 <= p.max_texture as f64
                && inside[l] as f64 <= p.max_samples as f64 * r.size as f64
        })
        .collect();
    let mut sky: Vec<bool> = label.iter().map(|&l| keep[l as usize]).collect();
    // Sky pixels beside an edge were left out above; each sky pixel takes in its neighbours of
    // (nearly) its colour that have no depth sample.
    let core = sky.clone();
    for i in (0..w * h).filter(|&i| core[i]) {
        for j in neighbours(i, w, h) {
            if !core[j] && !sampled[j] && close(i, j) {
                sky[j] = true;
            }
        }
    }
    // The pixels on each side of the skyline are blends of sky and structure (the camera's blur,
    // the image's compression, the 3x3 smoothing above): too far from either to have joined.
    // Each goes to the side whose colour it is nearer, the sky pixel beside it or the structure
    // pixel beyond it; twice, as the smoothing left a band two pixels wide.
    let distance = |a: usize, b: usize| -> u32 {
        (0..3).map(|c| (image.rgb[3 * a + c] as i32 - image.rgb[3 * b + c] as i32).unsigned_abs()).sum()
    };
    for _ in 0..2 {
        let edge = sky.clone();
        for i in (0..w * h).filter(|&i| edge[i]) {
            let (x, y) = (i % w, i / w);
            // (neighbour, the pixel beyond it), in the four directions.
            let steps = [
                (x > 1).then(|| (i - 1, i - 2)),
                (x + 2 < w).then(|| (i + 1, i + 2)),
                (y > 1).then(|| (i - w, i - 2 * w)),
                (y + 2 < h).then(|| (i + w, i + 2 * w)),
            ];
            for (j, beyond) in steps.into_iter().flatten() {
                if !edge[j] && !sampled[j] && !edge[beyond] && distance(j, i) < distance(j, beyond) {
                    sky[j] = true;
                }
            }
        }
    }
    // Before the holes are filled: a dark, textured speck enclosed by sky (a bird, a wire's knot)
    // is still sky, while structure the sky crept into joins the structure beside it.
    drop_dark_texture(p, &mut sky, &lum, w, h);
    fill_holes(&mut sky, &sampled, w, h, (p.max_hole as f64 * (w * h) as f64) as usize);
    sky
}

/// Takes out of the sky the pixels darker than `structure_luminance` of the frame's sky and
/// textured (mean |dx| + |dy| over a 15 px box above `structure_texture`): a facade or soffit
/// the sky region crept into through its smooth panels (nuScenes scene-0061's CAM_FRONT_RIGHT:
/// the lattice band and the rim of the overhanging building, luminance ~130 and box texture ~5
/// against the sky's ~185 and ~0.8). Sky is both bright for the frame and smooth around each
/// pixel, clouds included; the two together keep the darker cloud undersides and the blends at
/// a tree's outline (dark, or textured, seldom both).
fn drop_dark_texture(p: &Params, sky: &mut [bool], lum: &[f32], w: usize, h: usize) {
    let count = sky.iter().filter(|&&s| s).count();
    if count == 0 || p.structure_luminance <= 0.0 {
        return;
    }
    let mean = sky.iter().zip(lum).filter(|(&s, _)| s).map(|(_, &l)| l as f64).sum::<f64>() / count as f64;
    let texture: Vec<f64> = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let dx = if x + 1 < w { (lum[i + 1] - lum[i]).abs() } else { 0.0 };
            let dy = if y + 1 < h { (lum[i + w] - lum[i]).abs() } else { 0.0 };
            (dx + dy) as f64
        })
        .collect();
    const RADIUS: usize = 7;
    let (sum, area) = (box_sum(&texture, w, h, RADIUS), box_sum(&vec![1.0; w * h], w, h, RADIUS));
    for i in 0..w * h {
        if sky[i]
            && (lum[i] as f64) < p.structure_luminance as f64 * mean
            && sum[i] / area[i] > p.structure_texture as f64
        {
            sky[i] = false;
        }
    }
}

/// Makes sky of the non-sky components (4-way) that do not touch the image border, hold no
/// depth sample and have at most `max` pixels. Components are found over the rows' runs of
/// non-sky pixels (a union-find of runs that overlap a run of the row above), not pixel by
/// pixel: a few dozen runs a row instead of the ~1 M pixels a flood fill visits.
fn fill_holes(sky: &mut [bool], sampled: &[bool], w: usize, h: usize, max: usize) {
    if max == 0 || w == 0 {
        return;
    }
    // (row, first column, end column), row by row; `rows[y]..rows[y + 1]` are row y's.
    let mut runs: Vec<(usize, usize, usize)> = Vec::new();
    let mut rows = vec![0usize; h + 1];
    for y in 0..h {
        let row = &sky[y * w..(y + 1) * w];
        let mut x = 0;
        while x < w {
            if row[x] {
                x += 1;
                continue;
            }
            let start = x;
            while x < w && !row[x] {
                x += 1;
            }
            runs.push((y, start, x));
        }
        rows[y + 1] = runs.len();
    }
    let mut parent: Vec<usize> = (0..runs.len()).collect();
    fn root(parent: &mut [usize], mut a: usize) -> usize {
        while parent[a] != a {
            parent[a] = parent[parent[a]];
            a = parent[a];
        }
        a
    }
    // 4-connected: runs of neighbouring rows that share a column.
    for y in 1..h {
        let (mut i, mut j) = (rows[y - 1], rows[y]);
        while i < rows[y] && j < rows[y + 1] {
            let ((_, a0, a1), (_, b0, b1)) = (runs[i], runs[j]);
            if a0 < b1 && b0 < a1 {
                let (ra, rb) = (root(&mut parent, i), root(&mut parent, j));
                parent[ra.max(rb)] = ra.min(rb);
            }
            if a1 <= b1 {
                i += 1;
            } else {
                j += 1;
            }
        }
    }
    let mut size = vec![0usize; runs.len()];
    let mut enclosed = vec![true; runs.len()];
    for (k, &(y, x0, x1)) in runs.iter().enumerate() {
        let r = root(&mut parent, k);
        size[r] += x1 - x0;
        let border = y == 0 || y + 1 == h || x0 == 0 || x1 == w;
        if border || sampled[y * w + x0..y * w + x1].contains(&true) {
            enclosed[r] = false;
        }
    }
    for (k, &(y, x0, x1)) in runs.iter().enumerate() {
        let r = root(&mut parent, k);
        if enclosed[r] && size[r] <= max {
            sky[y * w + x0..y * w + x1].fill(true);
        }
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the camera image
        image: One<Image>,
        /// depth samples of structures (e.g. the aggregated LiDAR projection); sky lies above the highest in each column
        support: Optional<DepthMap>,
        /// Cityscapes-id segmentation (sky = 23); when given, it is the answer
        semantic: Optional<Segmentation>,
        /// the ego vehicle's body (EgoMask.mask), never sky (a hood mirrors the sky)
        ego: Optional<Mask>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// 1 = sky
        sky: One<Mask>,
    }
}

pub struct EstimateSky(Params, crate::model_worker::ModelWorker);

impl Stage for EstimateSky {
    const KIND: &'static str = "EstimateSky";
    // 3: hue_slack 12 -> 4 (warm grey concrete is not sky).
    // 4: dark, textured pixels are taken out of the sky (`structure_luminance`).
    const VERSION: u32 = 4;
    const SUMMARY: &'static str =
        "Image (+ structure depth samples) -> sky mask: smooth bright region grown from the top, above all depth";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        let worker = crate::model_worker::ModelWorker::new(params.worker.clone());
        Ok(EstimateSky(params, worker))
    }
    fn identity(&self) -> Result<Option<String>> {
        self.1.identity()
    }
    fn resource(&self) -> Option<dist4d_runtime::Resource> {
        self.1.resource()
    }
    fn run(&self, ctx: &TaskContext, mut i: Inputs) -> Result<Made<Outputs>> {
        let ego = i.ego.take();
        let mut out = self.sky(ctx, i)?;
        if let Some(ego) = super::ego_mask::wired(ego.as_ref(), out.sky.width, out.sky.height, "image")? {
            super::ego_mask::set_where(&mut out.sky.data, ego, 0);
        }
        Ok(out.into())
    }
}

impl EstimateSky {
    /// The sky from the worker, the dataset's segmentation or the estimate.
    fn sky(&self, ctx: &TaskContext, i: Inputs) -> Result<Outputs> {
        let (w, h) = (i.image.width, i.image.height);
        let has_semantic = i.semantic.as_ref().is_some_and(|s| s.width > 0 && s.height > 0);
        if self.1.is_set() && !has_semantic {
            // The segmenter's Cityscapes ids (op `segment`: `image` NPY uint8 H x W x 3 in,
            // `semantic` NPY uint8 H x W out); sky = 23, as a dataset's segmentation.
            use crate::model_worker::{npy_rgb8, read_npy_gray8, Exchange};
            let ex = Exchange::new()?;
            let inputs = vec![ex.put("image", "image.npy", &npy_rgb8(w, h, &i.image.rgb))?];
            let outputs = self.1.call(ctx, &ex, "segment", inputs, serde_json::json!({}))?;
            let ids = read_npy_gray8(&ex.get(&outputs, "semantic")?, w, h)
                .map_err(|e| e.context("the worker's `semantic` (uint8 Cityscapes ids)"))?;
            let data = ids.iter().map(|&id| (id == Segmentation::SKY) as u8).collect();
            return Ok(Outputs { sky: Mask { width: w, height: h, data } });
        }
        // Empty maps stand for a dataset without segmentations or a missing reference.
        if let Some(s) = i.semantic.filter(|s| s.width > 0 && s.height > 0) {
            ensure!(
                (s.width, s.height) == (w, h),
                "the semantic map is {}x{} but the image is {w}x{h}",
                s.width,
                s.height
            );
            let data = s.ids.iter().map(|&id| (id == Segmentation::SKY) as u8).collect();
            return Ok(Outputs { sky: Mask { width: w, height: h, data } });
        }
        let support = i.support.filter(|s| s.width > 0 && s.height > 0);
        if let Some(s) = &support {
            ensure!(
                (s.width, s.height) == (w, h),
                "the support depth is {}x{} but the image is {w}x{h}",
                s.width,
                s.height
            );
        }
        let sky = estimate_sky(&self.0, &i.image, support.as_ref());
        Ok(Outputs { sky: Mask { width: w, height: h, data: sky.into_iter().map(u8::from).collect() } })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 60x40 image: a blue gradient sky over a grey wall whose top edge is `skyline[x]`.
    fn scene(skyline: impl Fn(usize) -> usize) -> Image {
        let (w, h) = (60usize, 40usize);
        let mut rgb = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                if y < skyline(x) {
                    rgb.extend_from_slice(&[140 + (y as u8) / 2, 175, 225]);
                } else {
                    let t = ((x * 7 + y * 13) % 5) as u8 * 8; // texture
                    rgb.extend_from_slice(&[90 + t, 80 + t, 70 + t]);
                }
            }
        }
        Image { width: w as u32, height: h as u32, rgb }
    }

    #[test]
    fn smoothing_is_the_3x3_box_mean_with_replicated_edges() {
        let mut rng = dist4d_types::rng::Rng::new(11);
        for (w, h) in [(1usize, 1usize), (1, 4), (2, 3), (3, 1), (7, 5), (16, 9)] {
            let rgb: Vec<u8> = (0..3 * w * h).map(|_| rng.below(256) as u8).collect();
            let image = Image { width: w as u32, height: h as u32, rgb: rgb.clone() };
            let got = smoothed(&image);
            for y in 0..h {
                for x in 0..w {
                    for c in 0..3 {
                        let mut sum = 0u32;
                        for dy in [-1i64, 0, 1] {
                            for dx in [-1i64, 0, 1] {
                                let (xx, yy) = ((x as i64 + dx).clamp(0, w as i64 - 1), (y as i64 + dy).clamp(0, h as i64 - 1));
                                sum += rgb[3 * (yy as usize * w + xx as usize) + c] as u32;
                            }
                        }
                        assert_eq!(got[y * w + x][c] as u32, (sum + 4) / 9, "{w}x{h} at ({x}, {y}) channel {c}");
                    }
                }
            }
        }
    }

    #[test]
    fn the_sky_above_a_skyline_is_found_to_the_pixel() {
        let skyline = |x: usize| if x < 30 { 12 } else { 20 };
        let sky = estimate_sky(&Params::default(), &scene(skyline), None);
        // The 3x3 smoothing blurs the skyline by one pixel, in both directions.
        let wall_within =
            |x: usize, y: usize, r: usize| (x.saturating_sub(r)..(x + r + 1).min(60)).any(|xx| y + r >= skyline(xx));
        for y in 0..40 {
            for x in 0..60 {
                if !wall_within(x, y, 1) {
                    assert!(sky[y * 60 + x], "({x}, {y}) is sky");
                } else if y > skyline(x) {
                    assert!(!sky[y * 60 + x], "({x}, {y}) is wall");
                }
            }
        }
    }

    #[test]
    fn a_blurred_skyline_row_goes_to_the_side_whose_colour_it_is_nearer() {
        // The wall starts at row 20; row 19 is a blend a quarter of the way to the wall's
        // colour in columns 0..30 (sky at its centre) and three quarters in 30..60 (wall).
        let mut img = scene(|_| 20);
        for x in 0..60 {
            let i = 3 * (19 * 60 + x);
            let t = if x < 30 { 0.25 } else { 0.75 };
            for c in 0..3 {
                let (sky, wall) = (img.rgb[i + c] as f32, img.rgb[3 * (21 * 60 + x) + c] as f32);
                img.rgb[i + c] = (sky + t * (wall - sky)).round() as u8;
            }
        }
        let sky = estimate_sky(&Params::default(), &img, None);
        assert!((2..28).all(|x| sky[19 * 60 + x]), "nearer the sky: {:?}", &sky[19 * 60..20 * 60]);
        assert!((32..58).all(|x| !sky[19 * 60 + x]), "nearer the wall: {:?}", &sky[19 * 60..20 * 60]);
        assert!((0..60).all(|x| !sky[20 * 60 + x]), "the wall's top row");
    }

    #[test]
    fn a_sky_coloured_facade_with_depth_samples_is_not_sky() {
        // The whole image is smooth and sky-coloured, but the left half holds LiDAR-like rows
        // of samples (every 4th pixel of every 6th row): a bright facade, not sky.
        let img = scene(|_| 40);
        let mut support = DepthMap { width: 60, height: 40, data: vec![0.0; 2400] };
        for y in (3..40).step_by(6) {
            for x in (0..28).step_by(4) {
                support.data[y * 60 + x] = 20.0;
            }
        }
        // A thin dark pole at column 29 separates the two halves.
        let mut img = img;
        for y in 0..40 {
            img.rgb[3 * (y * 60 + 29)..3 * (y * 60 + 29) + 3].copy_from_slice(&[30, 30, 30]);
        }
        let sky = estimate_sky(&Params::default(), &img, Some(&support));
        assert!((0..40).all(|y| (0..28).all(|x| !sky[y * 60 + x])), "the measured half is not sky");
        assert!((0..40).all(|y| (31..60).all(|x| sky[y * 60 + x])), "the unmeasured half is sky");
    }

    #[test]
    fn dark_green_or_small_regions_are_not_sky() {
        let mut img = scene(|_| 10);
        for p in img.rgb.chunks_exact_mut(3).take(60 * 10) {
            p.copy_from_slice(&[60, 140, 50]); // a tree crown at the top
        }
        assert!(estimate_sky(&Params::default(), &img, None).iter().all(|&s| !s));
        // A 3x3 bright patch at the top is too small to be sky (at 1% of the image).
        let mut img = scene(|_| 0);
        for y in 0..3 {
            for x in 0..3 {
                img.rgb[3 * (y * 60 + x)..3 * (y * 60 + x) + 3].copy_from_slice(&[200, 210, 230]);
            }
        }
        assert!(estimate_sky(&Params { min_area: 0.01, ..Params::default() }, &img, None).iter().all(|&s| !s));
    }

    #[test]
    fn dark_textured_pixels_leave_the_sky_but_dark_smooth_or_bright_textured_ones_stay() {
        // 60x40: columns 0-19 bright smooth sky (200), 20-39 a darker smooth cloud (160), 40-59
        // a grey facade (130) with bright stripes every 4 columns, all taken for sky.
        let (w, h) = (60usize, 40usize);
        let lum: Vec<f32> = (0..w * h)
            .map(|i| match i % w {
                x if x < 20 => 200.0,
                x if x < 40 => 160.0,
                x if x % 4 == 0 => 190.0,
                _ => 130.0,
            })
            .collect();
        let mut sky = vec![true; w * h];
        drop_dark_texture(&Params::default(), &mut sky, &lum, w, h);
        let column = |x: usize| (0..h).all(|y| sky[y * w + x]);
        assert!((0..36).all(column), "the sky and the smooth cloud stay");
        assert!((48..60).all(|x| !column(x) || x % 4 == 0), "the facade's dark pixels leave");
        // Off: nothing changes.
        let mut all = vec![true; w * h];
        drop_dark_texture(&Params { structure_luminance: 0.0, ..Params::default() }, &mut all, &lum, w, h);
        assert!(all.iter().all(|&s| s));
    }

    #[test]
    fn a_dark_speck_inside_the_sky_becomes_sky_but_a_supported_one_does_not() {
        let mut img = scene(|_| 30);
        let speck = |img: &mut Image, x0: usize| {
            for y in 5..8 {
                for x in x0..x0 + 3 {
                    img.rgb[3 * (y * 60 + x)..3 * (y * 60 + x) + 3].copy_from_slice(&[20, 20, 20]);
                }
            }
        };
        speck(&mut img, 10);
        speck(&mut img, 40);
        let mut support = DepthMap { width: 60, height: 40, data: vec![0.0; 2400] };
        support.data[6 * 60 + 41] = 50.0; // the second speck is a measured lamp
        let p = Params { max_hole: 0.02, ..Params::default() };
        let sky = estimate_sky(&p, &img, Some(&support));
        assert!(sky[6 * 60 + 11], "an unsupported speck is a hole in the sky");
        assert!(!sky[6 * 60 + 41], "a measured one is a structure");
    }

    /// The holes a pixel-by-pixel flood fill finds: what `fill_holes` must fill, run by run.
    fn holes_by_flood_fill(sky: &[bool], sampled: &[bool], w: usize, h: usize, max: usize) -> Vec<bool> {
        let mut out = sky.to_vec();
        let mut seen = vec![false; w * h];
        for start in 0..w * h {
            if sky[start] || seen[start] {
                continue;
            }
            seen[start] = true;
            let (mut stack, mut members, mut enclosed) = (vec![start], Vec::new(), true);
            while let Some(i) = stack.pop() {
                let (x, y) = (i % w, i / w);
                members.push(i);
                enclosed &= x > 0 && y > 0 && x + 1 < w && y + 1 < h && !sampled[i];
                let near = [(x > 0, i.wrapping_sub(1)), (x + 1 < w, i + 1), (y > 0, i.wrapping_sub(w)), (y + 1 < h, i + w)];
                for (inside, j) in near {
                    if inside && !sky[j] && !seen[j] {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
            if enclosed && members.len() <= max {
                members.iter().for_each(|&i| out[i] = true);
            }
        }
        out
    }

    #[test]
    fn holes_are_the_small_enclosed_unmeasured_components_a_flood_fill_finds() {
        let mut rng = dist4d_types::rng::Rng::new(7);
        let (w, h) = (37, 23);
        let mut filled = 0;
        for round in 0..200 {
            // Mostly sky with scattered structure, or the other way round: every shape of run.
            let density = [3, 5, 8][round % 3];
            let sky: Vec<bool> = (0..w * h).map(|_| rng.below(10) < density).collect();
            let sampled: Vec<bool> = (0..w * h).map(|_| rng.below(40) == 0).collect();
            let max = [0, 1, 4, 30][round % 4];
            let mut runs = sky.clone();
            fill_holes(&mut runs, &sampled, w, h, max);
            assert_eq!(runs, holes_by_flood_fill(&sky, &sampled, w, h, max), "round {round}");
            filled += runs.iter().zip(&sky).filter(|(a, b)| a != b).count();
        }
        assert!(filled > 100, "the masks have holes to fill: {filled}");
    }
}
