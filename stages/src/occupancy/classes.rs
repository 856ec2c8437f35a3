//! The 18 Occ3D-nuScenes classes (0-16 as the nuScenes-lidarseg challenge's 16 classes plus
//! `others`, 17 = free), and where points and boxes get theirs (the tables are
//! `dist4d_types::occ3d`'s).
//!
//! nuScenes-lidarseg's 32 classes map as SurroundOcc's `learning_map` does
//! (weiyithu/SurroundOcc, `tools/generate_occupancy_nuscenes/nuscenes.yaml`, the lidarseg
//! challenge's table), whose 1-16 are Occ3D's 1-16; what that table sends to 0 (animal, debris,
//! pushable objects, bicycle racks, emergency vehicles, `static.other`, personal mobility,
//! strollers, wheelchairs) is Occ3D's `others` (0), except noise and the ego vehicle, whose points
//! are dropped: a spurious return or the ego's own body is not occupancy.

pub use dist4d_types::occ3d::{of_lidarseg, DRIVEABLE_SURFACE, DROP, FREE, FROM_LIDARSEG, MANMADE, NAMES};

/// Occ3D's `others`: occupied, class unknown or outside the 16.
pub const OTHERS: u8 = 0;

/// A point that no source labelled (no lidarseg, no camera saw it unoccluded, or its pixel's
/// class has no Occ3D counterpart): it takes a neighbour's label or the geometry rule
/// ([`super::aggregate_scene`]). Not [`DROP`]: it is still occupancy.
pub const UNLABELLED: u8 = 254;

/// Cityscapes label id (the 34 ids of `cityscapesscripts/helpers/labels.py`, not the 19
/// train ids; what a segmenter worker's op `segment` returns and `dist4d synth` writes) ->
/// Occ3D class, [`UNLABELLED`] where a LiDAR point cannot take the pixel's class. The table is
/// documented in docs/stages.md (LabelPoints).
pub const FROM_CITYSCAPES: [u8; 34] = [
    UNLABELLED, // 0 unlabeled
    UNLABELLED, // 1 ego vehicle
    UNLABELLED, // 2 rectification border
    UNLABELLED, // 3 out of roi
    OTHERS,     // 4 static
    OTHERS,     // 5 dynamic
    12,         // 6 ground -> other_flat
    11,         // 7 road -> driveable_surface
    13,         // 8 sidewalk
    11,         // 9 parking -> driveable_surface (nuScenes counts parking lots as driveable)
    12,         // 10 rail track -> other_flat
    MANMADE,    // 11 building
    MANMADE,    // 12 wall
    MANMADE,    // 13 fence
    1,          // 14 guard rail -> barrier
    MANMADE,    // 15 bridge
    MANMADE,    // 16 tunnel
    MANMADE,    // 17 pole
    MANMADE,    // 18 polegroup
    MANMADE,    // 19 traffic light
    MANMADE,    // 20 traffic sign
    16,         // 21 vegetation
    14,         // 22 terrain
    UNLABELLED, // 23 sky: a LiDAR return is not sky (a mislabelled edge)
    7,          // 24 person -> pedestrian
    2,          // 25 rider -> bicycle (nuScenes boxes a cyclist with the bicycle)
    4,          // 26 car
    10,         // 27 truck
    3,          // 28 bus
    9,          // 29 caravan -> trailer
    9,          // 30 trailer
    OTHERS,     // 31 train
    6,          // 32 motorcycle
    2,          // 33 bicycle
];

/// The Occ3D class of a Cityscapes id ([`FROM_CITYSCAPES`]; ids past it are [`UNLABELLED`]).
pub fn of_cityscapes(id: u8) -> u8 {
    FROM_CITYSCAPES.get(id as usize).copied().unwrap_or(UNLABELLED)
}

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

    #[test]
    fn cityscapes_ids_map_to_occ3d_and_sky_or_void_to_no_label() {
        // The ids `dist4d synth` writes (docs/datasets.md).
        let synth = [(7, 11), (8, 13), (11, 15), (17, 15), (21, 16), (22, 14), (24, 7), (26, 4)];
        for (id, occ) in synth {
            assert_eq!(of_cityscapes(id), occ, "Cityscapes {id}");
        }
        for id in [0, 1, 2, 3, 23, 34, 255] {
            assert_eq!(of_cityscapes(id), UNLABELLED, "Cityscapes {id}");
        }
        assert!(FROM_CITYSCAPES.iter().all(|&c| c < FREE || c == UNLABELLED), "never free, never dropped");
    }
}
