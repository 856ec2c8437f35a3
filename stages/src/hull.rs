//! 3D convex hull (Quickhull, Barber, Dobkin, Huhdanpaa 1996) returning which input points are
//! hull vertices: what hidden point removal needs, nothing more.
//!
//! Triangular faces with neighbour links; each face owns the points outside it (its conflict
//! list). A face's farthest outside point becomes the eye; the faces it sees are found by a
//! depth-first walk that lists the horizon edges in order; new faces fan from the eye to the
//! horizon; the visible faces' outside points move to the new faces or, inside all of them, are
//! done with. Points within `eps` of a face count as inside (coplanar points are not vertices,
//! as in Qhull's default). A horizon that does not close (a numerically inconsistent visible
//! region) makes the eye coplanar rather than corrupting the hull.

use glam::DVec3;

const NONE: u32 = u32::MAX;

#[derive(Clone, Copy)]
struct Conflict {
    p: DVec3,
    i: u32,
}

struct Face {
    v: [u32; 3],
    /// `adj[i]`: the face across edge `v[i] -> v[(i + 1) % 3]`.
    adj: [u32; 3],
    normal: DVec3,
    offset: f64,
    /// Outside points with their coordinates inline: reassignment then reads memory in order
    /// instead of jumping around the point array (the hot loop was bound by those misses).
    outside: Vec<Conflict>,
    far: u32,
    far_dist: f64,
    alive: bool,
}

impl Face {
    #[inline]
    fn distance(&self, p: DVec3) -> f64 {
        self.normal.dot(p) - self.offset
    }
}

struct Hull<'a> {
    pts: &'a [DVec3],
    faces: Vec<Face>,
    eps: f64,
    /// Visit stamp per face for the visibility walk.
    mark: Vec<u32>,
    stamp: u32,
    /// Dead faces to reuse (keeps the face array small and warm in cache).
    free: Vec<u32>,
    /// Emptied conflict lists to reuse.
    spare: Vec<Vec<Conflict>>,
}

/// Which points are vertices of the convex hull. Degenerate input (fewer than 4 points, or all
/// on a plane) makes every point a vertex.
pub fn hull_vertices(pts: &[DVec3]) -> Vec<bool> {
    let Some(h) = hull(pts) else {
        return vec![true; pts.len()];
    };
    let mut is_vertex = vec![false; pts.len()];
    for face in h.faces.iter().filter(|f| f.alive) {
        for &v in &face.v {
            is_vertex[v as usize] = true;
        }
    }
    is_vertex
}

