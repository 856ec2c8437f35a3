//! `EstimateEgo`: the recording car's body in one camera, estimated from the camera's own frames,
//! for cameras that no polygon, mask file or built-in rig of `EgoMask` covers.
//!
//! The body is the one thing in the image that does not move while the car does. A static scene
//! point at pixel p of frame t, at depth d, lands in frame t+k where the ego motion between the
//! two frames (their poses) puts it; the body stays at p. So, per working pixel and per other
//! frame of the window, three zero-mean normalised cross-correlations of a small patch of frame t:
//! - *same*: against frame t+k at the same pixel;
//! - *warped*: against frame t+k where the scene point would be (depth from the LiDAR projected
//!   into the image, filled a few pixels around each return; below the horizon where the LiDAR
//!   has nothing, the ground plane fitted to the LiDAR's low returns: the road the hood hides);
//! - *self*: against frame t itself shifted by the predicted motion, which says whether a scene
//!   point would look different at all after that motion. A lane line or kerb parallel to the
//!   motion, a smooth shading or an untextured patch looks the same shifted along the motion:
//!   such a pair says nothing (that is what over-masked the road in the first try, which took
//!   every edge fixed across frames for the body's outline).
//!
//! A pair votes *body* where the patch stays (same >= `still`) and the warped match is worse by
//! `margin`, and *scene* the other way round; it votes only where the predicted motion is at least
//! `min_parallax` working pixels, the patch has texture and the self test says the motion would
//! show. The body is attached to the image border (hood and boot at the bottom, roof edge at the
//! top), and its inside is often without votes (a glossy hood mirrors the moving sky), so the mask
//! is a *curtain* per column from the bottom border: the height that maximises
//! the votes it covers (a scene vote costs `scene_weight`, a tested pixel without a vote
//! `tested_cost`, an untested one `untested_cost`) less `smoothness` per row of change between
//! neighbouring columns, by dynamic programming. A run of masked columns with fewer than
//! `min_votes` body votes is dropped, and the curtain's edge comes `shrink` working pixels back
//! (a patch straddling the body's outline votes body a patch radius into the scene).
//!
//! Where it fails (docs/stages.md, EgoMask): a car that does not move gives no evidence (no
//! mask); body parts against the sky or without LiDAR depth behind them (pillars, roof edges)
//! get no votes; a vehicle driving at the ego's speed just in front of or behind it, and the
//! ego's own shadow, stay in place like the body; a single frame (a nuScenes keyframe without
//! its sweeps' images) says nothing.

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{anyhow, ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Calibration, DepthMap, Image, Mask, Pose};
use dist4d_types::geometry::Se3;
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Width (px) of the working images: the images are averaged down by the whole factor that
    /// comes nearest (1936 -> 484 with the default; 640 and under stay full size). 64-4096.
    pub working_width: u32,
    /// Radius (working px) of the compared patches: (2r+1)^2 pixels. 1-8.
    pub patch: u32,
    /// Smallest grey-level standard deviation of a patch that is compared (0-255 scale).
    pub min_texture: f64,
    /// Smallest predicted motion (working px) of a scene point for a pair to vote.
    pub min_parallax: f64,
    /// Correlation at or above which a patch "stays" (same pixel) or "follows" (warped). 0-1.
    pub still: f64,
    /// How much better the one match must be than the other for a vote. 0-2.
    pub margin: f64,
    /// Self-correlation after the predicted motion at or above which the motion would not show
    /// (a line along the motion, a smooth shading): no vote. -1-1.
    pub self_similar: f64,
    /// Radius (working px) around each LiDAR depth within which it stands for its neighbours.
    pub depth_fill: u32,
    /// Farthest ground (m, horizontal range) that stands in for missing LiDAR depth below the
    /// horizon; 0 = no ground plane.
    pub ground_range: f64,
    /// Cost of a scene vote inside the mask, per vote (a body vote gains 1).
    pub scene_weight: f64,
    /// Cost of a pixel inside the mask whose pairs voted neither way.
    pub tested_cost: f64,
    /// Cost of a pixel inside the mask that no pair could test (no texture, depth or motion).
    pub untested_cost: f64,
    /// Cost of one row of change in the curtain's height between neighbouring columns.
    pub smoothness: f64,
    /// Fewest body votes (working pixels) a run of masked columns needs to be kept.
    pub min_votes: u32,
    /// Working pixels by which the mask's edge comes back towards the border.
    pub shrink: u32,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            working_width: 480,
            patch: 2,
            min_texture: 4.0,
            min_parallax: 3.0,
            still: 0.8,
            margin: 0.3,
            self_similar: 0.5,
            depth_fill: 12,
            ground_range: 40.0,
            scene_weight: 2.0,
            tested_cost: 0.05,
            untested_cost: 0.005,
            smoothness: 0.3,
            min_votes: 20,
            shrink: 3,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .count("working_width", self.working_width as u64, 64, 4096)
            .count("patch", self.patch as u64, 1, 8)
            .within("min_texture", self.min_texture, 0.0, 255.0)
            .within("min_parallax", self.min_parallax, 0.0, 1000.0)
            .within("still", self.still, 0.0, 1.0)
            .within("margin", self.margin, 0.0, 2.0)
            .within("self_similar", self.self_similar, -1.0, 1.0)
            .count("depth_fill", self.depth_fill as u64, 0, 256)
            .within("ground_range", self.ground_range, 0.0, 1000.0)
            .within("scene_weight", self.scene_weight, 0.0, 1000.0)
            .within("tested_cost", self.tested_cost, 0.0, 1000.0)
            .within("untested_cost", self.untested_cost, 0.0, 1000.0)
            .within("smoothness", self.smoothness, 0.0, 1000.0)
            .count("min_votes", self.min_votes as u64, 0, 1 << 30)
            .count("shrink", self.shrink as u64, 0, 64)
            .done()
    }
}

