//! `HiddenPointRemoval`: the points of a cloud a camera can see (Katz, Tal, Basri 2007).
//!
//! Aggregated LiDAR seen from a camera mixes surfaces with what is behind them (the LiDAR sits
//! elsewhere, and other sweeps saw around corners); projected as is, background points leak
//! through foreground objects. DiST-4D removes them with HPR: each point p (relative to the camera
//! centre C) is flipped spherically, p' = p + 2 (R - |p|) p / |p|, and the points whose flips are
//! vertices of the convex hull of {p'} and C are the visible ones. Larger R keeps more points.
//! R = `radius_factor` x (the farthest point's distance), so the parameter does not depend on
//! the scene's scale; Open3D's `hidden_point_removal(C, R)` computes the same set.
//!
//! HPR also hides points the camera does see: the flip pulls a far point seen through a narrow
//! gap (a facade between tree trunks, below a crown) inside the hull of its near neighbours. On
//! the synthetic scene it drops about 500 correct LiDAR returns per image, most of them beyond
//! 40 m where LiDAR is sparsest. So a hidden point comes back when no kept point that projects
//! within a small window around it is nearer by more than `restore_tolerance`: a true occluder
//! (trunk, pole, car) has returns of its own right beside it. The window is measured in mean
//! sample spacings (sqrt(image area / kept points in the image)), so one setting serves a single
//! 32-beam sweep and three aggregated keyframes alike; it is taller than wide because LiDAR rings
//! are far apart vertically and dense along the row.
//!
//! Katz's operator and the restore window both judge occlusion by the points alone, and a car
//! 2 m away has only a few rings on it: between them, road and facades that other keyframes'
//! sweeps saw (the car was elsewhere then) come through, and each one spreads background depth
//! over the car in the completion. The dataset's boxes say where the objects are, so with the
//! frame's `boxes` wired, a point whose ray from the camera passes through a box is hidden, unless
//! it lies within `box_margin` of that box (the object's own return) and less than
//! `SELF_OCCLUSION` inside it along the ray (an own return farther in is on a face the object
//! turns away from the camera).
//!
//! Only points inside the camera's view (in front, within the image grown by `frustum_margin`)
//! go into the hull: the others never reach the image, and leaving them out makes the hull 5-6x
//! smaller for a surround rig.

use dist4d_runtime::Made;
use crate::camera::{CameraView, ViewPorts};
use crate::hull::hull_vertices;
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use anyhow::Result;
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_types::artifact::{Boxes3D, PointCloud};
use dist4d_types::geometry::{BoxTest, Se3};
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The flip radius as a multiple of the farthest point's distance from the camera.
    pub radius_factor: f64,
    /// Points must be in front of the camera by more than this (m).
    pub min_depth: f64,
    /// The image is grown by this fraction of its size on each side before culling.
    pub frustum_margin: f64,
    /// Half-width and half-height of the window searched for an occluder of a point HPR hid,
    /// in mean sample spacings; `[0, 0]` keeps exactly Katz et al.'s set.
    pub restore_window: [f64; 2],
    /// A kept point occludes a hidden one when it is nearer by more than this fraction.
    pub restore_tolerance: f64,
    /// Points within this distance (m) of an annotated box are its object's own returns and are
    /// not hidden by it.
    pub box_margin: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            radius_factor: 400.0,
            min_depth: 0.1,
            frustum_margin: 0.05,
            restore_window: [0.55, 1.8],
            restore_tolerance: 0.1,
            box_margin: 0.2,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        // The flip radius must exceed the farthest point's distance, or points fold inwards.
        c.above("radius_factor", self.radius_factor, 1.0, 1e6)
            .within("min_depth", self.min_depth, 0.0, 1000.0)
            .within("frustum_margin", self.frustum_margin, 0.0, 1.0)
            .within("restore_tolerance", self.restore_tolerance, 0.0, 1.0)
            .within("box_margin", self.box_margin, 0.0, 10.0);
        // Every hidden point scans its window: its area bounds the work.
        for (axis, v) in self.restore_window.into_iter().enumerate() {
            if !(v.is_finite() && (0.0..=16.0).contains(&v)) {
                c.push(ParamProblem {
                    field: "restore_window",
                    index: Some(axis),
                    other: None,
                    message: format!("must hold numbers in [0, 16] (mean sample spacings), found {v}"),
                });
            }
        }
        c.done()
    }
}

