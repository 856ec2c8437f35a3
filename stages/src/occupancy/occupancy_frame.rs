//! `Occupancy`: one frame's semantic occupancy in the Occ3D layout, from its scene's aggregate
//! ([`super::aggregate_scene`]):
//!
//! 1. **Semantics.** The static points, moved into the frame's ego frame, vote for the class of
//!    their voxel (the most points win; ties go to the lower class); then every box of the frame
//!    whose track has points draws them at its pose at this time, with the track's class, over
//!    what the static points said. Every other voxel is free (17). Then the ground is densified
//!    (`ground_fill` > 0): a LiDAR sees the road as rings metres apart, so on the bird's-eye view
//!    of the ground classes (driveable surface, other flat, sidewalk, terrain, in the two lowest
//!    layers) a morphological closing with a square of `2 * ground_fill + 1` voxels fills the
//!    gaps between rings (no wider than twice `ground_fill`) without growing the ground past its
//!    outer edge; a filled column takes the most common class and layer of the ground around it.
//!    The rings' spacing grows with range (a few metres at 20-40 m on a keyframe), wider than that
//!    closing bridges: columns at least `ground_fill_far_from` metres from the ego get a second
//!    closing, with a disc of radius `ground_fill_far` voxels (0: none; a square that wide
//!    leaves rectangular blocks on sparse real sweeps). Without it a sixth of the exact road of a
//!    keyframe was left free, half of it inside `mask_lidar`, teaching "free" on the road.
//! 2. **`mask_lidar`.** The frame's own sweep, ray by ray from the LiDAR to each return
//!    (Amanatides-Woo traversal): the voxels a ray passes through and the one it ends in were
//!    observed (Occ3D: "if a LiDAR beam passes through a voxel in the air, the voxel is free").
//! 3. **`mask_camera`.** From each camera of the frame, a ray every `camera_ray_step` pixels,
//!    through the voxels until the first occupied one (included) or `camera_max_distance`; a voxel
//!    is camera-visible when such a ray reaches it and the LiDAR observed it (in Occ3D's files
//!    `mask_camera` is a subset of `mask_lidar`).
//!
//! Grid and frame: [`super::grid`].
//!
//! Beside the grid the stage writes the frame's metadata (`meta`, JSON, exported beside
//! `labels.npz`): where its semantics come from (`semantics_source`, the scene's
//! `AggregateScene` summary's: `lidarseg`, `camera`, `geometry`, ...), so that a loader can
//! leave geometry-only frames out of a semantic loss.

use dist4d_runtime::Made;
use super::classes::FREE;
use super::grid::GridParams;
use crate::stage::Stage;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Boxes3D, Calibration, File, Mask, OccupancyGrid, PointCloud, Pose, TrackClouds};
use dist4d_types::geometry::Se3;
use dist4d_types::voxels::{cast_masks, MaskCamera};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    pub grid: GridParams,
    /// One camera ray per this many pixels in each direction.
    pub camera_ray_step: u32,
    /// Camera rays stop after this distance (m).
    pub camera_max_distance: f64,
    /// The ground's closing radius (voxels); 0 = no densification (see the module doc).
    pub ground_fill: u32,
    /// The far ground's closing radius (voxels); 0 = none.
    pub ground_fill_far: u32,
    /// Where the far closing starts: distance (m, bird's-eye) from the ego.
    pub ground_fill_far_from: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            grid: GridParams::default(),
            camera_ray_step: 4,
            camera_max_distance: 100.0,
            ground_fill: 3,
            ground_fill_far: 8,
            ground_fill_far_from: 15.0,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        self.grid.check(&mut c);
        c.count("ground_fill", self.ground_fill as u64, 0, 64)
            .count("ground_fill_far", self.ground_fill_far as u64, 0, 64)
            .within("ground_fill_far_from", self.ground_fill_far_from, 0.0, 10_000.0);
        c.count("camera_ray_step", self.camera_ray_step as u64, 1, 256).above(
            "camera_max_distance",
            self.camera_max_distance,
            0.0,
            10_000.0,
        );
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the scene's static points (world frame, Occ3D classes)
        static_points: One<PointCloud>,
        /// the scene's tracked objects in their box frames
        tracks: One<TrackClouds>,
        /// the boxes at the frame's time (`dataset.boxes`)
        boxes: One<Boxes3D>,
        /// the frame's own sweep, for the LiDAR rays
        sweep: One<PointCloud>,
        /// its LiDAR calibration
        lidar_calib: One<Calibration>,
        /// the ego pose at the sweep: the grid's frame
        lidar_pose: One<Pose>,
        /// every camera of the frame (`Gather("dataset.camera_calib", camera)`)
        camera_calibs: Many<Calibration>,
        /// their ego poses (`Gather("dataset.camera_pose", camera)`)
        camera_poses: Many<Pose>,
        /// the scene's `AggregateScene` summary (`scene.summary`), for the frame's metadata
        scene_summary: Optional<File>,
        /// the ego body in each camera (`Gather("ego.mask", camera)`): no camera ray is cast
        /// through it (the hood hides what lies behind it)
        ego_masks: OptionalMany<Mask>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// semantics, mask_lidar and mask_camera
        grid: One<OccupancyGrid>,
        /// JSON: the frame's metadata (`semantics_source`: where its classes come from)
        meta: One<File>,
    }
}