/// One frame of the window: position 0 is the frame whose mask is estimated.
pub struct Frame<'a> {
    pub position: i64,
    pub image: &'a Image,
    pub calib: &'a Calibration,
    pub pose: &'a Pose,
}

/// The estimate, and what it was made from (for the preview and the tests).
pub struct Estimate {
    /// Full image size, 1 = the body.
    pub mask: Mask,
    /// Working size: per pixel, body votes minus scene votes over the pairs that tested it.
    pub votes: Vec<i8>,
    pub working: (usize, usize),
    /// The factor from working to full pixels.
    pub factor: usize,
}

/// A grey image at working size, as f32.
struct Grey {
    w: usize,
    h: usize,
    v: Vec<f32>,
}

impl Grey {
    /// `image` averaged over `f` x `f` blocks (partial blocks at the right and bottom dropped).
    fn of(image: &Image, f: usize) -> Grey {
        let (iw, w, h) = (image.width as usize, image.width as usize / f, image.height as usize / f);
        let mut v = vec![0f32; w * h];
        let scale = 1.0 / (f * f) as f32;
        for y in 0..h {
            for yy in y * f..y * f + f {
                let row = &image.rgb[3 * yy * iw..3 * (yy + 1) * iw];
                for x in 0..w {
                    let mut s = 0u32;
                    for p in row[3 * x * f..3 * (x + 1) * f].chunks_exact(3) {
                        s += p[0] as u32 * 77 + p[1] as u32 * 150 + p[2] as u32 * 29;
                    }
                    v[y * w + x] += s as f32 / 256.0 * scale;
                }
            }
        }
        let mut g = Grey { w, h, v };
        g.smooth();
        g.smooth();
        g
    }

    /// A [1 2 1]/4 blur each way: interpolating a sharp, aliased image (thin lines near the
    /// horizon) at sub-pixel shifts changes it more than the shift does, which would look like
    /// a scene that does not follow its motion.
    fn smooth(&mut self) {
        let (w, h) = (self.w, self.h);
        let mut t = self.v.clone();
        for y in 0..h {
            for x in 0..w {
                let at = |xx: usize| self.v[y * w + xx];
                t[y * w + x] = 0.25 * at(x.saturating_sub(1)) + 0.5 * at(x) + 0.25 * at((x + 1).min(w - 1));
            }
        }
        for y in 0..h {
            for x in 0..w {
                let at = |yy: usize| t[yy * w + x];
                self.v[y * w + x] = 0.25 * at(y.saturating_sub(1)) + 0.5 * at(y) + 0.25 * at((y + 1).min(h - 1));
            }
        }
    }

    /// Bilinear sample at continuous index coordinates (pixel (i, j) centred at (i, j)), clamped
    /// to the image.
    #[inline]
    fn sample(&self, x: f64, y: f64) -> f32 {
        let x = x.clamp(0.0, (self.w - 1) as f64);
        let y = y.clamp(0.0, (self.h - 1) as f64);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.w - 1), (y0 + 1).min(self.h - 1));
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let a = self.v[y0 * self.w + x0] * (1.0 - fx) + self.v[y0 * self.w + x1] * fx;
        let b = self.v[y1 * self.w + x0] * (1.0 - fx) + self.v[y1 * self.w + x1] * fx;
        a * (1.0 - fy) + b * fy
    }
}

