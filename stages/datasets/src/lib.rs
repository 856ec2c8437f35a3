//! dist4d-datasets: the dataset readers (nuScenes v1.0, TRI DGP / DDAD) and the surround-camera
//! adapter that gives both one item tree and one set of source ports, the sensor file formats
//! they read, the per-image sidecar files (ground-truth depth, semantic maps) and the checks every
//! reader applies to metadata it is given (paths confined to the root, poses, calibrations).

pub mod checks;
pub mod dgp;
pub mod files;
pub mod nuscenes;
pub mod sidecar;
pub mod surround;
#[cfg(test)]
mod testing;
