//! Task keys, input resolution and the cache-hit decision: the one place that says whether a
//! task's result is already known. The scheduler runs through it and `explain` reports through it,
//! so what explain says is what a run will do.
//!
//! A task key is a blake3 hash, under the domain [`TASK_KEY_DOMAIN`], of: the stage kind and
//! version, the digest of the canonical params, per input port its name and the digests of the
//! exact input artifacts with their positions, and, for seeded stages, the item key. It does not
//! hash which upstream task made an input: a rerun upstream task that yields the same bytes leaves
//! downstream keys unchanged (early cutoff).
//!
//! A record is a hit only while the bytes of every output the run reads (a stage's input or an
//! export) can be had: inside the record (small outputs), as a blob in the store, or — for an output
//! the run exports and no stage reads, which the store does not keep (see [`Keys::exporting_to`]) —
//! as its files in the output folder. An output nothing reads may be missing, or unmade: a stage
//! may skip the work of outputs nothing of its run reads ([`crate::TaskContext::unread`]).

use crate::digest::{Digest, DigestBuilder};
use crate::export::OutputFolder;
use crate::item::ItemKey;
use crate::operator::{Dataset, FileDigests};
use crate::plan::{InputSrc, OuterPlan};
use crate::record::OutputRef;
use crate::store::Store;
use anyhow::{Context, Result};
use dist4d_graph::{NodeId, NodeKind, ParamsValue, Pipeline, StageNode};
use std::path::Path;
use std::sync::Arc;

/// Domain of params digests with an operator's identity folded in.
const IDENTITY_DOMAIN: &str = "dist4d-operator-identity-v1";

/// Domain of the params digests of variants' tasks.
const VARIANT_PARAMS_DOMAIN: &str = "dist4d-variant-params-v1";

/// Domain of task keys. Bump it when the key layout or the canonical params printer changes, so
/// that old records are never mistaken for new ones.
pub const TASK_KEY_DOMAIN: &str = "dist4d-task-v2";

/// Domain of task seeds.
pub const SEED_DOMAIN: &str = "dist4d-seed-v1";

/// Outputs only exported of at most this many bytes (a few filesystem blocks) are stored all the
/// same: they cost next to nothing in the store (a few KB of scores per item, against megabytes of
/// exports), while the task that made them may cost much to run again when a file is lost (a
/// stage that scores its item against references reads far more than it writes).
pub const STORED_EXPORT_MAX: u64 = 16 << 10;

/// The digest of checked params, as task keys and task records hold it.
pub fn params_digest(params: &ParamsValue) -> Digest {
    Digest::of(params.canonical.as_bytes())
}

/// The params digest of one variant's tasks: the shared params, the label and the variant's own
/// params (see [`dist4d_graph::Variants`]).
pub fn variant_params_digest(shared: &str, label: &str, own: &str) -> Digest {
    DigestBuilder::new(VARIANT_PARAMS_DOMAIN).str(shared).str(label).str(own).finish()
}

/// The task key of `stage` on `item` with params digest `params` and, per input port (in the
/// stage's port order), the positions and digests of its artifacts.
pub fn task_key(stage: &StageNode, params: &Digest, item: &ItemKey, inputs: &[Vec<(i64, Digest)>]) -> Digest {
    let mut b = DigestBuilder::new(TASK_KEY_DOMAIN);
    b.str(&stage.kind).u64(stage.version as u64).digest(params);
    for (spec, got) in stage.inputs.iter().zip(inputs) {
        b.str(&spec.port).u64(got.len() as u64);
        for (pos, d) in got {
            b.u64(*pos as u64).digest(d);
        }
    }
    if stage.seeded {
        b.bytes(&item.to_bytes());
    }
    b.finish()
}

/// Per node and output port: whether an input of some stage of `pipeline` reads it.
fn read_by_stages(pipeline: &Pipeline) -> Vec<Vec<bool>> {
    let mut read: Vec<Vec<bool>> = pipeline.nodes.iter().map(|n| vec![false; n.outputs.len()]).collect();
    for input in pipeline.nodes.iter().filter_map(|n| n.stage()).flat_map(|s| &s.inputs) {
        if let Some(r) = read[input.from].get_mut(input.from_port) {
            *r = true;
        }
    }
    read
}

