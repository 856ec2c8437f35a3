//! Keying a ready task: its inputs resolved, its key computed, and the one cache decision.

use super::book::OuterRun;
use super::task::{Job, Keyed, Src};
use super::Engine;
use crate::item::ItemKey;
use crate::keys::{Decision, Input, Keys, Unknown};
use crate::plan::InputSrc;
use anyhow::{bail, Result};
use dist4d_graph::{NodeId, NodeKind};

/// What the coordinator and the workers share: the engine and its key layer.
pub(super) struct Shared<'e, 'a> {
    pub engine: &'e Engine<'a>,
    pub keys: &'e Keys<'e>,
    /// Per node: its tasks are only taken from the cache ([`super::RunOptions::defer_resources`]).
    pub deferred: Vec<bool>,
}

/// A ready task as keying left it on the coordinator.
pub(super) enum Prepared {
    /// Cached, or known not to run here.
    Decided(Keyed),
    /// To run on a worker (keyed there first when `job.key` is `None`).
    Job(Job),
}

/// The cache decision for a task of `node` on `item` with `inputs`, the one place it is made.
/// `hashed`: raw files are hashed now (on a worker); before that (on the coordinator) a key that
/// needs them is [`Keyed::Unknown`].
pub(super) fn decide(
    shared: &Shared,
    node: NodeId,
    item: &ItemKey,
    inputs: &[Vec<Input>],
    may_execute: bool,
    hashed: bool,
) -> Result<Keyed> {
    Ok(match shared.keys.decide(node, item, inputs, hashed) {
        Decision::Cached { key, outputs } => Keyed::Cached(key, outputs),
        Decision::Run { .. } if !may_execute => Keyed::NotExecuted { deferred: false },
        Decision::Run { key, .. } => Keyed::Run(key),
        Decision::Unknown if !hashed => Keyed::Unknown,
        Decision::Unknown => bail!("{}", unknown_inputs(shared, node, inputs)),
    })
}

impl Shared<'_, '_> {
    /// Resolves a ready task's inputs without hashing raw files and decides whether it is cached;
    /// otherwise makes the job a worker runs.
    pub(super) fn prepare(&self, run: &OuterRun, slot: u32, task: u32) -> Result<Prepared> {
        let p = self.engine.pipeline;
        let t = &run.plan.tasks[task as usize];
        let node = t.node as usize;
        // Its worker is not started here, so its key (which holds the worker's identity) is not known.
        if self.deferred[node] {
            return Ok(Prepared::Decided(Keyed::NotExecuted { deferred: true }));
        }
        let may_execute = run.may_execute;
        let output = |u: u32, port: u16| run.outputs[u as usize].as_ref().map(|o| &o[port as usize]);
        let mut inputs = self.keys.resolve(&run.plan, task, |u, port| output(u, port).map(|o| o.r.digest), false);
        if let Some(e) = take_unreadable(&mut inputs) {
            return Err(e);
        }
        // Without hashing: a raw file, or an exported file whose stat changed, is for the worker.
        let key = match decide(self, node, &t.item, &inputs, may_execute, false)? {
            Keyed::Run(key) => Some(key),
            Keyed::Unknown => None,
            decided => return Ok(Prepared::Decided(decided)),
        };
        let srcs = t
            .inputs
            .iter()
            .map(|srcs| {
                srcs.iter()
                    .map(|src| match *src {
                        InputSrc::Task { task: u, port, .. } => {
                            let o = output(u, port).expect("upstream finished before its dependents are ready");
                            match (&o.mem, &o.r.inline) {
                                (Some(m), _) => Src::Mem(m.clone()),
                                (None, Some(b)) => Src::Inline(b.clone()),
                                (None, None) => Src::Cas(o.r.digest),
                            }
                        }
                        InputSrc::Source { node: sn, .. } => match &p.nodes[sn as usize].kind {
                            NodeKind::Source { port } => Src::Source { port: port.clone() },
                            NodeKind::Stage(_) => unreachable!("source inputs come from source nodes"),
                        },
                    })
                    .collect()
            })
            .collect();
        Ok(Prepared::Job(Job { slot, task, node, item: t.item, key, inputs, srcs, may_execute }))
    }
}

/// The error of the first input whose dataset source could not be fingerprinted, if any.
pub(super) fn take_unreadable(inputs: &mut [Vec<Input>]) -> Option<anyhow::Error> {
    for input in inputs.iter_mut().flatten() {
        if matches!(input.digest, Err(Unknown::Unreadable(_))) {
            if let Err(Unknown::Unreadable(e)) = std::mem::replace(&mut input.digest, Err(Unknown::Unhashed)) {
                return Some(e);
            }
        }
    }
    None
}

/// Which inputs of a task still have no digest after hashing, for the error.
fn unknown_inputs(shared: &Shared, node: NodeId, inputs: &[Vec<Input>]) -> String {
    let e = shared.engine;
    let stage = e.pipeline.nodes[node].stage().expect("jobs are for stages");
    let mut missing = Vec::new();
    for (input, spec) in inputs.iter().zip(&stage.inputs) {
        for a in input.iter().filter(|a| a.digest.is_err()) {
            let from = match a.src {
                InputSrc::Task { task, .. } => format!("upstream task {task}"),
                InputSrc::Source { node, .. } => e.pipeline.nodes[node as usize].name.clone(),
            };
            missing.push(format!("input `{}` ({from} for {})", spec.port, e.dataset.path(&a.item)));
        }
    }
    format!("no digest for {}", missing.join(", "))
}
