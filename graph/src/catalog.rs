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

/// A value its type accepts but that is out of range or inconsistent with another param (a
/// negative size, NaN, a minimum above its maximum): found after deserializing, so that `check`
/// refuses what every task would refuse (or would run out of memory on).
#[derive(Clone, Debug, PartialEq)]
pub struct ParamProblem {
    /// The field at fault, as written in the pipeline file.
    pub field: &'static str,
    /// For a list field, the element at fault.
    pub index: Option<usize>,
    /// The other field of a relation (`min_depth` must be below `max_depth`): when only that one
    /// was written, the diagnostic points there.
    pub other: Option<&'static str>,
    /// What is wrong, as a predicate of the field: "must be in [0, 1], found NaN".
    pub message: String,
}

impl ParamProblem {
    pub fn new(field: &'static str, message: impl Into<String>) -> ParamProblem {
        ParamProblem { field, index: None, other: None, message: message.into() }
    }
}

/// Range checks of params (or dataset config) that their types cannot express.
///
/// [`ParamsSpec::of`] requires it, so that every params struct says what it accepts. The default
/// finds nothing; that is right only for params without ranges (no fields, flags, free names).
pub trait Validate {
    /// Every problem, each naming its field; empty when the params are usable.
    fn validate(&self) -> Vec<ParamProblem> {
        Vec::new()
    }
}

/// Collects [`ParamProblem`]s with the checks params need most, worded alike everywhere.
#[derive(Default, Debug)]
pub struct ParamChecks(Vec<ParamProblem>);

impl ParamChecks {
    pub fn new() -> ParamChecks {
        ParamChecks::default()
    }

    /// A problem when `ok` is false.
    pub fn check(&mut self, ok: bool, field: &'static str, message: impl FnOnce() -> String) -> &mut Self {
        if !ok {
            self.0.push(ParamProblem::new(field, message()));
        }
        self
    }

    /// A finite number in `lo..=hi`.
    pub fn within(&mut self, field: &'static str, value: f64, lo: f64, hi: f64) -> &mut Self {
        self.check(value.is_finite() && (lo..=hi).contains(&value), field, || {
            format!("must be a number in [{lo}, {hi}], found {value}")
        })
    }

    /// A finite number above `lo` (strictly) and at most `hi`.
    pub fn above(&mut self, field: &'static str, value: f64, lo: f64, hi: f64) -> &mut Self {
        self.check(value.is_finite() && value > lo && value <= hi, field, || {
            format!("must be a number in ({lo}, {hi}], found {value}")
        })
    }

    /// A whole number in `lo..=hi`.
    pub fn count(&mut self, field: &'static str, value: u64, lo: u64, hi: u64) -> &mut Self {
        self.check((lo..=hi).contains(&value), field, || format!("must be in {lo}..={hi}, found {value}"))
    }

    /// `low` (field `field`) strictly below `high` (field `other`).
    pub fn below(&mut self, field: &'static str, low: f64, other: &'static str, high: f64) -> &mut Self {
        if low >= high && low.is_finite() && high.is_finite() {
            self.0.push(ParamProblem {
                field,
                index: None,
                other: Some(other),
                message: format!("must be below `{other}` ({high}), found {low}"),
            });
        }
        self
    }

    /// Names that become one path component each (a folder or file name in an output layout):
    /// at least one, no repeats, none empty, `.`, `..`, or holding `/`, `\` or NUL.
    pub fn path_names(&mut self, field: &'static str, names: &[String]) -> &mut Self {
        if names.is_empty() {
            self.0.push(ParamProblem::new(field, "must name at least one"));
        }
        for (i, name) in names.iter().enumerate() {
            let problem = match path_component_problem(name) {
                Some(p) => Some(p),
                None if names[..i].contains(name) => Some(format!("names `{name}` twice")),
                None => None,
            };
            if let Some(message) = problem {
                self.0.push(ParamProblem { field, index: Some(i), other: None, message });
            }
        }
        self
    }

    /// One name that becomes one path component (see [`ParamChecks::path_names`]).
    pub fn path_name(&mut self, field: &'static str, name: &str) -> &mut Self {
        if let Some(message) = path_component_problem(name) {
            self.0.push(ParamProblem::new(field, message));
        }
        self
    }

    pub fn push(&mut self, problem: ParamProblem) -> &mut Self {
        self.0.push(problem);
        self
    }

    pub fn done(&mut self) -> Vec<ParamProblem> {
        std::mem::take(&mut self.0)
    }
}

/// Why `name` cannot be one path component, if it cannot: joined to a folder, it must name an
/// entry of that folder and nothing outside it.
fn path_component_problem(name: &str) -> Option<String> {
    if name.is_empty() {
        return Some("must not be empty (it becomes a file or folder name)".into());
    }
    if name == "." || name == ".." {
        return Some(format!("must not be `{name}` (it becomes a file or folder name)"));
    }
    if let Some(c) = name.chars().find(|c| matches!(c, '/' | '\\' | '\0')) {
        return Some(format!(
            "must be one file or folder name, without `{}`, found `{}`",
            c.escape_default(),
            name.escape_default()
        ));
    }
    None
}

/// The check of a written params value: its canonical RON, or why it is not usable.
#[derive(Debug)]
pub enum ParamsError {
    /// The value does not have the params' type (unknown field, a string for a number).
    Type(DeError),
    /// It has the type but is out of range.
    Range(Vec<ParamProblem>),
}

type CheckFn = dyn Fn(Option<&Value>) -> Result<String, ParamsError> + Send + Sync;

/// The params of a stage (or the config of a dataset): their names, defaults, and a check that
/// turns the written value into canonical RON (every field, defaults filled), the form that
/// is hashed into task keys.
pub struct ParamsSpec {
    pub fields: Vec<ParamInfo>,
    check: Box<CheckFn>,
}

impl ParamsSpec {
    /// The spec of a serde params struct (`deny_unknown_fields`, `default`) and its ranges.
    pub fn of<P: DeserializeOwned + Serialize + Default + Validate + 'static>() -> ParamsSpec {
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
        let check = Box::new(|value: Option<&Value>| -> Result<String, ParamsError> {
            let params: P = match value {
                Some(v) => from_value(v).map_err(ParamsError::Type)?,
                None => P::default(),
            };
            let problems = params.validate();
            if !problems.is_empty() {
                return Err(ParamsError::Range(problems));
            }
            ron::to_string(&params)
                .map_err(|e| ParamsError::Type(DeError { message: format!("cannot write params: {e}"), span: None }))
        });
        ParamsSpec { fields, check }
    }

    /// Canonical RON of the params, or the first type error, or every range problem.
    pub fn check(&self, value: Option<&Value>) -> Result<String, ParamsError> {
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