/// The seed of a task: the first 8 bytes (little endian) of a blake3 hash, under [`SEED_DOMAIN`],
/// of the stage kind, the params digest and the item key.
///
/// It depends on nothing the scheduler decides (thread count, run order) and not on the input
/// content, so a task draws the same numbers in every run until its params change; two stages of
/// one kind with the same params draw the same numbers for the same item. A stage that uses it
/// must be declared seeded, so that its task keys include the item.
pub fn task_seed(kind: &str, params: &Digest, item: &ItemKey) -> u64 {
    let d = DigestBuilder::new(SEED_DOMAIN).str(kind).digest(params).bytes(&item.to_bytes()).finish();
    u64::from_le_bytes(d.0[..8].try_into().expect("a digest has 32 bytes"))
}

/// Why the digest of an input artifact is not known.
#[derive(Debug)]
pub enum Unknown {
    /// The upstream task that makes it has not finished (in explain: it will run).
    Upstream { task: u32 },
    /// A raw file it is read from would have to be hashed, and hashing was not allowed.
    Unhashed,
    /// The dataset could not fingerprint it.
    Unreadable(anyhow::Error),
}

/// One input artifact of a task: where it comes from, and its digest when known.
#[derive(Debug)]
pub struct Input {
    pub src: InputSrc,
    /// The upstream item it belongs to.
    pub item: ItemKey,
    pub digest: Result<Digest, Unknown>,
}

impl Input {
    /// Its position in the selection (see [`crate::operator::Artifact::pos`]).
    pub fn pos(&self) -> i64 {
        match self.src {
            InputSrc::Task { pos, .. } | InputSrc::Source { pos, .. } => pos,
        }
    }
}

/// What the store knows of a task.
pub enum Decision {
    /// A finished task with this key left every output readable: nothing to run.
    Cached { key: Digest, outputs: Vec<OutputRef> },
    /// No usable record of this key: the task runs. `lost` says why when there is a record.
    Run { key: Digest, lost: Option<Lost> },
    /// Some input digest is not known, so neither is the key; or, when hashing was not allowed,
    /// whether an exported file still holds an output's bytes.
    Unknown,
}

/// The output of a task record whose bytes are nowhere to be had (by output port).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lost {
    /// Its blob is missing from the store (removed by hand, found corrupt, or a power loss).
    Blob(usize),
    /// The task did not make it: no run that ran it read it.
    Unmade(usize),
    /// It is kept only in the output folder, and a file of it there is missing or holds other bytes
    /// (deleted, edited, overwritten by a run with other params, or the run exports elsewhere).
    Exported(usize),
}

/// The key layer of one pipeline on one dataset and store.
pub struct Keys<'a> {
    pipeline: &'a Pipeline,
    dataset: &'a dyn Dataset,
    store: &'a Store,
    /// Params digest per node (default for sources).
    params: Vec<Digest>,
    /// Per node declaring variants, the params digest of each variant's tasks (empty otherwise).
    variant_params: Vec<Vec<Digest>>,
    /// The output folder of the run, when it exports.
    folder: Option<Arc<OutputFolder>>,
    /// Per node and output port: exported into `folder` and read by no stage (all false without a folder).
    only_exported: Vec<Vec<bool>>,
    /// Per node and output port: read by a stage or exported by the pipeline.
    read: Vec<Vec<bool>>,
    /// Per node, the names of its output ports that are not (see `read`).
    unread: Vec<Vec<String>>,
}