/// Katz et al.'s operator: which of `points` are visible from `camera` for flip radius `radius`
/// (same semantics as Open3D's `hidden_point_removal`). Points at the camera centre are hidden.
pub fn hidden_point_removal(points: &[DVec3], camera: DVec3, radius: f64) -> Vec<bool> {
    let mut flipped = Vec::with_capacity(points.len() + 1);
    let mut index = Vec::with_capacity(points.len());
    for (i, p) in points.iter().enumerate() {
        let q = *p - camera;
        let norm = q.length();
        if norm > 0.0 && norm.is_finite() {
            flipped.push(q + q * (2.0 * (radius - norm) / norm));
            index.push(i);
        }
    }
    flipped.push(DVec3::ZERO);
    let on_hull = hull_vertices(&flipped);
    let mut visible = vec![false; points.len()];
    for (k, &i) in index.iter().enumerate() {
        visible[i] = on_hull[k];
    }
    visible
}

/// The visible points of `points` (in the frame `view` maps from), in their original order;
/// `boxes` (world frame, at their own `timestamp_us`: the cloud's, or the image's after
/// FollowTracks), when given, hide what lies behind them in the image taken at `camera_us`.
pub fn visible_points(params: &Params, points: &PointCloud, view: &CameraView, boxes: Option<(&Boxes3D, &Se3, i64)>) -> PointCloud {
    let (w, h) = (view.width as f64, view.height as f64);
    let (mu, mv) = (w * params.frustum_margin, h * params.frustum_margin);
    let mut kept = Vec::new();
    let mut xyz = Vec::new();
    for (i, p) in points.points.iter().enumerate() {
        let v = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        let c = view.to_camera(v);
        if c.z <= params.min_depth {
            continue;
        }
        let (u, vv) = view.pixel(c);
        if u >= -mu && u <= w + mu && vv >= -mv && vv <= h + mv {
            kept.push(i);
            xyz.push(v);
        }
    }
    let centre = view.center();
    let radius = params.radius_factor * xyz.iter().map(|p| p.distance(centre)).fold(0.0, f64::max);
    let mut visible = hidden_point_removal(&xyz, centre, radius);
    restore_unoccluded(params, &xyz, &mut visible, view);
    if let Some((boxes, cloud_from_world, camera_us)) = boxes {
        hide_behind_boxes(params, &xyz, &mut visible, centre, boxes, cloud_from_world, camera_us);
    }
    let has_labels = points.labels.len() == points.points.len();
    let mut out = PointCloud::default();
    for (k, &i) in kept.iter().enumerate() {
        if visible[k] {
            out.points.push(points.points[i]);
            if has_labels {
                out.labels.push(points.labels[i]);
            }
        }
    }
    out
}

/// Footprint cell (m) of an object's height grid. 5 cm is 30 px on a car 2 m away: a coarser
/// cell at the end of a cabin takes the roof's height over part of the bonnet and hides the road
/// seen over it (25 cm cells dropped 2 600 correct samples on the synthetic scene, 10 cm 750,
/// 5 cm 430, while removing the same ~2 400 leaks). Cells of the side the LiDAR saw mostly hold
/// a return: a ray through a car crosses dozens of them.
const OBJECT_CELL: f64 = 0.05;

/// How far (m) an object's own return may lie inside the object along the camera's ray and still
/// be seen. Other keyframes' sweeps saw a parked car's front, rear and far side; from a camera
/// beside it those faces are behind its near side, and their returns, being the car's own, were
/// kept: a fifth of the synthetic scene's wrong prompt samples (0.60% -> 0.49% of all samples
/// with 0.5 m; 0.15 / 0.8 m: 0.48 / 0.52%). Less than a car's half width, more than the
/// 5 cm cells and the scan noise of a near face seen at a slant.
const SELF_OCCLUSION: f64 = 0.5;