pub struct Occupancy(Params);

impl Stage for Occupancy {
    const KIND: &'static str = "Occupancy";
    // 2: the far ground closing; the metadata.
    // 3: the far closing with a disc.
    const VERSION: u32 = 3;
    const SUMMARY: &'static str =
        "a frame's semantic occupancy (Occ3D): the scene's static points and tracks voxelized, LiDAR and camera visibility";
    const GRAINS: &'static [&'static str] = &["frame"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["camera_calibs", "camera_poses"]];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(Occupancy(params))
    }

    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        ensure!(
            i.camera_calibs.len() == i.camera_poses.len(),
            "`camera_calibs` and `camera_poses` hold {} and {} items: wire both with Gather(.., camera)",
            i.camera_calibs.len(),
            i.camera_poses.len()
        );
        let ego_from_world = i.lidar_pose.ego_to_world.inverse();
        let cameras: Vec<(&Calibration, &Pose)> =
            i.camera_calibs.iter().zip(&i.camera_poses).map(|((_, c), (_, p))| (c, p)).collect();
        let grid = occupancy(&self.0, &i.static_points, &i.tracks, &i.boxes, &ego_from_world)?;
        // Each camera's ego mask, matched by its position in the gather.
        let blocked: Vec<Option<&Mask>> = i
            .camera_calibs
            .iter()
            .map(|(pos, _)| i.ego_masks.iter().find(|(p, _)| p == pos).map(|(_, m)| m))
            .collect();
        let grid = with_blocked_masks(&self.0, grid, &i.sweep, &i.lidar_calib, &ego_from_world, &cameras, &blocked)?;
        let meta = frame_meta(i.scene_summary.as_ref(), ctx.label)?;
        Ok(Outputs { grid, meta: File(serde_json::to_vec_pretty(&meta)?) }.into())
    }
}

/// The frame's metadata (module doc), from its scene's summary (`unknown` when not wired).
pub fn frame_meta(scene_summary: Option<&File>, item: &str) -> Result<serde_json::Value> {
    let (source, labels) = match scene_summary {
        None => ("unknown".to_string(), "the pipeline does not wire `scene_summary`".to_string()),
        Some(f) => {
            let v: serde_json::Value =
                serde_json::from_slice(&f.0).context("`scene_summary`: the AggregateScene summary is not JSON")?;
            let source = v["semantics_source"]
                .as_str()
                .context("`scene_summary` has no `semantics_source`: wire it from an AggregateScene's `summary`")?;
            (source.to_string(), v["labels"].as_str().unwrap_or_default().to_string())
        }
    };
    Ok(serde_json::json!({
        "item": item,
        "semantics_source": source,
        "geometry_only": source == "geometry",
        "labels": labels,
    }))
}

