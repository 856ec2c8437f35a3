//! How a stage is declared: a type implementing [`Stage`], with its params and its typed ports
//! (declared with [`crate::inputs!`] and [`crate::outputs!`]), and one line in its family's [`crate::stage_modules!`].
//! [`StageDef::of`] turns it into what the graph checks pipelines against (the schema: ports and
//! their artifact types come from the Rust types) and what the runtime runs (an operator that
//! decodes inputs by port name and encodes outputs with their type tags).
//!
//! ```ignore
//! crate::inputs! {
//!     pub struct Inputs {
//!         /// The sweep, in the LiDAR frame.
//!         points: One<PointCloud>,
//!         /// Cityscapes ids; the estimate is used when unwired.
//!         semantic: Optional<Segmentation>,
//!         /// The window of sweeps, by offset.
//!         sweeps: Many<PointCloud>,
//!     }
//! }
//! ```

use anyhow::{anyhow, bail, Context, Result};
use dist4d_graph::{ParamsSpec, ParamsValue, PortSpec, StageSchema, Validate};
use dist4d_runtime::{Made, Operator, TaskContext};
use dist4d_types::artifact::Artifact;
use serde::{de::DeserializeOwned, Serialize};
use std::marker::PhantomData;

/// What params structs are: serde structs with defaults and range checks.
pub trait Params: DeserializeOwned + Serialize + Default + Validate + Clone + Send + Sync + 'static {}
impl<T: DeserializeOwned + Serialize + Default + Validate + Clone + Send + Sync + 'static> Params for T {}

/// A stage kind.
pub trait Stage: Sized + Send + Sync + 'static {
    /// The name pipeline files use.
    const KIND: &'static str;
    /// Bumped whenever the output for the same inputs and params changes (part of task keys).
    const VERSION: u32;
    /// One line for `docs/stages.md` and messages.
    const SUMMARY: &'static str;
    /// Dimension names it may run per; the first is the default.
    const GRAINS: &'static [&'static str];
    /// Stages that draw random numbers (from [`TaskContext::seed`]) get the item in their task key.
    const SEEDED: bool = false;
    /// Params that must be the path template of one of the pipeline's exports (see
    /// [`dist4d_graph::StageSchema::export_template_params`]).
    const EXPORT_TEMPLATE_PARAMS: &'static [&'static str] = &[];
    /// Groups of `Many` inputs the stage pairs up by position (see
    /// [`dist4d_graph::StageSchema::aligned_inputs`]): a pipeline that selects them differently
    /// is refused by `check`.
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[];
    /// Stages that run once per variant of their params (a pair per frame offset, a novel view
    /// per lateral shift) say so, and split their params in [`Stage::variants`]: they run per
    /// `variant`, and [`Stage::run`] finds its variant with [`variant_of`].
    const VARIANTS: bool = false;
    type Params: Params;
    type Inputs: InputPorts;
    type Outputs: OutputPorts;
    fn new(params: Self::Params) -> Result<Self>;
    /// What besides params and version decides the outputs (an external worker's identity; see
    /// [`dist4d_runtime::Operator::identity`]).
    fn identity(&self) -> Result<Option<String>> {
        Ok(None)
    }
    /// What its tasks wait on besides the CPU (see [`dist4d_runtime::Operator::resource`]).
    fn resource(&self) -> Option<dist4d_runtime::Resource> {
        None
    }
    /// The most memory one task holds, when the stage bounds it (see
    /// [`dist4d_runtime::Operator::peak_memory`]).
    fn peak_memory(&self) -> Option<u64> {
        None
    }
    /// The params split into the shared part and the variants, in label order (see
    /// [`dist4d_graph::Variants::split`]); only called when [`Stage::VARIANTS`] is set.
    fn variants(_params: &Self::Params) -> Option<dist4d_graph::Variants> {
        None
    }
    /// The `Many` or optional input ports it does not read with `params`: planned with no
    /// sources, so the run never loads them (they arrive empty).
    fn unused_inputs(_params: &Self::Params) -> Vec<&'static str> {
        Vec::new()
    }
    /// The stage's work on one item: its outputs, or nothing to make with the reason
    /// ([`Made::Nothing`]: not a failure, see [`Made`]); a failure is the `Err`.
    fn run(&self, ctx: &TaskContext, inputs: Self::Inputs) -> Result<Made<Self::Outputs>>;
}

