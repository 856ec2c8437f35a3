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
//! Only points inside the camera's view (in front, within the image grown by `frustum_margin`)
//! go into the hull: the others never reach the image, and leaving them out makes the hull 5-6x
//! smaller for a surround rig.

use crate::artifact::PointCloud;
use crate::camera::CameraView;
use crate::hull::hull_vertices;
use crate::stage::{one, StageDef, TypedOp};
use anyhow::Result;
use dist4d_graph::PortSpec;
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
}

impl Default for Params {
    fn default() -> Self {
        Params { radius_factor: 400.0, min_depth: 0.1, frustum_margin: 0.05 }
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

/// The visible points of `points` (in the frame `view` maps from), in their original order.
pub fn visible_points(params: &Params, points: &PointCloud, view: &CameraView) -> PointCloud {
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
    let visible = hidden_point_removal(&xyz, centre, radius);
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

struct Op(Params);

impl TypedOp for Op {
    fn run(&self, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Vec<Vec<u8>>> {
        let points = one::<PointCloud>(inputs, 0)?;
        let view = CameraView::from_inputs(inputs)?;
        use crate::artifact::Artifact;
        Ok(vec![visible_points(&self.0, &points, &view).encode()])
    }
}

pub fn def() -> StageDef {
    StageDef::new::<Params>(
        "HiddenPointRemoval",
        1,
        "Point cloud -> the points one camera can see (Katz et al. 2007 spherical flip + convex hull)",
        crate::camera::cloud_and_camera_ports("the cloud, in the frame of `cloud_calib` at `cloud_pose`"),
        vec![PortSpec::one("points", "PointCloud", "the visible points, same frame, in input order")],
        vec!["camera"],
        |p: Params| Ok(Box::new(Op(p))),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn the_camera_centre_itself_is_hidden() {
        let pts = [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z, DVec3::new(1.0, 1.0, 1.0)];
        let vis = hidden_point_removal(&pts, DVec3::ZERO, 100.0);
        assert!(!vis[0]);
    }
}