/// Step 1 of the module doc: the semantics (masks all 0).
pub fn occupancy(
    p: &Params,
    static_points: &PointCloud,
    tracks: &TrackClouds,
    boxes: &Boxes3D,
    ego_from_world: &Se3,
) -> Result<OccupancyGrid> {
    let g = p.grid.grid();
    ensure!(
        static_points.labels.len() == static_points.points.len(),
        "the static points have {} labels for {} points",
        static_points.labels.len(),
        static_points.points.len()
    );
    let mut votes: HashMap<usize, [u32; 17]> = HashMap::new();
    for (q, &class) in static_points.points.iter().zip(&static_points.labels) {
        if class >= FREE {
            continue;
        }
        let ego = ego_from_world.apply(DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64));
        if let Some(v) = g.index(ego) {
            votes.entry(v).or_insert([0; 17])[class as usize] += 1;
        }
    }
    let best = |counts: &[u32; 17]| {
        counts.iter().enumerate().fold((0, 0), |(bc, bn), (c, &n)| if n > bn { (c, n) } else { (bc, bn) }).0 as u8
    };
    let nz = g.dims[2];
    let mut semantics = vec![FREE; g.len()];
    for (v, counts) in &votes {
        let class = best(counts);
        // The ground is a surface: a ground voxel stacked on a ground voxel that more points
        // voted for is the surface's noise straddling the layer boundary (a sidewalk 0.15 m up
        // in a layer topping at 0.2 m), not a second layer of ground; at 20 Hz, with ten times
        // the points, it put a false layer of sidewalk over 5% of the sidewalk.
        if is_ground(class) && v % nz > 0 {
            if let Some(below) = votes.get(&(v - 1)) {
                if is_ground(best(below)) && below.iter().sum::<u32>() > counts.iter().sum::<u32>() {
                    continue;
                }
            }
        }
        semantics[*v] = class;
    }
    let by_instance: HashMap<&str, usize> = tracks.tracks.iter().enumerate().map(|(k, t)| (t.instance.as_str(), k)).collect();
    for b in &boxes.boxes {
        let Some(&k) = by_instance.get(b.instance.as_str()) else { continue };
        let track = &tracks.tracks[k];
        let ego_from_box = ego_from_world.then_from(&Se3::from_wxyz_t(b.rotation, b.center));
        for q in &track.points {
            if let Some(v) = g.index(ego_from_box.apply(DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64))) {
                semantics[v] = track.class;
            }
        }
    }
    if p.ground_fill > 0 {
        fill_ground(&mut semantics, g.dims, p.ground_fill as usize, Shape::Square, |_, _| true);
    }
    if p.ground_fill_far > 0 {
        // A column's bird's-eye distance from the ego (the ego frame's origin), m.
        let (min, voxel, from) = (g.min, g.voxel, p.ground_fill_far_from);
        let far = move |i: usize, j: usize| {
            (min.x + (i as f64 + 0.5) * voxel).hypot(min.y + (j as f64 + 0.5) * voxel) >= from
        };
        fill_ground(&mut semantics, g.dims, p.ground_fill_far as usize, Shape::Disc, far);
    }
    let n = g.len();
    Ok(OccupancyGrid {
        dims: g.dims.map(|d| d as u32),
        semantics,
        mask_lidar: vec![0; n],
        mask_camera: vec![0; n],
    })
}

/// The structuring element of a ground closing.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Shape {
    Square,
    /// For the far closing: a square that wide bridges diagonal gaps 1.4 times as wide and
    /// leaves rectangular blocks on sparse real sweeps.
    Disc,
}

/// The ground classes: driveable surface, other flat, sidewalk, terrain.
fn is_ground(class: u8) -> bool {
    (11..=14).contains(&class)
}

