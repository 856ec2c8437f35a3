//! What the graph needs to know about stage kinds and dataset kinds to check a pipeline.
//!
//! The graph knows nothing about driving: artifact types are names, dimensions are names. The
//! `stages` crate describes its stages and datasets through these schemas.

use crate::de::{from_value, struct_fields, DeError};
use crate::source::SourceId;
use crate::syntax::{parse, Value};
use serde::{de::DeserializeOwned, Serialize};

/// One input or output port of a stage.
#[derive(Clone, Copy, Debug)]
pub struct PortSpec {
    pub name: &'static str,
    /// Artifact type name, e.g. `DepthMap`. Wiring requires equal type names.
    pub ty: &'static str,
    /// An input that takes several artifacts (a window, a gather) rather than one.
    pub many: bool,
    /// An input that may be left unwired; the operator then gets no artifact for it.
    pub optional: bool,
    pub doc: &'static str,
}

impl PortSpec {
    pub const fn one(name: &'static str, ty: &'static str, doc: &'static str) -> PortSpec {
        PortSpec { name, ty, many: false, optional: false, doc }
    }
    pub const fn many(name: &'static str, ty: &'static str, doc: &'static str) -> PortSpec {
        PortSpec { name, ty, many: true, optional: false, doc }
    }
    pub const fn optional(name: &'static str, ty: &'static str, doc: &'static str) -> PortSpec {
        PortSpec { name, ty, many: false, optional: true, doc }
    }
}

/// One dimension of a dataset's items, outermost first (e.g. scene, frame, camera).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DimSpec {
    pub name: &'static str,
    /// Whether `Window` and `Offset` selectors may move along it (frames yes, cameras no).
    pub ordered: bool,
}

/// An artifact a dataset yields per item of a grain, read from its raw files.
#[derive(Clone, Copy, Debug)]
pub struct SourcePortSpec {
    pub name: &'static str,
    pub ty: &'static str,
    /// Name of the innermost dimension of the items it is given for.
    pub grain: &'static str,
    pub doc: &'static str,
}

/// One param: its name and its default as RON text.
#[derive(Clone, Debug, PartialEq)]
pub struct ParamInfo {
    pub name: String,
    pub default: String,
}

type CheckFn = dyn Fn(Option<&Value>) -> Result<String, DeError> + Send + Sync;

/// The params of a stage (or the config of a dataset): their names, defaults, and a check that
/// turns the written value into canonical RON (every field, defaults filled), the form that
/// is hashed into task keys.
pub struct ParamsSpec {
    pub fields: Vec<ParamInfo>,
    check: Box<CheckFn>,
}

impl ParamsSpec {
    /// The spec of a serde params struct (`deny_unknown_fields`, `default`).
    pub fn of<P: DeserializeOwned + Serialize + Default + 'static>() -> ParamsSpec {
        let names = struct_fields::<P>();
        let defaults_text = ron::to_string(&P::default()).unwrap_or_default();
        let mut sources = crate::source::Sources::default();
        let id: SourceId = sources.add("defaults", defaults_text.clone());
        let defaults = parse(&defaults_text, id).ok();
        let fields = names
            .iter()
            .map(|n| {
                let default = defaults
                    .as_ref()
                    .and_then(|d| d.field(n))
                    .map(|f| defaults_text[f.value.span.start as usize..f.value.span.end as usize].to_string())
                    .unwrap_or_else(|| "(required)".into());
                ParamInfo { name: n.to_string(), default }
            })
            .collect();
        let check = Box::new(|value: Option<&Value>| -> Result<String, DeError> {
            let params: P = match value {
                Some(v) => from_value(v)?,
                None => P::default(),
            };
            ron::to_string(&params).map_err(|e| DeError { message: format!("cannot write params: {e}"), span: None })
        });
        ParamsSpec { fields, check }
    }

    /// Canonical RON of the params, or the first error.
    pub fn check(&self, value: Option<&Value>) -> Result<String, DeError> {
        (self.check)(value)
    }

    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.fields.iter().map(|f| f.name.as_str())
    }

    /// `a (default 1.0), b (default "x")` for messages.
    pub fn describe(&self) -> String {
        if self.fields.is_empty() {
            return "none".into();
        }
        self.fields.iter().map(|f| format!("{} (default {})", f.name, f.default)).collect::<Vec<_>>().join(", ")
    }
}

/// A stage kind as the graph sees it.
pub trait StageSchema: Send + Sync {
    fn kind(&self) -> &'static str;
    /// Bumped whenever the stage's output for the same inputs and params changes; part of task keys.
    fn version(&self) -> u32;
    fn summary(&self) -> &'static str;
    fn inputs(&self) -> &[PortSpec];
    fn outputs(&self) -> &[PortSpec];
    /// Dimension names the stage may run per; the first is the default.
    fn grains(&self) -> &[&'static str];
    fn params(&self) -> &ParamsSpec;
    /// Stages that draw random numbers get the item key in their task key (their seed derives from it).
    fn seeded(&self) -> bool {
        false
    }
}

/// A dataset kind as the graph sees it.
pub trait DatasetSchema: Send + Sync {
    fn kind(&self) -> &'static str;
    fn summary(&self) -> &'static str;
    fn dims(&self) -> &[DimSpec];
    fn ports(&self) -> &[SourcePortSpec];
    fn config(&self) -> &ParamsSpec;
    /// Config fields holding paths: relative ones are resolved against the directory of the file
    /// they were written in (or the working directory, for `--set`).
    fn path_fields(&self) -> &[&'static str] {
        &[]
    }
}

/// Every stage and dataset kind a pipeline may use.
pub trait Catalog: Sync {
    fn stage(&self, kind: &str) -> Option<&dyn StageSchema>;
    fn stage_kinds(&self) -> Vec<&'static str>;
    fn dataset(&self, kind: &str) -> Option<&dyn DatasetSchema>;
    fn dataset_kinds(&self) -> Vec<&'static str>;
    /// Whether artifacts of this type are encoded files that `export` may write out as they are.
    fn exportable(&self, ty: &str) -> bool;
}
