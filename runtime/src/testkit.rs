//! A synthetic dataset and toy stages, for the runtime's tests and benchmarks.
//!
//! `Grid(scenes, frames, cameras)` has sources `frame_value` (per frame) and `camera_value`
//! (per camera) whose content is a function of the item and a version that tests can bump (as if
//! a raw file changed). Stages: `Echo` (hash of its input, optionally padded to `size` bytes),
//! `Merge` (hash of several inputs), `ToFile` (an exportable copy), `FromFile` (a reader of one).

use crate::digest::{Digest, DigestBuilder};
use crate::item::{ItemKey, ItemSpace};
use crate::operator::{Artifact, Dataset, FileDigests, Made, Operator, Output, TaskContext};
use anyhow::{bail, Result};
use dist4d_graph::{Catalog, DatasetSchema, DimSpec, ParamsSpec, Pipeline, PortSpec, SourcePortSpec, StageSchema};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

#[derive(Serialize, Deserialize, Clone)]
#[serde(deny_unknown_fields, default)]
pub struct GridConfig {
    pub scenes: u32,
    pub frames: u32,
    pub cameras: u32,
    /// Scene labels, in order (`s0`, `s1`, ... past the end of the list).
    pub names: Vec<String>,
}

impl Default for GridConfig {
    fn default() -> Self {
        GridConfig { scenes: 2, frames: 4, cameras: 3, names: Vec::new() }
    }
}

pub struct Grid {
    pub config: GridConfig,
    /// (port, item) -> version; absent = 0. Bumping one is like editing a raw file.
    pub versions: Mutex<HashMap<(String, ItemKey), u64>>,
    pub loads: AtomicU64,
}

impl Grid {
    pub fn new(config: GridConfig) -> Grid {
        Grid { config, versions: Mutex::new(HashMap::new()), loads: AtomicU64::new(0) }
    }

    pub fn bump(&self, port: &str, item: ItemKey) {
        *self.versions.lock().unwrap().entry((port.to_string(), item)).or_default() += 1;
    }

    fn content(&self, port: &str, item: &ItemKey) -> Vec<u8> {
        let v = self.versions.lock().unwrap().get(&(port.to_string(), *item)).copied().unwrap_or(0);
        DigestBuilder::new("grid").str(port).bytes(&item.to_bytes()).u64(v).finish().0.to_vec()
    }
}

impl ItemSpace for Grid {
    fn count(&self, prefix: &ItemKey) -> u32 {
        match prefix.depth {
            0 => self.config.scenes,
            1 => self.config.frames,
            2 => self.config.cameras,
            _ => 0,
        }
    }
    fn label(&self, item: &ItemKey) -> String {
        let i = item.idx[item.depth as usize - 1];
        match item.depth {
            1 => self.config.names.get(i as usize).cloned().unwrap_or_else(|| format!("s{i}")),
            2 => format!("{i:03}"),
            _ => format!("cam{i}"),
        }
    }
}

impl Dataset for Grid {
    fn source_digest(&self, port: &str, item: &ItemKey, _: &dyn FileDigests) -> Result<Option<Digest>> {
        Ok(Some(Digest::of(&self.content(port, item))))
    }
    fn load_source(&self, port: &str, item: &ItemKey) -> Result<Vec<u8>> {
        self.loads.fetch_add(1, Ordering::Relaxed);
        Ok(self.content(port, item))
    }
}

