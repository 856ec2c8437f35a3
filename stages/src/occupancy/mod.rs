//! Semantic occupancy (Occ3D; DynamicCity's data): LiDAR aggregated over a scene, static points
//! in the world and each tracked object in its own box frame, voxelized per frame with the
//! visibility masks of LiDAR rays and camera rays, and written in the formats their loaders read.

pub mod classes;
pub mod grid;

use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_runtime::Made;

/// The artifacts of input `port`, a window of `frames` frames wired with
/// `Window(.., frame, 0, frames - 1)`, in frame order. An error when the wiring reaches outside the
/// window; nothing to make when the window runs past the scene's end (fewer frames came).
pub fn window<'a, A>(port: &str, list: &'a [(i64, A)], frames: usize) -> Result<Made<Vec<&'a A>>> {
    ensure!(
        list.iter().all(|(pos, _)| *pos >= 0 && (*pos as usize) < frames),
        "`{port}` reaches past the window of {frames} frames: wire it with Window(.., frame, 0, {})",
        frames.saturating_sub(1)
    );
    if list.len() < frames {
        return Ok(Made::Nothing(format!(
            "the window of {frames} frames runs past the scene's end ({} frame(s) from here)",
            list.len()
        )));
    }
    let mut sorted: Vec<&(i64, A)> = list.iter().collect();
    sorted.sort_by_key(|(pos, _)| *pos);
    Ok(Made::Outputs(sorted.into_iter().map(|(_, a)| a).collect()))
}

/// The warnings `run` prints when a pipeline's occupancy will be geometry only (issue 42: it
/// used to say so only in `aggregate.json`): one line per `AggregateScene` that has neither the
/// dataset's point labels (`has_point_labels`, and its `lidarseg` param) nor a `LabelPoints`
/// with a segmenter worker wired into `camera_labels`. `dataset` names the dataset in the line.
pub fn geometry_only_warnings(p: &dist4d_graph::Pipeline, has_point_labels: bool, dataset: &str) -> Vec<String> {
    let mut out = Vec::new();
    for node in &p.nodes {
        let Some(stage) = node.stage() else { continue };
        if stage.kind != aggregate_scene::AggregateScene::KIND {
            continue;
        }
        let lidarseg = has_point_labels && stage.params.get::<aggregate_scene::Params>().is_none_or(|a| a.lidarseg);
        let segmenter = stage.inputs.iter().filter(|i| i.port == "camera_labels").any(|i| {
            p.nodes.get(i.from).and_then(|n| n.stage()).is_some_and(|s| {
                s.kind == label_points::LabelPoints::KIND
                    && s.params.get::<label_points::Params>().is_some_and(|l| l.worker.is_some())
            })
        });
        if !lidarseg && !segmenter {
            out.push(format!(
                "stage `{}` (AggregateScene): dataset {dataset} has no LiDAR point labels and no segmenter is configured \
                 (`LabelPoints` worker), so occupancy semantics are geometry only: ground = driveable_surface, every other \
                 static point = others; each frame's meta.json says \"semantics_source\": \"geometry\" (docs/occupancy.md)",
                node.name
            ));
        }
    }
    out
}

crate::stage_modules! {
    dynamic_city::EncodeCarlaSC,
    poses_txt::PosesTxt,
    aggregate_scene::AggregateScene,
    annotations::Occ3dAnnotations,
    conditions::DitConditions,
    encode_occ3d::EncodeOcc3d,
    encode_occ3d_waymo::EncodeOcc3dWaymo,
    eval::EvalOccupancy,
    exact::ExactOccupancy,
    generate::GenerateHexPlane,
    hexplane::HexPlaneBaseline,
    label_points::LabelPoints,
    occupancy_frame::Occupancy,
    preview::OccupancyPreview,
    sheet::OccupancySheet,
}
