//! The metric-depth curation of DiST-4D (paper Sec. 3.1): multi-frame LiDAR, multi-view stereo
//! above the LiDAR, fusion, hidden point removal, the depth prompt and its completion.

pub mod aggregate;
pub mod complete;
pub mod fuse;
pub mod hpr;
pub mod mvs;
pub mod mvs_points;
pub mod nearest_fill;
pub mod project_lidar;
pub mod prompt;
