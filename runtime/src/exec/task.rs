//! A task's life, as types: **planned -> keyed -> ran -> committed -> exported**.
//!
//! - *planned*: in its outer item's plan ([`crate::plan`]), waiting for its upstream tasks
//!   ([`State::Planned`]).
//! - *keyed*: its inputs resolved and its key computed; [`super::key::decide`], the one place the
//!   cache is asked, says [`Keyed::Cached`] or [`Keyed::Run`] (or [`Keyed::Unknown`] while raw
//!   files are not hashed yet: the worker hashes them and asks the same function).
//! - *ran*: a worker ran its operator and stored its blobs ([`Ran`]); nothing is recorded yet.
//! - *committed*: the coordinator's [`super::book::Book::commit`] wrote its key, kept its outputs
//!   for its readers, planned its exports and wrote its record ([`State::Committed`]).
//! - *exported*: its files are in the output folder; the record of a task whose outputs are kept
//!   only there is written then, never before.
//!
//! A task can also end as failed, skipped (an input failed or was not executed), or with nothing
//! to make ([`crate::Made::Nothing`]), each a value, not an error to recognise.

use crate::digest::Digest;
use crate::export::{ExportError, FileStat};
use crate::item::ItemKey;
use crate::keys::Input;
use crate::operator::Blob;
use crate::record::{OutputRef, TaskRecord};
use crate::store::BlobError;
use anyhow::Result;
use std::sync::Arc;

/// Where a task of an active outer item is in its life.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(super) enum State {
    /// Waiting for its upstream tasks, or ready and queued.
    Planned,
    /// Keyed and handed to a worker.
    Running,
    /// Cached or ran, and committed: its outputs are there for its readers.
    Committed,
    Failed,
    Skipped,
}

/// An output as the coordinator holds it: the reference, plus the bytes while readers need them.
#[derive(Clone)]
pub(super) struct Produced {
    pub r: OutputRef,
    pub mem: Option<Blob>,
    /// Made by this run and kept only in the output folder: its task's record waits for its files.
    pub only_in_folder: bool,
}

/// Where a worker finds the bytes of one input artifact.
pub(super) enum Src {
    Mem(Blob),
    Inline(Arc<[u8]>),
    Cas(Digest),
    Source { port: String },
}

/// A keyed task (or one to key on the worker) that a worker runs.
pub(super) struct Job {
    pub slot: u32,
    pub task: u32,
    pub node: usize,
    pub item: ItemKey,
    /// Known when the coordinator could compute it without hashing raw files.
    pub key: Option<Digest>,
    pub inputs: Vec<Vec<Input>>,
    /// Where the bytes of each input are, in the shape of `inputs`.
    pub srcs: Vec<Vec<Src>>,
    /// False: only a cache hit is taken ([`super::RunOptions::execute_only`]).
    pub may_execute: bool,
}

/// What the cache decision says of a task.
pub(super) enum Keyed {
    Cached(Digest, Vec<OutputRef>),
    Run(Digest),
    /// Its key needs raw files hashed (a worker's job), or a task that did not execute.
    Unknown,
    /// Its key is known and it is not cached, but this run does not execute it (see
    /// [`Ended::NotExecuted`]).
    NotExecuted {
        deferred: bool,
    },
}

/// A task a worker ran: its blobs are stored, its record is not written yet (the coordinator's
/// commit writes it).
pub(super) struct Ran {
    pub key: Digest,
    /// Empty when it had nothing to make.
    pub produced: Vec<Produced>,
    pub micros: u64,
    pub record: Box<TaskRecord>,
    /// The reason it gave for having nothing to make.
    pub nothing: Option<String>,
}

/// How a task that was started ended (a failure is the `Err` beside it).
pub(super) enum Ended {
    Cached(Digest, Vec<OutputRef>),
    Ran(Ran),
    /// Not cached, and this run does not execute it: its outer item is not among those the run
    /// executes ([`super::RunOptions::execute_only`]), or its operator is left to a later run
    /// (`deferred`, [`super::RunOptions::defer_resources`]).
    NotExecuted {
        deferred: bool,
    },
    /// A blob input `port` needs is missing or corrupt: the task that made it runs again.
    LostInput {
        port: String,
        lost: BlobError,
    },
}

impl Ended {
    /// Whether the task made no outputs (it had nothing to make).
    pub fn made_nothing(&self) -> bool {
        match self {
            Ended::Cached(_, outs) => outs.is_empty(),
            Ended::Ran(ran) => ran.produced.is_empty(),
            Ended::NotExecuted { .. } | Ended::LostInput { .. } => false,
        }
    }
}

/// What workers and export threads tell the coordinator.
pub(super) enum Msg {
    Task {
        slot: u32,
        task: u32,
        /// The resource class whose slot the task held, if any.
        waited: Option<usize>,
        result: Result<Ended>,
    },
    /// An export job ended; `awaiting` is the id of the task record waiting for it, if any.
    Exported {
        slot: u32,
        task: u32,
        rel: String,
        result: std::result::Result<FileStat, ExportError>,
        awaiting: Option<u64>,
    },
}

/// The message of a panic caught in a worker or export thread.
pub(super) fn panic_message(p: &Box<dyn std::any::Any + Send>) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}
