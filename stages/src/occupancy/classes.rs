//! The 18 Occ3D-nuScenes classes (0-16 as the nuScenes-lidarseg challenge's 16 classes plus
//! `others`, 17 = free), and where points and boxes get theirs.
//!
//! nuScenes-lidarseg's 32 classes map as SurroundOcc's `learning_map` does
//! (weiyithu/SurroundOcc, `tools/generate_occupancy_nuscenes/nuscenes.yaml`, the lidarseg
//! challenge's table), whose 1-16 are Occ3D's 1-16; what that table sends to 0 (animal, debris,
//! pushable objects, bicycle racks, emergency vehicles, `static.other`, personal mobility,
//! strollers, wheelchairs) is Occ3D's `others` (0), except noise and the ego vehicle, whose points
//! are dropped: a spurious return or the ego's own body is not occupancy.

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

/// A colour per class, as SurroundOcc's visualisation draws Occ3D-nuScenes (weiyithu/SurroundOcc,
/// `tools/visual.py`, the `colors` table), which the occupancy papers' figures use; free is
/// not drawn (here: dark grey).
pub const PALETTE: [[u8; 3]; 18] = [
    [0, 0, 0],
    [255, 120, 50],
    [255, 192, 203],
    [255, 255, 0],
    [0, 150, 245],
    [0, 255, 255],
    [200, 180, 0],
    [255, 0, 0],
    [255, 240, 150],
    [135, 60, 0],
    [160, 32, 240],
    [255, 0, 255],
    [139, 137, 137],
    [75, 0, 75],
    [150, 240, 80],
    [230, 230, 250],
    [0, 175, 0],
    [40, 40, 40],
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

/// The Occ3D class of a box's category: nuScenes names (`vehicle.car`) by the same table, other
/// datasets' names (DGP's `Car`, `Pedestrian`) by what they say.
pub fn of_category(category: &str) -> u8 {
    let c = category.to_ascii_lowercase();
    let nuscenes: [(&str, u8); 14] = [
        ("human.pedestrian.personal_mobility", 0),
        ("human.pedestrian.stroller", 0),
        ("human.pedestrian.wheelchair", 0),
        ("human.pedestrian", 7),
        ("movable_object.barrier", 1),
        ("movable_object.trafficcone", 8),
        ("vehicle.bicycle", 2),
        ("vehicle.bus", 3),
        ("vehicle.car", 4),
        ("vehicle.construction", 5),
        ("vehicle.motorcycle", 6),
        ("vehicle.trailer", 9),
        ("vehicle.truck", 10),
        ("vehicle.emergency", 0),
    ];
    if let Some((_, class)) = nuscenes.iter().find(|(prefix, _)| c.starts_with(prefix)) {
        return *class;
    }
    let words: [(&str, u8); 10] = [
        ("motorcycle", 6),
        ("bicycle", 2),
        ("bike", 2),
        ("trailer", 9),
        ("truck", 10),
        ("bus", 3),
        ("car", 4),
        ("pedestrian", 7),
        ("cone", 8),
        ("barrier", 1),
    ];
    words.iter().find(|(w, _)| c.contains(w)).map_or(0, |(_, class)| *class)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lidarseg_and_categories_map_to_the_same_occ3d_classes() {
        assert_eq!(of_lidarseg(17), 4);
        assert_eq!(of_lidarseg(24), DRIVEABLE_SURFACE);
        assert_eq!(of_lidarseg(0), DROP);
        assert_eq!(of_lidarseg(31), DROP);
        assert_eq!(of_lidarseg(200), 0);
        assert_eq!(of_category("vehicle.car"), 4);
        assert_eq!(of_category("human.pedestrian.adult"), 7);
        assert_eq!(of_category("human.pedestrian.stroller"), 0);
        assert_eq!(of_category("vehicle.bus.rigid"), 3);
        assert_eq!(of_category("Car"), 4);
        assert_eq!(of_category("Motorcycle"), 6);
        assert_eq!(of_category("animal"), 0);
        assert_eq!(NAMES[FREE as usize], "free");
    }
}