impl<'a> Keys<'a> {
    pub fn new(pipeline: &'a Pipeline, dataset: &'a dyn Dataset, store: &'a Store) -> Keys<'a> {
        let params = pipeline.nodes.iter().map(|n| n.stage().map(|s| params_digest(&s.params)).unwrap_or_default());
        let variant_params = pipeline
            .nodes
            .iter()
            .map(|n| match n.stage().and_then(|s| s.variants.as_ref()) {
                Some(v) => v.each.iter().map(|(label, own)| variant_params_digest(&v.shared, label, own)).collect(),
                None => Vec::new(),
            })
            .collect();
        let only_exported = pipeline.nodes.iter().map(|n| vec![false; n.outputs.len()]).collect();
        let mut read = read_by_stages(pipeline);
        for x in &pipeline.exports {
            read[x.node][x.port] = true;
        }
        let unread = pipeline
            .nodes
            .iter()
            .zip(&read)
            .map(|(n, read)| n.outputs.iter().zip(read).filter(|(_, &r)| !r).map(|(o, _)| o.name.clone()).collect())
            .collect();
        Keys {
            pipeline,
            dataset,
            store,
            params: params.collect(),
            variant_params,
            folder: None,
            only_exported,
            read,
            unread,
        }
    }

    /// The names of the output ports of `node` that nothing of the run reads (see
    /// [`crate::TaskContext::unread`]).
    pub fn unread(&self, node: NodeId) -> &[String] {
        &self.unread[node]
    }

    /// Whether output `port` of `node` is read by a stage or exported.
    pub fn is_read(&self, node: NodeId, port: usize) -> bool {
        self.read[node].get(port).copied().unwrap_or(false)
    }

    /// Keys with each operator's identity ([`crate::Operator::identity`]) folded into its params
    /// digest.
    pub fn with_identities(mut self, identities: &[Option<String>]) -> Keys<'a> {
        let fold = |d: &Digest, id: &str| DigestBuilder::new(IDENTITY_DOMAIN).digest(d).str(id).finish();
        for (node, id) in identities.iter().enumerate() {
            if let Some(id) = id {
                self.params[node] = fold(&self.params[node], id);
                for v in &mut self.variant_params[node] {
                    *v = fold(v, id);
                }
            }
        }
        self
    }