/// An annotated object as an occluder: its box and, over a grid of its footprint, the height of
/// its own highest return. A car's box is air above the bonnet and the boot, where the road beyond
/// is in plain view; cells without a return occlude nothing (the object is not known to be there).
///
/// The cloud is at the LiDAR's time and the image at the camera's, up to ~50 ms apart around a
/// spinning LiDAR: a car at 10 m/s has moved half a metre. So the object's own returns are
/// looked for in its box at the cloud's time (`own`, `returns`), and it occludes from where it is
/// at the camera's time (`body`, moved along its annotated velocity).
struct Occluder {
    body: BoxTest,
    own: BoxTest,
    cells: [usize; 2],
    /// Cell side (m): `OBJECT_CELL`, or coarser for a box too large for a grid of that.
    cell: f64,
    lo: DVec3,
    /// Highest return in each cell, in the box's own axes (row-major over x, then y).
    tops: Vec<f64>,
}

impl Occluder {
    fn new(body: BoxTest, returns: BoxTest, own: BoxTest, xyz: &[DVec3]) -> Option<Occluder> {
        let (lo, hi) = body.corners();
        // At most 1000 cells a side, whatever size a box is annotated with.
        let cell = OBJECT_CELL.max((hi.x - lo.x).max(hi.y - lo.y) / 1000.0);
        if !cell.is_finite() {
            return None;
        }
        let cells = [0, 1].map(|a| (((hi[a] - lo[a]) / cell).ceil() as usize).clamp(1, 1000));
        let mut o = Occluder { body, own, cells, cell, lo, tops: vec![f64::NEG_INFINITY; cells[0] * cells[1]] };
        let mut any = false;
        for p in xyz.iter().filter(|p| o.own.contains(**p)) {
            let q = returns.local(*p);
            let c = o.cell(q);
            o.tops[c] = o.tops[c].max(q.z);
            any = true;
        }
        any.then_some(o)
    }

    fn cell(&self, q: DVec3) -> usize {
        let at = |a: usize| (((q[a] - self.lo[a]) / self.cell).max(0.0) as usize).min(self.cells[a] - 1);
        at(0) * self.cells[1] + at(1)
    }

    /// Whether the object stands between `eye` and `p`: the segment passes below the highest
    /// return of a cell it crosses. For one of the object's own returns, only the part of the
    /// segment more than `SELF_OCCLUSION` before it counts: a return on the far side of the
    /// object, or on a face turned away from the camera, is hidden by the object itself.
    fn hides(&self, eye: DVec3, p: DVec3) -> bool {
        let Some((a, mut b)) = self.body.clip(eye, p) else { return false };
        if self.own.contains(p) {
            let inside = (b - a).length();
            if inside <= SELF_OCCLUSION {
                return false;
            }
            b = a.lerp(b, (inside - SELF_OCCLUSION) / inside);
        }
        // Half a cell per step: no cell the segment crosses for more than that is skipped.
        let steps = ((b - a).length() / (0.5 * self.cell)).ceil().max(1.0) as usize;
        (0..=steps).any(|k| {
            let q = a.lerp(b, k as f64 / steps as f64);
            q.z <= self.tops[self.cell(q)]
        })
    }
}

