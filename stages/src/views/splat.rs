//! Forward warping of RGB-D images into another camera: every source pixel becomes a world point,
//! is projected into the target camera and splatted over its footprint with a soft z-buffer.
//!
//! Why footprints: a pixel of a source image is a small patch of surface, not a point. Seen from a
//! target camera that is nearer, or that looks at the surface at another angle, the patch covers
//! several target pixels; splatting it as a point (FreeVS's 1 px LiDAR splat) leaves gaps between
//! the points of a near surface through which the background shows ("leaks"). Here a point's
//! footprint is the box spanned by half the distance to its projected grid neighbours (left,
//! right, up and down in the source image) that lie on the same surface (source depths within
//! `edge_tolerance` of each other), at least one target pixel: boxes of neighbouring points tile
//! the surface whatever the magnification or the foreshortening, and never bridge a depth edge,
//! so a disocclusion stays a hole instead of being smeared over. A point without a same-surface
//! neighbour (an isolated sample, a thin pole) gets the isotropic footprint of a source pixel at
//! its depth: `depth / f_source * f_target / z_target` target pixels a side.
//!
//! Soft z-buffer: per target pixel, the points whose depth is within `surface_tolerance` of the
//! nearest one are averaged with tent weights (nearest the point's centre weighs most); a point
//! nearer than that resets the pixel, a farther one is dropped. Averaging the front surface gives
//! anti-aliased colour when the target is smaller than the source, and interpolated depth when it
//! is larger; the tolerance keeps a background surface out of a pixel a nearer surface covers
//! (the job of FreeVS's 5x5 "occupied territory" around foreground points, which dense footprints
//! do here without widening objects).
//!
//! Everything runs in source-row order on one thread, so the output is the same bytes whatever the
//! thread count (tasks run in parallel instead), and whatever the CPU: the per-row loops are
//! written to vectorise (a second build for AVX2 where the CPU has it), and vector lanes do the
//! scalar code's operations in its order.
//!
//! Per source row: project it (one array per quantity), work out every point's footprint in
//! vectorised loops (for a footprint of one target pixel, the common case when the target is
//! smaller than the source, also its pixel, weight and depth), then draw the points in order.
//! A 1600x900 frame into a 768x448 view takes about 10 ms on one core with AVX2, 26 ms without
//! (benches/novel_view.rs; 30 ms before the row loops were vectorised).

use anyhow::{ensure, Context, Result};
use dist4d_types::artifact::{Calibration, Pose};
use dist4d_types::geometry::Se3;
use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

/// A pinhole camera placed in the world: intrinsics, image size and camera-to-world pose
/// (x right, y down, z forward; pixel (i, j) covers [i, i+1) x [j, j+1)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PinholeView {
    pub k: [[f64; 3]; 3],
    pub width: u32,
    pub height: u32,
    pub world_from_cam: Se3,
}

impl PinholeView {
    /// The camera of `calib` on the ego vehicle at `pose`.
    pub fn new(calib: &Calibration, pose: &Pose) -> Result<PinholeView> {
        let k = calib.intrinsics.context("the camera calibration has no intrinsics")?;
        ensure!(
            k[2] == [0.0, 0.0, 1.0] && k[0][0] > 0.0 && k[1][1] > 0.0 && k[1][0] == 0.0,
            "the camera calibration's intrinsics are not a pinhole camera matrix: {k:?}"
        );
        ensure!(calib.width > 0 && calib.height > 0, "the camera calibration has an empty image size");
        Ok(PinholeView {
            k,
            width: calib.width,
            height: calib.height,
            world_from_cam: pose.ego_to_world.then_from(&calib.sensor_to_ego),
        })
    }

    /// The same camera with its image resized to `width` x `height`: the intrinsics scale with the
    /// image (fx, skew and cx by width'/width; fy and cy by height'/height: with pixel (i, j)
    /// covering [i, i+1) x [j, j+1), the principal point scales like any other image point). An
    /// aspect change (1600x900 -> 768x448) makes the pixels slightly non-square, as the image's.
    pub fn resized(&self, width: u32, height: u32) -> PinholeView {
        let (sx, sy) = (width as f64 / self.width as f64, height as f64 / self.height as f64);
        let k = self.k;
        PinholeView {
            k: [[k[0][0] * sx, k[0][1] * sx, k[0][2] * sx], [0.0, k[1][1] * sy, k[1][2] * sy], [0.0, 0.0, 1.0]],
            width,
            height,
            ..*self
        }
    }

    /// The inverse of the intrinsics (K is upper triangular with a last row of 0 0 1).
    fn k_inverse(&self) -> DMat3 {
        let k = self.k;
        DMat3::from_cols_array_2d(&[[k[0][0], 0.0, 0.0], [k[0][1], k[1][1], 0.0], [k[0][2], k[1][2], 1.0]]).inverse()
    }