    /// Keys for a run that exports into `folder`. Outputs that it exports and that no stage of
    /// the pipeline reads (larger than [`STORED_EXPORT_MAX`]) are then kept only there, as Bazel's
    /// "build without the bytes" keeps them out of its cache: the store records their digest and
    /// size, not their bytes, which exist once on disk instead of twice. No task of the run needs
    /// them; a later run that does not find them in place (deleted, edited, another folder) runs
    /// their task again.
    pub fn exporting_to(mut self, folder: Arc<OutputFolder>) -> Keys<'a> {
        let by_stages = read_by_stages(self.pipeline);
        for x in &self.pipeline.exports {
            self.only_exported[x.node][x.port] = !by_stages[x.node][x.port];
        }
        self.folder = Some(folder);
        self
    }

    /// Whether output `port` of stage node `node` is exported and read by no stage.
    pub fn only_exported(&self, node: NodeId, port: usize) -> bool {
        self.only_exported[node].get(port).copied().unwrap_or(false)
    }

    /// Whether an output of `size` bytes on output `port` of stage node `node` is kept only in
    /// the output folder, not in the store (see [`Keys::exporting_to`]).
    pub fn only_in_folder(&self, node: NodeId, port: usize, size: u64) -> bool {
        size > STORED_EXPORT_MAX && self.only_exported(node, port)
    }

    /// The params digest of stage node `node`.
    pub fn params(&self, node: NodeId) -> Digest {
        self.params[node]
    }

    /// The params digest the tasks of stage node `node` on `item` are keyed and seeded by: the
    /// node's, or for a stage with variants the shared part's and the item's own variant's, so
    /// that editing one variant reruns only its tasks.
    pub fn task_params(&self, node: NodeId, item: &ItemKey) -> Digest {
        match self.variant_params[node].as_slice() {
            [] => self.params[node],
            each => {
                let i = item.coords().last().map_or(0, |&i| i as usize);
                each.get(i).copied().unwrap_or(self.params[node])
            }
        }
    }

    /// The seed of stage node `node` on `item` (see [`task_seed`]).
    pub fn seed(&self, node: NodeId, item: &ItemKey) -> u64 {
        task_seed(&self.stage(node).kind, &self.task_params(node, item), item)
    }

    /// Every input artifact of task `task` of `plan`, per input port in port order, with its
    /// digest: an upstream output's from `upstream(task, port)` (`None` while that task has not
    /// finished), a dataset source's from its raw files' fingerprints, hashing files only when
    /// `hash` is set (the memo answers for unchanged files either way).
    pub fn resolve(
        &self,
        plan: &OuterPlan,
        task: u32,
        upstream: impl Fn(u32, u16) -> Option<Digest>,
        hash: bool,
    ) -> Vec<Vec<Input>> {
        let files = StoreFiles { store: self.store, allow_hash: hash };
        plan.tasks[task as usize]
            .inputs
            .iter()
            .map(|srcs| {
                srcs.iter()
                    .map(|&src| match src {
                        InputSrc::Task { task: u, port, .. } => Input {
                            src,
                            item: plan.tasks[u as usize].item,
                            digest: upstream(u, port).ok_or(Unknown::Upstream { task: u }),
                        },
                        InputSrc::Source { node, item, .. } => {
                            Input { src, item, digest: self.source_digest(node as usize, &item, &files) }
                        }
                    })
                    .collect()
            })
            .collect()
    }

    /// Fingerprints the sources among `inputs` that [`Keys::resolve`] left unhashed, now hashing
    /// their files.
    pub fn hash_sources(&self, inputs: &mut [Vec<Input>]) {
        let files = StoreFiles { store: self.store, allow_hash: true };
        for input in inputs.iter_mut().flatten() {
            if let (InputSrc::Source { node, item, .. }, Err(Unknown::Unhashed)) = (input.src, &input.digest) {
                input.digest = self.source_digest(node as usize, &item, &files);
            }
        }
    }

    /// Whether stage node `node` on `item` with these inputs is cached, must run, or cannot be
    /// keyed yet. A record is a hit only when the bytes of each output the run reads are there:
    /// inside the record, as a blob, or, for an output kept only in the output folder, as its files
    /// there (see [`OutputFolder::holds`]; an exported file whose stat changed is hashed only when
    /// `hash` is set, else the answer is `Unknown`). A record whose bytes are gone, or that did not
    /// make an output the run reads, is not a hit.
    pub fn decide(&self, node: NodeId, item: &ItemKey, inputs: &[Vec<Input>], hash: bool) -> Decision {
        let Some(digests) = known_digests(inputs) else { return Decision::Unknown };
        let key = task_key(self.stage(node), &self.task_params(node, item), item, &digests);
        let Some(rec) = self.store.lookup(&key) else { return Decision::Run { key, lost: None } };
        let mut unsure = false;
        for (port, o) in rec.outputs.iter().enumerate() {
            if !self.is_read(node, port) {
                continue;
            }
            if o.is_unmade() {
                return Decision::Run { key, lost: Some(Lost::Unmade(port)) };
            }
            if o.inline.is_some() {
                continue;
            }
            // The output folder first, where such outputs are; a blob of the same bytes (another
            // output's, or one an older dist4d stored) serves as well.
            let only_in_folder = self.only_in_folder(node, port, o.size);
            let exported = if only_in_folder { self.in_folder(node, port, item, o, hash) } else { None };
            match exported {
                Some(true) => {}
                _ if self.store.has_blob(&o.digest) => {}
                Some(false) => return Decision::Run { key, lost: Some(Lost::Exported(port)) },
                None if only_in_folder => unsure = true,
                None => return Decision::Run { key, lost: Some(Lost::Blob(port)) },
            }
        }
        if unsure {
            return Decision::Unknown;
        }
        Decision::Cached { key, outputs: rec.outputs }
    }

    /// Whether every file the run exports of output `port` of `node` on `item` holds `out`'s bytes
    /// (`None`: only hashing can tell, and `hash` is not set).
    fn in_folder(&self, node: NodeId, port: usize, item: &ItemKey, out: &OutputRef, hash: bool) -> Option<bool> {
        let folder = self.folder.as_ref()?;
        let mut answer = Some(true);
        for x in self.pipeline.exports.iter().filter(|x| x.node == node && x.port == port) {
            match folder.holds(x, item, self.dataset, &out.digest, out.size, hash) {
                Some(true) => {}
                Some(false) => return Some(false),
                None => answer = None,
            }
        }
        answer
    }

    fn stage(&self, node: NodeId) -> &'a StageNode {
        self.pipeline.nodes[node].stage().expect("keys are for stage nodes")
    }

    fn source_digest(&self, node: NodeId, item: &ItemKey, files: &StoreFiles) -> Result<Digest, Unknown> {
        let NodeKind::Source { port } = &self.pipeline.nodes[node].kind else {
            unreachable!("source inputs come from source nodes")
        };
        match self
            .dataset
            .source_digest(port, item, files)
            .with_context(|| format!("fingerprinting dataset.{port} for {}", self.dataset.path(item)))
        {
            Ok(Some(d)) => Ok(d),
            Ok(None) => Err(Unknown::Unhashed),
            Err(e) => Err(Unknown::Unreadable(e)),
        }
    }
}

