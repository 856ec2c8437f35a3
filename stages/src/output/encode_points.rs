//! `EncodePoints`: projected points as an NPY array, for readers of the `uvz` files.

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::Result;
use dist4d_graph::Validate;
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, ProjectedPoints};
use dist4d_types::formats::npy_f32;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Params {}

impl Validate for Params {}

crate::inputs! {
    pub struct Inputs {
        /// projected points
        points: One<ProjectedPoints>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// float32 (N, 3): u, v, depth
        npy: One<File>,
    }
}

pub struct EncodePoints;

impl Stage for EncodePoints {
    const KIND: &'static str = "EncodePoints";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "ProjectedPoints -> NPY float32 (N, 3) rows of u, v, depth";
    const GRAINS: &'static [&'static str] = &["camera", "frame", "scene"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(_: Params) -> Result<Self> {
        Ok(EncodePoints)
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        Ok(Outputs { npy: File(npy_f32(&[i.points.rows.len(), 3], i.points.rows.as_flattened())) }.into())
    }
}
