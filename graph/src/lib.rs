//! dist4d-graph: pipeline files (RON) to a validated, typed stage DAG.
//!
//! The graph knows nothing about driving: stage kinds, dataset kinds and artifact types come from a
//! [`Catalog`] that the `stages` crate provides. Loading a pipeline reports every problem at once,
//! each with `file:line:column` and a caret snippet.

pub mod canonical;
pub mod catalog;
pub mod de;
pub mod diag;
mod load;
pub mod pipeline;
pub mod source;
pub mod syntax;

pub use catalog::{
    Catalog, DatasetSchema, DimSpec, ParamChecks, ParamInfo, ParamProblem, ParamsError, ParamsSpec, PortSpec,
    SourcePortSpec, StageSchema, Validate,
};
pub use diag::Diagnostic;
pub use load::{load_file, load_str, LoadError};
pub use pipeline::{
    DatasetDecl, Dim, Export, Input, Node, NodeId, NodeKind, OutPort, Pipeline, Selector, StageNode, TemplatePart,
};

#[cfg(test)]
mod tests;
