//! The validated pipeline: a typed DAG of dataset sources and stages, wired port to port.

use crate::params::ParamsValue;
use petgraph::graph::{DiGraph, NodeIndex};
use std::fmt;
use std::path::PathBuf;

/// Index into [`Pipeline::nodes`].
pub type NodeId = usize;

/// Which upstream items feed one task of a stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Selector {
    /// The item itself, or the enclosing item when the upstream grain is coarser (an upstream
    /// item per `(a, b)` feeds each `(a, b, c)` under it).
    Same,
    /// Items whose coordinate along `dim` lies in `i+before ..= i+after`, clipped to the items
    /// that exist.
    Window { dim: usize, before: i32, after: i32 },
    /// The one item at `i+by` along `dim`; tasks whose offset falls outside the items that exist
    /// are not planned.
    Offset { dim: usize, by: i32 },
    /// Every item of the next-finer grain `dim` under this item.
    Gather { dim: usize },
    /// Every upstream item under the same outer item (the item of the outermost dimension).
    All,
    /// The one item at `i + offset` along `dim`, the offset being the task's variant's (see
    /// [`crate::VariantPlan`]); tasks whose offset falls outside the items are not planned.
    VariantOffset { dim: usize },
    /// The upstream items at this item's coordinates except along `dim`, which takes every value
    /// (all cameras of this frame, for a task of one camera): the "surround" of an item.
    Across { dim: usize },
}

impl Selector {
    /// Whether the selector can give more than one artifact.
    pub fn gives_many(self) -> bool {
        matches!(self, Selector::Window { .. } | Selector::Gather { .. } | Selector::All | Selector::Across { .. })
    }

    /// RON form, for `graph` output and messages.
    pub fn display(self, dims: &[Dim]) -> String {
        match self {
            Selector::Same => "same".into(),
            Selector::Window { dim, before, after } => {
                format!("Window({}, {before}, {after})", dims[dim].name)
            }
            Selector::Offset { dim, by } => format!("Offset({}, {by})", dims[dim].name),
            Selector::VariantOffset { dim } => format!("Offset({}, variant)", dims[dim].name),
            Selector::Gather { dim } => format!("Gather({})", dims[dim].name),
            Selector::All => "All".into(),
            Selector::Across { dim } => format!("Across({})", dims[dim].name),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Dim {
    pub name: String,
    pub ordered: bool,
}

/// An output port of a node.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct OutPort {
    pub name: String,
    pub ty: String,
}

/// One wired input of a stage.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Input {
    pub port: String,
    pub ty: String,
    pub from: NodeId,
    pub from_port: usize,
    pub selector: Selector,
    pub many: bool,
}

#[derive(Clone, Debug, PartialEq)]
pub struct StageNode {
    pub kind: String,
    pub version: u32,
    /// The checked params: typed, for building the operator, and canonical, for task keys.
    pub params: ParamsValue,
    pub seeded: bool,
    /// Runs on every `every`-th item of its grain's innermost dimension only (1: every item): a
    /// window per stride (DynamicCity's windows of 16 frames), not one at every frame.
    pub every: u32,
    pub inputs: Vec<Input>,
    /// For a stage that declares variants: its params split per variant (it runs per
    /// [`crate::VARIANT_DIM`]).
    pub variants: Option<crate::Variants>,
    /// The input ports it does not read with its params (see `StageSchema::unused_inputs`):
    /// planned with no sources.
    pub unused: Vec<&'static str>,
}

#[derive(Clone, Debug, PartialEq)]
pub enum NodeKind {
    /// A port of the dataset, read from raw files.
    Source {
        port: String,
    },
    Stage(StageNode),
}

#[derive(Clone, Debug, PartialEq)]
pub struct Node {
    /// `dataset.<port>` for sources, the stage name for stages.
    pub name: String,
    /// Number of dimensions of this node's items: 1 = per item of the outermost dimension, 2 = per
    /// item of the second, and so on (0 only in a pipeline that did not load).
    pub grain: usize,
    pub outputs: Vec<OutPort>,
    pub kind: NodeKind,
}

impl Node {
    pub fn stage(&self) -> Option<&StageNode> {
        match &self.kind {
            NodeKind::Stage(s) => Some(s),
            NodeKind::Source { .. } => None,
        }
    }
}

/// A piece of an export path template.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TemplatePart {
    Text(String),
    Dim(usize),
    /// `{frame.token}`: the dataset's own id of the item at that dimension (a nuScenes sample
    /// token), which loaders that find files by token need.
    Token(usize),
    /// `{frame:06}`: the item's label, a number, zero-padded to that many digits.
    Padded(usize, usize),
}

impl TemplatePart {
    /// The dimension this part names, if any.
    pub fn dim(&self) -> Option<usize> {
        match self {
            TemplatePart::Text(_) => None,
            TemplatePart::Dim(d) | TemplatePart::Token(d) | TemplatePart::Padded(d, _) => Some(*d),
        }
    }
}

