//! Why a run made nothing for some items: the first reason each stage's tasks gave when they had
//! nothing to make ([`NotApplicable`]). The run table only counts them ("n/a"); a stage that made
//! nothing at all (a window longer than the scene, a clip index with no clip) would otherwise go
//! unexplained, and its outputs would just be missing.

use crate::operator::{Artifact, NotApplicable, Operator, Output, Resource, TaskContext};
use crate::runs::StageStats;
use anyhow::Result;
use dist4d_graph::Pipeline;
use std::sync::{Arc, Mutex};

/// Per node, the reason its first task (by item label: the same whatever the thread count) gave
/// for having nothing to make, and that item.
#[derive(Default)]
pub struct WhyNothing {
    first: Mutex<Vec<Option<(String, String)>>>,
}

impl WhyNothing {
    /// `operators` (one per node, as [`crate::exec::Engine`] takes them), each noting here the
    /// first [`NotApplicable`] its tasks return; what they do is unchanged.
    pub fn wrap(self: &Arc<Self>, operators: Vec<Option<Box<dyn Operator>>>) -> Vec<Option<Box<dyn Operator>>> {
        *self.first.lock().unwrap_or_else(|e| e.into_inner()) = vec![None; operators.len()];
        operators
            .into_iter()
            .enumerate()
            .map(|(node, op)| op.map(|inner| Box::new(Noting { inner, node, why: self.clone() }) as Box<dyn Operator>))
            .collect()
    }

    fn note(&self, node: usize, reason: &str, item: &str) {
        let mut first = self.first.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(slot) = first.get_mut(node) {
            if slot.as_ref().is_none_or(|(_, noted)| item < noted.as_str()) {
                *slot = Some((reason.to_string(), item.to_string()));
            }
        }
    }

    /// One line per stage with tasks that had nothing to make: how many, and why (the reason its
    /// first such task gave; for tasks passed over, the inputs that had nothing; for tasks found
    /// cached as having nothing, that an earlier run said why).
    pub fn lines(&self, p: &Pipeline, stats: &[StageStats]) -> Vec<String> {
        let first = self.first.lock().unwrap_or_else(|e| e.into_inner());
        let had_nothing = |name: &str| stats.iter().any(|s| s.stage == name && s.not_applicable > 0);
        let mut out = Vec::new();
        for s in stats.iter().filter(|s| s.not_applicable > 0) {
            let Some(node) = p.node_by_name(&s.stage) else { continue };
            let why = match first.get(node).cloned().flatten() {
                Some((reason, item)) => format!("{reason} (e.g. {item})"),
                None => {
                    let mut from: Vec<&str> = p.nodes[node]
                        .stage()
                        .map(|st| st.inputs.iter().map(|i| p.nodes[i.from].name.as_str()).collect())
                        .unwrap_or_default();
                    from.retain(|n| had_nothing(n));
                    from.dedup();
                    if from.is_empty() {
                        "cached as having nothing to make (the run that ran them said why)".to_string()
                    } else {
                        let names: Vec<String> = from.iter().map(|n| format!("`{n}`")).collect();
                        format!("nothing came from {}", names.join(", "))
                    }
                }
            };
            let all = if s.executed + s.cached == 0 { ", nothing made" } else { "" };
            out.push(format!("n/a: {} ({}): {} of {}{all}: {why}", s.stage, s.kind, s.not_applicable, s.total));
        }
        out
    }
}

struct Noting {
    inner: Box<dyn Operator>,
    node: usize,
    why: Arc<WhyNothing>,
}

impl Operator for Noting {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<Artifact>]) -> Result<Vec<Output>> {
        let r = self.inner.run(ctx, inputs);
        if let Err(e) = &r {
            if let Some(NotApplicable(reason)) = e.downcast_ref::<NotApplicable>() {
                self.why.note(self.node, reason, ctx.label);
            }
        }
        r
    }
    fn identity(&self) -> Result<Option<String>> {
        self.inner.identity()
    }
    fn resource(&self) -> Option<Resource> {
        self.inner.resource()
    }
    fn peak_memory(&self) -> Option<u64> {
        self.inner.peak_memory()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exec::{Engine, RunOptions};
    use crate::store::{Access, Store};
    use crate::testkit;

    const PIPELINE: &str = r#"Pipeline(
    dataset: Grid(scenes: 1, frames: 2, cameras: 2),
    stages: {
        "a": Echo(inputs: {"x": "dataset.camera_value"}),
        "b": Echo(inputs: {"x": "a.y"}),
        "c": Echo(inputs: {"x": "dataset.camera_value"}),
    },
)"#;

    fn run(p: &Pipeline, store: &std::path::Path) -> Vec<String> {
        let store = Store::open(store, Access::Shared).unwrap();
        let why = Arc::new(WhyNothing::default());
        let ops = why.wrap(testkit::operators(p));
        let grid = testkit::grid_of(p);
        let engine = Engine { pipeline: p, dataset: &grid, operators: &ops, store: &store };
        let rec = engine.run(&RunOptions { jobs: 2, ..Default::default() }).unwrap().record;
        why.lines(p, &rec.stages)
    }

    #[test]
    fn each_stage_with_nothing_to_make_says_why_once() {
        let dir = tempfile::tempdir().unwrap();
        let nothing = r#"a.nothing_on=["s0/001/cam1", "s0/000/cam1"]"#;
        let p = testkit::load(PIPELINE, &[nothing]);
        let lines = run(&p, &dir.path().join("store"));
        assert_eq!(
            lines,
            [
                "n/a: a (Echo): 2 of 4: asked for nothing on s0/000/cam1 (e.g. s0/000/cam1)",
                "n/a: b (Echo): 2 of 4: nothing came from `a`",
            ]
        );
        // A rerun finds them cached as having nothing: the first run said why.
        let again = run(&p, &dir.path().join("store"));
        assert!(again[0].ends_with("2 of 4: cached as having nothing to make (the run that ran them said why)"));
    }
}
