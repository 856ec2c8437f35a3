//! Novel views (DiST-4D Sec. 3.3-3.4): curated RGB-D reprojected into other cameras, poses and
//! times, the conditions DiST-S is trained on and the self-supervised cycle-consistency pairs.

crate::stage_modules! {
    cycle_pair::CyclePair,
    fill_baseline::FillViewBaseline,
    frame_pair::FramePair,
    reproject::Reproject,
    resize_view::ResizeView,
    shift_view::ShiftView,
}
