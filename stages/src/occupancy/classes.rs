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
}