/// The value of a [`Made`], or, when it is [`Made::Nothing`], return that from the enclosing
/// [`Stage::run`].
#[macro_export]
macro_rules! or_nothing {
    ($made:expr) => {
        match $made {
            dist4d_runtime::Made::Outputs(value) => value,
            dist4d_runtime::Made::Nothing(why) => return Ok(dist4d_runtime::Made::Nothing(why)),
        }
    };
}

/// The variant a task of a variant-declaring stage runs: the entry of `variants` (the params'
/// map, in label order as [`Stage::variants`] gave it) at the item's innermost coordinate.
pub fn variant_of<'v, V>(
    ctx: &TaskContext,
    variants: &'v std::collections::BTreeMap<String, V>,
) -> Result<(&'v str, &'v V)> {
    let coords = ctx.item.coords();
    let i = *coords.last().ok_or_else(|| anyhow!("{}: a stage with variants runs per variant", ctx.label))? as usize;
    variants
        .iter()
        .nth(i)
        .map(|(label, v)| (label.as_str(), v))
        .ok_or_else(|| anyhow!("{}: no variant {i} (the params have {})", ctx.label, variants.len()))
}

/// The input artifacts of one task, by port name (as the runtime hands them over: one list per
/// wired input port).
pub struct InputSet<'a> {
    wired: &'a [&'static str],
    lists: &'a [Vec<dist4d_runtime::Artifact>],
}

impl InputSet<'_> {
    fn get(&self, port: &str) -> Option<&[dist4d_runtime::Artifact]> {
        self.wired.iter().position(|w| *w == port).and_then(|i| self.lists.get(i)).map(Vec::as_slice)
    }
}

/// An encoded output with its artifact type tag (the runtime checks it against the port's type
/// before the output enters the store).
pub use dist4d_runtime::Output as Encoded;

/// A struct of input ports, as [`crate::inputs!`] declares it.
pub trait InputPorts: Sized {
    fn specs() -> Vec<PortSpec>;
    fn decode(inputs: &InputSet) -> Result<Self>;
}

/// A struct of output ports, as [`crate::outputs!`] declares it.
pub trait OutputPorts: Sized {
    fn specs() -> Vec<PortSpec>;
    fn encode(self) -> Result<Vec<Encoded>>;
}

/// How many artifacts an input port carries: the field types of an [`crate::inputs!`] struct
/// ([`One`], [`Optional`], [`Many`], [`OptionalMany`], [`Group`]).
pub trait InPort {
    /// What the field holds.
    type Value;
    /// The schema entries of field `name` documented `doc` (one port, or a group's ports).
    fn specs(name: &'static str, doc: &'static str) -> Vec<PortSpec>;
    fn decode(port: &str, inputs: &InputSet) -> Result<Self::Value>;
}

/// What an output port carries: the field types of an [`crate::outputs!`] struct ([`One`],
/// [`OnDemand`]). A kind that is not one (an `Optional` output, an `OnDemand` input) does not
/// compile:
///
/// ```compile_fail
/// dist4d_stages::outputs! {
///     pub struct Outputs {
///         /// An output that may be missing: not a kind of output.
///         depth: Optional<dist4d_types::artifact::DepthMap>,
///     }
/// }
/// ```
///
/// ```compile_fail
/// dist4d_stages::inputs! {
///     pub struct Inputs {
///         /// Made only when read: a kind of output, not of input.
///         depth: OnDemand<dist4d_types::artifact::DepthMap>,
///     }
/// }
/// ```
///
/// ```compile_fail
/// dist4d_stages::outputs! {
///     pub struct Outputs {
///         /// A window is what a stage reads, not what it makes.
///         depths: Many<dist4d_types::artifact::DepthMap>,
///     }
/// }
/// ```
///
/// while the right kinds do:
///
/// ```
/// dist4d_stages::inputs! {
///     pub struct Inputs {
///         /// One depth map.
///         depth: One<dist4d_types::artifact::DepthMap>,
///         /// Its neighbours.
///         window: Many<dist4d_types::artifact::DepthMap>,
///     }
/// }
/// dist4d_stages::outputs! {
///     pub struct Outputs {
///         /// One depth map.
///         depth: One<dist4d_types::artifact::DepthMap>,
///         /// Made when something reads it.
///         preview: OnDemand<dist4d_types::artifact::Image>,
///     }
/// }
/// ```
pub trait OutPort {
    type Value;
    fn specs(name: &'static str, doc: &'static str) -> Vec<PortSpec>;
    fn encode(port: &str, value: Self::Value) -> Result<Vec<Encoded>>;
}

