//! dist4d-types: the artifacts stages exchange (point clouds, depth maps, images, calibrations,
//! poses, boxes), the rigid-body geometry they are expressed in, the file formats they are written
//! as, and the deterministic random numbers every module draws from.

pub mod artifact;
pub mod cancel;
pub mod deflate_rle;
pub mod formats;
pub mod geometry;
pub mod npy;
pub mod occ3d;
pub mod pickle;
pub mod rng;
pub mod voxels;
