//! `PairIndex`: the training pairs of a scene (DiST-S pairs, SCC pairs) as JSON lines, one per
//! pair, for a PyTorch loader: each `FramePair` / `CyclePair` record (frames, tokens, times,
//! poses, intrinsics at the model size, offset, shift, augmentation) plus `files`, the paths of
//! the pair's exported files relative to the output folder. The paths come from templates that
//! must be the pipeline's export templates of those files (`check` refuses one no export has).
//! Layout and a numpy-only loader: docs/novel-views.md.

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::File;
use serde::{Deserialize, Serialize};
use serde_json::Value;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Where each file of a pair is, relative to the output folder: the pipeline's export
    /// templates (`{scene}`, `{frame}`, `{camera}`, `{variant}` are the pair's labels).
    pub cond_image: String,
    pub cond_depth: String,
    pub mask: String,
    pub target_image: String,
    pub target_depth: String,
}

impl Default for Params {
    fn default() -> Self {
        let at = |what: &str| format!("{{scene}}/{{camera}}/{{frame}}_{{variant}}_{what}");
        Params {
            cond_image: at("cond.png"),
            cond_depth: at("cond_depth.npy"),
            mask: at("mask.png"),
            target_image: at("target.png"),
            target_depth: at("target_depth.npy"),
        }
    }
}

impl Params {
    fn templates(&self) -> [(&'static str, &String); 5] {
        [
            ("cond_image", &self.cond_image),
            ("cond_depth", &self.cond_depth),
            ("mask", &self.mask),
            ("target_image", &self.target_image),
            ("target_depth", &self.target_depth),
        ]
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        for (field, template) in self.templates() {
            c.check(["{scene}", "{frame}", "{camera}", "{variant}"].iter().all(|p| template.contains(p)), field, || {
                format!("must hold {{scene}}, {{frame}}, {{camera}} and {{variant}} (one file per pair), found `{template}`")
            });
        }
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// every pair record of the scene (`All("pairs.record")`)
        records: Many<File>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// JSON lines, one pair each
        jsonl: One<File>,
    }
}

pub struct PairIndex(Params);

impl Stage for PairIndex {
    const KIND: &'static str = "PairIndex";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "the training pairs of a scene as JSON lines, with the paths of their exported files";
    const GRAINS: &'static [&'static str] = &["scene"];
    const EXPORT_TEMPLATE_PARAMS: &'static [&'static str] =
        &["cond_image", "cond_depth", "mask", "target_image", "target_depth"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(PairIndex(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let mut out = Vec::new();
        for (pos, File(bytes)) in &i.records {
            let mut record: Value =
                serde_json::from_slice(bytes).with_context(|| format!("record {pos} is not JSON"))?;
            let label = |k: &str| record.get(k).and_then(Value::as_str).map(str::to_string);
            let (Some(scene), Some(frame), Some(camera), Some(variant)) =
                (label("scene"), label("frame"), label("camera"), label("variant"))
            else {
                anyhow::bail!("record {pos} lacks its scene, frame, camera or variant label");
            };
            let files: serde_json::Map<String, Value> = self
                .0
                .templates()
                .into_iter()
                .map(|(name, t)| {
                    let path = t
                        .replace("{scene}", &scene)
                        .replace("{frame}", &frame)
                        .replace("{camera}", &camera)
                        .replace("{variant}", &variant);
                    (name.to_string(), Value::String(path))
                })
                .collect();
            record["files"] = Value::Object(files);
            serde_json::to_writer(&mut out, &record)?;
            out.push(b'\n');
        }
        Ok(Outputs { jsonl: File(out) }.into())
    }
}
