//! Plane-sweep stereo with census costs and semi-global aggregation, for any number of calibrated
//! views (a rectified pair is the special case of one source shifted along x).
//!
//! Why this design: driving logs give calibrated neighbouring frames of one camera, not rectified
//! pairs, so the cost volume is built by sweeping fronto-parallel planes of the reference camera,
//! uniform in inverse depth, and sampling each source along its epipolar line. Census costs
//! survive exposure changes between frames; semi-global matching (Hirschmüller 2008, 8 paths)
//! regularises textureless stretches without smoothing across depth edges; a geometric
//! consistency check against the depth of a source view (the multi-view form of the left-right
//! check) removes occlusions and mismatches.
//!
//! The number of planes follows the geometry: planes are spaced so that the sample moves about
//! `plane_step_px` pixels along the longest epipolar line, capped at `max_planes`.
//!
//! Speed: the inner loops (census costs along each pixel's samples, the SGM passes, the winner
//! search, the census) are in `kernels`, as AVX2 code chosen at run time with a portable
//! fallback that gives the same bytes. A view's census is computed once, when it is made; the
//! winner is picked as the backward SGM pass completes each pixel, so the summed costs are never
//! stored; [`SweepBuffers`] carries the cost volume from one sweep to the next.

mod kernels;

use dist4d_types::cancel;
use dist4d_types::geometry::Se3;
use glam::{DMat3, DVec3};
use kernels::{Isa, SourceCensus};
use rayon::prelude::*;

/// A grey image with its pinhole intrinsics and pose, and the image's census transform: a view
/// takes part in several sweeps (as the reference of one, a source of others), and its census
/// is computed once, when it is made.
pub struct StereoView {
    width: usize,
    height: usize,
    grey: Vec<u8>,
    census: Vec<u64>,
    /// Intrinsics for continuous pixel coordinates (pixel (i, j) covers [i, i+1) x [j, j+1)).
    pub k: [[f64; 3]; 3],
    /// Camera frame -> world (any common frame).
    pub world_from_cam: Se3,
}

impl StereoView {
    /// The view of a `width` x `height` grey image (row-major).
    pub fn new(width: usize, height: usize, grey: Vec<u8>, k: [[f64; 3]; 3], world_from_cam: Se3) -> StereoView {
        assert_eq!(grey.len(), width * height, "a {width}x{height} view needs {} grey levels", width * height);
        let census = census(&grey, width, height);
        StereoView { width, height, grey, census, k, world_from_cam }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    pub fn grey(&self) -> &[u8] {
        &self.grey
    }

    /// The view at 1/`factor` of the resolution: grey levels averaged over factor x factor blocks
    /// (partial blocks at the right and bottom edges dropped), intrinsics scaled to match.
    pub fn downscaled(
        width: usize,
        height: usize,
        grey: &[u8],
        k: [[f64; 3]; 3],
        world_from_cam: Se3,
        factor: usize,
    ) -> StereoView {
        let f = factor.max(1);
        let (w, h) = (width / f, height / f);
        let mut out = vec![0u8; w * h];
        let area = (f * f) as u32;
        // Per output row: the block rows summed down each column (whole rows at a time, which
        // vectorises), then f columns at a time across.
        let mut columns = vec![0u32; w * f];
        for (y, out_row) in out.chunks_exact_mut(w.max(1)).enumerate() {
            columns.fill(0);
            for yy in y * f..(y + 1) * f {
                for (c, &g) in columns.iter_mut().zip(&grey[yy * width..][..w * f]) {
                    *c += g as u32;
                }
            }
            for (o, block) in out_row.iter_mut().zip(columns.chunks_exact(f)) {
                *o = ((block.iter().sum::<u32>() + area / 2) / area) as u8;
            }
        }
        let s = 1.0 / f as f64;
        let mut ks = k;
        for row in ks.iter_mut().take(2) {
            for v in row.iter_mut() {
                *v *= s;
            }
        }
        StereoView::new(w, h, out, ks, world_from_cam)
    }

    fn k_inv(&self) -> DMat3 {
        k_matrix(&self.k).inverse()
    }
}

/// 8-bit luma (ITU-R 601 weights) of RGB8 pixels: what the census compares.
pub fn grey(rgb: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3).map(|p| ((p[0] as u32 * 77 + p[1] as u32 * 150 + p[2] as u32 * 29) >> 8) as u8).collect()
}

