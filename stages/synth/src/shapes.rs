//! Primitives of the synthetic world and their exact ray intersections, plus a 2D uniform grid
//! over the ground plane to find the few primitives a ray can meet. The world is 2.5D (a street),
//! so a grid over x, y with a height bound per cell prunes almost everything.

#[cfg(test)]
use crate::material::class;
use crate::material::Material;
use glam::DVec3;

#[derive(Clone, Copy, Debug)]
pub enum Shape {
    /// A box rotated about z only: centre, half extents (along its own x, y, z), cos/sin of yaw.
    Box {
        c: DVec3,
        half: [f64; 3],
        cos: f64,
        sin: f64,
    },
    /// A vertical cylinder with flat caps.
    Cylinder {
        x: f64,
        y: f64,
        r: f64,
        z0: f64,
        z1: f64,
    },
    Sphere {
        c: DVec3,
        r: f64,
    },
}

impl Shape {
    pub fn oriented_box(c: DVec3, half: [f64; 3], yaw: f64) -> Shape {
        Shape::Box { c, half, cos: yaw.cos(), sin: yaw.sin() }
    }

    /// Whether the point is inside the solid (boundary included).
    pub fn contains(&self, p: DVec3) -> bool {
        match *self {
            Shape::Box { c, half, cos, sin } => {
                let d = p - c;
                let (lx, ly) = (d.x * cos + d.y * sin, -d.x * sin + d.y * cos);
                lx.abs() <= half[0] && ly.abs() <= half[1] && d.z.abs() <= half[2]
            }
            Shape::Cylinder { x, y, r, z0, z1 } => {
                (p.x - x).powi(2) + (p.y - y).powi(2) <= r * r && p.z >= z0 && p.z <= z1
            }
            Shape::Sphere { c, r } => (p - c).length_squared() <= r * r,
        }
    }

    /// Whether the solid and a box rotated about z only (centre `c`, half size `h`, yaw cos/sin)
    /// share any volume (touching is not sharing). Exact: separating axes for two boxes, the
    /// nearest point of the box for a cylinder's disc and a sphere.
    pub fn overlaps_box(&self, c: DVec3, h: f64, cos: f64, sin: f64) -> bool {
        // A point in the box's frame (its x, y axes; z unchanged).
        let local = |p: DVec3| {
            let d = p - c;
            DVec3::new(d.x * cos + d.y * sin, -d.x * sin + d.y * cos, d.z)
        };
        let eps = 1e-9;
        match *self {
            Shape::Box { c: bc, half, cos: bcos, sin: bsin } => {
                if (bc.z - c.z).abs() >= half[2] + h - eps {
                    return false;
                }
                // 2D separating axes: the two boxes' x and y axes.
                let axes = [(cos, sin), (-sin, cos), (bcos, bsin), (-bsin, bcos)];
                let d = (bc.x - c.x, bc.y - c.y);
                axes.iter().all(|&(ax, ay)| {
                    let dist = (d.0 * ax + d.1 * ay).abs();
                    let r_voxel = h * ((cos * ax + sin * ay).abs() + (-sin * ax + cos * ay).abs());
                    let r_prim = half[0] * (bcos * ax + bsin * ay).abs() + half[1] * (-bsin * ax + bcos * ay).abs();
                    dist < r_voxel + r_prim - eps
                })
            }
            Shape::Cylinder { x, y, r, z0, z1 } => {
                if z1 <= c.z - h + eps || z0 >= c.z + h - eps {
                    return false;
                }
                let q = local(DVec3::new(x, y, c.z));
                let (nx, ny) = (q.x.clamp(-h, h), q.y.clamp(-h, h));
                (q.x - nx).powi(2) + (q.y - ny).powi(2) < r * r - eps
            }
            Shape::Sphere { c: sc, r } => {
                let q = local(sc);
                let n = DVec3::new(q.x.clamp(-h, h), q.y.clamp(-h, h), q.z.clamp(-h, h));
                (q - n).length_squared() < r * r - eps
            }
        }
    }

