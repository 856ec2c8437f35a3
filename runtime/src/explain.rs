//! `explain`: per stage, how many tasks are cached, will run, or failed last time, and why each
//! task that will run does: never run, stage version changed, which param changed from what to
//! what, which input changed, an upstream task will run, or the bytes of an output are gone (a
//! blob from the store, or a file of an output kept only in the output folder).

use crate::digest::Digest;
use crate::exec::{select_outer, Engine};
use crate::export::OutputFolder;
use crate::item::ItemKey;
use crate::keys::{known_digests, Decision, Keys, Lost, Unknown};
use crate::plan::{plan_outer, InputSrc, View};
use crate::record::TaskRecord;
use crate::runs::list_runs;
use anyhow::Result;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::Path;
use std::sync::Arc;

#[derive(Debug, Default, Clone)]
pub struct StageExplain {
    pub stage: String,
    pub kind: String,
    pub cached: u64,
    pub will_run: u64,
    /// Tasks that had nothing to make (cached as such), or that have nothing because an input
    /// they need had nothing (see [`crate::Made::Nothing`]).
    pub not_applicable: u64,
    /// Tasks that will run and failed in the last run of this pipeline.
    pub failed_last_run: u64,
    /// Reason -> (how many tasks, an example item).
    pub reasons: BTreeMap<String, (u64, String)>,
}

/// What the previous task for the same stage and item looked like.
struct Previous {
    /// Its [`RunRanks`] rank: the newer the run of this pipeline on this dataset that used it, the higher.
    rank: usize,
    finished_ms: u64,
    version: u32,
    params: Digest,
    inputs: Vec<(String, Vec<Digest>)>,
}

/// Explains the tasks under the selected outer items (all when `outer_items` is `None`), with the
/// first `limit` items along the ordered dimension, as [`crate::RunOptions`] selects them,
/// for a run that exports into `out_dir` (whose files hold the outputs the store does not keep).
pub fn explain(
    engine: &Engine,
    outer_items: Option<&[String]>,
    limit: Option<u32>,
    out_dir: Option<&Path>,
) -> Result<Vec<StageExplain>> {
    Ok(explain_per_outer(engine, outer_items, limit, out_dir, true)?.0)
}

/// Per outer item (by index), how many of its tasks will run.
pub type PerOuter = Vec<(u32, u64)>;

/// [`explain`], and for each outer item (by index) how many of its tasks will run: what a
/// submission to a cluster plans shards from (an item with none needs no job). Without `hash`
/// (planning on a login node), raw files the fingerprint memo does not know are not read (not a
/// dataset's terabytes there) and model workers are not started (no GPU, maybe not the model's
/// environment): the tasks that need either count as will run, so a plan may take an item
/// whose work is done, never leave one out.
pub fn explain_per_outer(
    engine: &Engine,
    outer_items: Option<&[String]>,
    limit: Option<u32>,
    out_dir: Option<&Path>,
    hash: bool,
) -> Result<(Vec<StageExplain>, PerOuter)> {
    let p = engine.pipeline;
    let view = View::limited(p, engine.dataset, limit)?;
    let outers = select_outer(engine.dataset, &p.dims[0].name, outer_items)?;
    let x = Explainer::new(engine, out_dir, hash)?;
    let mut out: Vec<StageExplain> = vec![StageExplain::default(); p.nodes.len()];
    for n in p.stage_order() {
        out[n].stage = p.nodes[n].name.clone();
        out[n].kind = p.nodes[n].stage().unwrap().kind.clone();
    }
    let mut pending = Vec::with_capacity(outers.len());
    let will_run = |out: &[StageExplain]| out.iter().map(|e| e.will_run).sum::<u64>();
    for outer in outers {
        let before = will_run(&out);
        x.outer(&view, outer, &mut out);
        pending.push((outer, will_run(&out) - before));
    }
    Ok((p.stage_order().map(|n| std::mem::take(&mut out[n])).collect(), pending))
}

/// What explaining a pipeline's tasks compares against: the previous task of each stage and
/// item, the last run's failures, and the key layer a run would use.
struct Explainer<'e> {
    engine: &'e Engine<'e>,
    keys: Keys<'e>,
    previous: HashMap<(String, String, ItemKey), Previous>,
    /// Failures of the last run of this pipeline, by (stage, item).
    last_failures: HashMap<(String, String), String>,
    /// Per node: its model worker is not asked (planning without `hash`).
    unasked: Vec<bool>,
    hash: bool,
}