/// Box sums over (2r+1)^2 windows (clipped at the borders), separable, in f64 so that the
/// variances of bright flat patches do not cancel into noise.
fn box_sum(v: &[f64], w: usize, h: usize, r: usize) -> Vec<f64> {
    let mut rows = vec![0f64; w * h];
    for y in 0..h {
        let line = &v[y * w..(y + 1) * w];
        let mut s: f64 = line[..r.min(w - 1) + 1].iter().sum();
        for x in 0..w {
            rows[y * w + x] = s;
            if x + r + 1 < w {
                s += line[x + r + 1];
            }
            if x >= r {
                s -= line[x - r];
            }
        }
    }
    let mut out = vec![0f64; w * h];
    for x in 0..w {
        let mut s: f64 = (0..=r.min(h - 1)).map(|y| rows[y * w + x]).sum();
        for y in 0..h {
            out[y * w + x] = s;
            if y + r + 1 < h {
                s += rows[(y + r + 1) * w + x];
            }
            if y >= r {
                s -= rows[(y - r) * w + x];
            }
        }
    }
    out
}

/// Patch statistics of the target image: sums and the centred sum of squares per window.
struct Patches {
    n: Vec<f64>,
    sum: Vec<f64>,
    var: Vec<f64>,
}

impl Patches {
    fn of(a: &Grey, r: usize) -> Patches {
        let av: Vec<f64> = a.v.iter().map(|&x| x as f64).collect();
        let n = box_sum(&vec![1.0; a.w * a.h], a.w, a.h, r);
        let sum = box_sum(&av, a.w, a.h, r);
        let sq = box_sum(&av.iter().map(|x| x * x).collect::<Vec<_>>(), a.w, a.h, r);
        let var = (0..a.w * a.h).map(|i| (sq[i] - sum[i] * sum[i] / n[i]).max(0.0)).collect();
        Patches { n, sum, var }
    }

    /// Zero-mean normalised cross-correlation of the target's patches with those of `b` (same
    /// size), per pixel; 0 where either patch is flat.
    fn zncc(&self, a: &Grey, b: &[f32], r: usize) -> Vec<f32> {
        let bv: Vec<f64> = b.iter().map(|&x| x as f64).collect();
        let sb = box_sum(&bv, a.w, a.h, r);
        let sbb = box_sum(&bv.iter().map(|x| x * x).collect::<Vec<_>>(), a.w, a.h, r);
        let sab = box_sum(&a.v.iter().zip(&bv).map(|(&x, y)| x as f64 * y).collect::<Vec<_>>(), a.w, a.h, r);
        (0..a.w * a.h)
            .map(|i| {
                let vb = (sbb[i] - sb[i] * sb[i] / self.n[i]).max(0.0);
                let cov = sab[i] - self.sum[i] * sb[i] / self.n[i];
                let d = (self.var[i] * vb).sqrt();
                if d > 1e-6 {
                    (cov / d) as f32
                } else {
                    0.0
                }
            })
            .collect()
    }
}

/// The camera -> world transform of a frame.
fn world_from_camera(f: &Frame) -> Se3 {
    f.pose.ego_to_world.then_from(&f.calib.sensor_to_ego)
}