    fn k_matrix(&self) -> DMat3 {
        let k = self.k;
        DMat3::from_cols_array_2d(&[[k[0][0], 0.0, 0.0], [k[0][1], k[1][1], 0.0], [k[0][2], k[1][2], 1.0]])
    }

    /// Pixel coordinates and depth of a camera-frame point.
    pub fn project(&self, c: DVec3) -> (f64, f64, f64) {
        let k = self.k;
        ((k[0][0] * c.x + k[0][1] * c.y) / c.z + k[0][2], k[1][1] * c.y / c.z + k[1][2], c.z)
    }
}

/// How points become target pixels (see the module doc).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SplatParams {
    /// Points within this fraction of a pixel's nearest depth are the same surface and averaged.
    pub surface_tolerance: f32,
    /// Grid neighbours whose source depths differ by more than this fraction are on different
    /// surfaces: the footprint does not reach across to them.
    pub edge_tolerance: f32,
    /// The largest footprint half-size (target pixels): a surface seen edge-on in the source and
    /// face-on in the target would otherwise paint a long streak.
    pub max_splat_px: f32,
    /// Source depths beyond this (metres) are not projected (the curated sky sits at 100 m; set
    /// 99 to leave the sky out of the condition).
    pub max_depth: f32,
    /// Points nearer the target camera than this (metres) are not drawn.
    pub near: f32,
}

impl Default for SplatParams {
    fn default() -> Self {
        SplatParams { surface_tolerance: 0.02, edge_tolerance: 0.05, max_splat_px: 8.0, max_depth: 1000.0, near: 0.1 }
    }
}

impl SplatParams {
    /// Range checks, added to the stage's own.
    pub fn check(&self, checks: &mut dist4d_graph::ParamChecks) {
        checks
            .within("surface_tolerance", self.surface_tolerance as f64, 0.0, 1.0)
            .within("edge_tolerance", self.edge_tolerance as f64, 0.0, 10.0)
            .within("max_splat_px", self.max_splat_px as f64, 0.5, 64.0)
            .above("max_depth", self.max_depth as f64, 0.0, 1e7)
            .above("near", self.near as f64, 0.0, 1e3);
    }
}

/// One source: an RGB8 image and its depth (metres along the optical axis, 0 or non-finite =
/// none), seen by `view`.
pub struct RgbdView<'a> {
    pub rgb: &'a [u8],
    pub depth: &'a [f32],
    pub view: &'a PinholeView,
}

/// The sources drawn into the target camera.
#[derive(Clone, Debug, PartialEq)]
pub struct Reprojected {
    pub width: u32,
    pub height: u32,
    /// RGB8, black where no point landed.
    pub rgb: Vec<u8>,
    /// Metres along the target's optical axis, 0 where no point landed.
    pub depth: Vec<f32>,
    /// 1 where a point landed.
    pub valid: Vec<u8>,
}

/// One point as drawn: where it lands, its inverse depth and that quantity's slope across the
/// target image, its footprint's half-sizes and its colour.
#[derive(Clone, Copy)]
struct Splat {
    u: f32,
    v: f32,
    iz: f32,
    gu: f32,
    gv: f32,
    hx: f32,
    hy: f32,
    rgb: [f32; 3],
}

/// The pixels a footprint of half-size `h` centred at `c` covers along one axis: the first and
/// last whose centres it reaches, clipped to `0..size` (first > last when none). As floats: they
/// are whole numbers, and the weights and depths are computed from them as floats.
#[inline(always)]
fn covered(c: f32, h: f32, size: f32) -> (f32, f32) {
    (max((c - h - 0.5).ceil(), 0.0), min((c + h - 0.5).floor(), size - 1.0))
}

/// The tent weight, along one axis, of a pixel centre `d` from the centre of a footprint of
/// half-size `h`.
#[inline(always)]
fn tent(d: f32, h: f32) -> f32 {
    h + 0.5 - d.abs()
}

/// The depth (dx, dy) pixels from a point of inverse depth `iz` whose slope is (`gu`, `gv`): the
/// inverse depth of a plane is affine in the image, so this is exact on planes, where the point's
/// own depth would be off by its distance from the pixel centre (1-2% on a road seen at a grazing
/// angle). The slope may only refine the depth, never flip it (a bad fit near an edge).
#[inline(always)]
fn depth_at(iz: f32, gu: f32, gv: f32, dx: f32, dy: f32) -> f32 {
    let at = iz + gu * dx + gv * dy;
    1.0 / if (at > 0.5 * iz) & (at < 2.0 * iz) { at } else { iz }
}