impl<'e> Explainer<'e> {
    fn new(engine: &'e Engine<'e>, out_dir: Option<&Path>, hash: bool) -> Result<Explainer<'e>> {
        let p = engine.pipeline;
        let store = engine.store;
        let dataset = crate::runs::dataset_identity(p);
        let own_runs: Vec<_> = list_runs(&store.runs_dir())?
            .into_iter()
            .filter(|r| r.pipeline == p.name && r.status != crate::runs::RunStatus::Running)
            .collect();
        let last_run = own_runs.iter().rev().find(|r| r.read_dataset(&dataset)).cloned();
        let previous = previous_tasks(store, &RunRanks::read(store, &own_runs, &dataset)?);
        let last_failures = last_run
            .map(|r| r.failures.into_iter().map(|f| ((f.stage, f.item), f.error)).collect())
            .unwrap_or_default();
        let names: Vec<String> = p.nodes.iter().map(|n| n.name.clone()).collect();
        let unasked = |op: &dyn crate::Operator| !hash && op.resource().is_some();
        let identities = crate::operator::Identities::of_except(engine.operators, &names, unasked).all()?;
        let unasked: Vec<bool> = engine.operators.iter().map(|op| op.as_deref().is_some_and(unasked)).collect();
        let mut keys = Keys::new(p, engine.dataset, store).with_identities(&identities);
        if let Some(dir) = out_dir.filter(|_| !p.exports.is_empty()) {
            // A folder another pipeline owns holds nothing of this one's (a run would refuse it).
            let folder = OutputFolder::read(dir, &p.dims)?;
            if folder.owner().is_none_or(|o| o == p.name) {
                keys = keys.exporting_to(Arc::new(folder));
            }
        }
        Ok(Explainer { engine, keys, previous, last_failures, unasked, hash })
    }

    /// Counts the tasks of one outer item into `out` (per node), with the reasons of those that
    /// will run.
    fn outer(&self, view: &View, outer: u32, out: &mut [StageExplain]) {
        let p = self.engine.pipeline;
        let mut plan = plan_outer(p, view, outer);
        // Output digests of tasks known to be cached; None = will run.
        let mut outputs: Vec<Option<Vec<Digest>>> = vec![None; plan.tasks.len()];
        // Tasks with nothing to make, as a run would pass them over (known only from the records
        // of tasks that said so).
        let mut nothing = vec![false; plan.tasks.len()];
        for t in 0..plan.tasks.len() {
            let node = plan.tasks[t].node as usize;
            let item = plan.tasks[t].item;
            let label = self.engine.dataset.path(&item);
            if !nothing[t] && self.unasked[node] {
                out[node].will_run += 1;
                let entry = out[node].reasons.entry("its model worker is not asked when planning".into());
                entry.or_insert((0, label)).0 += 1;
                continue;
            }
            let decision = match nothing[t] {
                true => None,
                false => {
                    // The same resolution and decision as a run, hashing changed raw files as a run would.
                    let upstream =
                        |u: u32, port: u16| outputs[u as usize].as_ref().and_then(|o| o.get(port as usize).copied());
                    let inputs = self.keys.resolve(&plan, t as u32, upstream, self.hash);
                    let decision = self.keys.decide(node, &item, &inputs, self.hash);
                    Some((inputs, decision))
                }
            };
            let e = &mut out[node];
            let (inputs, lost) = match decision {
                Some((_, Decision::Cached { outputs: outs, .. }))
                    if !outs.is_empty() || p.nodes[node].outputs.is_empty() =>
                {
                    e.cached += 1;
                    outputs[t] = Some(outs.iter().map(|o| o.digest).collect());
                    continue;
                }
                // Nothing to make, found so or passed over: so are the tasks that need it.
                None | Some((_, Decision::Cached { .. })) => {
                    e.not_applicable += 1;
                    for d in plan.tasks[t].dependents.clone() {
                        nothing[d as usize] |= plan.drop_upstream(d, t as u32);
                    }
                    continue;
                }
                Some((inputs, Decision::Run { lost, .. })) => (inputs, lost),
                Some((inputs, Decision::Unknown)) => (inputs, None),
            };
            e.will_run += 1;
            for r in self.reasons(&plan, t, &label, &inputs, lost, e) {
                e.reasons.entry(r).or_insert((0, label.clone())).0 += 1;
            }
        }
    }

    /// Why task `t` of `plan` will run (counting it in `e` when it failed last time).
    fn reasons(
        &self,
        plan: &crate::plan::OuterPlan,
        t: usize,
        label: &str,
        inputs: &[Vec<crate::keys::Input>],
        lost: Option<Lost>,
        e: &mut StageExplain,
    ) -> Vec<String> {
        let p = self.engine.pipeline;
        let task = &plan.tasks[t];
        let node = task.node as usize;
        let stage = p.nodes[node].stage().unwrap();
        let mut reasons = Vec::new();
        if let Some(err) = self.last_failures.get(&(p.nodes[node].name.clone(), label.to_string())) {
            e.failed_last_run += 1;
            reasons.push(format!("failed in the last run: {}", first_line(err)));
        }
        match self.previous.get(&(p.nodes[node].name.clone(), stage.kind.clone(), task.item)) {
            None => reasons.push("never run".into()),
            Some(prev) => {
                if prev.version != stage.version {
                    reasons.push(format!("stage version changed: {} -> {}", prev.version, stage.version));
                }
                if prev.params != self.keys.params(node) {
                    let old = self.engine.store.get_blob(&prev.params).ok().and_then(|b| String::from_utf8(b).ok());
                    // A stage with variants: what changed in this task's own variant.
                    let variant = stage.variants.as_ref().map(|_| label.rsplit('/').next().unwrap_or_default());
                    reasons.extend(param_changes(old.as_deref(), &stage.params.canonical, variant));
                }
                reasons.extend(unknown_input_reasons(p, plan, stage, inputs));
                if let Some(digests) = &known_digests(inputs) {
                    for ((spec, now), (port, then)) in stage.inputs.iter().zip(digests).zip(&prev.inputs) {
                        let now: Vec<Digest> = now.iter().map(|(_, d)| *d).collect();
                        if port == &spec.port && &now != then {
                            let from = &p.nodes[spec.from].name;
                            reasons.push(format!("input `{}` (from `{from}`) changed", spec.port));
                        }
                    }
                }
            }
        }
        if reasons.is_empty() {
            reasons.push(lost_reason(p, node, lost));
        }
        reasons
    }
}