/// Depth per working pixel: the nearest LiDAR return of each block, spread `fill` pixels to
/// the pixels without one (the nearest by city-block distance, ties to the nearer depth), then
/// the ground plane below the horizon where there is still none.
fn working_depth(params: &Params, lidar: Option<&DepthMap>, f: usize, k: &[[f64; 3]; 3], calib: &Calibration, w: usize, h: usize) -> Vec<f32> {
    let mut d = vec![0f32; w * h];
    if let Some(l) = lidar.filter(|l| l.width > 0) {
        for y in 0..(h * f).min(l.height as usize) {
            for x in 0..(w * f).min(l.width as usize) {
                let z = l.data[y * l.width as usize + x];
                let c = &mut d[(y / f) * w + x / f];
                if z > 0.0 && z.is_finite() && (*c == 0.0 || z < *c) {
                    *c = z;
                }
            }
        }
    }
    // Spread by a two-pass chamfer transform carrying the value (distance in pixels, L1).
    let fill = params.depth_fill as u32;
    let mut dist: Vec<u32> = d.iter().map(|&z| if z > 0.0 { 0 } else { u32::MAX }).collect();
    let better = |dist: &mut Vec<u32>, d: &mut Vec<f32>, i: usize, j: usize| {
        let nd = dist[j].saturating_add(1);
        if nd < dist[i] || nd == dist[i] && d[j] < d[i] {
            dist[i] = nd;
            d[i] = d[j];
        }
    };
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if x > 0 {
                better(&mut dist, &mut d, i, i - 1);
            }
            if y > 0 {
                better(&mut dist, &mut d, i, i - w);
            }
        }
    }
    for y in (0..h).rev() {
        for x in (0..w).rev() {
            let i = y * w + x;
            if x + 1 < w {
                better(&mut dist, &mut d, i, i + 1);
            }
            if y + 1 < h {
                better(&mut dist, &mut d, i, i + w);
            }
        }
    }
    for (z, &n) in d.iter_mut().zip(&dist) {
        if n > fill {
            *z = 0.0;
        }
    }
    let ray = |x: usize, y: usize| {
        let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
        let yy = (v - k[1][2]) / k[1][1];
        DVec3::new((u - k[0][2] - k[0][1] * yy) / k[0][0], yy, 1.0)
    };
    if params.ground_range > 0.0 {
        // The ground: the 10th percentile of the heights (ego frame) of the returns 3-20 m away.
        let (rot, origin) = (calib.sensor_to_ego.matrix(), calib.sensor_to_ego.translation);
        let mut heights: Vec<f64> = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let z = d[y * w + x];
                if z > 0.0 {
                    let p = origin + rot * (ray(x, y) * z as f64);
                    let range = p.x.hypot(p.y);
                    if (3.0..20.0).contains(&range) {
                        heights.push(p.z);
                    }
                }
            }
        }
        if heights.len() >= 50 {
            heights.sort_by(f64::total_cmp);
            let ground = heights[heights.len() / 10];
            for y in 0..h {
                for x in 0..w {
                    if d[y * w + x] > 0.0 {
                        continue;
                    }
                    let dir = rot * ray(x, y);
                    if dir.z < -1e-6 {
                        let s = (ground - origin.z) / dir.z;
                        let p = origin + dir * s;
                        if s > 0.0 && p.x.hypot(p.y) < params.ground_range {
                            d[y * w + x] = s as f32;
                        }
                    }
                }
            }
        }
    }
    d
}

/// Per column, the height (rows from the border, 0..=h) of the curtain maximising the summed
/// `gain` of the rows it covers less `smoothness` per row of change between neighbouring
/// columns. `gain` is h x w with row 0 at the border. Exact, O(w h).
pub fn curtain(gain: &[f32], w: usize, h: usize, smoothness: f32) -> Vec<usize> {
    if w == 0 {
        return Vec::new();
    }
    let prefix = |x: usize| {
        let mut p = vec![0f32; h + 1];
        for r in 0..h {
            p[r + 1] = p[r] + gain[r * w + x];
        }
        p
    };
    let mut score = prefix(0);
    let mut back: Vec<Vec<u32>> = Vec::with_capacity(w);
    for x in 1..w {
        // best[r] = max over r' of score[r'] - smoothness |r - r'|, two passes.
        let mut best = score.clone();
        let mut arg: Vec<u32> = (0..=h as u32).collect();
        for r in 1..=h {
            if best[r - 1] - smoothness > best[r] {
                best[r] = best[r - 1] - smoothness;
                arg[r] = arg[r - 1];
            }
        }
        for r in (0..h).rev() {
            if best[r + 1] - smoothness > best[r] {
                best[r] = best[r + 1] - smoothness;
                arg[r] = arg[r + 1];
            }
        }
        let p = prefix(x);
        score = best.iter().zip(&p).map(|(b, g)| b + g).collect();
        back.push(arg);
    }
    let mut rows = vec![0usize; w];
    // The first best (the lowest curtain among equals).
    let mut top = 0;
    for r in 1..=h {
        if score[r] > score[top] {
            top = r;
        }
    }
    rows[w - 1] = top;
    for x in (1..w).rev() {
        rows[x - 1] = back[x - 1][rows[x]] as usize;
    }
    rows
}

