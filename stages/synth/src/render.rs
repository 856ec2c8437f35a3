//! Ray casting the world at a moment in time: camera images with exact depth and semantics, and
//! LiDAR sweeps. This is the renderer API evaluation uses for novel views: any pose, any time.

use super::shapes::{Grid, Prim};
use crate::material::{class, Material};
use crate::world::{ego_body, World, LANE_WIDTH, ROAD_HALF_WIDTH};
use dist4d_types::geometry::Se3;
use dist4d_types::rng::{mix, Rng};
use glam::DVec3;
use rayon::prelude::*;

/// Camera rays go no further than this; the ground beyond is shown as sky (a haze horizon).
pub const MAX_CAMERA_RANGE: f64 = 1000.0;

/// The world frozen at one time: static and moving primitives binned in one grid, so a ray
/// walks the cells once.
pub struct Snapshot<'w> {
    world: &'w World,
    grid: Grid,
}

/// What a ray met, resolved to what the sensors need.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceHit {
    pub t: f64,
    pub point: DVec3,
    /// Unit normal facing the ray.
    pub normal: DVec3,
    pub class: u8,
    pub instance: u32,
    pub material: Surface,
}

#[derive(Clone, Copy, Debug)]
pub enum Surface {
    Ground { lane_marking: bool },
    Prim(Material),
}

/// A rendered camera image: RGB8, depth along the optical axis (+inf for sky), Cityscapes ids.
pub struct CameraImage {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
    pub depth: Vec<f32>,
    pub semantic: Vec<u8>,
}

/// A pinhole camera: intrinsics, size, and camera-to-world pose (x right, y down, z forward).
#[derive(Clone, Copy, Debug)]
pub struct PinholeCamera {
    pub k: [[f64; 3]; 3],
    pub width: u32,
    pub height: u32,
    pub camera_to_world: Se3,
}