/// The hull's faces (the alive ones), or `None` for degenerate input.
fn hull(pts: &[DVec3]) -> Option<Hull<'_>> {
    let simplex = initial_simplex(pts)?;
    let scale = pts.iter().fold(0.0f64, |m, p| m.max(p.abs().max_element()));
    let mut h = Hull {
        pts,
        faces: Vec::new(),
        eps: scale * 1e-11,
        mark: Vec::new(),
        stamp: 0,
        free: Vec::new(),
        spare: Vec::new(),
    };
    h.build_simplex(simplex);
    // Every point starts in the conflict list of the first simplex face it is outside of.
    let mut first = [Vec::new(), Vec::new(), Vec::new(), Vec::new()];
    for (i, &p) in pts.iter().enumerate() {
        if simplex.contains(&(i as u32)) {
            continue;
        }
        if let Some(f) = (0..4).find(|&f| h.faces[f].distance(p) > h.eps) {
            first[f].push(Conflict { p, i: i as u32 });
        }
    }
    for (f, list) in first.into_iter().enumerate() {
        h.set_outside(f as u32, list);
    }
    // Faces with outside points: last made first (a stack keeps working where the last faces were
    // made, in cache; a heap by distance for every face took hidden point removal 1.6x as long),
    // except faces whose farthest point is within `1e4 eps` (a nearly flat patch), which wait,
    // farthest first, until no other face is left: taken in stack order, eyes barely above nearly
    // coplanar faces folded new faces over and left points inside the hull as vertices (a
    // thin slab under an apex; test `nearly_flat_clouds_fold_no_face_over_the_apex`).
    let mut pending = Pending { stack: Vec::new(), flat: std::collections::BinaryHeap::new(), flat_below: 1e4 * h.eps };
    for f in 0..4u32 {
        if !h.faces[f as usize].outside.is_empty() {
            pending.push(f, h.faces[f as usize].far_dist);
        }
    }
    let mut visible = Vec::new();
    let mut horizon: Vec<(u32, u32, u32, u32)> = Vec::new();
    let mut stack: Vec<(u32, u8, u8, u8)> = Vec::new();
    let mut orphans: Vec<Conflict> = Vec::new();
    let mut new_faces: Vec<u32> = Vec::new();
    while let Some(f) = pending.pop() {
        let face = &h.faces[f as usize];
        if !face.alive || face.outside.is_empty() {
            continue;
        }
        let eye_idx = face.far;
        let eye = pts[eye_idx as usize];
        h.find_horizon(f, eye, &mut visible, &mut horizon, &mut stack);
        if !closes(&horizon) {
            // Treat the eye as coplanar: drop it from this face and try the face again.
            let face = &mut h.faces[f as usize];
            let list: Vec<Conflict> =
                std::mem::take(&mut face.outside).into_iter().filter(|c| c.i != eye_idx).collect();
            h.set_outside(f, list);
            pending.push(f, h.faces[f as usize].far_dist);
            continue;
        }
        let k = horizon.len();
        new_faces.clear();
        for _ in 0..k {
            new_faces.push(h.alloc_face());
        }
        for (j, &(a, b, across, from)) in horizon.iter().enumerate() {
            let id = new_faces[j];
            let adj = [across, new_faces[(j + 1) % k], new_faces[(j + k - 1) % k]];
            h.init_face(id, [a, b, eye_idx], adj);
            let back = &mut h.faces[across as usize].adj;
            if let Some(s) = back.iter_mut().find(|x| **x == from) {
                *s = id;
            }
        }
        // Take the visible faces' outside points and free the faces (after the new faces took their
        // slots: a freed id reused now would confuse the neighbour links just written).
        orphans.clear();
        for &v in &visible {
            let face = &mut h.faces[v as usize];
            face.alive = false;
            orphans.extend_from_slice(&face.outside);
            let mut list = std::mem::take(&mut face.outside);
            list.clear();
            h.spare.push(list);
            h.free.push(v);
        }
        let new_range = &new_faces;
        for &c in &orphans {
            if c.i == eye_idx {
                continue;
            }
            let p = c.p;
            for &nf in new_range {
                let face = &mut h.faces[nf as usize];
                let d = face.distance(p);
                if d > h.eps {
                    if d > face.far_dist {
                        face.far_dist = d;
                        face.far = c.i;
                    }
                    face.outside.push(c);
                    break;
                }
            }
        }
        for &nf in new_range {
            if !h.faces[nf as usize].outside.is_empty() {
                pending.push(nf, h.faces[nf as usize].far_dist);
            }
        }
    }
    Some(h)
}

/// The faces still to process (see `hull_vertices`).
struct Pending {
    stack: Vec<u32>,
    flat: std::collections::BinaryHeap<(u64, u32)>,
    flat_below: f64,
}

impl Pending {
    fn push(&mut self, f: u32, far_dist: f64) {
        if far_dist >= self.flat_below {
            self.stack.push(f);
        } else {
            // Non-negative floats order as their bits.
            self.flat.push((far_dist.to_bits(), f));
        }
    }

    fn pop(&mut self) -> Option<u32> {
        self.stack.pop().or_else(|| self.flat.pop().map(|(_, f)| f))
    }
}

/// Whether the horizon edges form one closed loop, each ending where the next starts.
fn closes(horizon: &[(u32, u32, u32, u32)]) -> bool {
    horizon.len() >= 3 && (0..horizon.len()).all(|j| horizon[j].1 == horizon[(j + 1) % horizon.len()].0)
}