fn k_matrix(k: &[[f64; 3]; 3]) -> DMat3 {
    DMat3::from_cols_array_2d(k).transpose()
}

#[derive(Clone, Debug, PartialEq)]
pub struct SweepParams {
    pub min_depth: f64,
    pub max_depth: f64,
    pub max_planes: usize,
    pub plane_step_px: f64,
    /// SGM penalty for a one-plane change between neighbours (cost units: census bits, x2).
    pub p1: u16,
    /// SGM penalty for a larger jump.
    pub p2: u16,
    /// The best aggregated cost must beat the second best by this fraction.
    pub uniqueness: f64,
    /// The second best is sought at least this far (px, along the epipolar line) from the best.
    pub distinct_px: f64,
    /// Largest cost volume (with its aggregation, see [`volume_bytes`]) a sweep may allocate;
    /// beyond it the sweep is refused before anything is allocated.
    pub max_volume_bytes: u64,
}

/// Bytes a sweep of `width` x `height` pixels over `planes` planes holds at its peak: the
/// census cost volume (1 byte per pixel and plane) and the aggregated costs (2 bytes), alive
/// together during the aggregation, and the aggregation's path rows (3 directions x 2 rows of
/// u16 per plane and pixel of a row, with up to 32 planes of vector padding).
pub fn volume_bytes(width: usize, height: usize, planes: usize) -> u64 {
    let (w, h, n) = (width as u64, height as u64, planes as u64);
    let volume = w.saturating_mul(h).saturating_mul(n).saturating_mul(3);
    volume.saturating_add(w.saturating_mul(n + 32).saturating_mul(12))
}

/// A sweep refused because its cost volume exceeds [`SweepParams::max_volume_bytes`].
#[derive(Clone, Debug, PartialEq)]
pub struct VolumeTooLarge {
    pub width: usize,
    pub height: usize,
    pub planes: usize,
    pub bytes: u64,
    pub budget: u64,
}

impl std::fmt::Display for VolumeTooLarge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the stereo cost volume would need {} ({} x {} pixels x {} planes x 3 bytes, and its aggregation's \
             rows), over the budget of {}",
            gib(self.bytes),
            self.width,
            self.height,
            self.planes,
            gib(self.budget)
        )
    }
}

impl std::error::Error for VolumeTooLarge {}

fn gib(bytes: u64) -> String {
    format!("{:.1} GiB", bytes as f64 / (1u64 << 30) as f64)
}

/// Depth (0 = none) and confidence in [0, 1] per pixel of the reference view.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoDepth {
    pub width: usize,
    pub height: usize,
    pub depth: Vec<f32>,
    pub confidence: Vec<f32>,
}

/// Census bits per source; two sources' costs are summed, one source's is doubled.
const CENSUS_BITS: u32 = 48;
const COST_MAX: u8 = (2 * CENSUS_BITS) as u8;

/// 7x7 census transform (48 bits: neighbour darker than the centre), edges clamped.
pub fn census(grey: &[u8], w: usize, h: usize) -> Vec<u64> {
    kernels::census(Isa::best(), grey, w, h)
}

/// How a reference pixel moves in one source as inverse depth changes: source pixel =
/// (a + b rho).xy / (a + b rho).z with a = K_s R K_r^-1 [u v 1], b = K_s t.
struct Warp {
    m: DMat3,
    b: DVec3,
}

impl Warp {
    fn new(reference: &StereoView, source: &StereoView) -> Warp {
        let src_from_ref = source.world_from_cam.inverse().then_from(&reference.world_from_cam);
        let ks = k_matrix(&source.k);
        Warp { m: ks * src_from_ref.matrix() * reference.k_inv(), b: ks * src_from_ref.translation }
    }

    #[inline]
    fn at(&self, a: DVec3, rho: f64) -> Option<(f64, f64)> {
        let p = a + self.b * rho;
        (p.z > 1e-9).then(|| (p.x / p.z, p.y / p.z))
    }
}

/// Where a reference ray `a + b rho` (see [`Warp`]) lands in a source at inverse depth `rho`
/// (continuous pixel coordinates, possibly outside the image), if in front of it.
#[inline]
fn project(a: glam::Vec3, b: glam::Vec3, rho: f32) -> Option<(f32, f32)> {
    let z = a.z + b.z * rho;
    if z <= 1e-9 {
        return None;
    }
    let inv = 1.0 / z;
    Some(((a.x + b.x * rho) * inv, (a.y + b.y * rho) * inv))
}

