//! The 18 Occ3D-nuScenes classes (0-16 as the nuScenes-lidarseg challenge's 16 plus `others`,
//! 17 = free), and nuScenes-lidarseg's 32 classes mapped to them as SurroundOcc's `learning_map`
//! does (weiyithu/SurroundOcc, `tools/generate_occupancy_nuscenes/nuscenes.yaml`), noise and the
//! ego vehicle dropped: shared by the occupancy stages and the synthetic world's exact occupancy.

/// Occ3D-nuScenes class names, by index.
pub const NAMES: [&str; 18] = [
    "others",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
];

pub const FREE: u8 = 17;
pub const DRIVEABLE_SURFACE: u8 = 11;
pub const MANMADE: u8 = 15;
/// A point that makes no occupancy (noise, the ego vehicle).
pub const DROP: u8 = 255;

/// nuScenes-lidarseg class index -> Occ3D class.
pub const FROM_LIDARSEG: [u8; 32] = [
    DROP, // 0 noise
    0,    // 1 animal
    7,    // 2 human.pedestrian.adult
    7,    // 3 human.pedestrian.child
    7,    // 4 human.pedestrian.construction_worker
    0,    // 5 human.pedestrian.personal_mobility
    7,    // 6 human.pedestrian.police_officer
    0,    // 7 human.pedestrian.stroller
    0,    // 8 human.pedestrian.wheelchair
    1,    // 9 movable_object.barrier
    0,    // 10 movable_object.debris
    0,    // 11 movable_object.pushable_pullable
    8,    // 12 movable_object.trafficcone
    0,    // 13 static_object.bicycle_rack
    2,    // 14 vehicle.bicycle
    3,    // 15 vehicle.bus.bendy
    3,    // 16 vehicle.bus.rigid
    4,    // 17 vehicle.car
    5,    // 18 vehicle.construction
    0,    // 19 vehicle.emergency.ambulance
    0,    // 20 vehicle.emergency.police
    6,    // 21 vehicle.motorcycle
    9,    // 22 vehicle.trailer
    10,   // 23 vehicle.truck
    11,   // 24 flat.driveable_surface
    12,   // 25 flat.other
    13,   // 26 flat.sidewalk
    14,   // 27 flat.terrain
    15,   // 28 static.manmade
    0,    // 29 static.other
    16,   // 30 static.vegetation
    DROP, // 31 vehicle.ego
];

/// The Occ3D class of a lidarseg label (labels past the table are `others`).
pub fn of_lidarseg(label: u8) -> u8 {
    FROM_LIDARSEG.get(label as usize).copied().unwrap_or(0)
}

/// Occ3D-nuScenes' grid: [x_min, y_min, z_min, x_max, y_max, z_max] (m), as its README states it.
pub const RANGE: [f64; 6] = [-40.0, -40.0, -1.0, 40.0, 40.0, 5.4];
/// Its voxel edge (m).
pub const VOXEL: f64 = 0.4;
/// How far above the ego frame's origin the stated range sits in Occ3D's real files: the road
/// (ego z = 0) is in z layer 0 there, not the layer 2 the range alone gives (docs/occupancy.md).
pub const LIFT: f64 = 0.8;

/// The Occ3D-nuScenes grid in the ego frame, as the real files lay it out.
pub fn grid() -> crate::voxels::Grid {
    let dims = [0, 1, 2].map(|a| ((RANGE[a + 3] - RANGE[a]) / VOXEL).round() as usize);
    crate::voxels::Grid { min: glam::DVec3::new(RANGE[0], RANGE[1], RANGE[2] + LIFT), voxel: VOXEL, dims }
}
