//! Semantic occupancy (Occ3D; DynamicCity's data): LiDAR aggregated over a scene, static points
//! in the world and each tracked object in its own box frame, voxelized per frame with the
//! visibility masks of LiDAR rays and camera rays, and written in the formats their loaders read.

pub mod classes;
pub mod grid;

use anyhow::{ensure, Result};
use dist4d_runtime::NotApplicable;

/// The artifacts of input `port`, a window of `frames` frames wired with
/// `Window(.., frame, 0, frames - 1)`, in frame order. An error when the wiring reaches outside the
/// window; nothing to make when the window runs past the scene's end (fewer frames came).
pub fn window<'a, A>(port: &str, list: &'a [(i64, A)], frames: usize) -> Result<Vec<&'a A>> {
    ensure!(
        list.iter().all(|(pos, _)| *pos >= 0 && (*pos as usize) < frames),
        "`{port}` reaches past the window of {frames} frames: wire it with Window(.., frame, 0, {})",
        frames.saturating_sub(1)
    );
    if list.len() < frames {
        return Err(NotApplicable(format!(
            "the window of {frames} frames runs past the scene's end ({} frame(s) from here)",
            list.len()
        ))
        .into());
    }
    let mut sorted: Vec<&(i64, A)> = list.iter().collect();
    sorted.sort_by_key(|(pos, _)| *pos);
    Ok(sorted.into_iter().map(|(_, a)| a).collect())
}

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