/// The ego body of the frame at position 0 of `frames`, from the other frames of the window and
/// the LiDAR depth projected into it (`lidar`, the image's size; optional).
pub fn estimate(params: &Params, frames: &[Frame], lidar: Option<&DepthMap>) -> Result<Estimate> {
    crate::stage::ensure_valid(params)?;
    let target = frames
        .iter()
        .find(|f| f.position == 0)
        .ok_or_else(|| anyhow!("the window has no image at position 0 (the target frame)"))?;
    let (fw, fh) = (target.image.width as usize, target.image.height as usize);
    for f in frames {
        ensure!(
            f.image.width == 0 || (f.image.width as usize, f.image.height as usize) == (fw, fh),
            "the image at window position {} is {}x{}, the target's {fw}x{fh}",
            f.position,
            f.image.width,
            f.image.height
        );
        ensure!(
            f.image.rgb.len() == 3 * f.image.width as usize * f.image.height as usize,
            "the image at window position {} has {} bytes for {}x{} RGB",
            f.position,
            f.image.rgb.len(),
            f.image.width,
            f.image.height
        );
    }
    if let Some(l) = lidar.filter(|l| l.width > 0) {
        ensure!(
            (l.width as usize, l.height as usize) == (fw, fh),
            "the LiDAR depth is {}x{}, the image {fw}x{fh}",
            l.width,
            l.height
        );
    }
    let factor = ((fw as f64 / params.working_width as f64).round() as usize).max(1);
    let (w, h) = (fw / factor, fh / factor);
    let empty = |w: usize, h: usize| Estimate {
        mask: Mask { width: fw as u32, height: fh as u32, data: vec![0; fw * fh] },
        votes: vec![0; w * h],
        working: (w, h),
        factor,
    };
    let r = params.patch as usize;
    if w <= 2 * r + 1 || h <= 2 * r + 1 {
        return Ok(empty(w.max(1), h.max(1)));
    }
    let k = target.calib.intrinsics.ok_or_else(|| anyhow!("the camera calibration has no intrinsics"))?;
    let mut kw = k;
    for row in kw.iter_mut().take(2) {
        for v in row.iter_mut() {
            *v /= factor as f64;
        }
    }
    let a = Grey::of(target.image, factor);
    let stats = Patches::of(&a, r);
    let depth = working_depth(params, lidar, factor, &kw, target.calib, w, h);
    let min_var = params.min_texture * params.min_texture;
    let world_from_t = world_from_camera(target);
    let mut votes = vec![0i32; w * h];
    let mut tested = vec![0u32; w * h];
    let (mut pu, mut pv) = (vec![f64::NAN; w * h], vec![f64::NAN; w * h]);
    for other in frames.iter().filter(|f| f.position != 0 && f.image.width > 0) {
        dist4d_types::cancel::check()?;
        let b = Grey::of(other.image, factor);
        let kk = other.calib.intrinsics.ok_or_else(|| anyhow!("the camera calibration at window position {} has no intrinsics", other.position))?;
        let mut kkw = kk;
        for row in kkw.iter_mut().take(2) {
            for v in row.iter_mut() {
                *v /= factor as f64;
            }
        }
        let k_from_t = world_from_camera(other).inverse().then_from(&world_from_t);
        let (rot, t) = (k_from_t.matrix(), k_from_t.translation);
        // Where each pixel's scene point lands in the other frame (index coordinates).
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let z = depth[i] as f64;
                (pu[i], pv[i]) = (f64::NAN, f64::NAN);
                if z <= 0.0 {
                    continue;
                }
                let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
                let yy = (v - kw[1][2]) / kw[1][1];
                let p = DVec3::new((u - kw[0][2] - kw[0][1] * yy) / kw[0][0] * z, yy * z, z);
                let q = rot * p + t;
                if q.z < 0.1 {
                    continue;
                }
                let qz = kkw[2][0] * q.x + kkw[2][1] * q.y + kkw[2][2] * q.z;
                pu[i] = (kkw[0][0] * q.x + kkw[0][1] * q.y + kkw[0][2] * q.z) / qz - 0.5;
                pv[i] = (kkw[1][0] * q.x + kkw[1][1] * q.y + kkw[1][2] * q.z) / qz - 0.5;
            }
        }
        let warped: Vec<f32> =
            (0..w * h).map(|i| if pu[i].is_nan() { 0.0 } else { b.sample(pu[i], pv[i]) }).collect();
        // Frame t moved back by the predicted motion: what the same pixel of frame t+k would show
        // if the pixel were scene.
        let shifted: Vec<f32> = (0..w * h)
            .map(|i| {
                if pu[i].is_nan() {
                    0.0
                } else {
                    let (x, y) = ((i % w) as f64, (i / w) as f64);
                    a.sample(2.0 * x - pu[i], 2.0 * y - pv[i])
                }
            })
            .collect();
        let same = stats.zncc(&a, &b.v, r);
        let follow = stats.zncc(&a, &warped, r);
        let selfc = stats.zncc(&a, &shifted, r);
        let edge = r as f64;
        for i in 0..w * h {
            if pu[i].is_nan() || stats.var[i] / stats.n[i] < min_var {
                continue;
            }
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            let inside =
                pu[i] >= edge && pv[i] >= edge && pu[i] <= (w - 1) as f64 - edge && pv[i] <= (h - 1) as f64 - edge;
            let parallax = (pu[i] - x).hypot(pv[i] - y);
            if !inside || parallax < params.min_parallax || selfc[i] as f64 >= params.self_similar {
                continue;
            }
            tested[i] += 1;
            let (s, f) = (same[i] as f64, follow[i] as f64);
            if s >= params.still && f <= s - params.margin {
                votes[i] += 1;
            } else if f >= params.still && s <= f - params.margin {
                votes[i] -= 1;
            }
        }
    }
    // Gain of each pixel inside the mask.
    let gain: Vec<f32> = (0..w * h)
        .map(|i| {
            if tested[i] == 0 {
                return -params.untested_cost as f32;
            }
            let b = votes[i] as f64 / tested[i] as f64;
            let b = if b < 0.0 { b * params.scene_weight } else { b };
            (b - params.tested_cost) as f32
        })
        .collect();
    let body = |i: usize| (votes[i] > 0) as u32;
    let mut small = vec![0u8; w * h];
    // From the bottom border only: a curtain from the top ran down the sky (no votes, hardly any
    // cost) to a car following at the ego's speed, and the roof edges and pillars up there get
    // few votes anyway (sky behind them, no LiDAR depth).
    {
        let row_of = |r: usize| h - 1 - r;
        let flipped: Vec<f32> = (0..h).flat_map(|r| gain[row_of(r) * w..(row_of(r) + 1) * w].iter().copied()).collect();
        let heights = curtain(&flipped, w, h, params.smoothness as f32);
        // Runs of masked columns; each keeps only with enough body votes.
        let mut x = 0;
        while x < w {
            if heights[x] == 0 {
                x += 1;
                continue;
            }
            let start = x;
            while x < w && heights[x] > 0 {
                x += 1;
            }
            let found: u32 = (start..x).map(|c| (0..heights[c]).map(|r| body(row_of(r) * w + c)).sum::<u32>()).sum();
            if found >= params.min_votes.max(1) {
                for c in start..x {
                    let keep = heights[c].saturating_sub(params.shrink as usize);
                    for r in 0..keep {
                        small[row_of(r) * w + c] = 1;
                    }
                }
            }
        }
    }
    // Working -> full pixels (the rows and columns past the last whole block take its value).
    let mut data = vec![0u8; fw * fh];
    for y in 0..fh {
        let sy = (y / factor).min(h - 1);
        for x in 0..fw {
            data[y * fw + x] = small[sy * w + (x / factor).min(w - 1)];
        }
    }
    Ok(Estimate {
        mask: Mask { width: fw as u32, height: fh as u32, data },
        votes: votes.iter().map(|&v| v.clamp(-127, 127) as i8).collect(),
        working: (w, h),
        factor,
    })
}

