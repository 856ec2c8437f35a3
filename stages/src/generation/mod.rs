//! Generation (DiST-4D Sec. 3.2): DiST-T's future multi-camera RGB-D from a reference frame and
//! control signals (a learned model through a worker, or the built-in geometric baseline), and
//! the "bullet time" surround point cloud of each generated time step.

crate::stage_modules! {
    bev_layout::BevLayout,
    future::GenerateFuture,
    surround_cloud::SurroundCloud,
}