/// The ground densification of the module doc, on `semantics` (C order over `dims`): a closing
/// of radius `r`, filling only the columns (i, j) that `fills` allows.
fn fill_ground(semantics: &mut [u8], dims: [usize; 3], r: usize, shape: Shape, fills: impl Fn(usize, usize) -> bool) {
    let [nx, ny, nz] = dims;
    let low = nz.min(2);
    // Per column: its ground (layer, class) in the lowest layers, and whether anything occupies
    // them (a column with an object or a wall at the bottom is not filled).
    let mut ground: Vec<Option<(usize, u8)>> = vec![None; nx * ny];
    let mut taken = vec![false; nx * ny];
    for c in 0..nx * ny {
        for k in 0..low {
            let s = semantics[c * nz + k];
            if s != FREE {
                taken[c] = true;
                if is_ground(s) && ground[c].is_none() {
                    ground[c] = Some((k, s));
                }
            }
        }
    }
    // Closing = dilation then erosion, with a (2r+1)^2 square (separable: rows, then columns) or
    // a disc of radius r.
    let disc: Vec<(i64, i64)> = {
        let r = r as i64;
        (-r..=r).flat_map(|a| (-r..=r).map(move |b| (a, b))).filter(|(a, b)| a * a + b * b <= r * r).collect()
    };
    let box_any = |mask: &[bool]| -> Vec<bool> {
        if shape == Shape::Disc {
            let mut out = vec![false; nx * ny];
            for i in 0..nx {
                for j in 0..ny {
                    if !mask[i * ny + j] {
                        continue;
                    }
                    for &(a, b) in &disc {
                        let (ii, jj) = (i as i64 + a, j as i64 + b);
                        if ii >= 0 && jj >= 0 && (ii as usize) < nx && (jj as usize) < ny {
                            out[ii as usize * ny + jj as usize] = true;
                        }
                    }
                }
            }
            return out;
        }
        let mut rows = vec![false; nx * ny];
        for i in 0..nx {
            for j in 0..ny {
                let (a, b) = (j.saturating_sub(r), (j + r).min(ny - 1));
                rows[i * ny + j] = (a..=b).any(|jj| mask[i * ny + jj]);
            }
        }
        let mut out = vec![false; nx * ny];
        for i in 0..nx {
            for j in 0..ny {
                let (a, b) = (i.saturating_sub(r), (i + r).min(nx - 1));
                out[i * ny + j] = (a..=b).any(|ii| rows[ii * ny + j]);
            }
        }
        out
    };
    let is: Vec<bool> = ground.iter().map(Option::is_some).collect();
    let dilated = box_any(&is);
    let not_dilated: Vec<bool> = dilated.iter().map(|d| !d).collect();
    let closed: Vec<bool> = box_any(&not_dilated).iter().map(|d| !d).collect();
    for i in 0..nx {
        for j in 0..ny {
            let c = i * ny + j;
            if !closed[c] || taken[c] || !fills(i, j) {
                continue;
            }
            // The most common (layer, class) of the ground around it.
            let mut counts: HashMap<(usize, u8), u32> = HashMap::new();
            for ii in i.saturating_sub(r)..=(i + r).min(nx - 1) {
                for jj in j.saturating_sub(r)..=(j + r).min(ny - 1) {
                    if let Some(g) = ground[ii * ny + jj] {
                        *counts.entry(g).or_default() += 1;
                    }
                }
            }
            if let Some(((k, class), _)) = counts.into_iter().max_by_key(|&((k, class), n)| (n, std::cmp::Reverse((k, class)))) {
                semantics[c * nz + k] = class;
            }
        }
    }
}

/// Steps 2 and 3 of the module doc ([`dist4d_types::voxels::cast_masks`]).
pub fn with_masks(
    p: &Params,
    grid: OccupancyGrid,
    sweep: &PointCloud,
    lidar_calib: &Calibration,
    ego_from_world: &Se3,
    cameras: &[(&Calibration, &Pose)],
) -> Result<OccupancyGrid> {
    with_blocked_masks(p, grid, sweep, lidar_calib, ego_from_world, cameras, &[])
}

