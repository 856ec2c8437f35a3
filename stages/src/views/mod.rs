//! Drawing RGB-D views into other views: the library the `novel_view` and `generation` families
//! share, as `lift` and `camera` are everyone's. A view is an image, its depth and its camera
//! (`splat::PinholeView`); drawing one into another camera is `splat` (footprints and a soft
//! z-buffer), the objects that moved between the two times follow their boxes (`moving`), the
//! holes left are filled background first (`fill`), and `frames` and `resize` turn a dataset's
//! frames (image, depth, `ImageInfo`) into views at the model's size and records. Stages live in
//! the families; nothing here is one.

pub mod fill;
pub mod frames;
pub mod moving;
pub mod resize;
pub mod splat;

#[cfg(test)]
mod exactness_tests;
