//! Encoding stages: artifacts to the files of the user-facing layout (EXR, PNG, NPY, sheets).

pub mod depthroot;

crate::stage_modules! {
    clips::ClipIndex,
    encode_depth::EncodeDepth,
    encode_dist_depth::EncodeDistDepth,
    encode_image::EncodeImage,
    encode_ply::EncodePly,
    encode_points::EncodePoints,
    pair_index::PairIndex,
    pair_sheet::PairSheet,
    sheet::DepthSheet,
}
