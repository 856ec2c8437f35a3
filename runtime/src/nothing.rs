//! Why a run made nothing for some items: the first reason each stage's tasks gave when they had
//! nothing to make ([`crate::Made::Nothing`], kept by the engine in [`StageStats::nothing`]). The run table only counts them ("n/a"); a stage that made
//! nothing at all (a window longer than the scene, a clip index with no clip) would otherwise go
//! unexplained, and its outputs would just be missing.

use crate::runs::StageStats;
use dist4d_graph::Pipeline;

/// One line per stage with tasks that had nothing to make: how many, and why (the reason its
/// first such task gave, [`StageStats::nothing`]; for tasks passed over, the inputs that had
/// nothing; for tasks found cached as having nothing, that an earlier run said why).
pub fn lines(p: &Pipeline, stats: &[StageStats]) -> Vec<String> {
    let had_nothing = |name: &str| stats.iter().any(|s| s.stage == name && s.not_applicable > 0);
    let mut out = Vec::new();
    for s in stats.iter().filter(|s| s.not_applicable > 0) {
        let Some(node) = p.node_by_name(&s.stage) else { continue };
        let why = match &s.nothing {
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
        let ops = testkit::operators(p);
        let grid = testkit::grid_of(p);
        let engine = Engine { pipeline: p, dataset: &grid, operators: &ops, store: &store };
        let rec = engine.run(&RunOptions { jobs: 2, ..Default::default() }).unwrap().record;
        lines(p, &rec.stages)
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
