//! The shape every stage module shares: a [`StageDef`] (schema + how to build its operator from
//! checked params) and helpers to decode typed inputs.

use crate::artifact::Artifact;
use anyhow::{anyhow, bail, Context, Result};
use dist4d_graph::{ParamsSpec, ParamsValue, PortSpec, StageSchema, Validate};
use dist4d_runtime::{Operator, Output, TaskContext};
use serde::{de::DeserializeOwned, Serialize};

/// A stage's work on decoded params: input artifacts (per input port, in schema order) to the
/// encoded bytes of each output port, in schema order. `ctx` says which item the task is for and
/// gives its seed (see [`StageDef::seeded`]).
pub trait TypedOp: Send + Sync {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Vec<Vec<u8>>>;
}

/// Runs a [`TypedOp`]. `slots[i]` is the schema position of the i-th wired input, so that an
/// operator always sees its inputs in schema order, unwired optional ones as empty lists. Each
/// output is tagged with the artifact type its port declares, which the runtime checks.
struct OpAdapter {
    op: Box<dyn TypedOp>,
    kind: &'static str,
    slots: Vec<usize>,
    schema_len: usize,
    output_types: Vec<&'static str>,
}

impl Operator for OpAdapter {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Vec<Output>> {
        let outs = if self.slots.len() == self.schema_len {
            self.op.run(ctx, inputs)?
        } else {
            let mut full = vec![Vec::new(); self.schema_len];
            for (slot, artifacts) in self.slots.iter().zip(inputs) {
                full[*slot] = artifacts.clone();
            }
            self.op.run(ctx, &full)?
        };
        if outs.len() != self.output_types.len() {
            bail!("{} returned {} outputs, it declares {}", self.kind, outs.len(), self.output_types.len());
        }
        Ok(outs.into_iter().zip(&self.output_types).map(|(bytes, ty)| Output { ty, bytes }).collect())
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
                // `check` refused invalid params already; params made another way (`ParamsValue::new`)
                // are checked here.
                ensure_valid(params).with_context(|| format!("params of {kind}"))?;
                build(params.clone())
            }),
        }
    }

    /// Declares that the stage draws random numbers from `TaskContext::seed`: its task keys then
    /// include the item key, since its output depends on the item and not only on its inputs.
    pub fn seeded(mut self) -> StageDef {
        self.schema.seeded = true;
        self
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
        Ok(Box::new(OpAdapter {
            op: (self.build)(params)?,
            kind: schema.kind,
            slots,
            schema_len: schema.inputs.len(),
            output_types: schema.outputs.iter().map(|p| p.ty).collect(),
        }))
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

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_runtime::ItemKey;

    /// Returns its seed and how many artifacts each input port got.
    struct Probe;

    impl TypedOp for Probe {
        fn run(&self, ctx: &TaskContext, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Vec<Vec<u8>>> {
            Ok(vec![ctx.seed.to_le_bytes().to_vec(), inputs.iter().map(|i| i.len() as u8).collect()])
        }
    }

    fn def() -> StageDef {
        StageDef::new::<crate::stages::encode::NoParams>(
            "Probe",
            1,
            "",
            vec![PortSpec::optional("a", "Image", ""), PortSpec::one("b", "Pose", "")],
            vec![PortSpec::one("seed", "Bytes", ""), PortSpec::one("counts", "Counts", "")],
            vec!["camera"],
            |_| Ok(Box::new(Probe)),
        )
    }

    #[test]
    fn the_adapter_passes_the_task_context_and_tags_outputs_with_their_declared_types() {
        let params = def().schema.params.check(None).unwrap();
        let op = def().build(&params, &["b"]).unwrap();
        let ctx = TaskContext { item: ItemKey::new(&[0, 1]), seed: 42, label: "s/1" };
        let artifact = dist4d_runtime::Artifact { item: ctx.item, pos: 0, bytes: Default::default() };
        let outs = op.run(&ctx, &[vec![artifact]]).unwrap();
        assert_eq!(
            outs,
            vec![
                Output { ty: "Bytes", bytes: 42u64.to_le_bytes().to_vec() },
                Output { ty: "Counts", bytes: vec![0, 1] }
            ]
        );
        assert!(!def().schema.seeded);
        assert!(def().seeded().schema.seeded);
    }
}
