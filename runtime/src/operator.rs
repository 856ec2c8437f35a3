//! What the runtime runs: datasets (items and raw sources) and operators (stage functions).
//!
//! The runtime knows nothing of any domain; the `stages` crate implements these traits.

use crate::digest::Digest;
use crate::item::{ItemKey, ItemSpace};
use anyhow::Result;
use std::path::Path;
use std::sync::Arc;

/// Artifact bytes as passed between tasks.
pub type Blob = Arc<Vec<u8>>;

/// One artifact given to a task: the upstream item it belongs to, its position in the selection
/// (window/offset: the offset along the dimension; gather: the child index; all: the running
/// index), and its bytes.
#[derive(Clone, Debug)]
pub struct Artifact {
    pub item: ItemKey,
    pub pos: i64,
    pub bytes: Blob,
}

/// Raw-file digests as the runtime provides them to datasets: memoised, and possibly not allowed
/// to hash (then `None` means "not known without reading the file").
pub trait FileDigests {
    fn file_digest(&self, path: &Path) -> Result<Option<Digest>>;
}

/// A dataset: its item tree and its source ports, read from raw files.
pub trait Dataset: ItemSpace {
    /// The content digest of a source artifact, computed from the digests of the raw files it is
    /// read from (through `files`) and the metadata it depends on. `Ok(None)` when `files`
    /// declined to hash a file.
    fn source_digest(&self, port: &str, item: &ItemKey, files: &dyn FileDigests) -> Result<Option<Digest>>;
    /// The artifact itself.
    fn load_source(&self, port: &str, item: &ItemKey) -> Result<Vec<u8>>;
    /// What the item was read from, for the export index (`index.json`'s `sources`): for a
    /// driving log, the image's or sweep's token, file and timestamp. None when the dataset has
    /// nothing to say about the item.
    fn source_record(&self, _item: &ItemKey) -> Option<serde_json::Value> {
        None
    }
    /// The dataset's own id of an item, for `{dim.token}` in export paths (for nuScenes: a
    /// keyframe's sample token, an image's `sample_data` token). None when it has none.
    fn token(&self, _item: &ItemKey) -> Option<String> {
        None
    }
}

/// What a task knows about itself.
pub struct TaskContext<'a> {
    pub item: ItemKey,
    /// Seed for stages that draw random numbers: derived from the stage kind, its params and the
    /// item key ([`crate::keys::task_seed`]), so it is the same whatever the thread count or run
    /// order. A stage that uses it must be declared seeded (its task keys then include the item).
    pub seed: u64,
    /// The item's path of labels (`s0/003/cam2`), for messages.
    pub label: &'a str,
    /// The output ports that nothing of this run reads (no stage's input, no export): a stage may
    /// leave them unmade ([`Output::unmade`]) and save their work. A later run that reads one
    /// finds it unmade in the task's record and runs the task again.
    pub unread: &'a [String],
}

impl TaskContext<'_> {
    /// Whether anything of this run reads output port `port` (see [`TaskContext::unread`]).
    pub fn wants(&self, port: &str) -> bool {
        !self.unread.iter().any(|u| u == port)
    }
}

/// What a stage's work on one item made: its outputs, or nothing (with the reason) when the item
/// has nothing to make: a training pair whose target frame lies past the scene's end, a view of
/// a camera the item does not have. Nothing to make is not a failure (that is the `Err` beside
/// it): the run records the task with no outputs (a rerun does not ask again), drops it from the
/// lists of the tasks that gather it, passes the others over (they have nothing to make either),
/// and counts them all as "not applicable", saying the first reason.
#[derive(Clone, Debug, PartialEq)]
pub enum Made<T> {
    Outputs(T),
    Nothing(String),
}

impl<T> From<T> for Made<T> {
    fn from(outputs: T) -> Made<T> {
        Made::Outputs(outputs)
    }
}

impl<T> Made<T> {
    /// The outputs; panics with the reason when there was nothing to make (as `Option::unwrap`,
    /// for tests and callers that know).
    #[track_caller]
    pub fn unwrap(self) -> T {
        match self {
            Made::Outputs(t) => t,
            Made::Nothing(why) => panic!("nothing to make: {why}"),
        }
    }

    pub fn map<U>(self, f: impl FnOnce(T) -> U) -> Made<U> {
        match self {
            Made::Outputs(t) => Made::Outputs(f(t)),
            Made::Nothing(why) => Made::Nothing(why),
        }
    }
}

/// One output of a task: its bytes and the artifact type they are encoded as. The runtime checks
/// the type against the one the output port declares before anything is stored, so a wrongly
/// encoded output fails its own task instead of a reader downstream.
#[derive(Clone, Debug, PartialEq)]
pub struct Output {
    pub ty: &'static str,
    /// `None`: not made, as the run does not read it (see [`TaskContext::unread`]).
    pub bytes: Option<Vec<u8>>,
}

impl Output {
    pub fn new(ty: &'static str, bytes: Vec<u8>) -> Output {
        Output { ty, bytes: Some(bytes) }
    }