/// The smaller of two numbers that are not NaN: one instruction, where `f32::min`'s NaN rules
/// cost three and tip the vectoriser's cost model against the row loops.
#[inline(always)]
fn min(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// The larger of two numbers that are not NaN (see [`min`]).
#[inline(always)]
fn max(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// The soft z-buffer: per pixel the front depth and the weighted sums of the front surface.
struct Accumulator {
    width: usize,
    height: usize,
    /// `[front depth, weight, r, g, b, depth]` per pixel; weight 0 = empty.
    cells: Vec<[f32; 6]>,
    tolerance: f32,
}

impl Accumulator {
    /// Adds a point's weight `w` at depth `z` to cell `i`: a point nearer than the tolerance
    /// resets the cell, one within it joins the front surface, a farther one is dropped.
    #[inline]
    fn add(&mut self, i: usize, w: f32, z: f32, rgb: [f32; 3]) {
        let c = &mut self.cells[i];
        if c[1] == 0.0 || z < c[0] * (1.0 - self.tolerance) {
            *c = [z, w, w * rgb[0], w * rgb[1], w * rgb[2], w * z];
        } else if z <= c[0] * (1.0 + self.tolerance) {
            c[0] = c[0].min(z);
            c[1] += w;
            c[2] += w * rgb[0];
            c[3] += w * rgb[1];
            c[4] += w * rgb[2];
            c[5] += w * z;
        }
    }

    /// Splats a point at continuous pixel (u, v) over the box of half-sizes (hx, hy), with tent
    /// weights and the depth of [`depth_at`] at each covered pixel centre. (Footprints of one
    /// pixel, the common case, are worked out in [`footprints`] and only [`Accumulator::add`]ed.)
    fn splat(&mut self, p: &Splat) {
        let Splat { u, v, iz, gu, gv, hx, hy, rgb } = *p;
        let (x0, x1) = covered(u, hx, self.width as f32);
        let (y0, y1) = covered(v, hy, self.height as f32);
        let mut y = y0;
        while y <= y1 {
            let dy = y + 0.5 - v;
            let wy = tent(dy, hy);
            let row = y as usize * self.width;
            let mut x = x0;
            while x <= x1 {
                let dx = x + 0.5 - u;
                self.add(row + x as usize, tent(dx, hx) * wy, depth_at(iz, gu, gv, dx, dy), rgb);
                x += 1.0;
            }
            y += 1.0;
        }
    }

    fn finish(self) -> Reprojected {
        let n = self.width * self.height;
        let (mut rgb, mut depth, mut valid) = (vec![0u8; 3 * n], vec![0f32; n], vec![0u8; n]);
        for (i, c) in self.cells.iter().enumerate() {
            if c[1] > 0.0 {
                let inv = 1.0 / c[1];
                for k in 0..3 {
                    rgb[3 * i + k] = (c[2 + k] * inv).round().clamp(0.0, 255.0) as u8;
                }
                depth[i] = c[5] * inv;
                valid[i] = 1;
            }
        }
        Reprojected { width: self.width as u32, height: self.height as u32, rgb, depth, valid }
    }
}

/// Whether to run the row loops' AVX2 builds (see [`footprints`]).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn has_avx2() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}

/// A source row projected into the target, one array per quantity so that the loops over a row
/// vectorise, with an empty pixel at each end so that the first and last pixels' neighbours need
/// no test: pixel x of the row is entry x + 1.
struct ProjectedRow {
    u: Vec<f32>,
    v: Vec<f32>,
    /// Target depth and its inverse (stored: each point reads its neighbours' several times).
    z: Vec<f32>,
    iz: Vec<f32>,
    /// Source depth, 0 where the pixel draws nothing, and its inverse (0 there too).
    d: Vec<f32>,
    id: Vec<f32>,
}

/// A run of a [`ProjectedRow`] (see [`ProjectedRow::window`]).
struct RowWindow<'a> {
    u: &'a [f32],
    v: &'a [f32],
    z: &'a [f32],
    iz: &'a [f32],
    d: &'a [f32],
    id: &'a [f32],
}

impl ProjectedRow {
    fn new(w: usize) -> ProjectedRow {
        let zeros = || vec![0.0; w + 2];
        ProjectedRow { u: zeros(), v: zeros(), z: zeros(), iz: zeros(), d: zeros(), id: zeros() }
    }

    /// Entries `shift..shift + n`: with `shift` 0, 1 or 2, each pixel's left neighbour, itself
    /// or its right neighbour.
    #[inline(always)]
    fn window(&self, shift: usize, n: usize) -> RowWindow<'_> {
        let r = shift..shift + n;
        RowWindow {
            u: &self.u[r.clone()],
            v: &self.v[r.clone()],
            z: &self.z[r.clone()],
            iz: &self.iz[r.clone()],
            d: &self.d[r.clone()],
            id: &self.id[r],
        }
    }

    /// The row below the image: nothing drawn.
    fn clear(&mut self) {
        for a in [&mut self.u, &mut self.v, &mut self.z, &mut self.iz, &mut self.d, &mut self.id] {
            a.fill(0.0);
        }
    }
}

/// How a source camera's pixels move into the target camera.
struct Projection {
    /// A source pixel centre q = (x, y, 1) at depth d is the target-frame point d M q + t, at
    /// pixel (d K_t M q + K_t t) / its z.
    m: DMat3,
    km: DMat3,
    t: DVec3,
    kt: DVec3,
    max_depth: f32,
    near: f64,
}

