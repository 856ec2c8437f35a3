//! py123d's box labels as the categories dist4d uses: nuScenes category names, which the
//! occupancy classes, the bird's-eye layouts and the clip indexes read (`occupancy::classes::
//! of_category`). One table per label enum py123d writes (`box_detection_label_class` in a log's
//! `box_detections_se3.arrow` metadata), in the enum's value order, from py123d 0.7.0's
//! `py123d/parser/registry.py` and `py123d/datatypes/detections/box_detection_label.py`. A label
//! with no nuScenes counterpart keeps a name of the same form (`static_object.sign`,
//! `vehicle.train`) that the occupancy table maps to `others`. docs/datasets.md prints the tables.

/// (py123d enum class name, [(label name, dist4d category)] by value).
pub const TABLES: &[(&str, &[(&str, &str)])] = &[
    (
        "NuScenesBoxDetectionLabel",
        &[
            ("VEHICLE_CAR", "vehicle.car"),
            ("VEHICLE_TRUCK", "vehicle.truck"),
            ("VEHICLE_BUS_BENDY", "vehicle.bus.bendy"),
            ("VEHICLE_BUS_RIGID", "vehicle.bus.rigid"),
            ("VEHICLE_CONSTRUCTION", "vehicle.construction"),
            ("VEHICLE_EMERGENCY_AMBULANCE", "vehicle.emergency.ambulance"),
            ("VEHICLE_EMERGENCY_POLICE", "vehicle.emergency.police"),
            ("VEHICLE_TRAILER", "vehicle.trailer"),
            ("VEHICLE_BICYCLE", "vehicle.bicycle"),
            ("VEHICLE_MOTORCYCLE", "vehicle.motorcycle"),
            ("HUMAN_PEDESTRIAN_ADULT", "human.pedestrian.adult"),
            ("HUMAN_PEDESTRIAN_CHILD", "human.pedestrian.child"),
            ("HUMAN_PEDESTRIAN_CONSTRUCTION_WORKER", "human.pedestrian.construction_worker"),
            ("HUMAN_PEDESTRIAN_PERSONAL_MOBILITY", "human.pedestrian.personal_mobility"),
            ("HUMAN_PEDESTRIAN_POLICE_OFFICER", "human.pedestrian.police_officer"),
            ("HUMAN_PEDESTRIAN_STROLLER", "human.pedestrian.stroller"),
            ("HUMAN_PEDESTRIAN_WHEELCHAIR", "human.pedestrian.wheelchair"),
            ("MOVABLE_OBJECT_TRAFFICCONE", "movable_object.trafficcone"),
            ("MOVABLE_OBJECT_BARRIER", "movable_object.barrier"),
            ("MOVABLE_OBJECT_PUSHABLE_PULLABLE", "movable_object.pushable_pullable"),
            ("MOVABLE_OBJECT_DEBRIS", "movable_object.debris"),
            ("STATIC_OBJECT_BICYCLE_RACK", "static_object.bicycle_rack"),
            ("ANIMAL", "animal"),
        ],
    ),
    (
        "WODPerceptionBoxDetectionLabel",
        &[
            ("TYPE_UNKNOWN", "unknown"),
            ("TYPE_VEHICLE", "vehicle.car"),
            ("TYPE_PEDESTRIAN", "human.pedestrian.adult"),
            ("TYPE_SIGN", "static_object.sign"),
            // A Waymo cyclist box holds the bicycle and its rider, as a nuScenes bicycle box does.
            ("TYPE_CYCLIST", "vehicle.bicycle"),
        ],
    ),
    (
        "AV2SensorBoxDetectionLabel",
        &[
            ("ANIMAL", "animal"),
            ("ARTICULATED_BUS", "vehicle.bus.bendy"),
            ("BICYCLE", "vehicle.bicycle"),
            ("BICYCLIST", "vehicle.bicycle"),
            ("BOLLARD", "movable_object.barrier"),
            ("BOX_TRUCK", "vehicle.truck"),
            ("BUS", "vehicle.bus.rigid"),
            ("CONSTRUCTION_BARREL", "movable_object.trafficcone"),
            ("CONSTRUCTION_CONE", "movable_object.trafficcone"),
            ("DOG", "animal"),
            ("LARGE_VEHICLE", "vehicle.truck"),
            ("MESSAGE_BOARD_TRAILER", "vehicle.trailer"),
            ("MOBILE_PEDESTRIAN_CROSSING_SIGN", "static_object.sign"),
            ("MOTORCYCLE", "vehicle.motorcycle"),
            ("MOTORCYCLIST", "vehicle.motorcycle"),
            ("OFFICIAL_SIGNALER", "human.pedestrian.police_officer"),
            ("PEDESTRIAN", "human.pedestrian.adult"),
            ("RAILED_VEHICLE", "vehicle.train"),
            ("REGULAR_VEHICLE", "vehicle.car"),
            ("SCHOOL_BUS", "vehicle.bus.rigid"),
            ("SIGN", "static_object.sign"),
            ("STOP_SIGN", "static_object.sign"),
            ("STROLLER", "human.pedestrian.stroller"),
            ("TRAFFIC_LIGHT_TRAILER", "vehicle.trailer"),
            ("TRUCK", "vehicle.truck"),
            ("TRUCK_CAB", "vehicle.truck"),
            ("VEHICULAR_TRAILER", "vehicle.trailer"),
            ("WHEELCHAIR", "human.pedestrian.wheelchair"),
            ("WHEELED_DEVICE", "human.pedestrian.personal_mobility"),
            ("WHEELED_RIDER", "human.pedestrian.personal_mobility"),
        ],
    ),
    (
        "NuPlanBoxDetectionLabel",
        &[
            ("VEHICLE", "vehicle.car"),
            ("BICYCLE", "vehicle.bicycle"),
            ("PEDESTRIAN", "human.pedestrian.adult"),
            ("TRAFFIC_CONE", "movable_object.trafficcone"),
            ("BARRIER", "movable_object.barrier"),
            ("CZONE_SIGN", "static_object.sign"),
            ("GENERIC_OBJECT", "movable_object.pushable_pullable"),
        ],
    ),
    (
        "KITTI360BoxDetectionLabel",
        &[
            ("BICYCLE", "vehicle.bicycle"),
            ("BOX", "movable_object.pushable_pullable"),
            ("BUS", "vehicle.bus.rigid"),
            ("CAR", "vehicle.car"),
            ("CARAVAN", "vehicle.trailer"),
            ("LAMP", "static_object.lamp"),
            ("MOTORCYCLE", "vehicle.motorcycle"),
            ("PERSON", "human.pedestrian.adult"),
            ("POLE", "static_object.pole"),
            // Riders are boxed apart from their cycle in KITTI-360; nuScenes boxes them together.
            ("RIDER", "vehicle.bicycle"),
            ("SMALLPOLE", "static_object.pole"),
            ("STOP", "static_object.sign"),
            ("TRAFFIC_LIGHT", "static_object.traffic_light"),
            ("TRAFFIC_SIGN", "static_object.sign"),
            ("TRAILER", "vehicle.trailer"),
            ("TRAIN", "vehicle.train"),
            ("TRASH_BIN", "movable_object.pushable_pullable"),
            ("TRUCK", "vehicle.truck"),
            ("VENDING_MACHINE", "static_object.vending_machine"),
        ],
    ),
    (
        "PandasetBoxDetectionLabel",
        &[
            ("ANIMALS_BIRD", "animal"),
            ("ANIMALS_OTHER", "animal"),
            ("BICYCLE", "vehicle.bicycle"),
            ("BUS", "vehicle.bus.rigid"),
            ("CAR", "vehicle.car"),
            ("CONES", "movable_object.trafficcone"),
            ("CONSTRUCTION_SIGNS", "static_object.sign"),
            ("EMERGENCY_VEHICLE", "vehicle.emergency"),
            ("MEDIUM_SIZED_TRUCK", "vehicle.truck"),
            ("MOTORCYCLE", "vehicle.motorcycle"),
            ("MOTORIZED_SCOOTER", "vehicle.motorcycle"),
            ("OTHER_VEHICLE_CONSTRUCTION_VEHICLE", "vehicle.construction"),
            ("OTHER_VEHICLE_PEDICAB", "vehicle.bicycle"),
            ("OTHER_VEHICLE_UNCOMMON", "vehicle.car"),
            ("PEDESTRIAN", "human.pedestrian.adult"),
            ("PEDESTRIAN_WITH_OBJECT", "human.pedestrian.adult"),
            ("PERSONAL_MOBILITY_DEVICE", "human.pedestrian.personal_mobility"),
            // nuScenes annotates pick-ups as cars.
            ("PICKUP_TRUCK", "vehicle.car"),
            ("PYLONS", "movable_object.trafficcone"),
            ("ROAD_BARRIERS", "movable_object.barrier"),
            ("ROLLING_CONTAINERS", "movable_object.pushable_pullable"),
            ("SEMI_TRUCK", "vehicle.truck"),
            ("SIGNS", "static_object.sign"),
            ("TEMPORARY_CONSTRUCTION_BARRIERS", "movable_object.barrier"),
            ("TOWED_OBJECT", "vehicle.trailer"),
            ("TRAIN", "vehicle.train"),
            ("TRAM_SUBWAY", "vehicle.train"),
        ],
    ),
    (
        "DefaultBoxDetectionLabel",
        &[
            ("EGO", "ego"),
            ("VEHICLE", "vehicle.car"),
            ("TRAIN", "vehicle.train"),
            ("TWO_WHEELER", "vehicle.bicycle"),
            ("PERSON", "human.pedestrian.adult"),
            ("ANIMAL", "animal"),
            ("TRAFFIC_SIGN", "static_object.sign"),
            ("TRAFFIC_CONE", "movable_object.trafficcone"),
            ("TRAFFIC_LIGHT", "static_object.traffic_light"),
            ("BARRIER", "movable_object.barrier"),
            ("GENERIC_OBJECT", "movable_object.pushable_pullable"),
            ("OTHER", "unknown"),
        ],
    ),
];

/// The table of a label enum named by its class path (`py123d.parser.registry.NuScenesBoxDetectionLabel`).
pub fn table(class_path: &str) -> Option<&'static [(&'static str, &'static str)]> {
    let name = class_path.rsplit('.').next()?;
    TABLES.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_table_maps_the_main_classes_where_the_occupancy_classes_expect_them() {
        for (name, table) in TABLES {
            assert!(table.iter().any(|(_, c)| *c == "vehicle.car"), "{name}");
            assert!(table.iter().any(|(_, c)| c.starts_with("human.pedestrian") || *c == "vehicle.bicycle"), "{name}");
        }
        let nus = table("py123d.parser.registry.NuScenesBoxDetectionLabel").unwrap();
        assert_eq!(nus.len(), 23, "the 23 nuScenes detection categories");
        for (label, category) in nus {
            // The nuScenes table is the category names themselves, upper-cased with `_`.
            assert_eq!(category.replace('.', "_").to_ascii_uppercase(), *label);
        }
        assert_eq!(table("x.WODPerceptionBoxDetectionLabel").unwrap()[1], ("TYPE_VEHICLE", "vehicle.car"));
        assert!(table("x.Unknown").is_none());
    }
}