/// The source pixel the ray samples at `rho`, if it lands inside the source's `sw` x `sh` image.
#[inline]
fn sample_at(a: glam::Vec3, b: glam::Vec3, rho: f32, sw: f32, sh: f32) -> Option<(usize, usize)> {
    let (u, v) = project(a, b, rho)?;
    (u >= 0.0 && v >= 0.0 && u < sw && v < sh).then_some((u as usize, v as usize))
}

/// Inverse depths of the planes, far to near: the spacing moves the sample by about
/// `plane_step_px` along the longest epipolar line of a grid of reference pixels.
fn plane_inverse_depths(reference: &StereoView, warps: &[Warp], p: &SweepParams) -> Vec<f64> {
    let (rho_far, rho_near) = (1.0 / p.max_depth, 1.0 / p.min_depth);
    const SAMPLES: usize = 64;
    let mut longest: f64 = 0.0;
    for gy in 0..=8 {
        for gx in 0..=8 {
            let u = reference.width as f64 * gx as f64 / 8.0;
            let v = reference.height as f64 * gy as f64 / 8.0;
            for warp in warps {
                let a = warp.m * DVec3::new(u, v, 1.0);
                let mut length = 0.0;
                let mut last: Option<(f64, f64)> = None;
                for i in 0..=SAMPLES {
                    let rho = rho_far + (rho_near - rho_far) * i as f64 / SAMPLES as f64;
                    let now = warp.at(a, rho);
                    if let (Some(l), Some(n)) = (last, now) {
                        length += ((n.0 - l.0).powi(2) + (n.1 - l.1).powi(2)).sqrt();
                    }
                    last = now;
                }
                longest = longest.max(length);
            }
        }
    }
    let n = ((longest / p.plane_step_px.max(1e-3)).ceil() as usize + 1).clamp(8, p.max_planes.max(8));
    (0..n).map(|i| rho_far + (rho_near - rho_far) * i as f64 / (n - 1) as f64).collect()
}

/// The large buffers of a sweep, kept from one sweep to the next: the cost volume and the
/// forward SGM sums take tens of megabytes at MultiViewStereo's size, and fresh ones cost page
/// faults and zeroing every time. A sweep overwrites every entry it reads.
#[derive(Default)]
pub struct SweepBuffers {
    cost: Vec<u8>,
    sums: Vec<u16>,
}

/// The first `len` entries of `v`, which grows (never shrinks) to hold them; the old buffer is
/// freed before the new one is allocated, so the peak stays within the sweep's budget.
fn first<T: Copy + Default>(v: &mut Vec<T>, len: usize) -> &mut [T] {
    if v.len() < len {
        *v = Vec::new();
        *v = vec![T::default(); len];
    }
    &mut v[..len]
}

/// Depth of `reference` from `sources` by plane sweep, census and 8-path SGM, with uniqueness
/// and sub-plane (parabola) refinement. No source: no depth. Refused, before the cost volume is
/// allocated, when that volume would exceed `p.max_volume_bytes`.
pub fn sweep_depth(
    reference: &StereoView,
    sources: &[&StereoView],
    p: &SweepParams,
) -> Result<StereoDepth, VolumeTooLarge> {
    sweep_depth_with(&mut SweepBuffers::default(), reference, sources, p)
}