/// Per input port, the positions and digests of its artifacts, when every digest is known.
pub fn known_digests(inputs: &[Vec<Input>]) -> Option<Vec<Vec<(i64, Digest)>>> {
    inputs.iter().map(|port| port.iter().map(|a| a.digest.as_ref().ok().map(|d| (a.pos(), *d))).collect()).collect()
}

/// Raw-file digests through the store's memo; hashing a file only when allowed.
struct StoreFiles<'s> {
    store: &'s Store,
    allow_hash: bool,
}

impl FileDigests for StoreFiles<'_> {
    fn file_digest(&self, path: &Path) -> Result<Option<Digest>> {
        self.store.file_digest(path, self.allow_hash)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_graph::{Input as Wire, Selector};
    use serde::Serialize;

    #[derive(Serialize)]
    struct PinnedParams {
        radius: f32,
        max_depth: f64,
        steps: u32,
        names: Vec<String>,
        window: Option<(i32, i32)>,
        mode: Mode,
    }

    #[derive(Serialize)]
    enum Mode {
        Nearest,
    }

    /// A stage node written out in full, so that nothing but the key layer and the canonical
    /// printer can move its key.
    fn pinned_stage() -> StageNode {
        let params = PinnedParams {
            radius: 0.1,
            max_depth: 80.0,
            steps: 3,
            names: vec!["a \"b\"".into()],
            window: Some((-1, 1)),
            mode: Mode::Nearest,
        };
        let wire = |port: &str, selector, many| Wire {
            port: port.into(),
            ty: "Bytes".into(),
            from: 0,
            from_port: 0,
            selector,
            many,
        };
        StageNode {
            variants: None,
            unused: Vec::new(),
            kind: "Pinned".into(),
            version: 3,
            params: ParamsValue::new(params).unwrap(),
            seeded: true,
            every: 1,
            inputs: vec![
                wire("one", Selector::Same, false),
                wire("window", Selector::Window { dim: 1, before: -1, after: 1 }, true),
            ],
        }
    }

    /// The key of a pinned task. It changes when the key layout, the canonical params printer or
    /// the digest framing changes: then every cached result is invalidated, so such a change must
    /// be deliberate, with [`TASK_KEY_DOMAIN`] bumped and these values re-pinned.
    #[test]
    fn a_pinned_task_has_a_pinned_key_and_seed() {
        let stage = pinned_stage();
        assert_eq!(
            stage.params.canonical,
            r#"(radius:0.1,max_depth:80.0,steps:3,names:["a \"b\""],window:Some((-1,1)),mode:Nearest)"#
        );
        let params = params_digest(&stage.params);
        let inputs = vec![
            vec![(0, Digest::of(b"one"))],
            vec![(-1, Digest::of(b"previous")), (0, Digest::of(b"this")), (1, Digest::of(b"next"))],
        ];
        let item = ItemKey::new(&[0, 1, 2]);
        assert_eq!(
            task_key(&stage, &params, &item, &inputs).hex(),
            "a8a0f368b9ea2f61cf7f9afbfcc29d925dbf2fbeef2c1127e9716eaf0ba9226f"
        );
        assert_eq!(task_seed(&stage.kind, &params, &item), 8360173915529016704);
        // The item enters the key of a seeded stage only.
        let other = ItemKey::new(&[0, 1, 3]);
        assert_ne!(task_key(&stage, &params, &item, &inputs), task_key(&stage, &params, &other, &inputs));
        let unseeded = StageNode { seeded: false, ..pinned_stage() };
        assert_eq!(task_key(&unseeded, &params, &item, &inputs), task_key(&unseeded, &params, &other, &inputs));
    }
}
