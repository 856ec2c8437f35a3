//! Tasks under one item of the outermost dimension (an "outer item"): which (stage, item) pairs
//! exist and which upstream artifacts feed each.
//!
//! Planning is per outer item and lazy: the scheduler plans one when it has room, so memory
//! depends on the outer items in flight, not on the dataset size. The outer item is the natural
//! unit because selectors never reach across it (`All` reads every item under it).

use crate::item::{ItemKey, ItemSpace};
use anyhow::{bail, Result};
use dist4d_graph::{NodeKind, Pipeline, Selector};
use std::collections::HashMap;

/// Where one input artifact of a task comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputSrc {
    /// Output `port` of task `task` of the same plan.
    Task { task: u32, port: u16, pos: i64 },
    /// A dataset source node, read from raw files.
    Source { node: u32, item: ItemKey, pos: i64 },
}

#[derive(Clone, Debug)]
pub struct Task {
    pub node: u32,
    pub item: ItemKey,
    /// Per input port, in port order.
    pub inputs: Vec<Vec<InputSrc>>,
    /// Tasks that read this one's outputs.
    pub dependents: Vec<u32>,
    /// Upstream tasks this one waits for.
    pub upstream: u32,
}

pub struct OuterPlan {
    /// The index of the outer item along the outermost dimension.
    pub outer: u32,
    pub tasks: Vec<Task>,
}

/// The item tree seen through the run's filters: at most `limit.1` items along dimension
/// `limit.0` under each of its prefixes (see [`View::limited`]).
pub struct View<'a> {
    pub space: &'a dyn ItemSpace,
    pub limit: Option<(usize, u32)>,
}

