//! Scoring: depth against references (ground truth, held-out LiDAR) and the region above the
//! LiDAR's field of view.

pub mod report;

crate::stage_modules! {
    above_fov::AboveLidarFov,
    depth::EvalDepth,
}