/// The newest record of every (stage, kind, item) to say what changed against: this pipeline's
/// own previous task. Item keys are indices, so one stage and item of the same pipeline run on
/// another dataset into the same store is another task altogether: records are ranked by the
/// newest run of this pipeline on this dataset that used them, and those only other datasets'
/// runs used are left out. Unused records rank last, newest first (the latest alone misleads
/// after switching back: a run on a worker writes newer records than the cached ones the next run
/// goes back to). Keyed by kind too: pipelines sharing a store may give one stage name to stages
/// of different kinds, whose params have nothing to compare.
fn previous_tasks(store: &crate::Store, ranks: &RunRanks) -> HashMap<(String, String, ItemKey), Previous> {
    let mut previous: HashMap<(String, String, ItemKey), Previous> = HashMap::new();
    for (_, payload) in store.all_records() {
        let Ok(rec) = TaskRecord::decode(payload) else { continue };
        let Some(rank) = ranks.of(&rec.key) else { continue };
        let key = (rec.stage.clone(), rec.kind.clone(), rec.item);
        if previous.get(&key).is_some_and(|old| (old.rank, old.finished_ms) > (rank, rec.finished_ms)) {
            continue;
        }
        let prev = Previous {
            rank,
            finished_ms: rec.finished_ms,
            version: rec.version,
            params: rec.params,
            inputs: rec.inputs.into_iter().map(|i| (i.port, i.digests)).collect(),
        };
        previous.insert(key, prev);
    }
    previous
}

/// One reason per input without a digest: an upstream task that will run, a source that cannot
/// be read.
fn unknown_input_reasons(
    p: &dist4d_graph::Pipeline,
    plan: &crate::plan::OuterPlan,
    stage: &dist4d_graph::StageNode,
    inputs: &[Vec<crate::keys::Input>],
) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for (input, spec) in inputs.iter().zip(&stage.inputs) {
        for a in input {
            let why = match (&a.digest, a.src) {
                (Ok(_), _) => continue,
                (Err(Unknown::Upstream { task: u }), _) => {
                    format!("upstream `{}` will run", p.nodes[plan.tasks[*u as usize].node as usize].name)
                }
                (Err(_), InputSrc::Source { node: sn, .. }) => {
                    format!("input `{}` cannot be read from `{}`", spec.port, p.nodes[sn as usize].name)
                }
                (Err(_), InputSrc::Task { .. }) => format!("input `{}` is unknown", spec.port),
            };
            if !out.contains(&why) {
                out.push(why);
            }
        }
    }
    out
}