impl Projection {
    /// Projects source row `y` (its depths `depth`) into `out`.
    fn row(&self, y: usize, depth: &[f32], out: &mut ProjectedRow) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has AVX2.
            return unsafe { self.row_avx2(y, depth, out) };
        }
        self.row_portable(y, depth, out)
    }

    /// [`Projection::row`] built for AVX2 (see [`footprints`]).
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn row_avx2(&self, y: usize, depth: &[f32], out: &mut ProjectedRow) {
        self.row_portable(y, depth, out)
    }

    /// Branch-free (a pixel that draws nothing is computed, then zeroed) so that it vectorises.
    #[inline(always)]
    fn row_portable(&self, y: usize, depth: &[f32], out: &mut ProjectedRow) {
        let yc = y as f64 + 0.5;
        // Per row: the projection of (0, y, 1); each column adds x times the first column.
        let base = self.km * DVec3::new(0.0, yc, 1.0);
        let step = self.km.x_axis;
        let zbase = (self.m * DVec3::new(0.0, yc, 1.0)).z;
        let zstep = self.m.x_axis.z;
        let (t, kt, max_depth, near) = (self.t, self.kt, self.max_depth, self.near);
        let n = depth.len();
        let (u, v, z_out, iz, d_out, id) = (
            &mut out.u[1..n + 1],
            &mut out.v[1..n + 1],
            &mut out.z[1..n + 1],
            &mut out.iz[1..n + 1],
            &mut out.d[1..n + 1],
            &mut out.id[1..n + 1],
        );
        for x in 0..n {
            let d = depth[x];
            // Through i32: SSE converts signed integers to floats in vectors, not unsigned ones.
            let xc = x as i32 as f64 + 0.5;
            let d64 = d as f64;
            // The target depth, z = (d M q + t).z, is also the third coordinate of the target's
            // homogeneous pixel (K_t's last row is 0 0 1), to the bit.
            let z = d64 * (zbase + xc * zstep) + t.z;
            let hx = d64 * (base.x + xc * step.x) + kt.x;
            let hy = d64 * (base.y + xc * step.y) + kt.y;
            let drawn = (d > 0.0) & (d <= max_depth) & (z > near);
            let keep = |value: f32| if drawn { value } else { 0.0 };
            u[x] = keep((hx / z) as f32);
            v[x] = keep((hy / z) as f32);
            z_out[x] = keep(z as f32);
            d_out[x] = keep(d);
        }
        // The inverses in a loop of their own: all f32, it vectorises where the f64 one may not.
        for x in 0..n {
            let drawn = d_out[x] != 0.0;
            iz[x] = if drawn { 1.0 / z_out[x] } else { 0.0 };
            id[x] = if drawn { 1.0 / d_out[x] } else { 0.0 };
        }
    }
}

/// What [`footprints`] needs besides the rows.
struct FootprintParams {
    edge_tolerance: f32,
    max_splat_px: f32,
    /// Target over source focal length (geometric means).
    focal_ratio: f32,
    /// The target image's size.
    width: u32,
    height: u32,
}

/// The footprints of a row's points.
struct Footprints {
    /// Half-sizes and the inverse depth's slope (see [`Splat`]).
    hx: Vec<f32>,
    hy: Vec<f32>,
    gu: Vec<f32>,
    gv: Vec<f32>,
    /// The target pixel (row-major index) of a footprint that covers exactly one, with the
    /// point's weight and depth there; [`SEVERAL`] for the others, [`NOTHING`] for a pixel
    /// that draws nothing.
    pixel: Vec<u32>,
    weight: Vec<f32>,
    depth: Vec<f32>,
}

/// [`Footprints::pixel`] of a footprint that covers more than one pixel, or none.
const SEVERAL: u32 = u32::MAX;
/// [`Footprints::pixel`] of a source pixel that draws nothing.
const NOTHING: u32 = u32::MAX - 1;

/// A whole number in 0..2^23 as an integer, read from its bits: adding 2^23 leaves it in the
/// mantissa's low bits. Where `as` (which saturates) is done lane by lane by the vectoriser, this
/// is an add and a subtract on all lanes at once. (Garbage, not a panic, for other numbers.)
#[inline(always)]
fn whole_to_u32(f: f32) -> u32 {
    const TWO_TO_23: f32 = 8_388_608.0;
    (f + TWO_TO_23).to_bits().wrapping_sub(TWO_TO_23.to_bits())
}

impl Footprints {
    fn new(w: usize) -> Footprints {
        let zeros = || vec![0.0; w];
        Footprints {
            hx: zeros(),
            hy: zeros(),
            gu: zeros(),
            gv: zeros(),
            pixel: vec![SEVERAL; w],
            weight: zeros(),
            depth: zeros(),
        }
    }
}

