//! Scoring: depth against references (ground truth, held-out LiDAR) and the region above the
//! LiDAR's field of view.

pub mod above_fov;
pub mod depth;
pub mod report;
