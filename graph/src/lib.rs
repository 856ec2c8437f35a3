//! dist4d-graph: pipeline files (RON) to a validated, typed stage DAG.
//!
//! The graph knows nothing about driving: stage kinds, dataset kinds and artifact types come from a
//! [`Catalog`] that the `stages` crate provides. Loading a pipeline reports every problem at once,
//! each with `file:line:column` and a caret snippet.

pub mod canonical;
pub mod catalog;
pub mod checks;
pub mod de;
pub mod diag;
mod load;
pub mod params;
pub mod pipeline;
pub mod source;
pub mod syntax;

pub use catalog::{
    Catalog, DatasetSchema, DimSpec, PortSpec, SourcePortSpec, StageSchema, VariantPlan, Variants, VARIANT_DIM,
};
pub use checks::{ParamChecks, ParamProblem, Validate};
pub use diag::Diagnostic;
pub use load::{load_file, load_str, LoadError};
pub use params::{ParamInfo, ParamsError, ParamsSpec, ParamsValue};
pub use pipeline::{
    DatasetDecl, Dim, Export, Input, Node, NodeId, NodeKind, OutPort, Pipeline, Selector, StageNode, TemplatePart,
};

#[cfg(test)]
mod tests;