#[derive(Serialize, Deserialize, Default, Clone)]
#[serde(deny_unknown_fields, default)]
pub struct EchoParams {
    /// Changes the output.
    pub salt: u32,
    /// Does not change the output (for early-cutoff tests).
    pub note: String,
    /// Pad the output to this many bytes (0: 32 bytes).
    pub size: usize,
    /// Item paths (`s0/001/cam2`) on which the task fails.
    pub fail_on: Vec<String>,
    /// Sleep this long per task (for kill tests).
    pub sleep_ms: u64,
    /// Tag the output with a type no port declares (for the runtime's output type check).
    pub mistag: bool,
    /// Item paths on which the task has nothing to make ([`crate::Made::Nothing`]).
    pub nothing_on: Vec<String>,
    /// For `Vary`: a salt per variant label (the stage runs once per variant).
    pub variants: std::collections::BTreeMap<String, u32>,
    /// Leaves its output unmade when nothing of the run reads it ([`TaskContext::unread`]).
    pub on_demand: bool,
    /// Leaves its output unmade even when it is read (for the runtime's check).
    pub never_make: bool,
}

// Test params: any value is usable.
impl dist4d_graph::Validate for EchoParams {}
impl dist4d_graph::Validate for GridConfig {}

const DIMS: [DimSpec; 3] = [
    DimSpec { name: "scene", ordered: false },
    DimSpec { name: "frame", ordered: true },
    DimSpec { name: "camera", ordered: false },
];
const PORTS: [SourcePortSpec; 2] = [
    SourcePortSpec { name: "frame_value", ty: "Bytes", grain: "frame", doc: "" },
    SourcePortSpec { name: "camera_value", ty: "Bytes", grain: "camera", doc: "" },
];

pub struct TestCatalog {
    kinds: Vec<StageSchema>,
    grid: DatasetSchema,
}

fn kind(kind: &'static str, inputs: Vec<PortSpec>, outputs: Vec<PortSpec>, grains: Vec<&'static str>) -> StageSchema {
    StageSchema {
        kind,
        version: 1,
        summary: "test stage",
        inputs,
        outputs,
        grains,
        params: ParamsSpec::of::<EchoParams>(),
        seeded: false,
        export_template_params: vec![],
        aligned_inputs: vec![],
        unused_inputs: None,
        variants: None,
    }
}

impl Default for TestCatalog {
    fn default() -> Self {
        let all = vec!["camera", "frame", "scene", "variant"];
        TestCatalog {
            kinds: vec![
                kind("Echo", vec![PortSpec::one("x", "Bytes", "")], vec![PortSpec::one("y", "Bytes", "")], all.clone()),
                StageSchema {
                    // `salt: 404`: it does not read `xs` (handed over empty, never loaded).
                    unused_inputs: Some(|p| {
                        if p.get::<EchoParams>().is_some_and(|e| e.salt == 404) {
                            vec!["xs"]
                        } else {
                            Vec::new()
                        }
                    }),
                    ..kind(
                        "Merge",
                        vec![PortSpec::many("xs", "Bytes", "")],
                        vec![PortSpec::one("y", "Bytes", "")],
                        vec!["frame", "scene", "camera"],
                    )
                },
                kind(
                    "ToFile",
                    vec![PortSpec::one("x", "Bytes", "")],
                    vec![PortSpec::one("file", "File", "")],
                    all.clone(),
                ),
                kind(
                    "FromFile",
                    vec![PortSpec::one("file", "File", "")],
                    vec![PortSpec::one("y", "Bytes", "")],
                    all.clone(),
                ),
                kind(
                    "Pair",
                    vec![PortSpec::one("x", "Bytes", "")],
                    vec![PortSpec::one("y", "Bytes", ""), PortSpec::one("z", "Bytes", "")],
                    all,
                ),
                StageSchema {
                    variants: Some(|p| {
                        p.get::<EchoParams>()
                            .and_then(|e| dist4d_graph::Variants::split(e, |e| std::mem::take(&mut e.variants)))
                    }),
                    ..kind(
                        "Vary",
                        vec![PortSpec::one("x", "Bytes", "")],
                        vec![PortSpec::one("y", "Bytes", "")],
                        vec!["variant"],
                    )
                },
            ],
            grid: DatasetSchema {
                kind: "Grid",
                summary: "synthetic grid",
                dims: DIMS.to_vec(),
                ports: PORTS.to_vec(),
                config: ParamsSpec::of::<GridConfig>(),
                path_fields: Vec::new(),
            },
        }
    }
}

