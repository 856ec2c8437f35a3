//! Semantic occupancy (Occ3D; DynamicCity's data): LiDAR aggregated over a scene, static points
//! in the world and each tracked object in its own box frame, voxelized per frame with the
//! visibility masks of LiDAR rays and camera rays, and written in the formats their loaders read.

pub mod classes;
pub mod grid;

crate::stage_modules! {
    dynamic_city::EncodeCarlaSC,
    poses_txt::PosesTxt,
    aggregate_scene::AggregateScene,
    annotations::Occ3dAnnotations,
    conditions::DitConditions,
    encode_occ3d::EncodeOcc3d,
    eval::EvalOccupancy,
    exact::ExactOccupancy,
    generate::GenerateHexPlane,
    hexplane::HexPlaneBaseline,
    occupancy_frame::Occupancy,
    preview::OccupancyPreview,
    sheet::OccupancySheet,
}