/// [`with_masks`] where `blocked[k]`, when given, is camera k's ego mask: no ray through it.
pub fn with_blocked_masks(
    p: &Params,
    mut grid: OccupancyGrid,
    sweep: &PointCloud,
    lidar_calib: &Calibration,
    ego_from_world: &Se3,
    cameras: &[(&Calibration, &Pose)],
    blocked: &[Option<&Mask>],
) -> Result<OccupancyGrid> {
    let g = p.grid.grid();
    ensure!(grid.voxels() == g.len(), "the grid has {} voxels, its params {}", grid.voxels(), g.len());
    let mut views = Vec::with_capacity(cameras.len());
    for (k, (calib, pose)) in cameras.iter().enumerate() {
        let blocked = match blocked.get(k).copied().flatten() {
            Some(m) if m.width > 0 => {
                ensure!(
                    (m.width, m.height) == (calib.width, calib.height),
                    "camera {k}: its ego mask is {}x{}, its calibration {}x{}",
                    m.width,
                    m.height,
                    calib.width,
                    calib.height
                );
                m.data.clone()
            }
            _ => Vec::new(),
        };
        views.push(MaskCamera {
            ego_from_camera: ego_from_world.then_from(&pose.ego_to_world.then_from(&calib.sensor_to_ego)),
            k: calib.intrinsics.with_context(|| format!("camera {k}: its calibration has no intrinsics"))?,
            width: calib.width,
            height: calib.height,
            blocked,
        });
    }
    let returns = sweep
        .points
        .iter()
        .map(|q| lidar_calib.sensor_to_ego.apply(DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64)));
    let (lidar, camera) = cast_masks(
        &g,
        &grid.semantics,
        FREE,
        lidar_calib.sensor_to_ego.translation,
        returns,
        &views,
        p.camera_ray_step as usize,
        p.camera_max_distance,
    );
    grid.mask_lidar = lidar;
    grid.mask_camera = camera;
    Ok(grid)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::{Box3D, TrackCloud};

    fn flat_road_and_a_car() -> (PointCloud, TrackClouds, Boxes3D) {
        // Road points every 0.1 m around the origin, at world z = 0.
        let mut road = PointCloud::default();
        for i in -100..100 {
            for j in -100..100 {
                road.points.push([i as f32 * 0.1, j as f32 * 0.1, 0.0, 0.0]);
                road.labels.push(11);
            }
        }
        let car = TrackCloud {
            instance: "car".into(),
            class: 4,
            points: (0..20).flat_map(|a| (0..8).map(move |c| [a as f32 * 0.2 - 2.0, 0.0, c as f32 * 0.2 - 0.7])).collect(),
        };
        let boxes = Boxes3D {
            timestamp_us: 0,
            boxes: vec![Box3D {
                center: [8.0, 0.0, 0.8],
                size: [1.8, 4.0, 1.6],
                rotation: [1.0, 0.0, 0.0, 0.0],
                velocity: [0.0; 3],
                instance: "car".into(),
                category: "vehicle.car".into(),
                attributes: Vec::new(),
                num_lidar_pts: 0,
                interpolated: false,
                extrapolated: false,
            }],
        };
        (road, TrackClouds { tracks: vec![car] }, boxes)
    }

    #[test]
    fn the_ground_closing_fills_the_gaps_between_rings_and_not_past_the_edge() {
        // Rings of road 1.6 m apart (every 4th row of voxels) over x in [-8, 8], y in [-4, 4].
        let mut rings = PointCloud::default();
        for i in -20..20 {
            for j in -10..10 {
                if i % 4 == 0 {
                    rings.points.push([i as f32 * 0.4 + 0.2, j as f32 * 0.4 + 0.2, 0.0, 0.0]);
                    rings.labels.push(11);
                }
            }
        }
        let p = Params { ground_fill: 2, ..Params::default() };
        let g = p.grid.grid();
        let grid = occupancy(&p, &rings, &TrackClouds::default(), &Boxes3D::default(), &Se3::default()).unwrap();
        let at = |x: f64, y: f64| grid.semantics[g.index(DVec3::new(x, y, 0.0)).unwrap()];
        assert_eq!(at(0.6, 0.2), 11, "between two rings");
        assert_eq!(at(0.6, 3.8), 11);
        assert_eq!(at(0.6, 5.0), FREE, "past the road's edge");
        let none = occupancy(&Params { ground_fill: 0, ..p }, &rings, &TrackClouds::default(), &Boxes3D::default(), &Se3::default()).unwrap();
        assert_eq!(none.semantics[g.index(DVec3::new(0.6, 0.2, 0.0)).unwrap()], FREE);
    }

    #[test]
    fn far_rings_metres_apart_are_closed_beyond_ground_fill_far_from_only() {
        // Rings of road 3.2 m apart (every 8th row of voxels), x in [-36, 36] m, y in [-4, 4] m.
        let mut rings = PointCloud::default();
        for i in -90..90 {
            for j in -10..10 {
                if i % 8 == 0 {
                    rings.points.push([i as f32 * 0.4 + 0.2, j as f32 * 0.4 + 0.2, 0.0, 0.0]);
                    rings.labels.push(11);
                }
            }
        }
        let p = Params::default();
        let g = p.grid.grid();
        let at = |grid: &OccupancyGrid, x: f64, y: f64| grid.semantics[g.index(DVec3::new(x, y, 0.0)).unwrap()];
        let grid = occupancy(&p, &rings, &TrackClouds::default(), &Boxes3D::default(), &Se3::default()).unwrap();
        assert_eq!(at(&grid, 25.0, 0.2), 11, "between two far rings");
        assert_eq!(at(&grid, -25.0, 0.2), 11, "behind too");
        assert_eq!(at(&grid, 5.0, 0.2), FREE, "near rings 3.2 m apart are wider than `ground_fill`");
        assert_eq!(at(&grid, 25.0, 5.0), FREE, "past the road's edge");
        let none = Params { ground_fill_far: 0, ..Params::default() };
        let grid = occupancy(&none, &rings, &TrackClouds::default(), &Boxes3D::default(), &Se3::default()).unwrap();
        assert_eq!(at(&grid, 25.0, 0.2), FREE);
    }

    #[test]
    fn a_few_ground_points_over_a_ground_voxel_are_not_a_second_layer() {
        // A sidewalk at z = 0.15 (layer 0 spans -0.2..0.2 m), 20 points a voxel, and in one
        // column 2 noisy returns at 0.25 m (layer 1); a wall's foot keeps its two layers.
        let mut cloud = PointCloud::default();
        for n in 0..20 {
            cloud.points.push([4.2 + n as f32 * 0.01, 0.2, 0.15, 0.0]);
            cloud.labels.push(13);
            cloud.points.push([8.2 + n as f32 * 0.01, 0.2, 0.15, 0.0]);
            cloud.labels.push(13);
        }
        for n in 0..2 {
            cloud.points.push([4.2 + n as f32 * 0.01, 0.2, 0.25, 0.0]);
            cloud.labels.push(13);
            cloud.points.push([8.2 + n as f32 * 0.01, 0.2, 0.25, 0.0]);
            cloud.labels.push(15);
        }
        let p = Params { ground_fill: 0, ground_fill_far: 0, ..Params::default() };
        let g = p.grid.grid();
        let grid = occupancy(&p, &cloud, &TrackClouds::default(), &Boxes3D::default(), &Se3::default()).unwrap();
        let at = |x: f64, z: f64| grid.semantics[g.index(DVec3::new(x, 0.2, z)).unwrap()];
        assert_eq!((at(4.3, 0.15), at(4.3, 0.25)), (13, FREE), "sidewalk, and no sidewalk above it");
        assert_eq!((at(8.3, 0.15), at(8.3, 0.25)), (13, 15), "not ground: kept");
    }

    #[test]
    fn the_frame_metadata_repeats_the_scenes_semantics_source() {
        let summary = File(br#"{"semantics_source": "geometry", "labels": "geometry only: ..."}"#.to_vec());
        let meta = frame_meta(Some(&summary), "s/000").unwrap();
        assert_eq!((meta["semantics_source"].as_str(), meta["geometry_only"].as_bool()), (Some("geometry"), Some(true)));
        assert_eq!(frame_meta(None, "s/000").unwrap()["semantics_source"], "unknown");
        assert!(frame_meta(Some(&File(b"{}".to_vec())), "s/000").is_err(), "a summary without the field is miswired");
    }

    #[test]
    fn the_road_fills_layer_zero_a_car_stands_at_its_box_and_rays_mark_what_they_saw() {
        let (road, tracks, boxes) = flat_road_and_a_car();
        let p = Params::default();
        let g = p.grid.grid();
        let grid = occupancy(&p, &road, &tracks, &boxes, &Se3::default()).unwrap();
        let at = |x: f64, y: f64, z: f64| grid.semantics[g.index(DVec3::new(x, y, z)).unwrap()];
        assert_eq!(at(0.1, 0.1, 0.0), 11);
        assert_eq!(g.index(DVec3::new(0.1, 0.1, 0.0)).unwrap() % 16, 0);
        assert_eq!(at(0.1, 0.1, 0.5), FREE);
        assert_eq!(at(8.1, 0.1, 0.7), 4, "the car at its box");
        assert_eq!(at(20.0, 0.1, 0.7), FREE);
        // A LiDAR 1.8 m up seeing the road 5 m ahead, and a camera looking ahead at the car.
        let lidar = Calibration {
            sensor_to_ego: Se3::from_wxyz_t([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.8]),
            intrinsics: None,
            width: 0,
            height: 0,
        };
        let sweep = PointCloud { points: vec![[5.0, 0.1, -1.8, 0.0]], ..PointCloud::default() };
        let camera = Calibration {
            sensor_to_ego: Se3::from_wxyz_t([0.5, -0.5, 0.5, -0.5], [1.0, 0.0, 1.0]),
            intrinsics: Some([[20.0, 0.0, 20.0], [0.0, 20.0, 15.0], [0.0, 0.0, 1.0]]),
            width: 40,
            height: 30,
        };
        let pose = Pose { ego_to_world: Se3::default(), timestamp_us: 0 };
        let grid = with_masks(&p, grid, &sweep, &lidar, &Se3::default(), &[(&camera, &pose)]).unwrap();
        let lidar_seen: Vec<usize> = (0..grid.voxels()).filter(|&v| grid.mask_lidar[v] != 0).collect();
        assert!(lidar_seen.contains(&g.index(DVec3::new(5.0, 0.1, 0.0)).unwrap()), "the return's voxel");
        assert!(lidar_seen.contains(&g.index(DVec3::new(2.5, 0.05, 0.9)).unwrap()), "the air the ray crossed");
        assert!(!lidar_seen.contains(&g.index(DVec3::new(-5.0, 0.0, 0.0)).unwrap()), "behind: not seen");
        assert!(grid.mask_camera.iter().zip(&grid.mask_lidar).all(|(&c, &l)| c <= l), "camera within lidar");
        assert!(grid.mask_camera.iter().any(|&c| c != 0), "the camera saw what the LiDAR saw ahead");
        // The same camera whose lower half is the car's body: fewer voxels seen, none new; wholly
        // the body: none. An empty mask changes nothing.
        let fresh = || OccupancyGrid { mask_lidar: Vec::new(), mask_camera: Vec::new(), ..grid.clone() };
        let (w, h) = (camera.width as usize, camera.height as usize);
        let seen = |blocked: &Mask| {
            let out = with_blocked_masks(&p, fresh(), &sweep, &lidar, &Se3::default(), &[(&camera, &pose)], &[Some(blocked)]);
            out.unwrap().mask_camera
        };
        let lower = Mask { width: w as u32, height: h as u32, data: (0..w * h).map(|k| (k / w >= h / 2) as u8).collect() };
        let half = seen(&lower);
        let count = |m: &[u8]| m.iter().filter(|&&c| c != 0).count();
        assert!(count(&half) < count(&grid.mask_camera), "{} {}", count(&half), count(&grid.mask_camera));
        assert!(half.iter().zip(&grid.mask_camera).all(|(&a, &b)| a <= b));
        let all = Mask { data: vec![1; w * h], ..lower.clone() };
        assert_eq!(count(&seen(&all)), 0);
        let none = Mask { data: vec![0; w * h], ..lower.clone() };
        assert_eq!(seen(&none), grid.mask_camera);
        let wrong = Mask { width: 3, height: 2, data: vec![1; 6] };
        let e = with_blocked_masks(&p, fresh(), &sweep, &lidar, &Se3::default(), &[(&camera, &pose)], &[Some(&wrong)]);
        assert!(e.err().unwrap().to_string().contains("ego mask is 3x2"));
    }
}