fn port_spec<A: Artifact>(name: &'static str, doc: &'static str, many: bool, optional: bool) -> Vec<PortSpec> {
    vec![PortSpec { name, ty: A::TYPE, many, optional, doc: doc.trim() }]
}

/// Exactly one artifact (the field is the artifact): an input or an output.
pub struct One<A>(PhantomData<A>);
/// An input of one artifact, or none when the input is not wired (the field is an `Option`).
pub struct Optional<A>(PhantomData<A>);
/// An input of several artifacts (a window, a gather), each with its position (the offset along
/// the window's dimension, the index of a gathered item): the field is a `Vec<(i64, A)>`.
pub struct Many<A>(PhantomData<A>);
/// Several artifacts like [`Many`], or none when the input is not wired (an empty `Vec`): what a
/// stage gathers only when the pipeline has it (e.g. ground truth for a sheet).
pub struct OptionalMany<A>(PhantomData<A>);
/// An output made only when the run reads it (the field is an `Option`: `None` when
/// [`TaskContext::wants`] says nothing reads it, e.g. an encoding nobody exports). A later run
/// that reads it runs the task again.
pub struct OnDemand<A>(PhantomData<A>);
/// The ports of another [`crate::inputs!`] struct, under their own names (inputs several stages
/// share, such as the four a camera view is made from): the field is that struct.
pub struct Group<P>(PhantomData<P>);

impl<P: InputPorts> InPort for Group<P> {
    type Value = P;
    fn specs(_: &'static str, _: &'static str) -> Vec<PortSpec> {
        P::specs()
    }
    fn decode(_: &str, inputs: &InputSet) -> Result<P> {
        P::decode(inputs)
    }
}

fn decode_one<A: Artifact>(port: &str, a: &dist4d_runtime::Artifact) -> Result<A> {
    A::decode(&a.bytes).with_context(|| format!("decoding input `{port}` as {}", A::TYPE))
}

impl<A: Artifact> InPort for One<A> {
    type Value = A;
    fn specs(name: &'static str, doc: &'static str) -> Vec<PortSpec> {
        port_spec::<A>(name, doc, false, false)
    }
    fn decode(port: &str, inputs: &InputSet) -> Result<A> {
        match inputs.get(port) {
            Some([a]) => decode_one(port, a),
            Some(list) => bail!("input `{port}` takes one {}, it was given {}", A::TYPE, list.len()),
            None => bail!("input `{port}` is not wired"),
        }
    }
}

impl<A: Artifact> OutPort for One<A> {
    type Value = A;
    fn specs(name: &'static str, doc: &'static str) -> Vec<PortSpec> {
        port_spec::<A>(name, doc, false, false)
    }
    fn encode(_: &str, value: A) -> Result<Vec<Encoded>> {
        Ok(vec![Encoded::new(A::TYPE, value.encode())])
    }
}

impl<A: Artifact> OutPort for OnDemand<A> {
    type Value = Option<A>;
    fn specs(name: &'static str, doc: &'static str) -> Vec<PortSpec> {
        port_spec::<A>(name, doc, false, false)
    }
    fn encode(_: &str, value: Option<A>) -> Result<Vec<Encoded>> {
        Ok(vec![value.map_or_else(|| Encoded::unmade(A::TYPE), |v| Encoded::new(A::TYPE, v.encode()))])
    }
}

impl<A: Artifact> InPort for Optional<A> {
    type Value = Option<A>;
    fn specs(name: &'static str, doc: &'static str) -> Vec<PortSpec> {
        port_spec::<A>(name, doc, false, true)
    }
    fn decode(port: &str, inputs: &InputSet) -> Result<Option<A>> {
        match inputs.get(port) {
            None | Some([]) => Ok(None),
            Some([a]) => decode_one(port, a).map(Some),
            Some(list) => bail!("input `{port}` takes one {}, it was given {}", A::TYPE, list.len()),
        }
    }
}

fn decode_many<A: Artifact>(port: &str, list: &[dist4d_runtime::Artifact]) -> Result<Vec<(i64, A)>> {
    list.iter()
        .map(|a| {
            let x = A::decode(&a.bytes)
                .with_context(|| format!("decoding input `{port}` (position {}) as {}", a.pos, A::TYPE))?;
            Ok((a.pos, x))
        })
        .collect()
}