    /// Corners of the footprint (boxes), or of the bounding square.
    pub fn footprint_corners(&self) -> Vec<(f64, f64)> {
        match *self {
            Shape::Box { c, half, cos, sin } => [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
                .iter()
                .map(|(a, b)| {
                    let (lx, ly) = (a * half[0], b * half[1]);
                    (c.x + lx * cos - ly * sin, c.y + lx * sin + ly * cos)
                })
                .collect(),
            _ => {
                let (lo, hi) = self.bounds();
                vec![(lo.x, lo.y), (hi.x, lo.y), (hi.x, hi.y), (lo.x, hi.y)]
            }
        }
    }

    /// Whether the footprint meets the axis-aligned rectangle (separating axes for boxes; the
    /// bounding square, conservatively, for round shapes).
    pub fn overlaps_rect(&self, x0: f64, y0: f64, x1: f64, y1: f64) -> bool {
        let (lo, hi) = self.bounds();
        if hi.x < x0 || lo.x > x1 || hi.y < y0 || lo.y > y1 {
            return false;
        }
        let Shape::Box { c, half, cos, sin } = *self else { return true };
        // The rectangle's corners projected on the box's own axes.
        let corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)];
        for (ax, ay, h) in [(cos, sin, half[0]), (-sin, cos, half[1])] {
            let proj = corners.map(|(x, y)| (x - c.x) * ax + (y - c.y) * ay);
            let (mn, mx) = proj.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
            if mn > h || mx < -h {
                return false;
            }
        }
        true
    }

    /// Axis-aligned bounds.
    pub fn bounds(&self) -> (DVec3, DVec3) {
        match *self {
            Shape::Box { c, half, cos, sin } => {
                let ex = half[0] * cos.abs() + half[1] * sin.abs();
                let ey = half[0] * sin.abs() + half[1] * cos.abs();
                let e = DVec3::new(ex, ey, half[2]);
                (c - e, c + e)
            }
            Shape::Cylinder { x, y, r, z0, z1 } => (DVec3::new(x - r, y - r, z0), DVec3::new(x + r, y + r, z1)),
            Shape::Sphere { c, r } => (c - DVec3::splat(r), c + DVec3::splat(r)),
        }
    }

    /// Nearest hit with `t` in (t_min, t_max): distance along `d` (unit) and outward normal.
    #[inline]
    pub fn intersect(&self, o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> Option<(f64, DVec3)> {
        match *self {
            Shape::Box { c, half, cos, sin } => {
                // Into the box frame.
                let p = o - c;
                let lo = [p.x * cos + p.y * sin, -p.x * sin + p.y * cos, p.z];
                let ld = [d.x * cos + d.y * sin, -d.x * sin + d.y * cos, d.z];
                let (mut t0, mut t1) = (t_min, t_max);
                let mut axis = usize::MAX;
                let mut sign = 0.0;
                for a in 0..3 {
                    if ld[a].abs() < 1e-15 {
                        if lo[a].abs() > half[a] {
                            return None;
                        }
                        continue;
                    }
                    let inv = 1.0 / ld[a];
                    let (mut ta, mut tb) = ((-half[a] - lo[a]) * inv, (half[a] - lo[a]) * inv);
                    let mut s = -1.0;
                    if ta > tb {
                        std::mem::swap(&mut ta, &mut tb);
                        s = 1.0;
                    }
                    if ta > t0 {
                        t0 = ta;
                        axis = a;
                        sign = s;
                    }
                    t1 = t1.min(tb);
                    if t0 > t1 {
                        return None;
                    }
                }
                // A ray starting inside (axis unset) does not hit the outside of this box.
                if axis == usize::MAX {
                    return None;
                }
                let n = match axis {
                    0 => DVec3::new(sign * cos, sign * sin, 0.0),
                    1 => DVec3::new(-sign * sin, sign * cos, 0.0),
                    _ => DVec3::new(0.0, 0.0, sign),
                };
                Some((t0, n))
            }
            Shape::Cylinder { x, y, r, z0, z1 } => {
                let (px, py) = (o.x - x, o.y - y);
                let a = d.x * d.x + d.y * d.y;
                let mut best: Option<(f64, DVec3)> = None;
                if a > 1e-18 {
                    let b = px * d.x + py * d.y;
                    let cc = px * px + py * py - r * r;
                    let disc = b * b - a * cc;
                    if disc >= 0.0 {
                        let t = (-b - disc.sqrt()) / a;
                        if t > t_min && t < t_max {
                            let z = o.z + t * d.z;
                            if z >= z0 && z <= z1 {
                                best = Some((t, DVec3::new((px + t * d.x) / r, (py + t * d.y) / r, 0.0)));
                            }
                        }
                    }
                }
                // Caps.
                if d.z.abs() > 1e-15 {
                    for (zc, nz) in [(z1, 1.0), (z0, -1.0)] {
                        let t = (zc - o.z) / d.z;
                        if t > t_min && t < best.map_or(t_max, |b| b.0) && (nz * d.z) < 0.0 {
                            let (hx, hy) = (px + t * d.x, py + t * d.y);
                            if hx * hx + hy * hy <= r * r {
                                best = Some((t, DVec3::new(0.0, 0.0, nz)));
                            }
                        }
                    }
                }
                best
            }
            Shape::Sphere { c, r } => {
                let p = o - c;
                let b = p.dot(d);
                let cc = p.length_squared() - r * r;
                let disc = b * b - cc;
                if disc < 0.0 {
                    return None;
                }
                let t = -b - disc.sqrt();
                (t > t_min && t < t_max).then(|| (t, (p + d * t) / r))
            }
        }
    }
}

