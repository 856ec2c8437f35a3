//! `EvalCloud`: how much of a bullet-time cloud (`SurroundCloud`) is surface and how much flies.
//!
//! On any dataset:
//! - `beyond_far`: the share of points farther than `far_range` (50 m) from the cloud's origin
//!   (the ego at the step). The surround cameras see little real surface that far, and a
//!   cloud of flying pixels puts a third of its points there (the rays run on to the sky's
//!   100 m).
//! - `isolated_near`: the points within `near_range` (30 m) whose nearest other point is farther
//!   than `isolation` (1 m). Near the ego a surface is sampled every few centimetres, so a point
//!   alone there hangs in the air. Found with a hash of `isolation`-sized voxels (the 27 voxels
//!   around a point hold every point within `isolation` of it).
//!
//! On a synthetic dataset (`dataset.synth_world`), also `on_surface`: the share of points within
//! `surface_tolerance` (0.2 m) of the world's exact surface, with the moving objects where they
//! are at the time of the cameras that see the point. A point is on the surface when the ray
//! from one of the cameras that see it (`calibs` and `poses`, each at its own time) first meets
//! the world within the tolerance of it, or when a surface lies within the tolerance of it
//! ([`dist4d_synth::Snapshot::near_surface`]: the ground by its height, the primitives by 26
//! short rays; a point inside a primitive counts as on it). Both tests find a surface point at
//! that distance, so the share is never above the truth; the short rays can miss a plane between
//! 0.89 and 1 tolerance away.
//!
//! `dist4d eval` tabulates the three per step (the item's variant) with a mean row.

use dist4d_runtime::Made;
use crate::views::splat::PinholeView;
use crate::stage::Stage;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Calibration, File, PointCloud, Pose};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Metres from the cloud's origin beyond which a point counts in `beyond_far`.
    pub far_range: f64,
    /// Metres from the origin within which a lone point counts in `isolated_near`.
    pub near_range: f64,
    /// Metres: a point whose nearest neighbour is farther than this is alone.
    pub isolation: f64,
    /// Metres from the exact surface within which a point is on it (synthetic data).
    pub surface_tolerance: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { far_range: 50.0, near_range: 30.0, isolation: 1.0, surface_tolerance: 0.2 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .above("far_range", self.far_range, 0.0, 1e6)
            .above("near_range", self.near_range, 0.0, 1e6)
            .above("isolation", self.isolation, 0.0, 1e3)
            .above("surface_tolerance", self.surface_tolerance, 0.0, 1e3)
            .done()
    }
}

/// The scores of one cloud.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
pub struct CloudScores {
    pub points: u64,
    /// Share of the points beyond `far_range`.
    pub beyond_far: f64,
    /// Points within `near_range` whose nearest neighbour is farther than `isolation`.
    pub isolated_near: u64,
    /// Share of the points within `surface_tolerance` of the exact surface (synthetic data).
    pub on_surface: Option<f64>,
}

crate::inputs! {
    pub struct Inputs {
        /// the bullet-time cloud (`cloud.points`), in the ego frame of the rig's first camera
        points: One<PointCloud>,
        /// the cloud's frame: the first camera's ego pose at the step (`future.pose` of the task
        /// that made the cloud)
        pose: One<Pose>,
        /// the synthetic world (`dataset.synth_world`; empty elsewhere: no `on_surface`)
        world: One<File>,
        /// every camera of the step (`Across("dataset.camera_calib", camera)`)
        calibs: Many<Calibration>,
        /// their ego poses at the step (`Across("future.pose", camera)`), with their times
        poses: Many<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the scores, JSON
        json: One<File>,
    }
}

pub struct EvalCloud(Params);

impl Stage for EvalCloud {
    const KIND: &'static str = "EvalCloud";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "a bullet-time cloud's flying pixels: share beyond 50 m, lone points within 30 m, share on the exact surface";
    const GRAINS: &'static [&'static str] = &["variant"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EvalCloud(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let mut s = range_scores(&self.0, &i.points);
        if !i.world.0.is_empty() {
            s.on_surface = Some(on_surface(&self.0, &i)?);
        }
        Ok(Outputs { json: File(serde_json::to_vec(&s)?) }.into())
    }
}

