//! What the graph needs to know about stage kinds and dataset kinds to check a pipeline.
//!
//! The graph knows nothing about driving: artifact types are names, dimensions are names. The
//! `stages` crate describes its stages and datasets through these schemas.

use crate::params::{ParamsSpec, ParamsValue};
use serde::Serialize;
use std::collections::BTreeMap;

/// One input or output port of a stage.
#[derive(Clone, Copy, Debug)]
pub struct PortSpec {
    pub name: &'static str,
    /// Artifact type name, e.g. `Image`. Wiring requires equal type names.
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

/// One dimension of a dataset's items, outermost first (e.g. a recording, its time steps, its
/// sensors).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DimSpec {
    pub name: &'static str,
    /// Whether `Window` and `Offset` selectors may move along it (time steps yes, a set of sensors no).
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

/// A stage kind as the graph sees it: plain data, written once by the stage module.
pub struct StageSchema {
    pub kind: &'static str,
    /// Bumped whenever the stage's output for the same inputs and params changes; part of task keys.
    pub version: u32,
    pub summary: &'static str,
    pub inputs: Vec<PortSpec>,
    pub outputs: Vec<PortSpec>,
    /// Dimension names the stage may run per; the first is the default.
    pub grains: Vec<&'static str>,
    pub params: ParamsSpec,
    /// Whether the stage draws random numbers from its task's seed: its task keys then include
    /// the item key, since its output depends on the item and not only on its inputs.
    pub seeded: bool,
    /// Params (string fields) that say where the pipeline exports a file, for records that point
    /// at it (an index of training clips): each must be the path template of one of the
    /// pipeline's exports, so the two cannot drift apart.
    pub export_template_params: Vec<&'static str>,
    /// Groups of `Many` input ports the stage pairs up by position (images with their
    /// calibrations and poses): every wired port of a group must have the same selector, or some
    /// positions of one have no partner in the others and the task fails at run time. Checked when
    /// the pipeline is loaded.
    pub aligned_inputs: Vec<&'static [&'static str]>,
    /// For a stage that runs once per variant of its params (e.g. a training pair per frame
    /// offset), how to split checked params into the variants: such a stage runs per `variant`,
    /// the dimension [`VARIANT_DIM`] the pipeline then gets under the dataset's innermost one.
    pub variants: Option<fn(&ParamsValue) -> Option<Variants>>,
    /// The input ports the stage does not read with these params (a segmenter's images when no
    /// segmenter is configured): the planner hands them over empty, so their sources are never
    /// loaded (six JPEGs decoded per frame for nothing). Only optional or `Many` inputs.
    pub unused_inputs: Option<fn(&ParamsValue) -> Vec<&'static str>>,
}

/// The name of the dimension a pipeline gets when a stage declares variants: export templates
/// write `{variant}`, stages run per it with `grain: variant`.
pub const VARIANT_DIM: &str = "variant";

/// A stage's params split into what every variant shares and each variant's own part, in label
/// order. A task of one variant is keyed by the shared part and its own part only, so editing
/// one variant reruns that variant alone.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Variants {
    /// The params without their variants, canonical.
    pub shared: String,
    /// Each variant's label and canonical text.
    pub each: Vec<(String, String)>,
    /// How each variant's tasks are planned.
    pub plans: Vec<VariantPlan>,
}

/// What the planner needs to know of one variant.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct VariantPlan {
    /// The variant's offset along an ordered dimension: `Offset("s.p", frame, variant)` reads the
    /// item that far away (a pair's target frame), and a task whose offset falls outside the
    /// items is not planned.
    pub offset: i32,
    /// Optional input ports this variant's tasks do not read: they are planned without them
    /// (nothing loaded for a pair that does not use the other cameras).
    pub unused: Vec<&'static str>,
    /// Optional input ports this variant's tasks cannot do without: `check` refuses the
    /// pipeline when one is not wired (a pair drawn from the other cameras, without them).
    pub needs: Vec<&'static str>,
}

impl Variants {
    /// Splits `params`, whose variants `take` removes (leaving the rest to be shared).
    pub fn split<P: Serialize + Clone, V: Serialize>(
        params: &P,
        take: impl FnOnce(&mut P) -> BTreeMap<String, V>,
    ) -> Option<Variants> {
        Variants::split_planned(params, take, |_| VariantPlan::default())
    }

    /// Like [`Variants::split`], with each variant's [`VariantPlan`].
    pub fn split_planned<P: Serialize + Clone, V: Serialize>(
        params: &P,
        take: impl FnOnce(&mut P) -> BTreeMap<String, V>,
        plan: impl Fn(&V) -> VariantPlan,
    ) -> Option<Variants> {
        let mut shared = params.clone();
        let variants = take(&mut shared);
        let each = variants
            .iter()
            .map(|(label, v)| crate::canonical::to_canonical(v).ok().map(|text| (label.clone(), text)))
            .collect::<Option<Vec<_>>>()?;
        let plans = variants.values().map(plan).collect();
        Some(Variants { shared: crate::canonical::to_canonical(&shared).ok()?, each, plans })
    }

    pub fn labels(&self) -> Vec<String> {
        self.each.iter().map(|(label, _)| label.clone()).collect()
    }
}

/// A dataset kind as the graph sees it.
pub struct DatasetSchema {
    pub kind: &'static str,
    pub summary: &'static str,
    /// Outermost first.
    pub dims: Vec<DimSpec>,
    pub ports: Vec<SourcePortSpec>,
    pub config: ParamsSpec,
    /// Config fields holding paths: relative ones are resolved against the directory of the file
    /// they were written in (or the working directory, for `--set`).
    pub path_fields: Vec<&'static str>,
}

/// Every stage and dataset kind a pipeline may use.
pub trait Catalog: Sync {
    fn stage(&self, kind: &str) -> Option<&StageSchema>;
    fn stage_kinds(&self) -> Vec<&'static str>;
    fn dataset(&self, kind: &str) -> Option<&DatasetSchema>;
    fn dataset_kinds(&self) -> Vec<&'static str>;
    /// Whether artifacts of this type are encoded files that `export` may write out as they are.
    fn exportable(&self, ty: &str) -> bool;
}
