//! `EncodeOcc3dWaymo`: a frame's occupancy in Occ3D-Waymo's layout, beside Occ3D-nuScenes', for
//! scenes recorded by Waymo (py123d logs whose `dataset` is `wod-perception`).
//!
//! What Occ3D publishes for Waymo (Tsinghua-MARS-Lab/Occ3D README, "Occ3D-Waymo"; its `code`
//! branch, `projects/mmdet3d_plugin/datasets/pipelines/loading.py`, `LoadOccGTFromFileWaymo`;
//! CVT-Occ's `docs/dataset.md`), and where it differs from Occ3D-nuScenes:
//! - One `.npz` per frame, `<split>/<segment index:03>/<frame index:03>_04.npz` for the 0.4 m grid
//!   (the 0.1 m grid drops `_04`), not `gts/<scene>/<token>/labels.npz`.
//! - Keys `voxel_label` (classes), `origin_voxel_state` (the LiDAR mask), `final_voxel_state`
//!   (the camera mask) and `infov` (inside a camera's field of view: Waymo's five cameras do not
//!   see all around), not `semantics`, `mask_lidar`, `mask_camera`. Occ3D's own viewer
//!   (`utils/vis_occ.py`) also reads `ego2global`.
//! - Classes 0-14 (general object, then Waymo's box types vehicle, pedestrian, sign, cyclist, then
//!   its LiDAR segmentation's), and free = 23 in the files (the README says 15: its loaders remap
//!   23 -> 15 at load time).
//! - The same 200 x 200 x 16 grid of 0.4 m over [-40, -40, -1, 40, 40, 5.4] m, in Waymo's vehicle
//!   frame (x forward, y left, z up, the ground near z = 0), which is a py123d Waymo log's ego
//!   frame (its `rear_axle_to_imu_se3` is the identity).
//!
//! dist4d's occupancy carries Occ3D-nuScenes' 18 classes; [`FROM_OCC3D`] maps them, so Waymo's
//! finer static classes (sign, traffic light, pole, tree trunk) stay in building and vegetation.
//! The grid is resampled from the `occupancy` stage's (`from_grid`, dist4d's Occ3D-nuScenes grid,
//! lifted 0.8 m) by voxel centres: with the same voxel and a lift that differs by whole voxels
//! (0.8 m = 2 layers) every voxel is copied exactly; the two layers below dist4d's grid are
//! unobserved free.

use super::grid::GridParams;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::{Made, TaskContext};
use dist4d_types::artifact::{Calibration, File, OccupancyGrid, Pose};
use dist4d_types::formats::{npy_f64, npy_u8, npz};
use glam::DVec3;
use serde::{Deserialize, Serialize};

/// Occ3D-Waymo class names, by index (README: `TYPE_GENERALOBJECT` ... `TYPE_WALKABLE`).
pub const NAMES: [&str; 15] = [
    "general_object",
    "vehicle",
    "pedestrian",
    "sign",
    "cyclist",
    "traffic_light",
    "pole",
    "construction_cone",
    "bicycle",
    "motorcycle",
    "building",
    "vegetation",
    "tree_trunk",
    "road",
    "walkable",
];

/// Free in Occ3D-Waymo's files (loaders remap it to 15).
pub const WAYMO_FREE: u8 = 23;