impl<'w> Snapshot<'w> {
    /// The world at `t` seconds from the scene start.
    pub fn new(world: &'w World, t: f64) -> Snapshot<'w> {
        let mut prims = world.statics.clone();
        prims.extend(world.dynamic_prims(t));
        Snapshot { world, grid: Grid::build(prims, 4.0) }
    }

    /// Whether a surface of the world lies within `radius` of `p`: the ground plane (z = 0) by
    /// its distance, the primitives by rays of that length in the 26 directions of a cube's
    /// faces, edges and corners (so a plane is found up to ~0.89 `radius` away whatever its
    /// orientation, and up to `radius` when it faces one of them). A point inside a primitive
    /// counts as on it.
    pub fn near_surface(&self, p: DVec3, radius: f64) -> bool {
        if p.z.abs() <= radius {
            return true;
        }
        for i in -1i32..=1 {
            for j in -1i32..=1 {
                for k in -1i32..=1 {
                    if (i, j, k) == (0, 0, 0) {
                        continue;
                    }
                    let d = DVec3::new(i as f64, j as f64, k as f64).normalize();
                    if self.grid.cast(p, d, 0.0, radius).is_some() {
                        return true;
                    }
                }
            }
        }
        false
    }

    pub fn cast(&self, o: DVec3, d: DVec3, t_max: f64) -> Option<SurfaceHit> {
        let t_ground = if d.z < 0.0 && o.z > 0.0 { -o.z / d.z } else { f64::INFINITY };
        let limit = t_max.min(t_ground);
        if let Some((t, n, k)) = self.grid.cast(o, d, 1e-6, limit) {
            let p: &Prim = &self.grid.prims[k as usize];
            let normal = if n.dot(d) > 0.0 { -n } else { n };
            return Some(SurfaceHit {
                t,
                point: o + d * t,
                normal,
                class: p.class,
                instance: p.instance,
                material: Surface::Prim(p.material),
            });
        }
        if t_ground <= t_max {
            let point = o + d * t_ground;
            let (class, lane_marking) = match self.world.path.station(point.x, point.y) {
                Some((s, dd)) if dd.abs() <= ROAD_HALF_WIDTH => (class::ROAD, lane_marking(s, dd)),
                _ => (class::TERRAIN, false),
            };
            return Some(SurfaceHit {
                t: t_ground,
                point,
                normal: DVec3::Z,
                class,
                instance: 0,
                material: Surface::Ground { lane_marking },
            });
        }
        None
    }

    /// The exact semantic occupancy of a voxel grid around an ego pose: voxel (i, j, k) of
    /// `dims` (C order) spans `min + (i, j, k) * voxel` in the ego frame (`ego_to_world` places
    /// it in the world; the synthetic ego only turns about z). A voxel is occupied when it shares
    /// any volume with a primitive (exact tests, [`crate::shapes::Shape::overlaps_box`]) or reaches
    /// below the ground plane (z = 0). Its class (Cityscapes id) is the class of the primitive
    /// with the most of `samples`^3 points inside it (a primitive that shares only a sliver, no
    /// sample, still counts), else the ground's there (road within the road's half width of the
    /// path, terrain beyond). 0 = free. The ego vehicle's body is not in it (Occ3D leaves the ego
    /// out).
    pub fn occupancy(&self, ego_to_world: &Se3, min: DVec3, voxel: f64, dims: [usize; 3], samples: usize) -> Vec<u8> {
        let s = samples.max(1);
        let [nx, ny, nz] = dims;
        let offset = |a: usize| (a as f64 + 0.5) / s as f64 * voxel;
        let columns: Vec<Vec<u8>> = (0..nx * ny)
            .into_par_iter()
            .map(|c| {
                // A cancellation point per column: the caller turns a stop into an error and
                // discards the grid (see `dist4d_types::cancel`).
                if dist4d_types::cancel::requested() {
                    return vec![0u8; nz];
                }
                let (i, j) = (c / ny, c % ny);
                let corner = min + DVec3::new(i as f64 * voxel, j as f64 * voxel, 0.0);
                // The primitives that may reach the column: those binned where its corners are.
                let mut near: Vec<&Prim> = Vec::new();
                for (dx, dy) in [(0.0, 0.0), (voxel, 0.0), (0.0, voxel), (voxel, voxel)] {
                    let w = ego_to_world.apply(corner + DVec3::new(dx, dy, 0.0));
                    for p in self.grid.prims_at(w.x, w.y) {
                        if !near.iter().any(|q| std::ptr::eq(*q, p)) {
                            near.push(p);
                        }
                    }
                }
                let (yaw_cos, yaw_sin) = {
                    let x = ego_to_world.rotation * DVec3::X;
                    let n = (x.x * x.x + x.y * x.y).sqrt().max(1e-12);
                    (x.x / n, x.y / n)
                };
                let h = voxel / 2.0;
                let mut column = vec![0u8; nz];
                for (k, out) in column.iter_mut().enumerate() {
                    let centre = ego_to_world.apply(corner + DVec3::new(h, h, k as f64 * voxel + h));
                    let touching: Vec<&Prim> =
                        near.iter().copied().filter(|p| p.shape.overlaps_box(centre, h, yaw_cos, yaw_sin)).collect();
                    if !touching.is_empty() {
                        // The class of the primitive holding the most samples (the first on ties).
                        let mut counts = vec![0u32; touching.len()];
                        for a in 0..s {
                            for b in 0..s {
                                for d in 0..s {
                                    let e = corner + DVec3::new(offset(a), offset(b), k as f64 * voxel + offset(d));
                                    let w = ego_to_world.apply(e);
                                    if let Some(n) = touching.iter().position(|p| p.shape.contains(w)) {
                                        counts[n] += 1;
                                    }
                                }
                            }
                        }
                        let best = (0..touching.len()).max_by_key(|&n| (counts[n], std::cmp::Reverse(n))).unwrap_or(0);
                        *out = touching[best].class;
                    } else if centre.z - h < 0.0 {
                        *out = match self.world.path.station(centre.x, centre.y) {
                            Some((_, dd)) if dd.abs() <= ROAD_HALF_WIDTH => class::ROAD,
                            _ => class::TERRAIN,
                        };
                    }
                }
                column
            })
            .collect();
        columns.concat()
    }

    /// Renders one camera. Pixel (col, row) is the ray through image point (col + 0.5, row + 0.5),
    /// matching the floor() binning of projected points.
    pub fn render(&self, cam: &PinholeCamera) -> CameraImage {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let mut rgb = vec![0u8; w * h * 3];
        let mut depth = vec![0f32; w * h];
        let mut semantic = vec![0u8; w * h];
        let r = cam.camera_to_world.matrix();
        let o = cam.camera_to_world.translation;
        let k = cam.k;
        rgb.par_chunks_mut(w * 3).zip(depth.par_chunks_mut(w)).zip(semantic.par_chunks_mut(w)).enumerate().for_each(
            |(row, ((rgb, depth), semantic))| {
                let y = (row as f64 + 0.5 - k[1][2]) / k[1][1];
                for col in 0..w {
                    let x = (col as f64 + 0.5 - k[0][2] - k[0][1] * y) / k[0][0];
                    let dc = DVec3::new(x, y, 1.0);
                    let len = dc.length();
                    let d = r * (dc / len);
                    let (c, z, s) = match self.cast(o, d, MAX_CAMERA_RANGE) {
                        Some(hit) => (shade(&hit, d), (hit.t / len) as f32, hit.class),
                        None => (sky(d), f32::INFINITY, class::SKY),
                    };
                    rgb[col * 3..col * 3 + 3].copy_from_slice(&c);
                    depth[col] = z;
                    semantic[col] = s;
                }
            },
        );
        CameraImage { width: cam.width, height: cam.height, rgb, depth, semantic }
    }
}

fn lane_marking(s: f64, d: f64) -> bool {
    let half = 0.075;
    // Dashed centre line (3 m dash, 6 m gap); solid lines between the lanes and the parking strips.
    (d.abs() < half && s.rem_euclid(9.0) < 3.0) || ((d.abs() - LANE_WIDTH).abs() < half)
}

/// Smooth value noise in [0, 1] on a 2D lattice of unit spacing.
fn value_noise(x: f64, y: f64, seed: u64) -> f32 {
    let (ix, iy) = (fast_floor(x), fast_floor(y));
    let (fx, fy) = (ix as f64, iy as f64);
    let (tx, ty) = (x - fx, y - fy);
    let (sx, sy) = (tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty));
    let h = |i: i64, j: i64| {
        (mix(seed ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F))
            >> 40) as f64
            / (1u64 << 24) as f64
    };
    let a = h(ix, iy) + (h(ix + 1, iy) - h(ix, iy)) * sx;
    let b = h(ix, iy + 1) + (h(ix + 1, iy + 1) - h(ix, iy + 1)) * sx;
    (a + (b - a) * sy) as f32
}