/// A primitive: shape, look, Cityscapes class and instance (0 = none).
#[derive(Clone, Copy, Debug)]
pub struct Prim {
    pub shape: Shape,
    pub material: Material,
    pub class: u8,
    pub instance: u32,
}

impl Prim {
    pub fn new(shape: Shape, material: Material, class: u8, instance: u32) -> Prim {
        Prim { shape, material, class, instance }
    }
}

/// Primitives binned into square cells over x, y (CSR layout), each cell with its top height.
pub struct Grid {
    pub prims: Vec<Prim>,
    origin: [f64; 2],
    cell: f64,
    nx: usize,
    ny: usize,
    start: Vec<u32>,
    items: Vec<u32>,
    /// Height range of each item, beside it, so a ray passing above or below skips it unread.
    item_z: Vec<[f32; 2]>,
    top: Vec<f64>,
    z_max: f64,
}

impl Grid {
    /// The primitives whose footprint may cover the point (x, y) (those binned in its cell).
    pub fn prims_at(&self, x: f64, y: f64) -> impl Iterator<Item = &Prim> {
        let (i, j) = (((x - self.origin[0]) / self.cell).floor(), ((y - self.origin[1]) / self.cell).floor());
        let range = if self.prims.is_empty() || i < 0.0 || j < 0.0 || i >= self.nx as f64 || j >= self.ny as f64 {
            0..0
        } else {
            let c = j as usize * self.nx + i as usize;
            self.start[c] as usize..self.start[c + 1] as usize
        };
        self.items[range].iter().map(|&k| &self.prims[k as usize])
    }