/// [`sweep_depth`] in `buffers` that earlier sweeps may have grown.
///
/// A cancellation point (`dist4d_types::cancel`): once a stop is requested it returns early with
/// a partial result, which a caller must discard (check `cancel::check()` after it).
pub fn sweep_depth_with(
    buffers: &mut SweepBuffers,
    reference: &StereoView,
    sources: &[&StereoView],
    p: &SweepParams,
) -> Result<StereoDepth, VolumeTooLarge> {
    let (w, h) = (reference.width, reference.height);
    let mut out = StereoDepth { width: w, height: h, depth: vec![0.0; w * h], confidence: vec![0.0; w * h] };
    if sources.is_empty() || w == 0 || h == 0 {
        return Ok(out);
    }
    let warps: Vec<Warp> = sources.iter().map(|s| Warp::new(reference, s)).collect();
    let rhos = plane_inverse_depths(reference, &warps, p);
    let planes = rhos.len();
    let bytes = volume_bytes(w, h, planes);
    if bytes > p.max_volume_bytes {
        return Err(VolumeTooLarge { width: w, height: h, planes, bytes, budget: p.max_volume_bytes });
    }
    let ref_census = &reference.census;

    // Cost volume, [pixel][plane]; COST_MAX where no source sees the sample. Every entry is
    // written below.
    let isa = Isa::best();
    let cost = first(&mut buffers.cost, w * h * planes);
    let rhos32: Vec<f32> = rhos.iter().map(|&r| r as f32).collect();
    // f32 is ample for pixel coordinates and keeps the inner loop cheap.
    let rays = |s: usize, x: usize, y: usize| {
        ((warps[s].m * DVec3::new(x as f64 + 0.5, y as f64 + 0.5, 1.0)).as_vec3(), warps[s].b.as_vec3())
    };
    let views: Vec<SourceCensus> =
        sources.iter().map(|s| SourceCensus { census: &s.census, width: s.width, height: s.height }).collect();
    // A requested stop (see `dist4d_types::cancel`) leaves the rest of the work undone: rows are
    // skipped, the aggregation returns at its next row, and the caller, which checks for the stop
    // after the sweep, throws the partial result away.
    cost.par_chunks_mut(w * planes).enumerate().for_each(|(y, row)| {
        if cancel::requested() {
            return;
        }
        let mut pixel_rays = Vec::with_capacity(sources.len());
        for (x, cost_px) in row.chunks_exact_mut(planes).enumerate() {
            pixel_rays.clear();
            pixel_rays.extend((0..sources.len()).map(|s| rays(s, x, y)));
            kernels::pixel_costs(isa, ref_census[y * w + x], &pixel_rays, &views, &rhos32, COST_MAX, cost_px);
        }
    });
    if cancel::requested() {
        return Ok(out);
    }
    let step = rhos[1] - rhos[0];
    // Each pixel's summed costs are complete when the backward pass leaves it: the winner is
    // chosen there, so the sums are never written back and read again.
    let sums = first(&mut buffers.sums, w * h * planes);
    aggregate(isa, cost, sums, w, h, planes, p.p1, p.p2, |i, s| {
        let (best, sb) = kernels::argmin(isa, s);
        // At the ends of the range the minimum may lie beyond it: no depth.
        if best == 0 || best == planes - 1 {
            return;
        }
        // How far the sample moves per plane around the winner, in the source that moves it most
        // (the one that shapes the cost curve). Zero: no source saw the winning plane, so it won
        // on the COST_MAX filler alone.
        let (x, y) = (i % w, i / w);
        let motion = sources
            .iter()
            .enumerate()
            .filter_map(|(si, src)| {
                let (a, b) = rays(si, x, y);
                sample_at(a, b, rhos32[best], src.width as f32, src.height as f32)?;
                let (u0, v0) = project(a, b, rhos32[best - 1])?;
                let (u1, v1) = project(a, b, rhos32[best + 1])?;
                Some((u1 - u0).hypot(v1 - v0) / 2.0)
            })
            .fold(0.0f32, f32::max);
        if motion <= 0.0 {
            return;
        }
        // The runner-up must be a different match, `distinct_px` along the epipolar line away:
        // where a plane moves the sample a fraction of a pixel, the planes next to the winner
        // sample the same pixels and cost the same.
        // (Less a hair, so that exactly one pixel per plane, as in a rectified pair, is one plane.)
        let apart = ((p.distinct_px / motion as f64 - 1e-3).ceil() as usize).clamp(1, planes / 4);
        let second = kernels::min_outside(isa, s, best.saturating_sub(apart), best + apart);
        if (sb as f64) >= (1.0 - p.uniqueness) * second as f64 {
            return;
        }
        let (l, c, r) = (s[best - 1] as f64, sb as f64, s[best + 1] as f64);
        let curvature = l - 2.0 * c + r;
        let offset = if curvature > 0.0 { ((l - r) / (2.0 * curvature)).clamp(-0.5, 0.5) } else { 0.0 };
        let rho = rhos[best] + offset * step;
        if rho > 0.0 {
            out.depth[i] = (1.0 / rho) as f32;
            out.confidence[i] = (1.0 - sb as f64 / second.max(1) as f64) as f32;
        }
    });
    Ok(out)
}