/// Whether neighbour `n` (with `o` opposite it, both as (source depth, its inverse)) lies on the
/// surface of the point of source depth `d`: their depths are within the edge tolerance, or the
/// inverse depth goes on through the three at the same slope (10%). A plane's inverse depth is
/// affine in the image, so a road seen at a grazing angle, whose depth grows by more than the
/// tolerance from one row to the next, is still one surface, and a depth edge is not. Written
/// with `&` and `|` (no early returns) so that the row loop vectorises.
#[inline(always)]
fn same_surface(d: f32, id: f32, n: (f32, f32), o: (f32, f32), edge: f32) -> bool {
    let (a, b) = (n.1 - id, id - o.1);
    (n.0 != 0.0) & (((n.0 - d).abs() <= edge * d) | ((o.0 != 0.0) & ((a - b).abs() <= 0.1 * max(a.abs(), b.abs()))))
}

/// Footprints of row `cur` (with the rows above and below) into `out`: half the distance to the
/// same-surface grid neighbours, or a source pixel's isotropic size for an isolated point, and
/// the inverse depth's slope fitted through a same-surface neighbour along the row and one along
/// the column; for a footprint of one target pixel (most of them when the target is smaller than
/// the source), that pixel, weight and depth, so that drawing it is one [`Accumulator::add`].
///
/// Every quantity is computed for every pixel and the cases are selects, so that the loop
/// vectorises; the selects give the same numbers as the branches they replace, and the lanes do
/// the scalar code's operations in its order (Rust fuses no multiply-adds), so the output is the
/// same bits with or without vectors. The loop vectoriser judges 4 SSE lanes not worth it and 8
/// AVX2 lanes well worth it (a 1600x900 frame: 16 ms scalar, 3.6 ms in AVX2), so where the CPU
/// has AVX2 the loops run from a second build for it (as `stereo::kernels` does).
fn footprints(up: &ProjectedRow, cur: &ProjectedRow, down: &ProjectedRow, fp: &FootprintParams, out: &mut Footprints) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU has AVX2.
        return unsafe { footprints_avx2(up, cur, down, fp, out) };
    }
    footprints_portable(up, cur, down, fp, out)
}

/// [`footprints`] built for AVX2.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn footprints_avx2(
    up: &ProjectedRow,
    cur: &ProjectedRow,
    down: &ProjectedRow,
    fp: &FootprintParams,
    out: &mut Footprints,
) {
    footprints_portable(up, cur, down, fp, out)
}

#[inline(always)]
fn footprints_portable(
    up: &ProjectedRow,
    cur: &ProjectedRow,
    down: &ProjectedRow,
    fp: &FootprintParams,
    out: &mut Footprints,
) {
    let n = out.hx.len();
    let (edge, max_h, focal_ratio) = (fp.edge_tolerance, fp.max_splat_px, fp.focal_ratio);
    let (width, height, stride) = (fp.width as f32, fp.height as f32, fp.width);
    // The point, its left and right, up and down neighbours: slices of exactly n entries.
    let (p, l, r, t, b) = (cur.window(1, n), cur.window(0, n), cur.window(2, n), up.window(1, n), down.window(1, n));
    let (hx_out, hy_out, gu_out, gv_out) = (&mut out.hx[..n], &mut out.hy[..n], &mut out.gu[..n], &mut out.gv[..n]);
    for x in 0..n {
        let (pu, pv, piz, pd, pid) = (p.u[x], p.v[x], p.iz[x], p.d[x], p.id[x]);
        let (lu, lv, liz, ld, lid) = (l.u[x], l.v[x], l.iz[x], l.d[x], l.id[x]);
        let (ru, rv, riz, rd, rid) = (r.u[x], r.v[x], r.iz[x], r.d[x], r.id[x]);
        let (tu, tv, tiz, td, tid) = (t.u[x], t.v[x], t.iz[x], t.d[x], t.id[x]);
        let (bu, bv, biz, bd, bid) = (b.u[x], b.v[x], b.iz[x], b.d[x], b.id[x]);
        let same_left = same_surface(pd, pid, (ld, lid), (rd, rid), edge);
        let same_right = same_surface(pd, pid, (rd, rid), (ld, lid), edge);
        let same_up = same_surface(pd, pid, (td, tid), (bd, bid), edge);
        let same_down = same_surface(pd, pid, (bd, bid), (td, tid), edge);
        // Half-sizes: the farthest same-surface neighbour along each axis (0 for the others).
        let reach = |linked: bool, delta: f32| if linked { delta.abs() } else { 0.0 };
        let hx = max(
            max(reach(same_left, lu - pu), reach(same_right, ru - pu)),
            max(reach(same_up, tu - pu), reach(same_down, bu - pu)),
        );
        let hy = max(
            max(reach(same_left, lv - pv), reach(same_right, rv - pv)),
            max(reach(same_up, tv - pv), reach(same_down, bv - pv)),
        );
        // The slope: solve [du dv] g = d(1/z) for a neighbour along the row (right first) and
        // one along the column (down first).
        let (au, av, ai) = if same_right { (ru - pu, rv - pv, riz - piz) } else { (lu - pu, lv - pv, liz - piz) };
        let (cu, cv, ci) = if same_down { (bu - pu, bv - pv, biz - piz) } else { (tu - pu, tv - pv, tiz - piz) };
        let det = au * cv - av * cu;
        let fitted = (same_right | same_left) & (same_down | same_up) & (det.abs() > 1e-3);
        let gu = if fitted { (ai * cv - ci * av) / det } else { 0.0 };
        let gv = if fitted { (au * ci - cu * ai) / det } else { 0.0 };
        let linked = same_left | same_right | same_up | same_down;
        // An isolated point: a source pixel's size at its depth, (d / f_s) * (f_t / z_t).
        let isotropic = 0.5 * pd * focal_ratio / p.z[x];
        // max-min rather than clamp, whose check that 0.5 <= max_h would stop the vectoriser.
        let hx = min(max(if linked { hx * 0.5 } else { isotropic }, 0.5), max_h);
        let hy = min(max(if linked { hy * 0.5 } else { isotropic }, 0.5), max_h);
        (hx_out[x], hy_out[x], gu_out[x], gv_out[x]) = (hx, hy, gu, gv);
    }
    // A second loop: in the first, the vectoriser would have to check 7 outputs against 25
    // inputs for overlap, and gives up.
    let (hx, hy, gu, gv) = (&out.hx[..n], &out.hy[..n], &out.gu[..n], &out.gv[..n]);
    let (pixel, weight, depth) = (&mut out.pixel[..n], &mut out.weight[..n], &mut out.depth[..n]);
    for x in 0..n {
        // One target pixel: what Accumulator::splat would add there.
        let (pu, pv, piz) = (p.u[x], p.v[x], p.iz[x]);
        let (x0, x1) = covered(pu, hx[x], width);
        let (y0, y1) = covered(pv, hy[x], height);
        let (dx, dy) = (x0 + 0.5 - pu, y0 + 0.5 - pv);
        let one = (x0 == x1) & (y0 == y1);
        let index = whole_to_u32(y0).wrapping_mul(stride).wrapping_add(whole_to_u32(x0));
        pixel[x] = if p.d[x] == 0.0 {
            NOTHING
        } else if one {
            index
        } else {
            SEVERAL
        };
        weight[x] = tent(dx, hx[x]) * tent(dy, hy[x]);
        depth[x] = depth_at(piz, gu[x], gv[x], dx, dy);
    }
}

