//! Encoding stages: artifacts to the files of the user-facing layout (EXR, PNG, NPY, sheets).

pub mod encode;
