//! The metric-depth curation of DiST-4D (paper Sec. 3.1): multi-frame LiDAR, multi-view stereo
//! above the LiDAR, fusion, hidden point removal, the depth prompt and its completion.

crate::stage_modules! {
    aggregate::AggregateLidar,
    complete::CompleteDepth,
    ego_estimate::EstimateEgo,
    ego_mask::EgoMask,
    follow_tracks::FollowTracks,
    fuse::FusePoints,
    hpr::HiddenPointRemoval,
    mvs::MultiViewStereo,
    mvs_points::StaticMvsPoints,
    nearest_fill::NearestFill,
    project_lidar::ProjectLidar,
    prompt::DepthPrompt,
    sky::EstimateSky,
    temporal_blend::TemporalBlend,
}