/// Draws `sources` into `target`, in order (see the module doc).
pub fn reproject(sources: &[RgbdView], target: &PinholeView, params: &SplatParams) -> Result<Reprojected> {
    ensure!(target.width > 0 && target.height > 0, "the target camera has an empty image size");
    // Pixel coordinates become integers by their bits (see `whole_to_u32`), indices are u32.
    ensure!(
        target.width < 1 << 23
            && target.height < 1 << 23
            && (target.width as u64 * target.height as u64) < NOTHING as u64,
        "the target camera's image ({}x{}) is too large to draw into",
        target.width,
        target.height
    );
    let mut acc = Accumulator {
        width: target.width as usize,
        height: target.height as usize,
        cells: vec![[0.0; 6]; target.width as usize * target.height as usize],
        tolerance: params.surface_tolerance,
    };
    for (i, src) in sources.iter().enumerate() {
        draw(&mut acc, src, target, params).with_context(|| format!("source {i}"))?;
    }
    Ok(acc.finish())
}

fn draw(acc: &mut Accumulator, src: &RgbdView, target: &PinholeView, params: &SplatParams) -> Result<()> {
    let (w, h) = (src.view.width as usize, src.view.height as usize);
    ensure!(
        src.depth.len() == w * h && src.rgb.len() == 3 * w * h,
        "the image ({} bytes) and depth ({} values) are not {w}x{h} as the camera says",
        src.rgb.len(),
        src.depth.len()
    );
    let t_from_s = target.world_from_cam.inverse().then_from(&src.view.world_from_cam);
    let m = t_from_s.matrix() * src.view.k_inverse();
    let projection = Projection {
        m,
        km: target.k_matrix() * m,
        t: t_from_s.translation,
        kt: target.k_matrix() * t_from_s.translation,
        max_depth: params.max_depth,
        near: params.near as f64,
    };
    let fp = FootprintParams {
        edge_tolerance: params.edge_tolerance,
        max_splat_px: params.max_splat_px,
        // The isotropic footprint of a source pixel: (d / f_s) * (f_t / z_t), with the focal
        // lengths' geometric means (pixels may be slightly non-square after a resize).
        focal_ratio: ((target.k[0][0] * target.k[1][1]) / (src.view.k[0][0] * src.view.k[1][1])).sqrt() as f32,
        width: target.width,
        height: target.height,
    };
    // Only the rows between the first and the last pixel with a depth: a piece of a source (one
    // moving object, see `moving`) is mostly empty, and its empty rows draw nothing.
    let Some(first) = src.depth.iter().position(|&d| d > 0.0) else { return Ok(()) };
    let last = src.depth.iter().rposition(|&d| d > 0.0).unwrap_or(first);
    let (y0, y_end) = (first / w, last / w + 1);
    // rows[0] = y - 1, rows[1] = y, rows[2] = y + 1 (all empty beyond the drawn rows, which
    // hold no depth).
    let mut rows: [ProjectedRow; 3] = std::array::from_fn(|_| ProjectedRow::new(w));
    let mut feet = Footprints::new(w);
    projection.row(y0, &src.depth[y0 * w..(y0 + 1) * w], &mut rows[1]);
    for y in y0..y_end {
        if y + 1 < y_end {
            projection.row(y + 1, &src.depth[(y + 1) * w..(y + 2) * w], &mut rows[2]);
        } else {
            rows[2].clear();
        }
        footprints(&rows[0], &rows[1], &rows[2], &fp, &mut feet);
        let cur = rows[1].window(1, w);
        let rgb_row = &src.rgb[3 * y * w..3 * (y + 1) * w];
        // Slices of exactly w entries: no bounds checks in the loop.
        let (pixel, weight, depth) = (&feet.pixel[..w], &feet.weight[..w], &feet.depth[..w]);
        for (x, rgb) in rgb_row.chunks_exact(3).enumerate() {
            let rgb = [rgb[0], rgb[1], rgb[2]].map(f32::from);
            match pixel[x] {
                NOTHING => {}
                SEVERAL => acc.splat(&Splat {
                    u: cur.u[x],
                    v: cur.v[x],
                    iz: cur.iz[x],
                    gu: feet.gu[x],
                    gv: feet.gv[x],
                    hx: feet.hx[x],
                    hy: feet.hy[x],
                    rgb,
                }),
                i => acc.add(i as usize, weight[x], depth[x], rgb),
            }
        }
        rows.rotate_left(1);
    }
    Ok(())
}

