//! dist4d-datasets: the dataset readers (nuScenes v1.0, TRI DGP / DDAD) and the surround-camera
//! adapter that gives both one item tree and one set of source ports, the sensor file formats
//! they read, the per-image sidecar files (ground-truth depth, semantic maps) and the checks every
//! reader applies to metadata it is given (paths confined to the root, poses, calibrations).

pub mod checks;
pub mod dgp;
pub mod files;
pub mod nuscenes;
pub mod py123d;
pub mod registry;
pub mod sidecar;
pub mod surround;
pub mod synth;
#[cfg(test)]
mod testing;

pub use registry::{DatasetDef, Opened};

/// Every dataset kind, in the order `dist4d check` lists them: a reader is its module and its
/// line here.
pub const DATASETS: &[DatasetDef] = &[nuscenes::DATASET, dgp::DATASET, synth::DATASET, py123d::DATASET];