impl<'a> View<'a> {
    /// The items of `space`, at most `limit` of them along the pipeline's ordered dimension (the
    /// first its dataset's schema declares `ordered`, [`Pipeline::ordered_dim`]): a run's
    /// "first N frames" without the engine knowing what a frame is.
    pub fn limited(p: &Pipeline, space: &'a dyn ItemSpace, limit: Option<u32>) -> Result<View<'a>> {
        let limit = match limit {
            None => None,
            Some(n) => match p.ordered_dim() {
                Some(d) => Some((d, n)),
                None => bail!(
                    "a limit of {n} items needs an ordered dimension, and the dataset's dimensions ({}) have none",
                    p.dims.iter().map(|d| d.name.as_str()).collect::<Vec<_>>().join(", ")
                ),
            },
        };
        Ok(View { space, limit })
    }

    /// Every item of `space`.
    pub fn all(space: &'a dyn ItemSpace) -> View<'a> {
        View { space, limit: None }
    }

    pub fn count(&self, prefix: &ItemKey) -> u32 {
        let n = self.space.count(prefix);
        match self.limit {
            Some((dim, limit)) if prefix.depth as usize == dim => n.min(limit),
            _ => n,
        }
    }

    /// Every item of depth `depth` under `prefix`, in key order.
    pub fn items_under(&self, prefix: ItemKey, depth: usize, out: &mut Vec<ItemKey>) {
        if prefix.depth as usize >= depth {
            out.push(prefix);
            return;
        }
        for i in 0..self.count(&prefix) {
            self.items_under(prefix.child(i), depth, out);
        }
    }

    /// Whether every coordinate of `key` exists.
    fn exists(&self, key: &ItemKey) -> bool {
        (0..key.depth as usize).all(|d| key.idx[d] < self.count(&key.prefix(d)))
    }

    /// The upstream items (of grain `up`) that `sel` picks for `item`, with their positions.
    pub fn select(&self, sel: Selector, item: ItemKey, up: usize) -> Vec<(ItemKey, i64)> {
        match sel {
            Selector::Same => vec![(item.prefix(up), 0)],
            Selector::Window { dim, before, after } => (before..=after)
                .filter_map(|delta| self.shifted(item.prefix(up), dim, delta).map(|k| (k, delta as i64)))
                .collect(),
            // Resolved to an `Offset` by the planner, which knows the variants.
            Selector::VariantOffset { .. } => Vec::new(),
            Selector::Offset { dim, by } => {
                self.shifted(item.prefix(up), dim, by).map(|k| vec![(k, by as i64)]).unwrap_or_default()
            }
            Selector::Gather { .. } => (0..self.count(&item)).map(|j| (item.child(j), j as i64)).collect(),
            Selector::Across { dim } => {
                let base = item.prefix(up);
                (0..self.count(&base.prefix(dim)))
                    .filter_map(|j| {
                        let mut k = base;
                        k.idx[dim] = j;
                        self.exists(&k).then_some((k, j as i64))
                    })
                    .collect()
            }
            Selector::All => {
                let mut all = Vec::new();
                self.items_under(item.prefix(1), up, &mut all);
                all.into_iter().enumerate().map(|(i, k)| (k, i as i64)).collect()
            }
        }
    }

    fn shifted(&self, mut key: ItemKey, dim: usize, delta: i32) -> Option<ItemKey> {
        let c = key.idx[dim] as i64 + delta as i64;
        if c < 0 || c > u32::MAX as i64 {
            return None;
        }
        key.idx[dim] = c as u32;
        self.exists(&key).then_some(key)
    }
}

impl OuterPlan {
    /// Upstream task `u` of task `d` turned out to have nothing to make: its artifacts leave
    /// `d`'s inputs. Whether one of `d`'s inputs is left with nothing (then `d` has nothing to
    /// make either).
    pub fn drop_upstream(&mut self, d: u32, u: u32) -> bool {
        let task = &mut self.tasks[d as usize];
        let mut emptied = false;
        for srcs in &mut task.inputs {
            let before = srcs.len();
            srcs.retain(|s| !matches!(s, InputSrc::Task { task, .. } if *task == u));
            emptied |= before > 0 && srcs.is_empty();
        }
        emptied
    }
}

/// Plans every task under outer item `outer`. Tasks whose single input does not exist (an `Offset`
/// past the end of a dimension) are not planned, nor are tasks that depend on them, nor the
/// items a stage's `every` skips.
pub fn plan_outer(pipeline: &Pipeline, view: &View, outer: u32) -> OuterPlan {
    let mut tasks: Vec<Task> = Vec::new();
    let mut index: HashMap<(u32, ItemKey), u32> = HashMap::new();
    let outer_key = ItemKey::new(&[outer]);
    let mut items = Vec::new();
    // Each variant's offset, found once per plan rather than once per task and input.
    let variant_offsets: Vec<i32> = (0..pipeline.variants.len()).map(|i| pipeline.variant_offset(i)).collect();
    for node_id in pipeline.stage_order() {
        let node = &pipeline.nodes[node_id];
        let stage = node.stage().expect("stage_order yields stages");
        items.clear();
        view.items_under(outer_key, node.grain, &mut items);
        'items: for &item in &items {
            // `every: n`: only every n-th item of its innermost dimension.
            if stage.every > 1 && item.coords().last().is_some_and(|&c| c % stage.every != 0) {
                continue;
            }
            let mut inputs = Vec::with_capacity(stage.inputs.len());
            let mut ups: Vec<u32> = Vec::new();
            // A variant's plan: its offset, and the optional inputs it does not read.
            let plan = stage.variants.as_ref().and_then(|v| v.plans.get(*item.coords().last().unwrap_or(&0) as usize));
            for input in &stage.inputs {
                let from = &pipeline.nodes[input.from];
                if plan.is_some_and(|p| p.unused.contains(&input.port.as_str()))
                    || stage.unused.contains(&input.port.as_str())
                {
                    inputs.push(Vec::new());
                    continue;
                }
                let selector = match input.selector {
                    Selector::VariantOffset { dim } => {
                        let v = item.coords().last().copied().unwrap_or(0) as usize;
                        let by = variant_offsets.get(v).copied().unwrap_or(0);
                        Selector::Offset { dim, by }
                    }
                    other => other,
                };
                let mut srcs = Vec::new();
                for (key, pos) in view.select(selector, item, from.grain) {
                    match &from.kind {
                        NodeKind::Source { .. } => {
                            srcs.push(InputSrc::Source { node: input.from as u32, item: key, pos })
                        }
                        NodeKind::Stage(_) => {
                            if let Some(&t) = index.get(&(input.from as u32, key)) {
                                srcs.push(InputSrc::Task { task: t, port: input.from_port as u16, pos });
                                if !ups.contains(&t) {
                                    ups.push(t);
                                }
                            }
                        }
                    }
                }
                if srcs.is_empty() || (!input.many && srcs.len() != 1) {
                    continue 'items;
                }
                inputs.push(srcs);
            }
            let id = tasks.len() as u32;
            for &u in &ups {
                tasks[u as usize].dependents.push(id);
            }
            index.insert((node_id as u32, item), id);
            tasks.push(Task { node: node_id as u32, item, inputs, dependents: Vec::new(), upstream: ups.len() as u32 });
        }
    }
    OuterPlan { outer, tasks }
}