/// Draws the sky of `sources` (each an image and a depth map holding the sky's fill value where
/// it is the sky, 0 elsewhere) into the pixels of `surfaces` that nothing landed on, at depth
/// `sky_depth`. The sky is a direction, not a surface (see [`crate::lift`]): it is drawn as seen
/// from the target camera's centre, each source turned as it is but not moved, so that it does
/// not come nearer as the camera moves.
pub fn draw_sky(
    surfaces: &mut Reprojected,
    sources: &[RgbdView],
    target: &PinholeView,
    params: &SplatParams,
    sky_depth: f32,
) -> Result<()> {
    let at_target: Vec<PinholeView> = sources
        .iter()
        .map(|s| {
            let mut v = *s.view;
            v.world_from_cam.translation = target.world_from_cam.translation;
            v
        })
        .collect();
    let views: Vec<RgbdView> =
        sources.iter().zip(&at_target).map(|(s, v)| RgbdView { rgb: s.rgb, depth: s.depth, view: v }).collect();
    let sky = reproject(&views, target, &SplatParams { max_depth: f32::MAX, ..params.clone() })?;
    for px in 0..surfaces.valid.len() {
        if surfaces.valid[px] == 0 && sky.valid[px] != 0 {
            surfaces.rgb[3 * px..3 * px + 3].copy_from_slice(&sky.rgb[3 * px..3 * px + 3]);
            surfaces.depth[px] = sky_depth;
            surfaces.valid[px] = 1;
        }
    }
    Ok(())
}