/// Semi-global aggregation over 8 paths (Hirschmüller 2008) of a [pixel][plane] cost volume:
/// `done(pixel, sums)` receives each pixel's summed path costs, once; `scratch` (the volume's
/// size, any content) holds the first pass's sums. Two scanline passes
/// (forward: paths from the left, top-left, top, top-right; backward: their mirrors), each
/// keeping one row of path costs per direction; each path follows
/// L(p, d) = C(p, d) + min(L(q, d), L(q, d +- 1) + P1, min L(q) + P2) - min L(q), in 16 bits
/// (8 paths of at most 96 + P2 each cannot overflow them, see `mvs::MAX_PENALTY`).
#[allow(clippy::too_many_arguments)]
fn aggregate(
    isa: Isa,
    cost: &[u8],
    scratch: &mut [u16],
    w: usize,
    h: usize,
    n: usize,
    p1: u16,
    p2: u16,
    done: impl FnMut(usize, &[u16]),
) {
    kernels::aggregate(isa, cost, scratch, w, h, n, p1, p2, done)
}

/// Keeps the depths of `reference` that at least one of the `checks` (another view and its own
/// depth map) confirms (see [`confirmed`]). Failing pixels lose depth and confidence.
pub fn keep_consistent(
    reference: &StereoView,
    depth: &mut StereoDepth,
    checks: &[(&StereoView, &StereoDepth)],
    max_px: f64,
    max_rel: f64,
) {
    let mut kept = vec![false; depth.depth.len()];
    for (other, other_depth) in checks {
        for (k, ok) in kept.iter_mut().zip(confirmed(reference, depth, other, other_depth, max_px, max_rel)) {
            *k |= ok;
        }
    }
    for ((z, c), k) in depth.depth.iter_mut().zip(depth.confidence.iter_mut()).zip(kept) {
        if !k {
            *z = 0.0;
            *c = 0.0;
        }
    }
}