/// `points`, `beyond_far` and `isolated_near` of a cloud.
pub fn range_scores(p: &Params, cloud: &PointCloud) -> CloudScores {
    let pts: Vec<DVec3> = cloud.points.iter().map(|q| DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64)).collect();
    let n = pts.len();
    let beyond = pts.iter().filter(|q| q.length() > p.far_range).count();
    let cell = |q: &DVec3| ((q.x / p.isolation).floor() as i64, (q.y / p.isolation).floor() as i64, (q.z / p.isolation).floor() as i64);
    let mut voxels: HashMap<(i64, i64, i64), Vec<u32>> = HashMap::new();
    for (k, q) in pts.iter().enumerate() {
        voxels.entry(cell(q)).or_default().push(k as u32);
    }
    let r2 = p.isolation * p.isolation;
    let mut isolated = 0u64;
    for (k, q) in pts.iter().enumerate() {
        if q.length() >= p.near_range {
            continue;
        }
        let (cx, cy, cz) = cell(q);
        let mut alone = true;
        'search: for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(list) = voxels.get(&(cx + dx, cy + dy, cz + dz)) {
                        if list.iter().any(|&m| m as usize != k && pts[m as usize].distance_squared(*q) <= r2) {
                            alone = false;
                            break 'search;
                        }
                    }
                }
            }
        }
        isolated += alone as u64;
    }
    CloudScores { points: n as u64, beyond_far: beyond as f64 / n.max(1) as f64, isolated_near: isolated, on_surface: None }
}

/// The share of the cloud's points on the exact surface (see the module doc).
fn on_surface(p: &Params, i: &Inputs) -> Result<f64> {
    let renderer = dist4d_synth::Renderer::shared(&i.world.0)?;
    let world: serde_json::Value = serde_json::from_slice(&i.world.0)?;
    let name = world["scene"].as_str().unwrap_or_default();
    let scene = renderer.scene_index(name).with_context(|| format!("the synthetic world has no scene `{name}`"))?;
    ensure!(
        i.calibs.len() == i.poses.len() && i.calibs.iter().zip(&i.poses).all(|(c, q)| c.0 == q.0),
        "`calibs` and `poses` must be wired with the same selector (Across(.., camera))"
    );
    let cams: Vec<(PinholeView, i64)> = i
        .calibs
        .iter()
        .zip(&i.poses)
        .map(|((_, c), (_, q))| Ok((PinholeView::new(c, q)?, q.timestamp_us)))
        .collect::<Result<_>>()?;
    let mut snapshots = HashMap::new();
    for (_, t) in &cams {
        if !snapshots.contains_key(t) {
            snapshots.insert(*t, renderer.snapshot_at_timestamp(scene, *t)?);
        }
    }
    let cam_from_world: Vec<_> = cams.iter().map(|(v, _)| v.world_from_cam.inverse()).collect();
    let tol = p.surface_tolerance;
    let mut on = 0u64;
    for q in &i.points.points {
        let world = i.pose.ego_to_world.apply(DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64));
        let mut seen_by = Vec::new();
        let mut found = false;
        for (k, (view, t)) in cams.iter().enumerate() {
            let c = cam_from_world[k].apply(world);
            if c.z <= 0.0 {
                continue;
            }
            let (u, v, _) = view.project(c);
            if u < 0.0 || v < 0.0 || u >= view.width as f64 || v >= view.height as f64 {
                continue;
            }
            seen_by.push(*t);
            let centre = view.world_from_cam.translation;
            let (dir, dist) = ((world - centre).normalize(), world.distance(centre));
            if let Some(hit) = snapshots[t].cast(centre, dir, dist + tol) {
                if (hit.t - dist).abs() <= tol {
                    found = true;
                    break;
                }
            }
        }
        if !found {
            if seen_by.is_empty() {
                seen_by = cams.iter().map(|(_, t)| *t).collect();
            }
            seen_by.dedup();
            found = seen_by.iter().any(|t| snapshots[t].near_surface(world, tol));
        }
        on += found as u64;
        dist4d_types::cancel::check()?;
    }
    Ok(on as f64 / i.points.points.len().max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(points: &[[f32; 3]]) -> PointCloud {
        PointCloud { points: points.iter().map(|p| [p[0], p[1], p[2], 0.0]).collect(), ..PointCloud::default() }
    }

    #[test]
    fn far_and_lone_points_are_counted() {
        // A 2 x 2 m patch sampled every 0.1 m at 10 m, two points alone at 20 m and 40 m (the
        // one at 40 m is beyond near_range) and one beyond 50 m.
        let mut pts = Vec::new();
        for a in 0..20 {
            for b in 0..20 {
                pts.push([10.0, a as f32 * 0.1, b as f32 * 0.1]);
            }
        }
        pts.extend([[20.0, 0.0, 1.0], [40.0, 0.0, 1.0], [60.0, 0.0, 1.0]]);
        let s = range_scores(&Params::default(), &cloud(&pts));
        assert_eq!(s.points, 403);
        assert_eq!(s.isolated_near, 1);
        assert!((s.beyond_far - 1.0 / 403.0).abs() < 1e-12);
        // Two points 0.9 m apart keep each other company.
        let s = range_scores(&Params::default(), &cloud(&[[5.0, 0.0, 0.0], [5.9, 0.0, 0.0]]));
        assert_eq!(s.isolated_near, 0);
    }
}