impl Hull<'_> {
    fn push_face(&mut self, v: [u32; 3], adj: [u32; 3]) {
        let id = self.alloc_face();
        self.init_face(id, v, adj);
    }

    /// A face slot: a freed one when there is one.
    fn alloc_face(&mut self) -> u32 {
        if let Some(id) = self.free.pop() {
            return id;
        }
        self.faces.push(Face {
            v: [0; 3],
            adj: [NONE; 3],
            normal: DVec3::ZERO,
            offset: 0.0,
            outside: Vec::new(),
            far: NONE,
            far_dist: 0.0,
            alive: false,
        });
        self.mark.push(0);
        (self.faces.len() - 1) as u32
    }

    fn init_face(&mut self, id: u32, v: [u32; 3], adj: [u32; 3]) {
        let [a, b, c] = v.map(|i| self.pts[i as usize]);
        let normal = (b - a).cross(c - a).normalize_or_zero();
        let outside = self.spare.pop().unwrap_or_default();
        let face = &mut self.faces[id as usize];
        *face = Face { v, adj, normal, offset: normal.dot(a), outside, far: NONE, far_dist: 0.0, alive: true };
    }

    fn set_outside(&mut self, f: u32, list: Vec<Conflict>) {
        let face = &mut self.faces[f as usize];
        face.far = NONE;
        face.far_dist = 0.0;
        for c in &list {
            let d = face.distance(c.p);
            if d > face.far_dist {
                face.far_dist = d;
                face.far = c.i;
            }
        }
        face.outside = list;
    }

    fn build_simplex(&mut self, s: [u32; 4]) {
        let [a, b, c, d] = s;
        // Orient (a, b, c) so that d is below it.
        let (pa, pb, pc, pd) = (self.pts[a as usize], self.pts[b as usize], self.pts[c as usize], self.pts[d as usize]);
        let (b, c) = if (pb - pa).cross(pc - pa).dot(pd - pa) > 0.0 { (c, b) } else { (b, c) };
        let _ = (pb, pc);
        // Faces: 0 = (a, b, c), 1 = (a, d, b), 2 = (b, d, c), 3 = (c, d, a).
        self.push_face([a, b, c], [1, 2, 3]);
        self.push_face([a, d, b], [3, 2, 0]);
        self.push_face([b, d, c], [1, 3, 0]);
        self.push_face([c, d, a], [2, 1, 0]);
    }

    /// The faces `eye` sees (starting at `start`, which it sees) and the horizon in order: edges
    /// `(a, b, face across, visible face)` as the visible faces ran them.
    fn find_horizon(
        &mut self,
        start: u32,
        eye: DVec3,
        visible: &mut Vec<u32>,
        horizon: &mut Vec<(u32, u32, u32, u32)>,
        stack: &mut Vec<(u32, u8, u8, u8)>,
    ) {
        visible.clear();
        horizon.clear();
        stack.clear();
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.mark.iter_mut().for_each(|m| *m = 0);
            self.stamp = 1;
        }
        let stamp = self.stamp;
        self.mark[start as usize] = stamp;
        visible.push(start);
        // (face, first edge, edges done, edges to do)
        stack.push((start, 0, 0, 3));
        while let Some(top) = stack.last_mut() {
            let (f, first, done, total) = *top;
            if done == total {
                stack.pop();
                continue;
            }
            top.2 += 1;
            let i = ((first + done) % 3) as usize;
            let face = &self.faces[f as usize];
            let n = face.adj[i];
            if self.mark[n as usize] == stamp {
                continue;
            }
            if self.faces[n as usize].distance(eye) > self.eps {
                self.mark[n as usize] = stamp;
                visible.push(n);
                let back = self.faces[n as usize].adj.iter().position(|&x| x == f).unwrap_or(0) as u8;
                stack.push((n, (back + 1) % 3, 0, 2));
            } else {
                horizon.push((face.v[i], face.v[(i + 1) % 3], n, f));
            }
        }
    }
}