    pub fn build(prims: Vec<Prim>, cell: f64) -> Grid {
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        let bounds: Vec<(DVec3, DVec3)> = prims.iter().map(|p| p.shape.bounds()).collect();
        for (a, b) in &bounds {
            lo = lo.min(*a);
            hi = hi.max(*b);
        }
        if prims.is_empty() {
            lo = DVec3::ZERO;
            hi = DVec3::ZERO;
        }
        let nx = (((hi.x - lo.x) / cell).ceil() as usize).max(1);
        let ny = (((hi.y - lo.y) / cell).ceil() as usize).max(1);
        let cell_range = |a: f64, b: f64, o: f64, n: usize| {
            let i0 = (((a - o) / cell).floor().max(0.0) as usize).min(n - 1);
            let i1 = (((b - o) / cell).floor().max(0.0) as usize).min(n - 1);
            i0..=i1
        };
        // Long rotated boxes (sidewalks of a whole straight) touch far fewer cells than their
        // bounding rectangle: bin them by exact footprint overlap.
        let touches = |p: &Prim, i: usize, j: usize| {
            let (cx0, cy0) = (lo.x + i as f64 * cell, lo.y + j as f64 * cell);
            p.shape.overlaps_rect(cx0, cy0, cx0 + cell, cy0 + cell)
        };
        let mut count = vec![0u32; nx * ny + 1];
        let mut top = vec![f64::NEG_INFINITY; nx * ny];
        for (p, (a, b)) in prims.iter().zip(&bounds) {
            for j in cell_range(a.y, b.y, lo.y, ny) {
                for i in cell_range(a.x, b.x, lo.x, nx) {
                    if touches(p, i, j) {
                        count[j * nx + i + 1] += 1;
                        top[j * nx + i] = top[j * nx + i].max(b.z);
                    }
                }
            }
        }
        for k in 1..count.len() {
            count[k] += count[k - 1];
        }
        let start = count.clone();
        let mut fill = count;
        let mut items = vec![0u32; *start.last().unwrap_or(&0) as usize];
        let mut item_z = vec![[0f32; 2]; items.len()];
        for (p, (a, b)) in bounds.iter().enumerate() {
            for j in cell_range(a.y, b.y, lo.y, ny) {
                for i in cell_range(a.x, b.x, lo.x, nx) {
                    if !touches(&prims[p], i, j) {
                        continue;
                    }
                    let c = j * nx + i;
                    items[fill[c] as usize] = p as u32;
                    // Rounded outward so the test stays conservative.
                    item_z[fill[c] as usize] = [(a.z as f32).next_down(), (b.z as f32).next_up()];
                    fill[c] += 1;
                }
            }
        }
        Grid { prims, origin: [lo.x, lo.y], cell, nx, ny, start, items, item_z, top, z_max: hi.z }
    }

