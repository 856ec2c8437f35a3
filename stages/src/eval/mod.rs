//! Scoring: depth against references (ground truth, held-out LiDAR) and the region above the
//! LiDAR's field of view; the sky and depth-boundary metrics and the edge detector they use.

pub mod boundary;
pub mod canny;
pub mod image_scores;
pub mod labels;
pub mod report;
pub mod sky;

crate::stage_modules! {
    above_fov::AboveLidarFov,
    cloud::EvalCloud,
    depth::EvalDepth,
    moving::OnMovingObjects,
    novel_view::EvalNovelView,
    render_synthetic::RenderSynthetic,
    temporal::EvalTemporal,
}