/// Four points spanning a tetrahedron of clearly non-zero volume, or `None`.
fn initial_simplex(pts: &[DVec3]) -> Option<[u32; 4]> {
    if pts.len() < 4 {
        return None;
    }
    let mut ext = [0u32; 6];
    for (i, p) in pts.iter().enumerate() {
        for axis in 0..3 {
            if p[axis] < pts[ext[2 * axis] as usize][axis] {
                ext[2 * axis] = i as u32;
            }
            if p[axis] > pts[ext[2 * axis + 1] as usize][axis] {
                ext[2 * axis + 1] = i as u32;
            }
        }
    }
    let mut best = (0.0, 0, 0);
    for i in 0..6 {
        for j in i + 1..6 {
            let d = pts[ext[i] as usize].distance_squared(pts[ext[j] as usize]);
            if d > best.0 {
                best = (d, ext[i], ext[j]);
            }
        }
    }
    let (_, a, b) = best;
    if best.0 == 0.0 {
        return None;
    }
    let (pa, pb) = (pts[a as usize], pts[b as usize]);
    let dir = (pb - pa).normalize();
    let (mut c, mut cd) = (0u32, 0.0);
    for (i, p) in pts.iter().enumerate() {
        let v = *p - pa;
        let d = (v - dir * v.dot(dir)).length_squared();
        if d > cd {
            cd = d;
            c = i as u32;
        }
    }
    let normal = (pb - pa).cross(pts[c as usize] - pa);
    if normal.length() <= 1e-12 * best.0 {
        return None;
    }
    let normal = normal.normalize();
    let (mut d, mut dd) = (0u32, 0.0);
    for (i, p) in pts.iter().enumerate() {
        let h = normal.dot(*p - pa).abs();
        if h > dd {
            dd = h;
            d = i as u32;
        }
    }
    if dd <= 1e-10 * best.0.sqrt() {
        return None;
    }
    Some([a, b, c, d])
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::rng::Rng;

    #[test]
    fn a_cube_with_inner_points_has_its_corners_as_vertices() {
        let mut pts = Vec::new();
        for i in 0..8 {
            pts.push(DVec3::new((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64));
        }
        let mut rng = Rng::new(1);
        for _ in 0..1000 {
            pts.push(DVec3::new(rng.range(0.01, 0.99), rng.range(0.01, 0.99), rng.range(0.01, 0.99)));
        }
        // Face centres are coplanar with the faces: not vertices.
        pts.push(DVec3::new(0.5, 0.5, 1.0));
        let v = hull_vertices(&pts);
        assert!(v[..8].iter().all(|&x| x));
        assert_eq!(v.iter().filter(|&&x| x).count(), 8);
    }

    #[test]
    fn every_point_on_a_sphere_is_a_vertex_and_none_inside() {
        let mut rng = Rng::new(2);
        let mut pts = Vec::new();
        for _ in 0..5000 {
            let p = DVec3::new(rng.normal(), rng.normal(), rng.normal()).normalize() * 10.0;
            pts.push(p);
            pts.push(p * rng.range(0.1, 0.95));
        }
        let v = hull_vertices(&pts);
        for (i, &x) in v.iter().enumerate() {
            assert_eq!(x, i % 2 == 0, "point {i}");
        }
    }

    #[test]
    fn degenerate_input_makes_every_point_a_vertex() {
        let flat: Vec<DVec3> = (0..10).map(|i| DVec3::new(i as f64, (i * i) as f64, 0.0)).collect();
        assert!(hull_vertices(&flat).iter().all(|&x| x));
        assert_eq!(hull_vertices(&flat[..2]), vec![true, true]);
    }

    #[test]
    fn nearly_flat_clouds_fold_no_face_over_the_apex() {
        // A slab 1e-10 thin under an apex: taken in stack order, the slab's nearly coplanar faces
        // folded over (the apex 1.0 above a surviving face, and interior points as vertices).
        for seed in 0..10 {
            let mut rng = Rng::new(seed);
            let mut pts: Vec<DVec3> = (0..3000)
                .map(|_| DVec3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), 1e-10 * rng.normal()))
                .collect();
            pts.push(DVec3::new(0.0, 0.0, 1.0));
            let h = hull(&pts).expect("not degenerate");
            // Every point lies below every face of a convex hull, up to the slab's own thickness
            // (within it, near-coplanar points may fold by ~1e3 eps, as with a heap): no face is
            // folded over the apex.
            for face in h.faces.iter().filter(|f| f.alive) {
                let worst = pts.iter().map(|&p| face.distance(p)).fold(f64::MIN, f64::max);
                assert!(worst <= 1e5 * h.eps, "seed {seed}: a point {worst:e} above a face");
            }
        }
    }

    /// Brute force: a point is a vertex when some plane through it has all others strictly on
    /// one side; checked via the hull's faces instead: every point must lie inside every face.
    #[test]
    fn random_clouds_give_hulls_that_contain_every_point() {
        let mut rng = Rng::new(3);
        let pts: Vec<DVec3> =
            (0..3000).map(|_| DVec3::new(rng.normal(), rng.normal() * 2.0, rng.range(-1.0, 1.0))).collect();
        let v = hull_vertices(&pts);
        let verts: Vec<DVec3> = pts.iter().zip(&v).filter(|(_, &x)| x).map(|(p, _)| *p).collect();
        assert!(verts.len() > 20 && verts.len() < 400, "{}", verts.len());
        // A non-vertex is a convex combination of vertices: it cannot be farther along any
        // direction than every vertex.
        for k in 0..200 {
            let dir = DVec3::new((k as f64).sin(), (k as f64 * 1.7).cos(), (k as f64 * 0.3).sin()).normalize();
            let best_vertex = verts.iter().map(|p| p.dot(dir)).fold(f64::MIN, f64::max);
            let best_any = pts.iter().map(|p| p.dot(dir)).fold(f64::MIN, f64::max);
            assert!((best_vertex - best_any).abs() < 1e-12);
        }
    }
}