impl<A: Artifact> InPort for Many<A> {
    type Value = Vec<(i64, A)>;
    fn specs(name: &'static str, doc: &'static str) -> Vec<PortSpec> {
        port_spec::<A>(name, doc, true, false)
    }
    fn decode(port: &str, inputs: &InputSet) -> Result<Vec<(i64, A)>> {
        decode_many(port, inputs.get(port).ok_or_else(|| anyhow!("input `{port}` is not wired"))?)
    }
}

impl<A: Artifact> InPort for OptionalMany<A> {
    type Value = Vec<(i64, A)>;
    fn specs(name: &'static str, doc: &'static str) -> Vec<PortSpec> {
        port_spec::<A>(name, doc, true, true)
    }
    fn decode(port: &str, inputs: &InputSet) -> Result<Vec<(i64, A)>> {
        decode_many(port, inputs.get(port).unwrap_or_default())
    }
}

/// Declares a struct of typed input ports: each field `name: One<T>`, `Optional<T>`, `Many<T>`,
/// `OptionalMany<T>` or `Group<P>` with a doc comment, in port order. Implements
/// [`InputPorts`] for it; an output kind ([`OnDemand`]) does not compile.
#[macro_export]
macro_rules! inputs {
    ($($struct:tt)*) => {
        $crate::__ports!(input InPort InputPorts; $($struct)*);
    };
}

/// Declares a struct of typed output ports: each field `name: One<T>` or `OnDemand<T>` with a doc
/// comment, in port order. Implements [`OutputPorts`] for it; an input kind (`Optional`, `Many`,
/// ...) does not compile.
#[macro_export]
macro_rules! outputs {
    ($($struct:tt)*) => {
        $crate::__ports!(output OutPort OutputPorts; $($struct)*);
    };
}