/// `floor` without the libm call it compiles to on baseline x86-64 (no SSE4.1).
#[inline]
fn fast_floor(x: f64) -> i64 {
    let i = x as i64;
    if (i as f64) > x {
        i - 1
    } else {
        i
    }
}

/// Texture coordinates on a surface: ground plane for horizontal faces, (along, up) for walls.
fn surface_uv(p: DVec3, n: DVec3) -> (f64, f64) {
    if n.z.abs() > 0.7 {
        (p.x, p.y)
    } else {
        let h = (n.x * n.x + n.y * n.y).sqrt().max(1e-9);
        (p.x * (-n.y / h) + p.y * (n.x / h), p.z)
    }
}

const SUN: DVec3 = DVec3::new(0.38, 0.26, 0.887);

fn shade(hit: &SurfaceHit, d: DVec3) -> [u8; 3] {
    let (u, v) = surface_uv(hit.point, hit.normal);
    // Fine grain (stereo needs texture at every range) plus a coarse blotch.
    let fine = value_noise(u * 8.0, v * 8.0, 11) - 0.5;
    let coarse = value_noise(u * 0.7, v * 0.7, 12) - 0.5;
    let mut albedo = match hit.material {
        Surface::Ground { lane_marking: true } => [0.85, 0.85, 0.82],
        Surface::Ground { .. } => grey(0.3),
        Surface::Prim(m) => material_albedo(m, hit, u, v),
    };
    let grain = match hit.material {
        Surface::Prim(Material::Glass) | Surface::Prim(Material::EgoBody) => 0.05,
        Surface::Prim(Material::Foliage) => 0.6,
        _ => 0.25,
    };
    for c in albedo.iter_mut() {
        *c *= 1.0 + grain * fine + 0.15 * coarse;
    }
    let _ = d;
    let light = 0.45 + 0.55 * hit.normal.dot(SUN).max(0.0) as f32;
    albedo.map(|c| (c * light * 255.0).clamp(0.0, 255.0) as u8)
}