/// Occ3D-nuScenes class (dist4d's, by index) -> Occ3D-Waymo class. Where Waymo has no
/// counterpart: barrier -> general object (Occ3D's class for objects outside the others); bus,
/// construction vehicle, trailer, truck -> vehicle (Waymo's vehicle box holds them all); bicycle
/// -> cyclist (Waymo boxes a bicycle with its rider as a cyclist, and py123d's Waymo reader gives
/// those boxes dist4d's bicycle); other flat -> road and terrain -> walkable (Occ3D's viewer
/// colours "curb, road, lane marker, other ground" as road and "walkable, sidewalk" as walkable;
/// Waymo's walkable is e.g. a grassy hill); manmade -> building.
pub const FROM_OCC3D: [u8; 18] = [
    0,          // 0 others -> general object
    0,          // 1 barrier -> general object
    4,          // 2 bicycle -> cyclist
    1,          // 3 bus -> vehicle
    1,          // 4 car -> vehicle
    1,          // 5 construction_vehicle -> vehicle
    9,          // 6 motorcycle
    2,          // 7 pedestrian
    7,          // 8 traffic_cone -> construction cone
    1,          // 9 trailer -> vehicle
    1,          // 10 truck -> vehicle
    13,         // 11 driveable_surface -> road
    13,         // 12 other_flat -> road
    14,         // 13 sidewalk -> walkable
    14,         // 14 terrain -> walkable
    10,         // 15 manmade -> building
    11,         // 16 vegetation
    WAYMO_FREE, // 17 free
];

/// The Occ3D-Waymo class of a dist4d (Occ3D-nuScenes) class; classes past the table are
/// general objects.
pub fn of_occ3d(class: u8) -> u8 {
    FROM_OCC3D.get(class as usize).copied().unwrap_or(0)
}

/// The `dataset` py123d writes in the metadata of Waymo Open Perception logs (py123d 0.7,
/// `parser/wod/wod_perception_parser.py`).
pub const WAYMO_PERCEPTION: &str = "wod-perception";

/// When the stage writes the layout.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum When {
    /// When the scene's source dataset (`dataset.source_dataset`) is Waymo Perception; other
    /// scenes have nothing to make, and the run says so once.
    #[default]
    Auto,
    /// For every scene (another car's log in Occ3D-Waymo's layout, or a test).
    Always,
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    pub when: When,
    /// The grid of the occupancy it reads (set it as `Occupancy`'s): places its voxels.
    pub from_grid: GridParams,
    /// Occ3D-Waymo's grid: [-40, -40, -1, 40, 40, 5.4] m, 0.4 m, in the vehicle frame (lift 0).
    pub grid: GridParams,
}

/// Occ3D-Waymo's 0.4 m grid as its README states it, in Waymo's vehicle frame.
pub fn waymo_grid() -> GridParams {
    GridParams { range: [-40.0, -40.0, -1.0, 40.0, 40.0, 5.4], voxel: 0.4, lift: 0.0 }
}

impl Default for Params {
    fn default() -> Self {
        Params { when: When::Auto, from_grid: GridParams::default(), grid: waymo_grid() }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        // Each grid's problems name the grid, then its field (`grid`: `voxel` must be ...).
        let mut out = Vec::new();
        for (name, grid) in [("from_grid", &self.from_grid), ("grid", &self.grid)] {
            let mut c = ParamChecks::new();
            grid.check(&mut c);
            out.extend(c.done().into_iter().map(|p| ParamProblem::new(name, format!("`{}` {}", p.field, p.message))));
        }
        out
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the frame's occupancy (on `from_grid`, with Occ3D-nuScenes' classes)
        grid: One<OccupancyGrid>,
        /// the scene's source dataset (`dataset.source_dataset`)
        source: One<File>,
        /// the ego pose at the frame's LiDAR time (`dataset.lidar_pose`): `ego2global`
        pose: One<Pose>,
        /// every camera of the frame (`Gather("dataset.camera_calib", camera)`): `infov`
        camera_calibs: Many<Calibration>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// `<frame:03>_04.npz`: `voxel_label`, `origin_voxel_state`, `final_voxel_state`, `infov`
        /// (uint8 X x Y x Z), `ego2global` (float64 4 x 4)
        npz: One<File>,
    }
}

pub struct EncodeOcc3dWaymo {
    params: Params,
}