/// Why a task whose inputs and params are as before will run: an output's bytes are gone.
fn lost_reason(p: &dist4d_graph::Pipeline, node: usize, lost: Option<Lost>) -> String {
    let port = |i: usize| p.nodes[node].outputs[i].name.as_str();
    match lost {
        Some(Lost::Exported(i)) => {
            format!("output `{}` is kept only in the output folder, and its file there is missing or changed", port(i))
        }
        Some(Lost::Unmade(i)) => {
            format!("output `{}` is read now, and the cached task did not make it (nothing read it then)", port(i))
        }
        Some(Lost::Blob(i)) => format!("the cached bytes of output `{}` are missing from the store", port(i)),
        None => "no record of this exact task (removed by gc)".into(),
    }
}

/// Which records a pipeline's own runs used: the task keys of its runs on this dataset, ranked
/// by the run (newest highest), and those of its runs on other datasets.
struct RunRanks {
    ours: HashMap<Digest, usize>,
    others: HashSet<Digest>,
}

impl RunRanks {
    /// At most this many of the pipeline's newest runs are read: each lists every task key it
    /// used (32 bytes a task), and older ones have been superseded for nearly every task.
    const RUNS: usize = 16;

    fn read(store: &crate::Store, runs: &[crate::RunRecord], dataset: &str) -> Result<RunRanks> {
        let mut ranks = RunRanks { ours: HashMap::new(), others: HashSet::new() };
        let newest = &runs[runs.len().saturating_sub(Self::RUNS)..];
        for (i, r) in newest.iter().enumerate() {
            let keys = crate::gc::read_keys(&crate::runs::keys_path(store, &r.id))?;
            if r.read_dataset(dataset) {
                ranks.ours.extend(keys.into_iter().map(|k| (k, i + 1)));
            } else {
                ranks.others.extend(keys);
            }
        }
        Ok(ranks)
    }

    /// The rank of a record (0: no run of ours used it); `None` for one only runs on other
    /// datasets used, which is not this pipeline's task at all.
    fn of(&self, key: &Digest) -> Option<usize> {
        match self.ours.get(key) {
            Some(&rank) => Some(rank),
            None if self.others.contains(key) => None,
            None => Some(0),
        }
    }
}

fn first_line(s: &str) -> &str {
    s.lines().next().unwrap_or("")
}

/// `param `min_depth` changed: 1.0 -> 2.0` for each field whose canonical text differs. For a
/// task of a stage with variants (`variant`: its label), the `variants` map is compared at that
/// label only: `variant `t+2` changed: (offset:2,..) -> (..)`.
fn param_changes(old: Option<&str>, new: &str, variant: Option<&str>) -> Vec<String> {
    let Some(old) = old else { return vec!["params changed".into()] };
    let fields = |text: &str| -> (BTreeMap<String, String>, Option<String>) {
        let mut sources = dist4d_graph::source::Sources::default();
        let id = sources.add("p", text);
        match dist4d_graph::syntax::parse(text, id) {
            Ok(v) => {
                let fields = v.fields().unwrap_or(&[]);
                let own = variant.and_then(|label| {
                    let map = fields.iter().find(|f| f.name.text == "variants")?;
                    let dist4d_graph::syntax::ValueKind::Map(entries) = &map.value.kind else { return None };
                    let (_, value) = entries.iter().find(|(k, _)| k.as_str() == Some(label))?;
                    Some(sources.slice(value.span).to_string())
                });
                let all =
                    fields.iter().map(|f| (f.name.text.clone(), sources.slice(f.value.span).to_string())).collect();
                (all, own)
            }
            Err(_) => (BTreeMap::new(), None),
        }
    };
    let ((a, own_a), (b, own_b)) = (fields(old), fields(new));
    let mut out = Vec::new();
    for (k, v) in &b {
        match a.get(k) {
            Some(o) if o == v => {}
            Some(_) if k == "variants" && variant.is_some() => {
                let label = variant.unwrap_or_default();
                match (own_a.as_deref(), own_b.as_deref()) {
                    (Some(o), Some(n)) if o != n => out.push(format!("variant `{label}` changed: {o} -> {n}")),
                    (None, Some(_)) => out.push(format!("variant `{label}` is new")),
                    _ => {}
                }
            }
            Some(o) => out.push(format!("param `{k}` changed: {o} -> {v}")),
            None => out.push(format!("param `{k}` is new: {v}")),
        }
    }
    for k in a.keys().filter(|k| !b.contains_key(*k)) {
        out.push(format!("param `{k}` was removed"));
    }
    if out.is_empty() {
        out.push("params or the stage's worker (its name, version or weights) changed".into());
    }
    out
}