/// A source's depth split for drawing: its surface pixels as [`crate::lift::surface_only`] keeps
/// them (the rest 0) and its sky (the fill value where the depth is the sky, the rest 0).
pub fn lift_source(
    depth: &[f32],
    view: &PinholeView,
    support: Option<&[f32]>,
    lift: &crate::lift::LiftParams,
) -> (Vec<f32>, Vec<f32>) {
    let (w, h) = (view.width as usize, view.height as usize);
    let surface = crate::lift::surface_only(depth, w, h, crate::lift::focal_of(&view.k), support, lift);
    let sky = depth.iter().map(|&z| if lift.is_sky(z) && z.is_finite() { z } else { 0.0 }).collect();
    (surface, sky)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(w: u32, h: u32, f: f64, world_from_cam: Se3) -> PinholeView {
        PinholeView {
            k: [[f, 0.0, w as f64 / 2.0], [0.0, f, h as f64 / 2.0], [0.0, 0.0, 1.0]],
            width: w,
            height: h,
            world_from_cam,
        }
    }

    /// A camera looking along world +z from `x` (camera frame = world frame, shifted).
    fn at(x: f64, w: u32, h: u32, f: f64) -> PinholeView {
        view(w, h, f, Se3::from_yaw(0.0, DVec3::new(x, 0.0, 0.0)))
    }

    #[test]
    fn a_plane_seen_from_a_shifted_camera_keeps_its_depth_and_leaves_no_gaps() {
        // A fronto-parallel wall at 10 m with a colour ramp, seen from 1 m to the right and
        // magnified (the target's focal length doubled): every target pixel that sees the wall is
        // covered, at 10 m.
        let (w, h) = (64u32, 48u32);
        let src = at(0.0, w, h, 50.0);
        let depth = vec![10.0f32; (w * h) as usize];
        let rgb: Vec<u8> = (0..w * h).flat_map(|i| [(i % w * 4) as u8, (i / w * 5) as u8, 7]).collect();
        let tgt = at(1.0, w, h, 100.0);
        let out =
            reproject(&[RgbdView { rgb: &rgb, depth: &depth, view: &src }], &tgt, &SplatParams::default()).unwrap();
        // The wall spans source x in [-6.4, 6.4] m: in the target, u = 100 * (X - 1) / 10 + 32.
        for y in 0..h as usize {
            for x in 0..w as usize {
                let u = x as f64 + 0.5;
                let wall_x = (u - 32.0) / 10.0 + 1.0;
                let v = y as f64 + 0.5;
                let wall_y = (v - 24.0) / 10.0;
                let inside = wall_x.abs() < 6.3 && wall_y.abs() < 4.7;
                let i = y * w as usize + x;
                if inside {
                    assert_eq!(out.valid[i], 1, "hole at ({x}, {y})");
                    assert!((out.depth[i] - 10.0).abs() < 1e-4, "{}", out.depth[i]);
                    // The colour ramp is continuous: red = 4 * source column.
                    let src_col = wall_x * 5.0 + 32.0;
                    assert!(
                        (out.rgb[3 * i] as f64 - 4.0 * (src_col - 0.5)).abs() < 4.0,
                        "({x},{y}) {}",
                        out.rgb[3 * i]
                    );
                }
                if wall_x.abs() > 6.5 || wall_y.abs() > 4.9 {
                    assert_eq!(out.valid[i], 0, "({x}, {y}) outside the wall");
                }
            }
        }
    }

    #[test]
    fn a_nearer_surface_hides_the_one_behind_and_a_disocclusion_stays_a_hole() {
        // A wall at 20 m and a 2 m wide board at 5 m in front of it, seen from 0.5 m to the left:
        // the board moves right more than the wall, uncovering wall the source never saw.
        let (w, h) = (80u32, 40u32);
        let f = 40.0;
        let src = at(0.0, w, h, f);
        let mut depth = vec![20.0f32; (w * h) as usize];
        let mut rgb = vec![100u8; 3 * (w * h) as usize];
        for y in 0..h as usize {
            for x in 0..w as usize {
                let xw = (x as f64 + 0.5 - 40.0) / f * 5.0;
                if xw.abs() < 1.0 {
                    depth[y * w as usize + x] = 5.0;
                    rgb[3 * (y * w as usize + x)] = 250;
                }
            }
        }
        let tgt = at(-0.5, w, h, f);
        let out =
            reproject(&[RgbdView { rgb: &rgb, depth: &depth, view: &src }], &tgt, &SplatParams::default()).unwrap();
        let row = 20usize;
        let at_col = |x: usize| (out.valid[row * 80 + x], out.depth[row * 80 + x], out.rgb[3 * (row * 80 + x)]);
        // Board: world x in (-1, 1) at 5 m -> target u = 40 * (X + 0.5) / 5 + 40 in (36, 52).
        for x in 37..51 {
            let (valid, z, r) = at_col(x);
            assert!(valid == 1 && (z - 5.0).abs() < 1e-3 && r == 250, "board at {x}: {valid} {z} {r}");
        }
        // Wall the board hid in the source (world x in (-4, 4) at 20 m) and that the target sees:
        // left of the board, target u in (40 * (-4 + 0.5) / 20 + 40, 36) = (33, 36): a hole.
        for x in 33..36 {
            assert_eq!(at_col(x).0, 0, "disoccluded wall at {x} must stay a hole, got {:?}", at_col(x));
        }
        // The wall further out keeps its depth.
        let (valid, z, r) = at_col(10);
        assert!(valid == 1 && (z - 20.0).abs() < 1e-3 && r == 100);
    }

    #[test]
    fn resizing_scales_the_intrinsics_with_the_image() {
        let v = view(1600, 900, 1266.0, Se3::default()).resized(768, 448);
        let p = DVec3::new(2.0, -1.0, 10.0);
        let (u, vv, _) = view(1600, 900, 1266.0, Se3::default()).project(p);
        let (u2, v2, _) = v.project(p);
        assert!((u2 - u * 768.0 / 1600.0).abs() < 1e-9 && (v2 - vv * 448.0 / 900.0).abs() < 1e-9);
    }

    #[test]
    fn wrong_sizes_are_errors_not_panics() {
        let src = at(0.0, 4, 4, 2.0);
        let err = reproject(&[RgbdView { rgb: &[0; 3], depth: &[1.0; 16], view: &src }], &src, &SplatParams::default())
            .unwrap_err();
        assert!(format!("{err:#}").contains("not 4x4"), "{err:#}");
    }
}