/// What [`crate::inputs!`] and [`crate::outputs!`] share: the struct, with each field's value
/// type and schema entries from its port kind through `$kind` ([`InPort`] or [`OutPort`]), and
/// the decoding or encoding of `$ports`.
#[doc(hidden)]
#[macro_export]
macro_rules! __ports {
    (@convert input $name:ident { $( $field:ident : $port:ident < $ty:ty > ),* }) => {
        #[allow(unused_variables)]
        fn decode(inputs: &$crate::stage::InputSet) -> anyhow::Result<Self> {
            Ok($name {
                $( $field: <$crate::stage::$port<$ty> as $crate::stage::InPort>::decode(stringify!($field), inputs)?, )*
            })
        }
    };
    (@convert output $name:ident { $( $field:ident : $port:ident < $ty:ty > ),* }) => {
        #[allow(unused_mut)]
        fn encode(self) -> anyhow::Result<Vec<$crate::stage::Encoded>> {
            let mut out = Vec::new();
            $( out.extend(<$crate::stage::$port<$ty> as $crate::stage::OutPort>::encode(stringify!($field), self.$field)?); )*
            Ok(out)
        }
    };
    (
        $dir:ident $kind:ident $ports:ident;
        $(#[$meta:meta])*
        $vis:vis struct $name:ident {
            $( $(#[doc = $doc:literal])* $field:ident : $port:ident < $ty:ty > ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        $vis struct $name {
            $( $(#[doc = $doc])* pub $field: <$crate::stage::$port<$ty> as $crate::stage::$kind>::Value, )*
        }

        impl $crate::stage::$ports for $name {
            fn specs() -> Vec<dist4d_graph::PortSpec> {
                let mut specs = Vec::new();
                $( specs.extend(<$crate::stage::$port<$ty> as $crate::stage::$kind>::specs(stringify!($field), concat!($($doc),*))); )*
                specs
            }
            $crate::__ports!(@convert $dir $name { $( $field : $port < $ty > ),* });
        }
    };
}

/// Declares a family's stage modules and registers their stages, one line per stage:
/// `module::StageType`. Adding a stage is its module plus one line here.
#[macro_export]
macro_rules! stage_modules {
    ($( $module:ident :: $stage:ident ),* $(,)?) => {
        $( pub mod $module; )*

        /// Every stage of this family, for the registry.
        pub fn stages() -> Vec<$crate::stage::StageDef> {
            vec![$( $crate::stage::StageDef::of::<$module::$stage>() ),*]
        }
    };
}

type BuildFn = Box<dyn Fn(&ParamsValue, &[&'static str]) -> Result<Box<dyn Operator>> + Send + Sync>;

/// A stage kind: its schema (what the graph checks pipelines against) and how to build its
/// operator from checked params.
pub struct StageDef {
    pub schema: StageSchema,
    build: BuildFn,
}

impl StageDef {
    pub fn of<S: Stage>() -> StageDef {
        StageDef {
            schema: StageSchema {
                kind: S::KIND,
                version: S::VERSION,
                summary: S::SUMMARY,
                inputs: S::Inputs::specs(),
                outputs: S::Outputs::specs(),
                grains: S::GRAINS.to_vec(),
                params: ParamsSpec::of::<S::Params>(),
                seeded: S::SEEDED,
                export_template_params: S::EXPORT_TEMPLATE_PARAMS.to_vec(),
                aligned_inputs: S::ALIGNED_INPUTS.to_vec(),
                variants: S::VARIANTS.then_some(|p: &ParamsValue| p.get::<S::Params>().and_then(S::variants)),
                unused_inputs: Some(|p: &ParamsValue| p.get::<S::Params>().map(S::unused_inputs).unwrap_or_default()),
            },
            build: Box::new(|checked, wired| {
                let params = checked.get::<S::Params>().ok_or_else(|| {
                    anyhow!(
                        "params of {}: checked as another type, not {}",
                        S::KIND,
                        std::any::type_name::<S::Params>()
                    )
                })?;
                // `check` refused invalid params already; params that reach here another way are checked too.
                ensure_valid(params).with_context(|| format!("params of {}", S::KIND))?;
                let stage = S::new(params.clone()).with_context(|| format!("building {}", S::KIND))?;
                Ok(Box::new(StageOp { stage, wired: wired.to_vec() }))
            }),
        }
    }

    /// The operator for checked params (as the graph produced them) and the names of the wired
    /// input ports, in the order the runtime hands their artifacts over.
    pub fn build(&self, params: &ParamsValue, wired: &[&str]) -> Result<Box<dyn Operator>> {
        let wired = wired
            .iter()
            .map(|w| {
                self.schema
                    .inputs
                    .iter()
                    .find(|p| p.name == *w)
                    .map(|p| p.name)
                    .ok_or_else(|| anyhow!("{} has no input `{w}`", self.schema.kind))
            })
            .collect::<Result<Vec<_>>>()?;
        (self.build)(params, &wired)
    }
}

/// Runs a [`Stage`] as a runtime operator.
struct StageOp<S> {
    stage: S,
    wired: Vec<&'static str>,
}

impl<S: Stage> Operator for StageOp<S> {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<dist4d_runtime::Artifact>]) -> Result<Made<Vec<Encoded>>> {
        let inputs = S::Inputs::decode(&InputSet { wired: &self.wired, lists: inputs })?;
        Ok(match self.stage.run(ctx, inputs)? {
            Made::Outputs(outputs) => Made::Outputs(outputs.encode()?),
            Made::Nothing(why) => Made::Nothing(why),
        })
    }
    fn identity(&self) -> Result<Option<String>> {
        self.stage.identity()
    }
    fn resource(&self) -> Option<dist4d_runtime::Resource> {
        self.stage.resource()
    }
    fn peak_memory(&self) -> Option<u64> {
        self.stage.peak_memory()
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

/// The artifact at window position `pos` of a `Many` input (`Window(.., frame, -1, 1)` gives
/// positions -1, 0, 1), or an error naming the port.
pub fn at_position<'a, A>(list: &'a [(i64, A)], pos: i64, port: &str) -> Result<&'a A> {
    list.iter()
        .find(|(p, _)| *p == pos)
        .map(|(_, a)| a)
        .ok_or_else(|| anyhow::anyhow!("input `{port}` has nothing at position {pos}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::DepthMap;

    #[test]
    fn an_unwired_optional_many_input_is_an_empty_list_and_an_unwired_many_an_error() {
        let inputs = InputSet { wired: &[], lists: &[] };
        assert!(<OptionalMany<DepthMap> as InPort>::decode("gt", &inputs).unwrap().is_empty());
        let err = <Many<DepthMap> as InPort>::decode("gt", &inputs).unwrap_err();
        assert!(err.to_string().contains("`gt` is not wired"), "{err}");
        let spec = &<OptionalMany<DepthMap> as InPort>::specs("gt", "ground truth")[0];
        assert!(spec.many && spec.optional && spec.ty == DepthMap::TYPE);
    }
}
