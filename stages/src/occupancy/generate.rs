//! `GenerateHexPlane`: DynamicCity's DiT as an external worker: the next window's HexPlane
//! (its padded rollout) from the window's conditions ([`super::conditions`]: trajectory, command,
//! layout) and the previous window's rollout, which DynamicCity's DiT can condition on
//! (`hex_cond`). The DiT is a model: this stage only runs with a `worker` (op
//! `generate_hexplane`, docs/workers.md); without one it has nothing to make. The engine checks
//! the rollout it returns (finite, shaped as its `hex_txyz` says) and adds the padding mask.
//! `workers/hexplane_persist.py` is a reference: the persistence baseline (the next window is
//! the previous one).

use crate::model_worker::{Exchange, ModelWorker, WorkerSpec};
use crate::stage::Stage;
use anyhow::Result;
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::{Made, TaskContext};
use dist4d_types::artifact::File;
use serde::{Deserialize, Serialize};
use serde_json::json;

#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The DiT as an external worker (op `generate_hexplane`). Its name, version and weights
    /// enter the task keys.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worker: Option<WorkerSpec>,
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        if let Some(w) = &self.worker {
            w.check(&mut c);
        }
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the window's conditions (`conditions.json`: trajectory, command)
        conditions: One<File>,
        /// the window's layout (`conditions.layout`: layout.npz)
        layout: One<File>,
        /// the previous window's rollout (`Offset("hexplane.rollout", frame, -16)`)
        previous: One<File>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// rollout.npz: the generated `rollout` (C, H, W) float32, its `mask` and `hex_txyz`
        rollout: One<File>,
    }
}

pub struct GenerateHexPlane(ModelWorker);

impl Stage for GenerateHexPlane {
    const KIND: &'static str = "GenerateHexPlane";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "DynamicCity's DiT as a worker: the next window's HexPlane rollout from its conditions and the previous window's";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(GenerateHexPlane(ModelWorker::new(params.worker)))
    }
    fn identity(&self) -> Result<Option<String>> {
        self.0.identity()
    }
    fn resource(&self) -> Option<dist4d_runtime::Resource> {
        self.0.resource()
    }

    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        if !self.0.is_set() {
            return Ok(Made::Nothing("no DiT worker: set `worker` to generate HexPlanes".into()));
        }
        let ex = Exchange::new()?;
        let inputs = vec![
            ex.put("conditions", "conditions.json", &i.conditions.0)?,
            ex.put("layout", "layout.npz", &i.layout.0)?,
            ex.put("previous", "previous.npz", &i.previous.0)?,
        ];
        let outputs = self.0.call(ctx, &ex, "generate_hexplane", inputs, json!({}))?;
        let (_, _, file) = super::hexplane::worker_rollout(&ex, &outputs)?;
        Ok(Outputs { rollout: File(file) }.into())
    }
}