fn grey(v: f32) -> [f32; 3] {
    [v, v, v]
}

fn material_albedo(m: Material, hit: &SurfaceHit, u: f64, v: f64) -> [f32; 3] {
    match m {
        Material::Road => grey(0.3),
        Material::Sidewalk | Material::Kerb if hit.normal.z > 0.5 => {
            let tile = |x: f64| (x / 0.6).rem_euclid(1.0) < 0.05;
            if tile(u) || tile(v) {
                grey(0.42)
            } else {
                grey(0.6)
            }
        }
        Material::Sidewalk | Material::Kerb => grey(0.5),
        Material::Facade { hue, floor_height, window_width } => {
            if hit.normal.z.abs() > 0.5 {
                return grey(0.25);
            }
            let fh = floor_height as f64;
            let zf = v.rem_euclid(fh) / fh;
            let period = window_width as f64 * 2.0;
            let window = v > 1.5 && (0.3..0.75).contains(&zf) && u.rem_euclid(period) < window_width as f64;
            if window {
                [0.12, 0.16, 0.24]
            } else {
                hue
            }
        }
        Material::Roof => grey(0.25),
        Material::Metal => grey(0.35),
        Material::Bark => [0.33, 0.24, 0.15],
        Material::Foliage => [0.18, 0.42, 0.13],
        Material::CarPaint(c) => c,
        Material::Glass => [0.1, 0.12, 0.15],
        Material::Cloth(c) => c,
        Material::Skin => [0.85, 0.65, 0.5],
        Material::EgoBody => grey(0.7),
    }
}

fn sky(d: DVec3) -> [u8; 3] {
    let e = d.z.clamp(0.0, 1.0) as f32;
    let horizon = [0.78, 0.85, 0.93];
    let zenith = [0.33, 0.52, 0.82];
    let t = e.sqrt();
    [0, 1, 2].map(|i| ((horizon[i] + (zenith[i] - horizon[i]) * t) * 255.0) as u8)
}

/// LiDAR reflectivity (0-255 scale at normal incidence) of a surface.
fn reflectivity(s: Surface) -> f64 {
    match s {
        Surface::Ground { lane_marking: true } => 90.0,
        Surface::Ground { .. } => 12.0,
        Surface::Prim(m) => match m {
            Material::Road => 12.0,
            Material::Sidewalk | Material::Kerb => 22.0,
            Material::Facade { .. } | Material::Roof => 28.0,
            Material::Metal => 45.0,
            Material::Bark => 15.0,
            Material::Foliage => 18.0,
            Material::CarPaint(_) => 35.0,
            Material::Glass => 6.0,
            Material::Cloth(_) | Material::Skin => 10.0,
            Material::EgoBody => 30.0,
        },
    }
}