/// Per pixel of `reference`: whether `other`'s depth map confirms its depth. The point goes to
/// `other`, takes the depth found there, and must come back within `max_px` pixels and `max_rel`
/// relative depth. Pixels without depth, or whose point leaves `other`'s image, are not confirmed.
fn confirmed(
    reference: &StereoView,
    depth: &StereoDepth,
    other: &StereoView,
    other_depth: &StereoDepth,
    max_px: f64,
    max_rel: f64,
) -> Vec<bool> {
    let other_from_ref = other.world_from_cam.inverse().then_from(&reference.world_from_cam);
    let ref_from_other = other_from_ref.inverse();
    let (kr, kr_inv, ko, ko_inv) = (k_matrix(&reference.k), reference.k_inv(), k_matrix(&other.k), other.k_inv());
    let w = depth.width;
    let project = |k: &DMat3, p: DVec3| {
        let q = *k * p;
        (q.x / q.z, q.y / q.z)
    };
    depth
        .depth
        .par_iter()
        .enumerate()
        .map(|(i, &z)| {
            if z <= 0.0 {
                return false;
            }
            let (x, y) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
            let p = other_from_ref.apply(kr_inv * DVec3::new(x, y, 1.0) * z as f64);
            if p.z <= 0.0 {
                return false;
            }
            let (u, v) = project(&ko, p);
            if !(u >= 0.0 && v >= 0.0 && u < other.width as f64 && v < other.height as f64) {
                return false;
            }
            let (ou, ov) = (u.floor() + 0.5, v.floor() + 0.5);
            let zo = other_depth.depth[v as usize * other_depth.width + u as usize] as f64;
            if zo <= 0.0 {
                return false;
            }
            let back = ref_from_other.apply(ko_inv * DVec3::new(ou, ov, 1.0) * zo);
            let (bu, bv) = project(&kr, back);
            back.z > 0.0 && (bu - x).hypot(bv - y) <= max_px && (back.z - z as f64).abs() <= max_rel * z as f64
        })
        .collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Value noise texture in [0, 255] on a surface parameterised by (s, t) metres.
    fn texture(s: f64, t: f64) -> u8 {
        let h = |i: i64, j: i64| {
            let mut x = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
            x ^= x >> 31;
            x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
            x ^= x >> 29;
            (x & 0xFFFF) as f64 / 65535.0
        };
        let mut v = 0.0;
        for (scale, weight) in [(0.08, 0.6), (0.3, 0.4)] {
            let (a, b) = (s / scale, t / scale);
            let (i, j) = (a.floor() as i64, b.floor() as i64);
            let (fa, fb) = (a - i as f64, b - j as f64);
            let n = h(i, j) * (1.0 - fa) * (1.0 - fb)
                + h(i + 1, j) * fa * (1.0 - fb)
                + h(i, j + 1) * (1.0 - fa) * fb
                + h(i + 1, j + 1) * fa * fb;
            v += n * weight;
        }
        (v * 255.0) as u8
    }

    /// A scene of a back wall at z = 30 and a box face at z = 12 (|x| < 3, |y| < 2), seen from
    /// camera centres along x; rendered exactly by ray casting. Returns the view and the true depth.
    fn render(cx: f64, w: usize, h: usize) -> (StereoView, Vec<f32>) {
        let k = [[300.0, 0.0, w as f64 / 2.0], [0.0, 300.0, h as f64 / 2.0], [0.0, 0.0, 1.0]];
        let mut grey = vec![0u8; w * h];
        let mut depth = vec![0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let rx = (x as f64 + 0.5 - k[0][2]) / 300.0;
                let ry = (y as f64 + 0.5 - k[1][2]) / 300.0;
                let (z, s, t) = {
                    let (bx, by) = (cx + rx * 12.0, ry * 12.0);
                    if bx.abs() < 3.0 && by.abs() < 2.0 {
                        (12.0, bx + 100.0, by)
                    } else {
                        (30.0, cx + rx * 30.0, ry * 30.0)
                    }
                };
                grey[y * w + x] = texture(s, t);
                depth[y * w + x] = z as f32;
            }
        }
        (StereoView::new(w, h, grey, k, Se3::from_yaw(0.0, DVec3::new(cx, 0.0, 0.0))), depth)
    }

    /// A textured wall at z = 30 seen by a camera at (0, 0, `cz`) looking along +z: driving
    /// towards it puts the epipole at the image centre.
    fn render_ahead(cz: f64, w: usize, h: usize) -> StereoView {
        let f = 150.0;
        let k = [[f, 0.0, w as f64 / 2.0], [0.0, f, h as f64 / 2.0], [0.0, 0.0, 1.0]];
        let mut grey = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let (rx, ry) = ((x as f64 + 0.5 - k[0][2]) / f, (y as f64 + 0.5 - k[1][2]) / f);
                // Texture coordinates in quarter metres: features of a pixel or two at 30 m.
                grey[y * w + x] = texture(rx * (30.0 - cz) / 4.0, ry * (30.0 - cz) / 4.0);
            }
        }
        let pose = Se3::from_wxyz_t([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, cz]);
        StereoView::new(w, h, grey, k, pose)
    }

    #[test]
    fn driving_ahead_gives_confident_depth_away_from_the_epipole() {
        // Planes are spaced for the longest epipolar line (the corners); near the centre a plane
        // moves the sample a fraction of a pixel, so the runner-up must be sought a pixel away,
        // not a plane away, or every such match looks ambiguous.
        let (w, h) = (160, 120);
        let reference = render_ahead(0.0, w, h);
        let (back, ahead) = (render_ahead(-3.0, w, h), render_ahead(3.0, w, h));
        let d = sweep_depth(&reference, &[&back, &ahead], &params()).unwrap();
        let (mut ring, mut confident, mut good) = (0, 0, 0);
        for y in 0..h {
            for x in 0..w {
                let r = (x as f64 + 0.5 - w as f64 / 2.0).hypot(y as f64 + 0.5 - h as f64 / 2.0);
                if !(25.0..55.0).contains(&r) {
                    continue;
                }
                ring += 1;
                let (z, c) = (d.depth[y * w + x], d.confidence[y * w + x]);
                if z > 0.0 && c >= 0.4 {
                    confident += 1;
                    good += ((z - 30.0).abs() < 0.05 * 30.0) as usize;
                }
            }
        }
        // (With the runner-up a plane away, about half of them.)
        assert!(confident as f64 > 0.9 * ring as f64, "{confident} of {ring} confident");
        assert!(good as f64 > 0.95 * confident as f64, "{good} of {confident} within 5%");
    }

    /// The MultiViewStereo stage's defaults, from 5 m.
    pub(crate) fn params() -> SweepParams {
        SweepParams { min_depth: 5.0, ..crate::curation::mvs::Params::default().sweep() }
    }

    #[test]
    fn recovers_a_box_in_front_of_a_wall_from_two_neighbours() {
        let (w, h) = (160, 120);
        let (reference, truth) = render(0.0, w, h);
        let (left, _) = render(-1.0, w, h);
        let (right, _) = render(1.0, w, h);
        let mut depth = sweep_depth(&reference, &[&left, &right], &params()).unwrap();
        let right_depth = sweep_depth(&right, &[&reference], &params()).unwrap();
        keep_consistent(&reference, &mut depth, &[(&right, &right_depth)], 1.0, 0.02);
        let (mut valid, mut good) = (0, 0);
        for (z, t) in depth.depth.iter().zip(&truth) {
            if *z > 0.0 {
                valid += 1;
                if ((z - t) / t).abs() < 0.03 {
                    good += 1;
                }
            }
        }
        assert!(valid as f64 > 0.7 * (w * h) as f64, "valid {valid} of {}", w * h);
        assert!(good as f64 > 0.97 * valid as f64, "good {good} of {valid}");
        assert!(depth
            .confidence
            .iter()
            .zip(&depth.depth)
            .all(|(c, z)| (*z > 0.0) == (*c > 0.0) && (0.0..=1.0).contains(c)));
    }

    #[test]
    fn a_sweep_over_the_memory_budget_is_refused_before_allocating() {
        let (w, h) = (160, 120);
        let (reference, _) = render(0.0, w, h);
        let (left, _) = render(-1.0, w, h);
        // A plane every 0.01 px: the plane count reaches max_planes.
        let dense = SweepParams { plane_step_px: 0.01, max_planes: 1024, ..params() };
        let need = volume_bytes(w, h, 1024);
        assert_eq!(need, 160 * 120 * 1024 * 3 + 160 * (1024 + 32) * 12, "the volume and the path rows");
        let e = sweep_depth(&reference, &[&left], &SweepParams { max_volume_bytes: need - 1, ..dense.clone() })
            .unwrap_err();
        assert_eq!((e.width, e.height, e.planes, e.bytes), (w, h, 1024, need));
        assert!(e.to_string().contains("160 x 120 pixels x 1024 planes"), "{e}");
        // Exactly at the budget it runs.
        assert!(sweep_depth(&reference, &[&left], &SweepParams { max_volume_bytes: need, ..dense }).is_ok());
        // The sizes cannot overflow into a small number.
        assert_eq!(volume_bytes(usize::MAX, 2, 8), u64::MAX);
    }

    #[test]
    fn without_sources_there_is_no_depth() {
        let (reference, _) = render(0.0, 40, 30);
        let d = sweep_depth(&reference, &[], &params()).unwrap();
        assert!(d.depth.iter().all(|&z| z == 0.0));
    }

    #[test]
    fn a_mismatched_depth_fails_the_consistency_check() {
        let (w, h) = (80, 60);
        let (reference, truth) = render(0.0, w, h);
        let (right, right_truth) = render(1.0, w, h);
        let mut depth = StereoDepth { width: w, height: h, depth: truth.clone(), confidence: vec![1.0; w * h] };
        let mut wrong = depth.clone();
        for z in wrong.depth.iter_mut() {
            *z *= 1.2;
        }
        let other = StereoDepth { width: w, height: h, depth: right_truth, confidence: vec![1.0; w * h] };
        keep_consistent(&reference, &mut depth, &[(&right, &other)], 1.0, 0.02);
        keep_consistent(&reference, &mut wrong, &[(&right, &other)], 1.0, 0.02);
        let kept = depth.depth.iter().filter(|&&z| z > 0.0).count();
        // Pixels that leave the other image (a 1 m shift moves the wall 10 px, the box 25 px) cannot be checked.
        assert!(kept as f64 > 0.6 * (w * h) as f64, "{kept}");
        assert!(wrong.depth.iter().all(|&z| z == 0.0) || wrong.depth.iter().filter(|&&z| z > 0.0).count() < w * h / 20);
    }

    #[test]
    fn downscaling_averages_blocks_and_scales_intrinsics() {
        let grey: Vec<u8> = (0..16).map(|i| i as u8 * 10).collect();
        let k = [[100.0, 0.0, 2.0], [0.0, 100.0, 2.0], [0.0, 0.0, 1.0]];
        let v = StereoView::downscaled(4, 4, &grey, k, Se3::from_yaw(0.0, DVec3::ZERO), 2);
        assert_eq!((v.width, v.height), (2, 2));
        assert_eq!(v.grey[0], ((0 + 10 + 40 + 50) as f32 / 4.0).round() as u8);
        assert_eq!(v.k[0][0], 50.0);
        assert_eq!(v.k[1][2], 1.0);
        assert_eq!(v.k[2][2], 1.0);
    }
}
