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
//! thread count (tasks run in parallel instead).

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

/// The soft z-buffer: per pixel the front depth and the weighted sums of the front surface.
struct Accumulator {
    width: usize,
    height: usize,
    /// `[front depth, weight, r, g, b, depth]` per pixel; weight 0 = empty.
    cells: Vec<[f32; 6]>,
    tolerance: f32,
}

impl Accumulator {
    #[inline]
    fn add(&mut self, x: usize, y: usize, w: f32, z: f32, rgb: [f32; 3]) {
        let c = &mut self.cells[y * self.width + x];
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

    /// Splats a point at continuous pixel (u, v) over the box of half-sizes (hx, hy). Its depth
    /// at each covered pixel centre comes from its inverse depth `iz` and that quantity's slope
    /// (`gu`, `gv` per target pixel): the inverse depth of a plane is affine in the image, so
    /// this is exact on planes, where the point's own depth would be off by its distance from the
    /// pixel centre (1-2% on a road seen at a grazing angle).
    #[inline]
    fn splat(&mut self, p: &Splat) {
        let Splat { u, v, iz, gu, gv, hx, hy, rgb } = *p;
        let x0 = (u - hx - 0.5).ceil().max(0.0);
        let x1 = (u + hx - 0.5).floor().min(self.width as f32 - 1.0);
        let y0 = (v - hy - 0.5).ceil().max(0.0);
        let y1 = (v + hy - 0.5).floor().min(self.height as f32 - 1.0);
        if x0 > x1 || y0 > y1 {
            return;
        }
        let (x0, x1, y0, y1) = (x0 as usize, x1 as usize, y0 as usize, y1 as usize);
        for y in y0..=y1 {
            let dy = y as f32 + 0.5 - v;
            let wy = hy + 0.5 - dy.abs();
            for x in x0..=x1 {
                let dx = x as f32 + 0.5 - u;
                let wx = hx + 0.5 - dx.abs();
                // The slope may only refine the depth, never flip it (a bad fit near an edge).
                let at = iz + gu * dx + gv * dy;
                let z = if at > 0.5 * iz && at < 2.0 * iz { 1.0 / at } else { 1.0 / iz };
                self.add(x, y, wx * wy, z, rgb);
            }
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

/// A source row projected into the target: per pixel (u, v, target depth, source depth); source
/// depth 0 where the pixel draws nothing.
type ProjectedRow = Vec<[f32; 4]>;

/// Draws `sources` into `target`, in order (see the module doc).
pub fn reproject(sources: &[RgbdView], target: &PinholeView, params: &SplatParams) -> Result<Reprojected> {
    ensure!(target.width > 0 && target.height > 0, "the target camera has an empty image size");
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
    // Target camera frame from the source camera frame; a source pixel centre q = (x, y, 1) at
    // depth d is the target-frame point d * M q + t, at pixel (K_t (d M q + t)) / its z.
    let t_from_s = target.world_from_cam.inverse().then_from(&src.view.world_from_cam);
    let m = t_from_s.matrix() * src.view.k_inverse();
    let km = target.k_matrix() * m;
    let kt = target.k_matrix() * t_from_s.translation;
    let t = t_from_s.translation;
    // The isotropic footprint of a source pixel: (d / f_s) * (f_t / z_t), with the focal lengths'
    // geometric means (pixels may be slightly non-square after a resize).
    let focal_ratio = ((target.k[0][0] * target.k[1][1]) / (src.view.k[0][0] * src.view.k[1][1])).sqrt() as f32;
    let max_depth = params.max_depth;
    let near = params.near as f64;
    let project_row = |y: usize, out: &mut ProjectedRow| {
        let yc = y as f64 + 0.5;
        // Per row: the projection of (0, y, 1); each column adds x times the first column.
        let base = km * DVec3::new(0.0, yc, 1.0);
        let step = km.x_axis;
        let zbase = (m * DVec3::new(0.0, yc, 1.0)).z;
        let zstep = m.x_axis.z;
        for (x, o) in out.iter_mut().enumerate() {
            let d = src.depth[y * w + x];
            *o = [0.0; 4];
            if !(d > 0.0 && d <= max_depth) {
                continue;
            }
            let xc = x as f64 + 0.5;
            let d64 = d as f64;
            let z = d64 * (zbase + xc * zstep) + t.z;
            if z <= near {
                continue;
            }
            let hx = d64 * (base.x + xc * step.x) + kt.x;
            let hy = d64 * (base.y + xc * step.y) + kt.y;
            let hz = d64 * (base.z + xc * step.z) + kt.z;
            *o = [(hx / hz) as f32, (hy / hz) as f32, z as f32, d];
        }
    };
    let mut rows: [ProjectedRow; 3] = [vec![[0.0; 4]; w], vec![[0.0; 4]; w], vec![[0.0; 4]; w]];
    if h > 0 {
        project_row(0, &mut rows[1]);
    }
    let edge = params.edge_tolerance;
    let max_h = params.max_splat_px;
    for y in 0..h {
        // rows[0] = y - 1, rows[1] = y, rows[2] = y + 1 (all zero beyond the image).
        if y + 1 < h {
            project_row(y + 1, &mut rows[2]);
        } else {
            rows[2].iter_mut().for_each(|p| *p = [0.0; 4]);
        }
        let (up, cur, down) = (&rows[0], &rows[1], &rows[2]);
        let rgb_row = &src.rgb[3 * y * w..3 * (y + 1) * w];
        for x in 0..w {
            let p = cur[x];
            let d = p[3];
            if d == 0.0 {
                continue;
            }
            let (mut hx, mut hy, mut linked) = (0f32, 0f32, false);
            let left = if x > 0 { cur[x - 1] } else { [0.0; 4] };
            let right = if x + 1 < w { cur[x + 1] } else { [0.0; 4] };
            // Neighbour `n` (with `o` opposite it) lies on this point's surface when their source
            // depths are within the edge tolerance, or when the inverse depth goes on through the
            // three at the same slope (10%): a plane's inverse depth is affine in the image, so a
            // road seen at a grazing angle, whose depth grows by more than the tolerance from
            // one row to the next, is still one surface, and a depth edge is not.
            let same = |n: [f32; 4], o: [f32; 4]| {
                if n[3] == 0.0 {
                    return false;
                }
                if (n[3] - d).abs() <= edge * d {
                    return true;
                }
                if o[3] == 0.0 {
                    return false;
                }
                let (a, b) = (1.0 / n[3] - 1.0 / d, 1.0 / d - 1.0 / o[3]);
                (a - b).abs() <= 0.1 * a.abs().max(b.abs())
            };
            let (same_left, same_right, same_up, same_down) =
                (same(left, right), same(right, left), same(up[x], down[x]), same(down[x], up[x]));
            for (n, linked_to) in [(left, same_left), (right, same_right), (up[x], same_up), (down[x], same_down)] {
                if linked_to {
                    hx = hx.max((n[0] - p[0]).abs());
                    hy = hy.max((n[1] - p[1]).abs());
                    linked = true;
                }
            }
            let iz = 1.0 / p[2];
            let (mut gu, mut gv) = (0.0, 0.0);
            let along_row = if same_right {
                Some(right)
            } else if same_left {
                Some(left)
            } else {
                None
            };
            let along_col = if same_down {
                Some(down[x])
            } else if same_up {
                Some(up[x])
            } else {
                None
            };
            if let (Some(a), Some(b)) = (along_row, along_col) {
                // Solve [du dv] g = d(1/z) for the two neighbours.
                let (au, av, ai) = (a[0] - p[0], a[1] - p[1], 1.0 / a[2] - iz);
                let (bu, bv, bi) = (b[0] - p[0], b[1] - p[1], 1.0 / b[2] - iz);
                let det = au * bv - av * bu;
                if det.abs() > 1e-3 {
                    gu = (ai * bv - bi * av) / det;
                    gv = (au * bi - bu * ai) / det;
                }
            }
            if linked {
                hx *= 0.5;
                hy *= 0.5;
            } else {
                hx = 0.5 * d * focal_ratio / p[2];
                hy = hx;
            }
            let rgb = [rgb_row[3 * x] as f32, rgb_row[3 * x + 1] as f32, rgb_row[3 * x + 2] as f32];
            acc.splat(&Splat { u: p[0], v: p[1], iz, gu, gv, hx: hx.clamp(0.5, max_h), hy: hy.clamp(0.5, max_h), rgb });
        }
        rows.rotate_left(1);
    }
    Ok(())
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