/// An HDL-32E-like spinning LiDAR.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct LidarModel {
    pub beams: u32,
    pub min_elevation_deg: f64,
    pub max_elevation_deg: f64,
    /// Firings per revolution per beam (nuScenes sweeps hold 32 x 1084 points).
    pub azimuth_steps: u32,
    pub max_range: f64,
    /// Gaussian range noise, metres.
    pub range_noise: f64,
    /// Probability that a return is lost.
    pub dropout: f64,
}

impl Default for LidarModel {
    fn default() -> Self {
        LidarModel {
            beams: 32,
            min_elevation_deg: -30.67,
            max_elevation_deg: 10.67,
            azimuth_steps: 1084,
            max_range: 80.0,
            range_noise: 0.02,
            dropout: 0.02,
        }
    }
}

/// One sweep in the sensor frame: x, y, z, intensity, ring per point, plus the Cityscapes class
/// and instance of what each beam hit. Like nuScenes, every firing is a point; firings with no
/// return (sky, out of range, dropout) sit at the sensor origin with intensity 0 and class 0.
pub struct LidarSweep {
    pub points: Vec<[f32; 5]>,
    pub class: Vec<u8>,
    pub instance: Vec<u32>,
}

impl Snapshot<'_> {
    /// Scans from `sensor_to_world`; `sensor_to_ego` places the ego body so low beams graze it.
    pub fn scan(&self, model: &LidarModel, sensor_to_world: &Se3, sensor_to_ego: &Se3, seed: u64) -> LidarSweep {
        let n = (model.beams * model.azimuth_steps) as usize;
        let (r_w, o_w) = (sensor_to_world.matrix(), sensor_to_world.translation);
        let (r_e, o_e) = (sensor_to_ego.matrix(), sensor_to_ego.translation);
        let body = ego_body();
        let rows: Vec<([f32; 5], u8, u32)> = (0..n)
            .into_par_iter()
            .map(|i| {
                let beam = i as u32 % model.beams;
                let step = i as u32 / model.beams;
                let el = (model.min_elevation_deg
                    + (model.max_elevation_deg - model.min_elevation_deg) * beam as f64
                        / (model.beams.max(2) - 1) as f64)
                    .to_radians();
                let az = std::f64::consts::TAU * step as f64 / model.azimuth_steps as f64;
                let ds = DVec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                let mut rng = Rng::new(mix(seed ^ (i as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93)));
                let lost = rng.next_f64() < model.dropout;
                let noise = rng.normal() * model.range_noise;
                // The ego body first (in the ego frame), then the world.
                let de = r_e * ds;
                let ego = body
                    .iter()
                    .filter_map(|p| p.shape.intersect(o_e, de, 1e-6, 5.0).map(|(t, n)| (t, n, p)))
                    .min_by(|a, b| a.0.total_cmp(&b.0));
                let (t, cos_inc, refl, class, instance) = if let Some((t, n, p)) = ego {
                    (t, n.dot(de).abs(), reflectivity(Surface::Prim(p.material)), p.class, 0)
                } else if let Some(hit) = self.cast(o_w, r_w * ds, model.max_range) {
                    (hit.t, hit.normal.dot(r_w * ds).abs(), reflectivity(hit.material), hit.class, hit.instance)
                } else {
                    return ([0.0, 0.0, 0.0, 0.0, beam as f32], 0, 0);
                };
                if lost {
                    return ([0.0, 0.0, 0.0, 0.0, beam as f32], 0, 0);
                }
                let range = (t + noise).max(0.0);
                let p = ds * range;
                let intensity = (refl * (0.3 + 0.7 * cos_inc)).round().clamp(0.0, 255.0);
                ([p.x as f32, p.y as f32, p.z as f32, intensity as f32, beam as f32], class, instance)
            })
            .collect();
        let mut sweep =
            LidarSweep { points: Vec::with_capacity(n), class: Vec::with_capacity(n), instance: Vec::with_capacity(n) };
        for (p, c, i) in rows {
            sweep.points.push(p);
            sweep.class.push(c);
            sweep.instance.push(i);
        }
        sweep
    }
}