/// Hides the visible points of `xyz` that one of `boxes` stands between the camera centre and
/// (see [`Occluder`]); points within `box_margin` of a box are its own.
/// `camera_us`: the image's time.
fn hide_behind_boxes(params: &Params, xyz: &[DVec3], visible: &mut [bool], centre: DVec3, boxes: &Boxes3D, cloud_from_world: &Se3, camera_us: i64) {
    let dt = (camera_us - boxes.timestamp_us) as f64 * 1e-6;
    let occluders: Vec<Occluder> = boxes
        .boxes
        .iter()
        .filter_map(|b| {
            let returns = b.test(cloud_from_world, 0.0, 0.0);
            let own = b.test(cloud_from_world, params.box_margin, -params.box_margin);
            let mut moved = b.clone();
            for (c, v) in moved.center.iter_mut().zip(b.velocity) {
                *c += if v.is_finite() { v * dt } else { 0.0 };
            }
            Occluder::new(moved.test(cloud_from_world, 0.0, 0.0), returns, own, xyz)
        })
        .collect();
    if occluders.is_empty() {
        return;
    }
    for (p, vis) in xyz.iter().zip(visible.iter_mut()).filter(|(_, v)| **v) {
        if occluders.iter().any(|o| o.hides(centre, *p)) {
            *vis = false;
        }
    }
}

/// Marks visible the hidden points of `xyz` that no visible point occludes in the image: none
/// projects within `restore_window` at a depth below (1 - `restore_tolerance`) of theirs.
fn restore_unoccluded(params: &Params, xyz: &[DVec3], visible: &mut [bool], view: &CameraView) {
    if params.restore_window == [0.0, 0.0] {
        return;
    }
    let (w, h) = (view.width as i64, view.height as i64);
    let pixel = |p: &DVec3| {
        let c = view.to_camera(*p);
        let (u, v) = view.pixel(c);
        (u.floor() as i64, v.floor() as i64, c.z as f32)
    };
    let kept: Vec<(i64, i64, f32)> =
        xyz.iter().zip(visible.iter()).filter(|(_, &v)| v).map(|(p, _)| pixel(p)).collect();
    let in_image = kept.iter().filter(|(u, v, _)| (0..w).contains(u) && (0..h).contains(v)).count();
    let spacing = ((w * h) as f64 / in_image.max(1) as f64).sqrt();
    let [rx, ry] = params.restore_window.map(|r| (r * spacing).round() as i64);
    let occluders = WindowMin::new(&kept, (w, h), (rx, ry));
    let keep = 1.0 - params.restore_tolerance as f32;
    for (p, vis) in xyz.iter().zip(visible.iter_mut()).filter(|(_, v)| !**v) {
        let (u, v, z) = pixel(p);
        if (0..w).contains(&u) && (0..h).contains(&v) && occluders.nearest(u, v) >= z * keep {
            *vis = true;
        }
    }
}

/// The nearest depth among points within a window (`|du| <= rx`, `|dv| <= ry` pixels) of a
/// pixel, asked only at the pixels of hidden points: a few hundred per image against ~10 000 kept
/// points, so the kept points are binned into cells of the window's size (a window then meets at
/// most 2 x 2 cells) instead of each splatting its window into an image-sized map (that splat was
/// most of HiddenPointRemoval's time outside the hull). The same minimum, so the same points come
/// back.
struct WindowMin {
    /// Kept points that can be within a window of an image pixel, grouped by cell: `(u, v, z)`.
    points: Vec<(i64, i64, f32)>,
    /// `points[start[c]..start[c + 1]]` lie in cell `c` (row-major, `cols` per row).
    start: Vec<usize>,
    cols: i64,
    rows: i64,
    /// Pixel of the corner of cell 0: `(-rx, -ry)`.
    origin: (i64, i64),
    cell: (i64, i64),
    window: (i64, i64),
}