/// A frame in Occ3D-Waymo's layout, each volume C order over (X, Y, Z) of `grid`.
#[derive(Debug, PartialEq)]
pub struct WaymoFrame {
    pub dims: [usize; 3],
    pub voxel_label: Vec<u8>,
    pub origin_voxel_state: Vec<u8>,
    pub final_voxel_state: Vec<u8>,
    pub infov: Vec<u8>,
    /// World-from-vehicle, row-major.
    pub ego2global: [f64; 16],
}

/// Resamples `occ` (on `from`) onto `to` by voxel centres, mapping classes by [`FROM_OCC3D`];
/// `infov` marks the voxels whose centre lies in front of a camera and projects inside its
/// image. A voxel of `to` outside `from` is free and unobserved.
pub fn waymo_frame(
    occ: &OccupancyGrid,
    from: &GridParams,
    to: &GridParams,
    pose: &Pose,
    cameras: &[&Calibration],
) -> Result<WaymoFrame> {
    let (src, dst) = (from.grid(), to.grid());
    let want = src.dims.map(|d| d as u32);
    ensure!(
        occ.dims == want,
        "the occupancy's grid is {:?} voxels but `from_grid` makes {:?}: set `from_grid` as the `Occupancy` stage's `grid`",
        occ.dims,
        want
    );
    let n = dst.len();
    let mut f = WaymoFrame {
        dims: dst.dims,
        voxel_label: vec![WAYMO_FREE; n],
        origin_voxel_state: vec![0; n],
        final_voxel_state: vec![0; n],
        infov: vec![0; n],
        ego2global: [0.0; 16],
    };
    let views: Vec<View> = cameras.iter().filter_map(|c| View::of(c)).collect();
    for i in 0..n {
        let centre = dst.centre(i);
        if let Some(s) = src.index(centre) {
            f.voxel_label[i] = of_occ3d(occ.semantics[s]);
            f.origin_voxel_state[i] = (occ.mask_lidar[s] != 0) as u8;
            f.final_voxel_state[i] = (occ.mask_camera[s] != 0) as u8;
        }
        f.infov[i] = views.iter().any(|v| v.sees(centre)) as u8;
    }
    let r = pose.ego_to_world.matrix();
    let t = pose.ego_to_world.translation;
    for row in 0..3 {
        for col in 0..3 {
            f.ego2global[row * 4 + col] = r.col(col)[row];
        }
        f.ego2global[row * 4 + 3] = t[row];
    }
    f.ego2global[15] = 1.0;
    Ok(f)
}

/// A pinhole camera as `infov` needs it: ego -> camera, intrinsics, image size.
struct View {
    ego_to_camera: dist4d_types::geometry::Se3,
    k: [[f64; 3]; 3],
    size: (f64, f64),
}

impl View {
    fn of(c: &Calibration) -> Option<View> {
        Some(View {
            ego_to_camera: c.sensor_to_ego.inverse(),
            k: c.intrinsics?,
            size: (c.width as f64, c.height as f64),
        })
    }

    fn sees(&self, ego: DVec3) -> bool {
        let c = self.ego_to_camera.apply(ego);
        if c.z <= 0.0 {
            return false;
        }
        let k = &self.k;
        let u = (k[0][0] * c.x + k[0][1] * c.y + k[0][2] * c.z) / c.z;
        let v = (k[1][0] * c.x + k[1][1] * c.y + k[1][2] * c.z) / c.z;
        u >= 0.0 && u < self.size.0 && v >= 0.0 && v < self.size.1
    }
}

/// Whether a scene whose `source_dataset` port says `source` is Waymo Perception.
pub fn is_waymo(source: &str) -> bool {
    source.trim() == WAYMO_PERCEPTION
}