impl Catalog for TestCatalog {
    fn stage(&self, kind: &str) -> Option<&StageSchema> {
        self.kinds.iter().find(|k| k.kind == kind)
    }
    fn stage_kinds(&self) -> Vec<&'static str> {
        self.kinds.iter().map(|k| k.kind).collect()
    }
    fn dataset(&self, kind: &str) -> Option<&DatasetSchema> {
        (kind == self.grid.kind).then_some(&self.grid)
    }
    fn dataset_kinds(&self) -> Vec<&'static str> {
        vec![self.grid.kind]
    }
    fn exportable(&self, ty: &str) -> bool {
        ty == "File"
    }
}

struct EchoOp {
    params: EchoParams,
    /// The names and artifact types of its output ports (one, or two for `Pair`: the same bytes
    /// each, told apart by the port's index).
    outputs: Vec<(&'static str, &'static str)>,
}

impl Operator for EchoOp {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<Artifact>]) -> Result<Made<Vec<Output>>> {
        let params = &self.params;
        if params.sleep_ms > 0 {
            std::thread::sleep(std::time::Duration::from_millis(params.sleep_ms));
        }
        if params.fail_on.iter().any(|f| f == ctx.label) {
            bail!("asked to fail on {}", ctx.label);
        }
        if params.nothing_on.iter().any(|f| f == ctx.label) {
            return Ok(Made::Nothing(format!("asked for nothing on {}", ctx.label)));
        }
        let mut b = DigestBuilder::new("echo");
        b.u64(params.salt as u64);
        if !params.variants.is_empty() {
            let i = *ctx.item.coords().last().unwrap_or(&0) as usize;
            b.u64(*params.variants.values().nth(i).unwrap_or(&0) as u64);
        }
        for input in inputs {
            for a in input {
                b.u64(a.pos as u64).bytes(&a.bytes);
            }
        }
        let d = b.finish();
        let n = if params.size == 0 { 32 } else { params.size };
        let made = |(port, (name, ty)): (usize, &(&'static str, &'static str))| {
            let ty = if params.mistag { "Mistagged" } else { *ty };
            if params.never_make || (params.on_demand && !ctx.wants(name)) {
                return Output::unmade(ty);
            }
            let d = if port == 0 { d } else { DigestBuilder::new("echo port").digest(&d).u64(port as u64).finish() };
            Output::new(ty, d.0.iter().copied().cycle().take(n).collect())
        };
        Ok(Made::Outputs(self.outputs.iter().enumerate().map(made).collect()))
    }
}

/// The grid dataset a pipeline names, with its config.
pub fn grid_of(p: &Pipeline) -> Grid {
    Grid::new(p.dataset.config.get::<GridConfig>().expect("a Grid pipeline's config is a GridConfig").clone())
}

/// Operators for a pipeline of test stages.
pub fn operators(p: &Pipeline) -> Vec<Option<Box<dyn Operator>>> {
    let catalog = TestCatalog::default();
    p.nodes
        .iter()
        .map(|n| {
            n.stage().map(|s| {
                let params = s.params.get::<EchoParams>().expect("test stages take EchoParams").clone();
                let outputs =
                    catalog.stage(&s.kind).expect("a test stage kind").outputs.iter().map(|o| (o.name, o.ty)).collect();
                Box::new(EchoOp { params, outputs }) as Box<dyn Operator>
            })
        })
        .collect()
}

/// Loads a test pipeline from text.
pub fn load(text: &str, sets: &[&str]) -> Pipeline {
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    let here = std::path::Path::new(".");
    dist4d_graph::load_str(
        "test.ron",
        text,
        std::path::Path::new("test.ron"),
        here,
        &sets,
        here,
        &TestCatalog::default(),
    )
    .unwrap_or_else(|e| panic!("{}", e.render()))
}