impl WindowMin {
    fn new(points: &[(i64, i64, f32)], (w, h): (i64, i64), (rx, ry): (i64, i64)) -> WindowMin {
        let (rx, ry) = (rx.max(0), ry.max(0));
        let cell = (2 * rx + 1, 2 * ry + 1);
        let origin = (-rx, -ry);
        let (cols, rows) = ((w + 2 * rx + cell.0 - 1) / cell.0, (h + 2 * ry + cell.1 - 1) / cell.1);
        // Points farther than the window outside the image reach no image pixel.
        let cell_of = |&(u, v, _): &(i64, i64, f32)| -> Option<usize> {
            let (x, y) = (u - origin.0, v - origin.1);
            ((0..w + 2 * rx).contains(&x) && (0..h + 2 * ry).contains(&y))
                .then(|| ((y / cell.1) * cols + x / cell.0) as usize)
        };
        let mut start = vec![0usize; (cols * rows) as usize + 1];
        for c in points.iter().filter_map(cell_of) {
            start[c + 1] += 1;
        }
        for c in 1..start.len() {
            start[c] += start[c - 1];
        }
        let mut next = start.clone();
        let mut binned = vec![(0, 0, 0.0f32); start[start.len() - 1]];
        for p in points {
            if let Some(c) = cell_of(p) {
                binned[next[c]] = *p;
                next[c] += 1;
            }
        }
        WindowMin { points: binned, start, cols, rows, origin, cell, window: (rx, ry) }
    }

    /// The nearest depth within the window of image pixel `(u, v)`; +inf when there is none.
    fn nearest(&self, u: i64, v: i64) -> f32 {
        let (rx, ry) = self.window;
        let cells = |lo: i64, hi: i64, size: i64, n: i64| (lo.max(0) / size)..=(hi / size).min(n - 1);
        let (x, y) = (u - self.origin.0, v - self.origin.1);
        let mut nearest = f32::INFINITY;
        for cy in cells(y - ry, y + ry, self.cell.1, self.rows) {
            for cx in cells(x - rx, x + rx, self.cell.0, self.cols) {
                let c = (cy * self.cols + cx) as usize;
                for &(pu, pv, z) in &self.points[self.start[c]..self.start[c + 1]] {
                    if (pu - u).abs() <= rx && (pv - v).abs() <= ry {
                        nearest = nearest.min(z);
                    }
                }
            }
        }
        nearest
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the visible points, same frame, in input order
        points: One<PointCloud>,
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the cloud, in the frame of `cloud_calib` at `cloud_pose`
        points: One<PointCloud>,
        /// the cloud's sensor and pose, the camera's calibration and pose
        view: Group<ViewPorts>,
        /// annotated boxes (the frame's, or at the image's time after FollowTracks): what lies
        /// behind one is hidden
        boxes: Optional<Boxes3D>,
    }
}

pub struct HiddenPointRemoval(Params);

