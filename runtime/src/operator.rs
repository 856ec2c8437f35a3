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
}

/// One output of a task: its bytes and the artifact type they are encoded as. The runtime checks
/// the type against the one the output port declares before anything is stored, so a wrongly
/// encoded output fails its own task instead of a reader downstream.
#[derive(Clone, Debug, PartialEq)]
pub struct Output {
    pub ty: &'static str,
    pub bytes: Vec<u8>,
}

/// A stage's work on one item: input artifacts (per input port, in port order) to its outputs
/// (per output port, in port order). Must be deterministic: same inputs, same bytes.
pub trait Operator: Send + Sync {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<Artifact>]) -> Result<Vec<Output>>;
}