/// The target image with the estimate tinted red (EgoMask's preview) and the pixels that voted
/// body marked yellow, scene green: what the estimate saw.
pub fn preview(image: &Image, e: &Estimate) -> Image {
    let mut out = super::ego_mask::preview(image, &e.mask);
    let (fw, (w, _)) = (image.width as usize, e.working);
    for (i, &v) in e.votes.iter().enumerate() {
        if v == 0 {
            continue;
        }
        let (x, y) = ((i % w) * e.factor + e.factor / 2, (i / w) * e.factor + e.factor / 2);
        let px = &mut out.rgb[3 * (y * fw + x)..3 * (y * fw + x) + 3];
        px.copy_from_slice(if v > 0 { &[255, 230, 0] } else { &[0, 220, 60] });
    }
    out
}

crate::inputs! {
    pub struct Inputs {
        /// the camera's images of a window of frames: Window("dataset.image", frame, -2, 2)
        images: Many<Image>,
        /// their calibrations (same Window)
        calibs: Many<Calibration>,
        /// their ego poses (same Window)
        poses: Many<Pose>,
        /// the LiDAR projected into the target image (ProjectLidar.depth of the aggregate): the
        /// depth a scene pixel moves with
        depth: Optional<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// 1 = the ego vehicle's body (all 0 when the frames give no evidence)
        mask: One<Mask>,
        /// the image with the mask tinted red, body votes yellow, scene votes green; made only
        /// when the run reads it
        preview: OnDemand<Image>,
    }
}

pub struct EstimateEgo(Params);