impl Stage for HiddenPointRemoval {
    const KIND: &'static str = "HiddenPointRemoval";
    const VERSION: u32 = 4;
    const SUMMARY: &'static str =
        "Point cloud -> the points one camera can see (Katz et al. 2007 spherical flip + convex hull)";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(HiddenPointRemoval(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let view = i.view.view()?;
        let cloud_from_world = i.view.cloud_pose.ego_to_world.then_from(&i.view.cloud_calib.sensor_to_ego).inverse();
        let boxes = i.boxes.as_ref().map(|b| (b, &cloud_from_world, i.view.camera_pose.timestamp_us));
        Ok(Outputs { points: visible_points(&self.0, &i.points, &view, boxes) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::Box3D;

    /// A parked car's box: 4 m long along x (-2..2), 2 m wide (y 4..6), 1.5 m tall.
    fn car_box() -> Boxes3D {
        let b = Box3D {
            center: [0.0, 5.0, 0.75],
            size: [2.0, 4.0, 1.5],
            rotation: [1.0, 0.0, 0.0, 0.0],
            velocity: [f64::NAN; 3],
            instance: "car".into(),
            category: "vehicle.car".into(),
            attributes: vec![],
            num_lidar_pts: 0,
            interpolated: false,
            extrapolated: false,
        };
        Boxes3D { timestamp_us: 0, boxes: vec![b] }
    }

    #[test]
    fn an_object_hides_what_is_behind_its_returns_not_behind_the_air_of_its_box() {
        // A 4 m long, 1.5 m tall box beside the camera's line of sight, seen side-on from 5 m: its
        // returns are a low body (0.5 m) along its whole length and a cabin (1.5 m) over its
        // first metre; beyond it a wall at y = 10.
        let boxes = car_box();
        let mut xyz = Vec::new();
        for i in 0..=80 {
            let x = -2.0 + i as f64 * 0.05;
            let top = if x < -1.0 { 1.5 } else { 0.5 };
            for k in 0..=10 {
                xyz.push(DVec3::new(x, 4.0, top * k as f64 / 10.0));
            }
        }
        let own = xyz.len();
        let wall = [
            DVec3::new(-3.75, 10.0, 1.0), // behind the cabin
            DVec3::new(1.0, 10.0, 1.0),   // over the body, in the box's air
            DVec3::new(1.0, 10.0, 0.3),   // behind the body
            DVec3::new(6.0, 10.0, 0.5),   // beside the box
        ];
        xyz.extend(wall);
        let eye = DVec3::new(0.0, 0.0, 0.6);
        let mut visible = vec![true; xyz.len()];
        hide_behind_boxes(&Params::default(), &xyz, &mut visible, eye, &boxes, &Se3::from_yaw(0.0, DVec3::ZERO), 0);
        assert!(visible[..own].iter().all(|&v| v), "the object's own returns stay");
        assert_eq!(visible[own..], [false, true, false, true]);
        // Without returns the box is not known to be occupied: nothing is hidden.
        let mut visible = vec![true; wall.len()];
        hide_behind_boxes(&Params::default(), &wall, &mut visible, eye, &boxes, &Se3::from_yaw(0.0, DVec3::ZERO), 0);
        assert!(visible.iter().all(|&v| v));
    }

    #[test]
    fn an_object_hides_its_own_far_side() {
        // The car's box seen side-on: returns on its near face (y = 4, this sweep) and on its far
        // face (y = 6, seen by another keyframe's sweep from the other side). The far face's
        // returns are the object's own but behind its near face.
        let boxes = car_box();
        let face = |y: f64| {
            // One return at the middle of each 5 cm cell along the face (a cell without one is not
            // known to be occupied).
            (0..40).flat_map(move |i| (0..=10).map(move |k| DVec3::new(-0.975 + i as f64 * 0.05, y, 0.15 * k as f64)))
        };
        let xyz: Vec<DVec3> = face(4.0).chain(face(6.0)).collect();
        let near = xyz.len() / 2;
        let mut visible = vec![true; xyz.len()];
        let eye = DVec3::new(0.0, 0.0, 0.6);
        hide_behind_boxes(&Params::default(), &xyz, &mut visible, eye, &boxes, &Se3::from_yaw(0.0, DVec3::ZERO), 0);
        assert!(visible[..near].iter().all(|&v| v), "the near face stays");
        let kept: Vec<DVec3> = xyz[near..].iter().zip(&visible[near..]).filter(|(_, v)| **v).map(|(p, _)| *p).collect();
        assert!(kept.is_empty(), "the far face is hidden by the near one: {kept:?}");
    }

    #[test]
    fn a_wall_hides_what_is_behind_it() {
        // A dense wall at x = 10 (y, z in [-2, 2]) and points behind it at x = 20 within its
        // shadow; points at x = 20 outside the shadow stay visible.
        let mut pts = Vec::new();
        for i in 0..41 {
            for j in 0..41 {
                pts.push(DVec3::new(10.0, -2.0 + i as f64 * 0.1, -2.0 + j as f64 * 0.1));
            }
        }
        let wall = pts.len();
        let behind = [DVec3::new(20.0, 0.0, 0.0), DVec3::new(20.0, 1.0, -1.0), DVec3::new(20.0, -2.5, 0.5)];
        let beside = [DVec3::new(20.0, 10.0, 0.0), DVec3::new(20.0, -9.0, 3.0)];
        pts.extend(behind);
        pts.extend(beside);
        let vis = hidden_point_removal(&pts, DVec3::ZERO, 100.0 * 25.0);
        assert!(!vis[wall] && !vis[wall + 1] && !vis[wall + 2], "{:?}", &vis[wall..]);
        assert!(vis[wall + 3] && vis[wall + 4]);
        let wall_visible = vis[..wall].iter().filter(|&&v| v).count();
        assert!(wall_visible as f64 > 0.95 * wall as f64, "{wall_visible}/{wall}");
    }

    #[test]
    fn a_hidden_point_comes_back_unless_a_kept_point_beside_it_is_nearer() {
        // Camera at the origin looking along +z of the cloud frame, 160x120, f = 100.
        let view = CameraView::looking_along_z(160, 120, 100.0);
        let at = |u: f64, v: f64, z: f64| DVec3::new((u + 0.5 - 80.0) / 100.0 * z, (v + 0.5 - 60.0) / 100.0 * z, z);
        // Kept: a pole 5 m away in column 40, rows 20..100 every 10 rows (LiDAR rings), and a
        // wall point 30 m away at (104, 55).
        let mut xyz: Vec<DVec3> = (2..10).map(|r| at(40.0, r as f64 * 10.0, 5.0)).collect();
        xyz.push(at(104.0, 55.0, 30.0));
        let hidden = [
            at(43.0, 45.0, 30.0),  // behind the pole, between two of its rings: stays hidden
            at(60.0, 50.0, 30.0),  // 20 px beside the pole: nothing nearer around it
            at(100.0, 50.0, 31.0), // beside a wall point at about its depth
            at(104.0, 70.0, 40.0), // 10 rows below the wall point, 25% further: occluded
        ];
        let kept = xyz.len();
        xyz.extend(hidden);
        let mut visible: Vec<bool> = (0..xyz.len()).map(|i| i < kept).collect();
        // 9 kept points in 160 x 120 px: a mean spacing of 46 px, so the window is 6 x 20 px.
        let params = Params { restore_window: [0.13, 0.435], ..Params::default() };
        restore_unoccluded(&params, &xyz, &mut visible, &view);
        assert_eq!(&visible[kept..], &[false, true, true, false]);
        // A zero window keeps Katz et al.'s set.
        let mut katz: Vec<bool> = (0..xyz.len()).map(|i| i < kept).collect();
        restore_unoccluded(&Params { restore_window: [0.0, 0.0], ..params }, &xyz, &mut katz, &view);
        assert!(katz[kept..].iter().all(|&v| !v));
    }

    #[test]
    fn window_minimum_is_the_splat_of_every_point_in_reach() {
        // Against the image-sized splat it replaced: points inside, at and beyond the border.
        let mut rng = dist4d_types::rng::Rng::new(4);
        let (w, h) = (97i64, 61i64);
        for (rx, ry) in [(0, 0), (1, 3), (4, 9), (30, 70)] {
            let points: Vec<(i64, i64, f32)> = (0..400)
                .map(|_| {
                    let u = rng.range(-45.0, w as f64 + 45.0).floor() as i64;
                    let v = rng.range(-80.0, h as f64 + 80.0).floor() as i64;
                    (u, v, rng.range(1.0, 50.0) as f32)
                })
                .collect();
            let mut splat = vec![f32::INFINITY; (w * h) as usize];
            for &(u, v, z) in &points {
                for y in (v - ry).max(0)..(v + ry + 1).min(h) {
                    for x in (u - rx).max(0)..(u + rx + 1).min(w) {
                        let n = &mut splat[(y * w + x) as usize];
                        *n = n.min(z);
                    }
                }
            }
            let grid = WindowMin::new(&points, (w, h), (rx, ry));
            for y in 0..h {
                for x in 0..w {
                    assert_eq!(grid.nearest(x, y).to_bits(), splat[(y * w + x) as usize].to_bits(), "({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn the_camera_centre_itself_is_hidden() {
        let pts = [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z, DVec3::new(1.0, 1.0, 1.0)];
        let vis = hidden_point_removal(&pts, DVec3::ZERO, 100.0);
        assert!(!vis[0]);
    }
}