impl Stage for EncodeOcc3dWaymo {
    const KIND: &'static str = "EncodeOcc3dWaymo";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "OccupancyGrid -> Occ3D-Waymo <frame>_04.npz (voxel_label, origin_voxel_state, final_voxel_state, infov; free 23), for Waymo scenes";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EncodeOcc3dWaymo { params })
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let source = String::from_utf8_lossy(&i.source.0).into_owned();
        if self.params.when == When::Auto && !is_waymo(&source) {
            let said = if source.is_empty() { "unknown".to_string() } else { format!("`{source}`") };
            return Ok(Made::Nothing(format!(
                "the scene's source dataset is {said}, not Waymo Perception (`{WAYMO_PERCEPTION}`); \
                 `when: Always` writes Occ3D-Waymo's layout for any scene"
            )));
        }
        let cameras: Vec<&Calibration> = i.camera_calibs.iter().map(|(_, c)| c).collect();
        let f = waymo_frame(&i.grid, &self.params.from_grid, &self.params.grid, &i.pose, &cameras)?;
        Ok(Outputs { npz: File(encode(&f)) }.into())
    }
}

/// The `.npz` of a frame, as `np.savez_compressed` writes it.
pub fn encode(f: &WaymoFrame) -> Vec<u8> {
    npz(&[
        ("voxel_label", npy_u8(&f.dims, &f.voxel_label)),
        ("origin_voxel_state", npy_u8(&f.dims, &f.origin_voxel_state)),
        ("final_voxel_state", npy_u8(&f.dims, &f.final_voxel_state)),
        ("infov", npy_u8(&f.dims, &f.infov)),
        ("ego2global", npy_f64(&[4, 4], &f.ego2global)),
    ])
}