    /// An output the stage did not make because nothing of the run reads it.
    pub fn unmade(ty: &'static str) -> Output {
        Output { ty, bytes: None }
    }
}

/// A stage's work on one item: input artifacts (per input port, in port order) to its outputs
/// (per output port, in port order). Must be deterministic: same inputs, same bytes.
pub trait Operator: Send + Sync {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<Artifact>]) -> Result<Made<Vec<Output>>>;
    /// What, besides its params, decides this operator's outputs and is known only when it runs:
    /// an external worker's name, version and weights digest. Folded into its task keys, so a new
    /// model version reruns exactly its stage and what depends on it. `None` for code that the
    /// stage version covers.
    fn identity(&self) -> Result<Option<String>> {
        Ok(None)
    }
    /// What this operator's tasks wait on besides the CPU (a model worker on a GPU), if
    /// anything: they then run on threads of their own, at most `slots` at once per resource
    /// name, instead of holding the CPU threads while they wait. Asked after [`Self::identity`].
    fn resource(&self) -> Option<Resource> {
        None
    }
    /// The most memory (bytes) one task of this operator holds at once, when the operator bounds
    /// it (a task refuses work that would need more): what a run checks `--jobs` against.
    fn peak_memory(&self) -> Option<u64> {
        None
    }
}

/// An external resource tasks wait on: its name (operators naming the same one share its
/// slots) and how many tasks it serves at once (for a model worker: its processes times its
/// batch).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Resource {
    pub name: String,
    pub slots: usize,
}

/// The identities of a pipeline's operators (see [`Operator::identity`]), by node, and why the
/// operators whose identity could not be had (a worker that does not start) are unavailable:
/// their tasks fail, each with that reason, and the rest of the run goes on.
pub struct Identities {
    pub ids: Vec<Option<String>>,
    pub unavailable: Vec<Option<String>>,
}

impl Identities {
    pub fn of(operators: &[Option<Box<dyn Operator>>], names: &[String]) -> Identities {
        Identities::of_except(operators, names, |_| false)
    }

    /// The identities of the operators but those `skip` names, which are not asked (asking
    /// starts a model worker: not on a node that will not run it); theirs are `None`.
    pub fn of_except(
        operators: &[Option<Box<dyn Operator>>],
        names: &[String],
        skip: impl Fn(&dyn Operator) -> bool,
    ) -> Identities {
        let mut ids = Vec::with_capacity(operators.len());
        let mut unavailable = Vec::with_capacity(operators.len());
        for (op, name) in operators.iter().zip(names) {
            match op.as_deref().filter(|op| !skip(*op)).map(|op| op.identity()).transpose() {
                Ok(id) => {
                    ids.push(id.flatten());
                    unavailable.push(None);
                }
                Err(e) => {
                    ids.push(None);
                    unavailable.push(Some(format!("stage `{name}`: its worker is unavailable: {e:#}")));
                }
            }
        }
        Identities { ids, unavailable }
    }

    /// Every identity, or the first reason one is unavailable.
    pub fn all(self) -> Result<Vec<Option<String>>> {
        match self.unavailable.into_iter().flatten().next() {
            Some(why) => Err(anyhow::anyhow!(why)),
            None => Ok(self.ids),
        }
    }
}

/// A dataset seen through a pipeline with variants: its items, each of the innermost dimension
/// extended by one coordinate per variant (the pipeline's last dimension). Sources are never per
/// variant, so everything else is the dataset's.
pub struct WithVariants {
    pub inner: Box<dyn Dataset>,
    /// The dataset's own number of dimensions.
    pub depth: usize,
    pub labels: Vec<String>,
}

impl ItemSpace for WithVariants {
    fn count(&self, prefix: &ItemKey) -> u32 {
        if prefix.depth as usize == self.depth {
            self.labels.len() as u32
        } else {
            self.inner.count(prefix)
        }
    }
    fn label(&self, item: &ItemKey) -> String {
        if item.depth as usize == self.depth + 1 {
            self.labels.get(item.idx[self.depth] as usize).cloned().unwrap_or_else(|| "?".into())
        } else {
            self.inner.label(item)
        }
    }
}

impl Dataset for WithVariants {
    fn source_digest(&self, port: &str, item: &ItemKey, files: &dyn FileDigests) -> Result<Option<Digest>> {
        self.inner.source_digest(port, item, files)
    }
    fn load_source(&self, port: &str, item: &ItemKey) -> Result<Vec<u8>> {
        self.inner.load_source(port, item)
    }
    fn source_record(&self, item: &ItemKey) -> Option<serde_json::Value> {
        // A variant item's sources are its dataset item's.
        self.inner.source_record(&item.prefix(item.depth.min(self.depth as u8) as usize))
    }
    fn token(&self, item: &ItemKey) -> Option<String> {
        if item.depth as usize > self.depth {
            return None; // a variant has no token of its own
        }
        self.inner.token(item)
    }
}
