//! Claims on outer items, so that processes sharing a store share the work.

use super::{pipeline_digest, Engine};
use crate::digest::DigestBuilder;
use crate::item::{ItemKey, ItemSpace};
use crate::lease::{Claim, Holder};
use crate::store::Store;
use anyhow::Result;
use dist4d_graph::Pipeline;
use std::time::{Duration, Instant};

/// How often a run looks again at the outer items other processes hold.
pub(super) const CLAIM_POLL: Duration = Duration::from_millis(200);

/// Claims on outer items, so that processes sharing a store share the work instead of each
/// doing all of it: a process runs an outer item only while it holds the item's claim (a file
/// under the store's `leases/claims/`, see [`crate::lease::Claim`]); an item another live
/// process holds waits, and once let go it is admitted and finds its tasks cached. The claim's
/// name is the pipeline's digest with the item's label: processes running different pipelines
/// (or params) do not wait for each other.
pub(super) struct Claims<'e> {
    store: &'e Store,
    space: &'e dyn ItemSpace,
    pipeline: String,
    dim: String,
    said: std::collections::HashSet<u32>,
    last_poll: Instant,
}

impl<'e> Claims<'e> {
    pub(super) fn new(engine: &'e Engine, p: &Pipeline) -> Claims<'e> {
        Claims {
            store: engine.store,
            space: engine.dataset,
            pipeline: pipeline_digest(p).hex(),
            dim: p.dims[0].name.clone(),
            said: Default::default(),
            last_poll: Instant::now(),
        }
    }

    pub(super) fn take(&mut self, outer: u32) -> Result<std::result::Result<Claim, Holder>> {
        let label = self.space.label(&ItemKey::new(&[outer]));
        let name = DigestBuilder::new("dist4d-claim").str(&self.pipeline).str(&label).finish().hex();
        self.store.claim(&name[..32])
    }

    /// Says that the run waits for another process (for the first few items: with many
    /// processes on one store, collisions are many and each one is ordinary).
    pub(super) fn waiting_for(&mut self, outer: u32, holder: &Holder) {
        if self.said.len() == 3 && self.said.insert(outer) {
            eprintln!("(and more: items other processes are running are waited for, silently from now on)");
        }
        if self.said.len() < 3 && self.said.insert(outer) {
            let label = self.space.label(&ItemKey::new(&[outer]));
            eprintln!(
                "{} `{label}` is being run by another process sharing the store ({}); this run takes its results when it ends",
                self.dim,
                holder.describe()
            );
        }
    }

    pub(super) fn poll_due(&mut self) -> bool {
        let due = self.last_poll.elapsed() >= CLAIM_POLL;
        if due {
            self.last_poll = Instant::now();
        }
        due
    }
}
