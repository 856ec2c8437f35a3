//! The shape every stage module shares: a [`StageDef`] (schema + how to build its operator from
//! canonical params) and helpers to decode typed inputs.

use anyhow::{anyhow, Context, Result};
use dist4d_graph::{ParamsSpec, PortSpec, StageSchema, Validate};
use dist4d_runtime::{Operator, TaskContext};
use dist4d_types::artifact::Artifact;
use serde::{de::DeserializeOwned, Serialize};

/// A stage's work on decoded params; the context is rarely needed, so it is left out.
pub trait TypedOp: Send + Sync {
    fn run(&self, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Vec<Vec<u8>>>;
}

/// Runs a [`TypedOp`]. `slots[i]` is the schema position of the i-th wired input, so that an
/// operator always sees its inputs in schema order, unwired optional ones as empty lists.
struct OpAdapter {
    op: Box<dyn TypedOp>,
    slots: Vec<usize>,
    schema_len: usize,
}

impl Operator for OpAdapter {
    fn run(&self, _ctx: &TaskContext, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Vec<Vec<u8>>> {
        if self.slots.len() == self.schema_len {
            return self.op.run(inputs);
        }
        let mut full = vec![Vec::new(); self.schema_len];
        for (slot, artifacts) in self.slots.iter().zip(inputs) {
            full[*slot] = artifacts.clone();
        }
        self.op.run(&full)
    }
}

type BuildFn = Box<dyn Fn(&str) -> Result<Box<dyn TypedOp>> + Send + Sync>;

pub struct StageDef {
    pub kind: &'static str,
    pub version: u32,
    pub summary: &'static str,
    pub inputs: Vec<PortSpec>,
    pub outputs: Vec<PortSpec>,
    pub grains: Vec<&'static str>,
    pub params: ParamsSpec,
    build: BuildFn,
}

impl StageDef {
    #[allow(clippy::too_many_arguments)]
    pub fn new<P: DeserializeOwned + Serialize + Default + Validate + 'static>(
        kind: &'static str,
        version: u32,
        summary: &'static str,
        inputs: Vec<PortSpec>,
        outputs: Vec<PortSpec>,
        grains: Vec<&'static str>,
        build: fn(P) -> Result<Box<dyn TypedOp>>,
    ) -> StageDef {
        StageDef {
            kind,
            version,
            summary,
            inputs,
            outputs,
            grains,
            params: ParamsSpec::of::<P>(),
            build: Box::new(move |canonical| {
                let params: P = parse_canonical(canonical).with_context(|| format!("params of {kind}"))?;
                // `check` refused these already; params that reach here another way are checked too.
                ensure_valid(&params).with_context(|| format!("params of {kind}"))?;
                build(params)
            }),
        }
    }

    /// The operator for canonical params (as the graph produced them) and the names of the
    /// wired input ports, in schema order.
    pub fn build(&self, canonical: &str, wired: &[&str]) -> Result<Box<dyn Operator>> {
        let slots = wired
            .iter()
            .map(|w| {
                self.inputs.iter().position(|p| p.name == *w).ok_or_else(|| anyhow!("{} has no input `{w}`", self.kind))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Box::new(OpAdapter { op: (self.build)(canonical)?, slots, schema_len: self.inputs.len() }))
    }
}

impl StageSchema for StageDef {
    fn kind(&self) -> &'static str {
        self.kind
    }
    fn version(&self) -> u32 {
        self.version
    }
    fn summary(&self) -> &'static str {
        self.summary
    }
    fn inputs(&self) -> &[PortSpec] {
        &self.inputs
    }
    fn outputs(&self) -> &[PortSpec] {
        &self.outputs
    }
    fn grains(&self) -> &[&'static str] {
        &self.grains
    }
    fn params(&self) -> &ParamsSpec {
        &self.params
    }
}

/// An error listing every range problem of `params` (none: Ok).
pub fn ensure_valid<P: Validate>(params: &P) -> Result<()> {
    let problems = params.validate();
    if problems.is_empty() {
        return Ok(());
    }
    let list: Vec<String> = problems.iter().map(|p| format!("`{}` {}", p.field, p.message)).collect();
    Err(anyhow!("{}", list.join("; ")))
}

/// Reads a params struct back from its canonical RON text.
pub fn parse_canonical<P: DeserializeOwned>(text: &str) -> Result<P> {
    dist4d_graph::de::from_canonical(text).map_err(|e| anyhow!("{e}"))
}

/// An input port of artifact type `A` taking one artifact.
pub fn input<A: Artifact>(name: &'static str, doc: &'static str) -> PortSpec {
    PortSpec::one(name, A::TYPE, doc)
}

/// An optional input port of artifact type `A` (may be left unwired).
pub fn optional_input<A: Artifact>(name: &'static str, doc: &'static str) -> PortSpec {
    PortSpec::optional(name, A::TYPE, doc)
}

/// Decodes the artifact of optional input `i`, if it is wired.
pub fn maybe_one<A: Artifact>(inputs: &[Vec<dist4d_runtime::Artifact>], i: usize) -> Result<Option<A>> {
    match inputs.get(i).and_then(|v| v.first()) {
        None => Ok(None),
        Some(a) => A::decode(&a.bytes).with_context(|| format!("decoding input {i} as {}", A::TYPE)).map(Some),
    }
}

/// Decodes every artifact of a several-artifact input `i`, with its position (window offset).
pub fn each<A: Artifact>(inputs: &[Vec<dist4d_runtime::Artifact>], i: usize) -> Result<Vec<(i64, A)>> {
    let list = inputs.get(i).ok_or_else(|| anyhow!("input {i} is missing"))?;
    list.iter()
        .map(|a| {
            A::decode(&a.bytes)
                .with_context(|| format!("decoding input {i} (position {}) as {}", a.pos, A::TYPE))
                .map(|x| (a.pos, x))
        })
        .collect()
}

/// Decodes the single artifact of input `i`.
pub fn one<A: Artifact>(inputs: &[Vec<dist4d_runtime::Artifact>], i: usize) -> Result<A> {
    let a = inputs.get(i).and_then(|v| v.first()).ok_or_else(|| anyhow!("input {i} is missing"))?;
    A::decode(&a.bytes).with_context(|| format!("decoding input {i} as {}", A::TYPE))
}