    /// Nearest primitive hit with t in (t_min, t_max).
    pub fn cast(&self, o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> Option<(f64, DVec3, u32)> {
        if self.prims.is_empty() {
            return None;
        }
        // Clip to the grid's xy box (and to its top: a rising ray above every primitive is done).
        let (x0, y0) = (self.origin[0], self.origin[1]);
        let (x1, y1) = (x0 + self.nx as f64 * self.cell, y0 + self.ny as f64 * self.cell);
        let (mut ta, mut tb) = (t_min, t_max);
        for (oo, dd, lo, hi) in [(o.x, d.x, x0, x1), (o.y, d.y, y0, y1)] {
            if dd.abs() < 1e-15 {
                if oo < lo || oo > hi {
                    return None;
                }
            } else {
                let (mut a, mut b) = ((lo - oo) / dd, (hi - oo) / dd);
                if a > b {
                    std::mem::swap(&mut a, &mut b);
                }
                ta = ta.max(a);
                tb = tb.min(b);
            }
        }
        if d.z > 0.0 {
            tb = tb.min((self.z_max - o.z) / d.z);
        } else if o.z > self.z_max && d.z < 1e-15 {
            return None;
        }
        if ta > tb {
            return None;
        }
        let p = o + d * ta;
        let mut i = (((p.x - x0) / self.cell).floor() as isize).clamp(0, self.nx as isize - 1);
        let mut j = (((p.y - y0) / self.cell).floor() as isize).clamp(0, self.ny as isize - 1);
        let step_x: isize = if d.x >= 0.0 { 1 } else { -1 };
        let step_y: isize = if d.y >= 0.0 { 1 } else { -1 };
        let next_bound = |k: isize, step: isize, origin: f64| origin + (k + (step > 0) as isize) as f64 * self.cell;
        let mut t_next_x = if d.x.abs() < 1e-15 { f64::INFINITY } else { (next_bound(i, step_x, x0) - o.x) / d.x };
        let mut t_next_y = if d.y.abs() < 1e-15 { f64::INFINITY } else { (next_bound(j, step_y, y0) - o.y) / d.y };
        let dt_x = if d.x.abs() < 1e-15 { f64::INFINITY } else { self.cell / d.x.abs() };
        let dt_y = if d.y.abs() < 1e-15 { f64::INFINITY } else { self.cell / d.y.abs() };
        let mut best: Option<(f64, DVec3, u32)> = None;
        let mut t_cell = ta;
        // Primitives spanning several cells are tested once per ray (a small recent-ids box).
        let mut tested = [u32::MAX; 16];
        let mut next_slot = 0;
        loop {
            let t_exit = t_next_x.min(t_next_y).min(tb);
            let c = j as usize * self.nx + i as usize;
            // The ray's lowest height inside this cell; skip cells whose contents are all below.
            let (za, zb) = (o.z + d.z * t_cell, o.z + d.z * t_exit);
            let (z_low, z_high) = (za.min(zb), za.max(zb));
            if z_low <= self.top[c] {
                let limit = best.map_or(tb, |b| b.0);
                let (zl, zh) = (z_low as f32, z_high as f32);
                let range = self.start[c] as usize..self.start[c + 1] as usize;
                for (&k, z) in self.items[range.clone()].iter().zip(&self.item_z[range]) {
                    if zl > z[1] || zh < z[0] || tested.contains(&k) {
                        continue;
                    }
                    tested[next_slot] = k;
                    next_slot = (next_slot + 1) % tested.len();
                    if let Some((t, n)) =
                        self.prims[k as usize].shape.intersect(o, d, t_min, best.map_or(limit, |b| b.0))
                    {
                        best = Some((t, n, k));
                    }
                }
            }
            if let Some(b) = best {
                if b.0 <= t_exit {
                    return best;
                }
            }
            if t_exit >= tb {
                return best;
            }
            t_cell = t_exit;
            if t_next_x < t_next_y {
                i += step_x;
                t_next_x += dt_x;
                if i < 0 || i >= self.nx as isize {
                    return best;
                }
            } else {
                j += step_y;
                t_next_y += dt_y;
                if j < 0 || j >= self.ny as isize {
                    return best;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(o: [f64; 3], d: [f64; 3]) -> (DVec3, DVec3) {
        (DVec3::from_array(o), DVec3::from_array(d).normalize())
    }

    #[test]
    fn a_rotated_box_is_hit_on_its_face_with_the_right_normal() {
        let b = Shape::oriented_box(DVec3::new(10.0, 0.0, 1.0), [1.0, 2.0, 1.0], std::f64::consts::FRAC_PI_2);
        // Rotated 90 degrees: its local y (half 2) is along world -x.
        let (o, d) = ray([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]);
        let (t, n) = b.intersect(o, d, 0.0, 100.0).unwrap();
        assert!((t - 8.0).abs() < 1e-12, "{t}");
        assert!((n - DVec3::new(-1.0, 0.0, 0.0)).length() < 1e-12, "{n}");
        let (o, d) = ray([0.0, 5.0, 1.0], [1.0, 0.0, 0.0]);
        assert!(b.intersect(o, d, 0.0, 100.0).is_none());
    }

    #[test]
    fn cylinders_and_spheres_have_exact_distances() {
        let c = Shape::Cylinder { x: 5.0, y: 0.0, r: 0.5, z0: 0.0, z1: 3.0 };
        let (o, d) = ray([0.0, 0.0, 1.0], [1.0, 0.0, 0.0]);
        assert!((c.intersect(o, d, 0.0, 100.0).unwrap().0 - 4.5).abs() < 1e-12);
        // Looking down onto the cap.
        let (o, d) = ray([5.0, 0.0, 10.0], [0.0, 0.0, -1.0]);
        let (t, n) = c.intersect(o, d, 0.0, 100.0).unwrap();
        assert!((t - 7.0).abs() < 1e-12 && n.z == 1.0);
        let s = Shape::Sphere { c: DVec3::new(0.0, 10.0, 0.0), r: 2.0 };
        // Exact overlap with a voxel (a cube of half size 0.2, yawed 30 degrees).
        let (vc, vs) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        assert!(s.overlaps_box(DVec3::new(0.0, 11.9, 0.0), 0.2, vc, vs), "a sliver of the sphere");
        assert!(!s.overlaps_box(DVec3::new(0.0, 12.5, 0.0), 0.2, vc, vs));
        assert!(c.overlaps_box(DVec3::new(5.6, 0.0, 1.0), 0.2, 1.0, 0.0), "0.1 m of the cylinder in it");
        assert!(!c.overlaps_box(DVec3::new(5.75, 0.0, 1.0), 0.2, 1.0, 0.0), "5 cm apart");
        assert!(!c.overlaps_box(DVec3::new(5.7, 0.0, 1.0), 0.2, 1.0, 0.0), "touching is not sharing");
        // A box yawed 90 degrees (2 m along y, 4 m along x after the turn) against voxels.
        let b = Shape::oriented_box(DVec3::new(10.0, 0.0, 1.0), [1.0, 2.0, 1.0], std::f64::consts::FRAC_PI_2);
        assert!(b.overlaps_box(DVec3::new(12.15, 0.0, 1.0), 0.2, 1.0, 0.0), "5 cm of it");
        assert!(!b.overlaps_box(DVec3::new(12.25, 0.0, 1.0), 0.2, 1.0, 0.0));
        assert!(b.overlaps_box(DVec3::new(10.0, 1.15, 1.0), 0.2, vc, vs), "a yawed voxel at its side");
        assert!(!b.overlaps_box(DVec3::new(10.0, 1.0, 2.2), 0.2, 1.0, 0.0), "above its top");
        let (o, d) = ray([0.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        assert!((s.intersect(o, d, 0.0, 100.0).unwrap().0 - 8.0).abs() < 1e-12);
    }

    #[test]
    fn the_grid_finds_the_same_nearest_hit_as_brute_force() {
        let mut rng = dist4d_types::rng::Rng::new(3);
        let mut prims = Vec::new();
        for _ in 0..300 {
            let c = DVec3::new(rng.range(-50.0, 50.0), rng.range(-50.0, 50.0), rng.range(0.0, 5.0));
            let shape = match rng.below(3) {
                0 => Shape::oriented_box(
                    c,
                    [rng.range(0.2, 3.0), rng.range(0.2, 3.0), rng.range(0.2, 3.0)],
                    rng.range(0.0, 6.0),
                ),
                1 => Shape::Cylinder { x: c.x, y: c.y, r: rng.range(0.1, 1.0), z0: 0.0, z1: rng.range(1.0, 8.0) },
                _ => Shape::Sphere { c, r: rng.range(0.2, 2.0) },
            };
            prims.push(Prim::new(shape, Material::Metal, class::POLE, 0));
        }
        let grid = Grid::build(prims.clone(), 4.0);
        for _ in 0..3000 {
            let o = DVec3::new(rng.range(-60.0, 60.0), rng.range(-60.0, 60.0), rng.range(0.0, 6.0));
            let d = DVec3::new(rng.normal(), rng.normal(), rng.normal() * 0.3).normalize();
            let brute = prims
                .iter()
                .enumerate()
                .filter_map(|(k, p)| p.shape.intersect(o, d, 1e-9, 1e3).map(|(t, _)| (t, k as u32)))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            let fast = grid.cast(o, d, 1e-9, 1e3).map(|(t, _, k)| (t, k));
            match (brute, fast) {
                (None, None) => {}
                (Some(a), Some(b)) => assert!((a.0 - b.0).abs() < 1e-9, "{a:?} {b:?} from {o} along {d}"),
                other => panic!("{other:?} from {o} along {d}"),
            }
        }
    }
}
