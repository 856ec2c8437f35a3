//! The shape every stage module shares: a [`StageDef`] (schema + how to build its operator from
//! checked params) and helpers to decode typed inputs.

use anyhow::{anyhow, Context, Result};
use dist4d_graph::{ParamsSpec, ParamsValue, PortSpec, StageSchema, Validate};
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

type BuildFn = Box<dyn Fn(&ParamsValue) -> Result<Box<dyn TypedOp>> + Send + Sync>;

/// A stage kind: its schema (what the graph checks pipelines against) and how to build its
/// operator from checked params.
pub struct StageDef {
    pub schema: StageSchema,
    build: BuildFn,
}

impl StageDef {
    #[allow(clippy::too_many_arguments)]
    pub fn new<P: DeserializeOwned + Serialize + Default + Validate + Clone + Send + Sync + 'static>(
        kind: &'static str,
        version: u32,
        summary: &'static str,
        inputs: Vec<PortSpec>,
        outputs: Vec<PortSpec>,
        grains: Vec<&'static str>,
        build: fn(P) -> Result<Box<dyn TypedOp>>,
    ) -> StageDef {
        StageDef {
            schema: StageSchema {
                kind,
                version,
                summary,
                inputs,
                outputs,
                grains,
                params: ParamsSpec::of::<P>(),
                seeded: false,
            },
            build: Box::new(move |checked| {
                let params = checked.get::<P>().ok_or_else(|| {
                    anyhow!("params of {kind}: checked as another type, not {}", std::any::type_name::<P>())
                })?;
                // `check` refused invalid params already; params that reach here another way are checked too.
                ensure_valid(params).with_context(|| format!("params of {kind}"))?;
                build(params.clone())
            }),
        }
    }

    /// The operator for checked params (as the graph produced them) and the names of the
    /// wired input ports, in schema order.
    pub fn build(&self, params: &ParamsValue, wired: &[&str]) -> Result<Box<dyn Operator>> {
        let schema = &self.schema;
        let slots = wired
            .iter()
            .map(|w| {
                schema
                    .inputs
                    .iter()
                    .position(|p| p.name == *w)
                    .ok_or_else(|| anyhow!("{} has no input `{w}`", schema.kind))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Box::new(OpAdapter { op: (self.build)(params)?, slots, schema_len: schema.inputs.len() }))
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