/// The warnings `run` prints when an `EncodeOcc3dWaymo`'s `from_grid` is not the grid of the
/// `Occupancy` (or `ExactOccupancy`) stage feeding it: its voxels would land in the wrong place
/// (a different lift keeps the sizes, so the stage's own check cannot see it).
pub fn grid_mismatch_warnings(p: &dist4d_graph::Pipeline) -> Vec<String> {
    let mut out = Vec::new();
    for node in &p.nodes {
        let Some(stage) = node.stage().filter(|s| s.kind == EncodeOcc3dWaymo::KIND) else { continue };
        let Some(params) = stage.params.get::<Params>() else { continue };
        for input in stage.inputs.iter().filter(|i| i.port == "grid") {
            let Some(up) = p.nodes.get(input.from).and_then(|n| n.stage()) else { continue };
            let upstream = if up.kind == super::occupancy_frame::Occupancy::KIND {
                up.params.get::<super::occupancy_frame::Params>().map(|o| o.grid.clone())
            } else if up.kind == super::exact::ExactOccupancy::KIND {
                up.params.get::<super::exact::Params>().map(|o| o.grid.clone())
            } else {
                None
            };
            if let Some(grid) = upstream.filter(|g| *g != params.from_grid) {
                out.push(format!(
                    "stage `{}` (EncodeOcc3dWaymo): `from_grid` {:?} is not the grid of stage `{}` ({:?}), whose \
                     occupancy it reads: set `{}.from_grid` as `{}.grid`, or its voxels land in the wrong place",
                    node.name, params.from_grid, p.nodes[input.from].name, grid, node.name, p.nodes[input.from].name
                ));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::classes::FREE;
    use super::*;
    use dist4d_types::formats::read_npy_u8;
    use dist4d_types::geometry::Se3;

    fn nuscenes_grid_with(f: impl Fn(DVec3) -> (u8, u8, u8)) -> OccupancyGrid {
        let g = GridParams::default().grid();
        let n = g.len();
        let (mut semantics, mut mask_lidar, mut mask_camera) = (vec![0; n], vec![0; n], vec![0; n]);
        for i in 0..n {
            (semantics[i], mask_lidar[i], mask_camera[i]) = f(g.centre(i));
        }
        OccupancyGrid { dims: g.dims.map(|d| d as u32), semantics, mask_lidar, mask_camera }
    }

    fn identity_pose() -> Pose {
        Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::ZERO), timestamp_us: 0 }
    }

    #[test]
    fn classes_map_to_occ3d_waymo_and_free_is_23() {
        assert_eq!(of_occ3d(4), 1, "car -> vehicle");
        assert_eq!(of_occ3d(10), 1, "truck -> vehicle");
        assert_eq!(of_occ3d(7), 2, "pedestrian");
        assert_eq!(of_occ3d(2), 4, "bicycle -> cyclist");
        assert_eq!(of_occ3d(8), 7, "traffic cone -> construction cone");
        assert_eq!(of_occ3d(11), 13, "driveable surface -> road");
        assert_eq!(of_occ3d(13), 14, "sidewalk -> walkable");
        assert_eq!(of_occ3d(15), 10, "manmade -> building");
        assert_eq!(of_occ3d(16), 11);
        assert_eq!(of_occ3d(FREE), WAYMO_FREE);
        assert_eq!(of_occ3d(200), 0);
        assert!(FROM_OCC3D.iter().all(|&c| (c as usize) < NAMES.len() || c == WAYMO_FREE));
        assert_eq!((NAMES[0], NAMES[13], NAMES[14]), ("general_object", "road", "walkable"));
    }

    #[test]
    fn the_waymo_grid_is_the_nuscenes_grid_two_layers_lower_and_copies_voxels_exactly() {
        let to = waymo_grid().grid();
        assert_eq!(to.dims, [200, 200, 16]);
        // The vehicle frame's ground (z = 0) is in layer 2 (-0.2..0.2 m); x forward along i.
        let road = to.index(DVec3::new(0.1, 0.1, 0.0)).unwrap();
        assert_eq!((road / 16 / 200, road / 16 % 200, road % 16), (100, 100, 2));
        assert_eq!(to.index(DVec3::new(-39.9, -39.9, -0.99)), Some(0));
        // Road at ego z 0, a car 1 m up, free above; the LiDAR saw everything below 3 m, the
        // cameras below 2 m.
        let occ = nuscenes_grid_with(|c| {
            let class = if c.z < 0.2 {
                11
            } else if c.z < 1.4 && c.x > 5.0 && c.x < 9.0 {
                4
            } else {
                FREE
            };
            (class, (c.z < 3.0) as u8, (c.z < 2.0) as u8)
        });
        let f = waymo_frame(&occ, &GridParams::default(), &waymo_grid(), &identity_pose(), &[]).unwrap();
        let at = |x: f64, y: f64, z: f64| to.index(DVec3::new(x, y, z)).unwrap();
        assert_eq!(f.voxel_label[at(0.1, 0.1, 0.0)], 13, "road in layer 2");
        assert_eq!(f.voxel_label[at(7.0, 0.1, 1.0)], 1, "the car");
        assert_eq!(f.voxel_label[at(0.1, 0.1, 2.5)], WAYMO_FREE);
        // Below dist4d's grid (ego z < -0.2): free and unobserved.
        let below = at(0.1, 0.1, -0.5);
        assert_eq!((f.voxel_label[below], f.origin_voxel_state[below], f.final_voxel_state[below]), (WAYMO_FREE, 0, 0));
        assert_eq!((f.origin_voxel_state[at(0.1, 0.1, 2.5)], f.final_voxel_state[at(0.1, 0.1, 2.5)]), (1, 0));
        // Every voxel the two grids share is copied: as many road voxels as dist4d's grid holds.
        let roads = |v: &[u8], c: u8| v.iter().filter(|&&x| x == c).count();
        assert_eq!(roads(&f.voxel_label, 13), roads(&occ.semantics, 11));
        assert_eq!(roads(&f.voxel_label, 1), roads(&occ.semantics, 4));
    }

    #[test]
    fn infov_is_what_a_forward_camera_sees_and_ego2global_is_the_pose() {
        let occ = nuscenes_grid_with(|_| (FREE, 1, 1));
        // A camera 2 m up looking forward (optical z = ego x, optical x = -ego y, optical y =
        // -ego z), 90 degrees wide.
        let rot = glam::DQuat::from_mat3(&glam::DMat3::from_cols(
            DVec3::new(0.0, -1.0, 0.0),
            DVec3::new(0.0, 0.0, -1.0),
            DVec3::new(1.0, 0.0, 0.0),
        ));
        let camera = Calibration {
            sensor_to_ego: Se3 { rotation: rot, translation: DVec3::new(0.0, 0.0, 2.0) },
            intrinsics: Some([[100.0, 0.0, 100.0], [0.0, 100.0, 100.0], [0.0, 0.0, 1.0]]),
            width: 200,
            height: 200,
        };
        let pose = Pose {
            ego_to_world: Se3::from_yaw(std::f64::consts::FRAC_PI_2, DVec3::new(10.0, 20.0, 1.0)),
            timestamp_us: 0,
        };
        let f = waymo_frame(&occ, &GridParams::default(), &waymo_grid(), &pose, &[&camera]).unwrap();
        let to = waymo_grid().grid();
        let at = |x: f64, y: f64, z: f64| f.infov[to.index(DVec3::new(x, y, z)).unwrap()];
        assert_eq!(at(20.0, 0.1, 1.0), 1, "ahead");
        assert_eq!(at(-20.0, 0.1, 1.0), 0, "behind");
        assert_eq!(at(5.0, 20.0, 1.0), 0, "beside, outside the 90 degrees");
        let seen = f.infov.iter().filter(|&&v| v == 1).count() as f64 / f.infov.len() as f64;
        assert!(seen > 0.1 && seen < 0.3, "{seen}");
        // Row-major world-from-vehicle: a quarter turn left, then the translation.
        let m = f.ego2global;
        let want = [0.0, -1.0, 0.0, 10.0, 1.0, 0.0, 0.0, 20.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        assert!(m.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-12), "{m:?}");
    }

    #[test]
    fn the_npz_holds_occ3d_waymos_keys_dtypes_and_shapes() {
        let occ = nuscenes_grid_with(|c| (if c.z < 0.2 { 11 } else { FREE }, 1, (c.x > 0.0) as u8));
        let f = waymo_frame(&occ, &GridParams::default(), &waymo_grid(), &identity_pose(), &[]).unwrap();
        let bytes = encode(&f);
        for (key, want) in [
            ("voxel_label", &f.voxel_label),
            ("origin_voxel_state", &f.origin_voxel_state),
            ("final_voxel_state", &f.final_voxel_state),
            ("infov", &f.infov),
        ] {
            let member = dist4d_datasets::files::npz_member(&bytes, key).unwrap();
            let (shape, data) = read_npy_u8(&member).unwrap_or_else(|e| panic!("{key}: {e:#}"));
            assert_eq!(shape, [200, 200, 16], "{key}");
            assert_eq!(&data, want, "{key}");
        }
        let pose =
            dist4d_datasets::files::parse_npy(&dist4d_datasets::files::npz_member(&bytes, "ego2global").unwrap())
                .unwrap();
        assert_eq!((pose.shape, pose.data[0], pose.data[15]), (vec![4, 4], 1.0, 1.0));
        assert!(dist4d_datasets::files::npz_member(&bytes, "semantics").is_err(), "not Occ3D-nuScenes' keys");
    }

    #[test]
    fn a_grid_of_other_sizes_than_from_grid_is_refused_with_what_to_set() {
        let occ = OccupancyGrid {
            dims: [10, 10, 4],
            semantics: vec![0; 400],
            mask_lidar: vec![0; 400],
            mask_camera: vec![0; 400],
        };
        let e = waymo_frame(&occ, &GridParams::default(), &waymo_grid(), &identity_pose(), &[]).unwrap_err();
        assert!(format!("{e:#}").contains("set `from_grid`"), "{e:#}");
        assert!(is_waymo("wod-perception") && !is_waymo("nuscenes") && !is_waymo("wod-motion") && !is_waymo(""));
    }
}