/// An output port written into the user-facing dataset layout.
#[derive(Clone, Debug, PartialEq)]
pub struct Export {
    pub node: NodeId,
    pub port: usize,
    /// The template as written, with one `{dimension}` placeholder per dimension of the grain.
    pub template: String,
    pub parts: Vec<TemplatePart>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct DatasetDecl {
    pub kind: String,
    /// The checked config: typed, for opening the dataset, and canonical, for the pipeline digest.
    pub config: ParamsValue,
}

/// A checked pipeline: every node exists, every wire is typed and allowed.
#[derive(Clone, Debug)]
pub struct Pipeline {
    pub name: String,
    pub path: PathBuf,
    pub dataset: DatasetDecl,
    pub dims: Vec<Dim>,
    pub nodes: Vec<Node>,
    /// Node ids in an order where every node comes after its inputs.
    pub order: Vec<NodeId>,
    pub exports: Vec<Export>,
    /// The labels of the variant dimension (the last of `dims`, named [`crate::VARIANT_DIM`])
    /// when a stage declares variants; empty otherwise.
    pub variants: Vec<String>,
}

impl Pipeline {
    /// The dimension items are ordered along (time, for driving data): the first one the
    /// dataset's schema declares `ordered`. The engine takes ready tasks in its order and cuts a
    /// run's limit along it.
    pub fn ordered_dim(&self) -> Option<usize> {
        self.dims.iter().position(|d| d.ordered)
    }

    pub fn node_by_name(&self, name: &str) -> Option<NodeId> {
        self.nodes.iter().position(|n| n.name == name)
    }

    /// Ids of the stage nodes (not sources), in topological order.
    pub fn stage_order(&self) -> impl Iterator<Item = NodeId> + '_ {
        self.order.iter().copied().filter(|&n| self.nodes[n].stage().is_some())
    }

    /// The offset of variant `i` (from the stage that declares the variants; 0 when it gives none).
    pub fn variant_offset(&self, i: usize) -> i32 {
        self.nodes
            .iter()
            .filter_map(|n| n.stage()?.variants.as_ref())
            .find_map(|v| v.plans.get(i).map(|p| p.offset))
            .unwrap_or(0)
    }

    /// Name of a grain (its innermost dimension).
    pub fn grain_name(&self, grain: usize) -> &str {
        if grain == 0 {
            "dataset"
        } else {
            &self.dims[grain - 1].name
        }
    }

    /// The stage DAG as a petgraph graph (nodes are [`NodeId`]s, edges carry the input index).
    pub fn digraph(&self) -> DiGraph<NodeId, usize> {
        let mut g = DiGraph::new();
        let idx: Vec<NodeIndex> = (0..self.nodes.len()).map(|n| g.add_node(n)).collect();
        for (n, node) in self.nodes.iter().enumerate() {
            if let Some(stage) = node.stage() {
                for (i, input) in stage.inputs.iter().enumerate() {
                    g.add_edge(idx[input.from], idx[n], i);
                }
            }
        }
        g
    }

    /// Graphviz DOT of the DAG: sources as ellipses, stages as boxes, edges labelled with ports.
    pub fn to_dot(&self) -> String {
        let mut out = format!("digraph \"{}\" {{\n  rankdir=LR;\n  node [fontname=\"Helvetica\"];\n", esc(&self.name));
        for (i, node) in self.nodes.iter().enumerate() {
            let grain = self.grain_name(node.grain);
            match &node.kind {
                NodeKind::Source { .. } => out.push_str(&format!(
                    "  n{i} [shape=ellipse, label=\"{}\\n{} per {}\"];\n",
                    esc(&node.name),
                    esc(&node.outputs[0].ty),
                    grain
                )),
                NodeKind::Stage(s) => out.push_str(&format!(
                    "  n{i} [shape=box, label=\"{}\\n{} v{} per {}\"];\n",
                    esc(&node.name),
                    esc(&s.kind),
                    s.version,
                    grain
                )),
            }
        }
        for (i, node) in self.nodes.iter().enumerate() {
            if let Some(s) = node.stage() {
                for input in &s.inputs {
                    let from = &self.nodes[input.from];
                    let sel = match input.selector {
                        Selector::Same => String::new(),
                        other => format!(" {}", other.display(&self.dims)),
                    };
                    out.push_str(&format!(
                        "  n{} -> n{i} [label=\"{} -> {}{}\\n{}\"];\n",
                        input.from,
                        esc(&from.outputs[input.from_port].name),
                        esc(&input.port),
                        esc(&sel),
                        esc(&input.ty)
                    ));
                }
            }
        }
        out.push_str("}\n");
        out
    }
}

fn esc(s: &str) -> String {
    s.replace('\\', "\\\\").replace('"', "\\\"")
}

impl fmt::Display for Selector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{self:?}")
    }
}