impl Stage for EstimateEgo {
    const KIND: &'static str = "EstimateEgo";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "Camera images of a window of frames + LiDAR depth -> the ego body: what stays in place while the scene moves";
    const GRAINS: &'static [&'static str] = &["camera"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["images", "calibs", "poses"]];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EstimateEgo(params))
    }
    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let mut frames = Vec::new();
        for (pos, image) in &i.images {
            let calib =
                i.calibs.iter().find(|(p, _)| p == pos).ok_or_else(|| anyhow!("no camera_calib at position {pos}"))?;
            let pose = i.poses.iter().find(|(p, _)| p == pos).ok_or_else(|| anyhow!("no camera_pose at position {pos}"))?;
            frames.push(Frame { position: *pos, image, calib: &calib.1, pose: &pose.1 });
        }
        // A camera item without an image (the dataset says why) has no body to find.
        if frames.iter().any(|f| f.position == 0 && f.image.width == 0) {
            let mask = Mask { width: 0, height: 0, data: Vec::new() };
            let preview = ctx.wants("preview").then(|| Image { width: 0, height: 0, rgb: Vec::new() });
            return Ok(Outputs { mask, preview }.into());
        }
        let e = estimate(&self.0, &frames, i.depth.as_ref())?;
        let preview = match frames.iter().find(|f| f.position == 0) {
            Some(t) if ctx.wants("preview") => Some(preview(t.image, &e)),
            _ => None,
        };
        Ok(Outputs { mask: e.mask, preview }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: u32 = 320;
    const H: u32 = 180;

    /// A front camera 1.5 m above the ground looking along the ego's +x (f = 300 px).
    fn camera() -> Calibration {
        Calibration {
            sensor_to_ego: Se3::from_wxyz_t([0.5, -0.5, 0.5, -0.5], [1.5, 0.0, 1.5]),
            intrinsics: Some([[300.0, 0.0, W as f64 / 2.0], [0.0, 300.0, H as f64 / 2.0], [0.0, 0.0, 1.0]]),
            width: W,
            height: H,
        }
    }

    /// Smooth texture without a direction it is invariant along (sines of several directions).
    fn texture(a: f64, b: f64) -> f64 {
        128.0 + 40.0 * (a * 7.1 + b * 2.3).sin() + 30.0 * (a * 3.7 - b * 8.9).sin() + 25.0 * (a * 13.3 + b * 11.9).sin()
    }

    /// The world: the ground (z = 0) textured by `ground(x, y)`, a wall at x = `wall` textured in
    /// (y, z), sky (flat grey) beyond. Renders frame `frame` with the ego at x = frame * step, and
    /// gives the exact depth at every third pixel (LiDAR returns); the rows from `body_from` down
    /// show a textured body fixed to the camera instead (the LiDAR sees through it).
    fn render(frame: i64, step: f64, wall: f64, ground: &dyn Fn(f64, f64) -> f64, body_from: u32) -> (Image, Pose, DepthMap) {
        let cam = camera();
        let pose = Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::new(frame as f64 * step, 0.0, 0.0)), timestamp_us: frame * 100_000 };
        let world_from_cam = pose.ego_to_world.then_from(&cam.sensor_to_ego);
        let (rot, origin) = (world_from_cam.matrix(), world_from_cam.translation);
        let mut rgb = vec![0u8; (3 * W * H) as usize];
        let mut depth = DepthMap::new(W, H);
        // What a ray through (u, v) hits: (depth, grey level).
        let hit = |u: f64, v: f64| {
            let dir = rot * DVec3::new((u - W as f64 / 2.0) / 300.0, (v - H as f64 / 2.0) / 300.0, 1.0);
            let mut hit = (f64::INFINITY, 170.0);
            if dir.z < -1e-9 {
                let s = -origin.z / dir.z;
                let p = origin + dir * s;
                hit = (s, ground(p.x, p.y));
            }
            if dir.x > 1e-9 {
                let s = (wall - origin.x) / dir.x;
                let p = origin + dir * s;
                if s < hit.0 && p.z >= 0.0 {
                    hit = (s, texture(p.y * 3.0, p.z * 3.0));
                }
            }
            hit
        };
        for y in 0..H {
            for x in 0..W {
                let i = (y * W + x) as usize;
                // 4x4 samples per pixel, as a lens blurs what is finer than a pixel.
                let scene = (0..16).map(|s| hit(x as f64 + (s % 4) as f64 / 4.0 + 0.125, y as f64 + (s / 4) as f64 / 4.0 + 0.125).1).sum::<f64>() / 16.0;
                let v = if y >= body_from { texture(x as f64 * 0.11, y as f64 * 0.13) } else { scene };
                rgb[3 * i..3 * i + 3].fill(v.clamp(0.0, 255.0) as u8);
                let centre = hit(x as f64 + 0.5, y as f64 + 0.5).0;
                if centre.is_finite() && x % 3 == 0 && y % 3 == 0 {
                    depth.data[i] = centre as f32;
                }
            }
        }
        (Image { width: W, height: H, rgb }, pose, depth)
    }

    /// The estimate of frame 1 from frames 0..2, and the share of the rows from `body_from` down
    /// that it masks and of the rows above.
    fn masked(step: f64, wall: f64, ground: &dyn Fn(f64, f64) -> f64, body_from: u32) -> (f64, f64) {
        let cam = camera();
        let rendered: Vec<_> = (0..3).map(|f| render(f, step, wall, ground, body_from)).collect();
        let frames: Vec<Frame> = rendered
            .iter()
            .enumerate()
            .map(|(k, (image, pose, _))| Frame { position: k as i64 - 1, image, calib: &cam, pose })
            .collect();
        let e = estimate(&Params::default(), &frames, Some(&rendered[1].2)).unwrap();
        assert_eq!((e.mask.width, e.mask.height, e.factor), (W, H, 1));
        let share = |rows: std::ops::Range<u32>| {
            let n = rows.len() as f64 * W as f64;
            rows.flat_map(|y| (0..W).map(move |x| (y * W + x) as usize)).filter(|&i| e.mask.data[i] == 1).count() as f64 / n
        };
        (share(body_from.min(H)..H), share(0..body_from.min(H)))
    }

    #[test]
    fn the_body_that_stays_while_the_textured_scene_moves_is_masked_and_nothing_else() {
        let ground = |x: f64, y: f64| texture(x * 2.0, y * 2.0);
        let (body, scene) = masked(1.0, 12.0, &ground, 150);
        assert!(body > 0.9, "body masked {body}");
        assert!(scene < 0.01, "scene masked {scene}");
        // Without a body, nothing.
        let (_, scene) = masked(1.0, 12.0, &ground, H);
        assert_eq!(scene, 0.0);
    }

    #[test]
    fn a_car_that_does_not_move_gives_no_evidence() {
        let ground = |x: f64, y: f64| texture(x * 2.0, y * 2.0);
        let (body, scene) = masked(0.0, 12.0, &ground, 150);
        assert_eq!((body, scene), (0.0, 0.0));
    }

    #[test]
    fn lines_along_the_motion_stay_in_place_but_are_not_the_body() {
        // Lane lines: the ground's texture depends only on y (across the motion), so every row of
        // the road looks the same in each frame, like a body; no wall (sky beyond).
        let lanes = |_: f64, y: f64| if (y * 2.0).rem_euclid(3.0) < 0.4 { 230.0 } else { 60.0 + 20.0 * (y * 5.0).sin() };
        let (_, scene) = masked(1.0, 1e6, &lanes, H);
        assert_eq!(scene, 0.0, "the lanes are not the body");
        let (body, scene) = masked(1.0, 12.0, &lanes, 150);
        assert!(body > 0.9 && scene < 0.01, "with a body below them: body {body}, scene {scene}");
    }

    #[test]
    fn the_curtain_follows_the_gain_and_bridges_what_says_nothing() {
        // 6 columns, 5 rows from the border: a body 2 rows high in columns 0-2 (its inside says
        // nothing in column 1), scene from row 2 up everywhere.
        let (w, h) = (6, 5);
        let mut gain = vec![-1.0f32; w * h];
        for x in 0..3 {
            gain[x] = 1.0;
            gain[w + x] = 1.0;
        }
        gain[1] = -0.01;
        let rows = curtain(&gain, w, h, 0.3);
        assert_eq!(rows, vec![2, 2, 2, 0, 0, 0]);
        // A steep smoothness keeps one height for all.
        assert!(curtain(&gain, w, h, 100.0).windows(2).all(|p| p[0] == p[1]));
        assert!(curtain(&[], 0, 3, 0.3).is_empty());
    }

    #[test]
    fn frames_of_another_size_and_a_missing_target_are_errors_that_say_so() {
        let cam = camera();
        let pose = Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::ZERO), timestamp_us: 0 };
        let a = Image { width: W, height: H, rgb: vec![0; (3 * W * H) as usize] };
        let b = Image { width: 10, height: 10, rgb: vec![0; 300] };
        let frames = [Frame { position: 0, image: &a, calib: &cam, pose: &pose }, Frame { position: 1, image: &b, calib: &cam, pose: &pose }];
        let e = estimate(&Params::default(), &frames, None).err().unwrap().to_string();
        assert!(e.contains("position 1") && e.contains("10x10"), "{e}");
        let e = estimate(&Params::default(), &frames[1..], None).err().unwrap().to_string();
        assert!(e.contains("position 0"), "{e}");
        let bad = Params { patch: 0, ..Default::default() };
        assert!(estimate(&bad, &frames[..1], None).is_err());
        // One frame alone: nothing to compare, an empty mask of the image's size.
        let one = estimate(&Params::default(), &frames[..1], None).unwrap();
        assert_eq!(one.mask.data.len(), (W * H) as usize);
        assert!(one.mask.data.iter().all(|&v| v == 0));
    }
}
