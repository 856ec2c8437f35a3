//! dist4d-stages: the driving domain. Geometry, dataset readers, and every stage, each a module
//! with its params, ports and a plain function that does the work.

pub mod artifact;
pub mod camera;
pub mod dataset_checks;
pub mod dgp;
pub mod files;
pub mod geometry;
pub mod hull;
pub mod middlebury;
pub mod nuscenes;
pub mod sidecar;
pub mod stage;
pub mod stereo;
pub mod synth;
pub mod stages {
    pub mod above_fov;
    pub mod aggregate;
    pub mod complete;
    pub mod encode;
    pub mod eval;
    pub mod fuse;
    pub mod hpr;
    pub mod mvs;
    pub mod mvs_points;
    pub mod nearest_fill;
    pub mod project_lidar;
    pub mod prompt;
}

use anyhow::{anyhow, Context, Result};
use dist4d_graph::{Catalog, DatasetSchema, Pipeline, StageSchema};
use dist4d_runtime::{Dataset, Operator};
use stage::{parse_canonical, StageDef};

/// Every stage kind and dataset kind dist4d has.
pub struct Registry {
    stages: Vec<StageDef>,
    nuscenes: nuscenes::NuScenesSchema,
    dgp: dgp::DgpSchema,
}

impl Default for Registry {
    fn default() -> Self {
        Registry {
            stages: vec![
                stages::above_fov::def(),
                stages::aggregate::def(),
                stages::complete::def(),
                stages::eval::def(),
                stages::fuse::def(),
                stages::hpr::def(),
                stages::mvs::def(),
                stages::mvs_points::def(),
                stages::nearest_fill::def(),
                stages::prompt::def(),
                stages::project_lidar::def(),
                stages::encode::encode_depth(),
                stages::encode::encode_points(),
                stages::encode::depth_sheet_def(),
            ],
            nuscenes: nuscenes::NuScenesSchema::default(),
            dgp: dgp::DgpSchema::default(),
        }
    }
}

impl Registry {
    pub fn stage_defs(&self) -> &[StageDef] {
        &self.stages
    }

    /// Opens the dataset a pipeline names.
    pub fn open_dataset(&self, p: &Pipeline) -> Result<Box<dyn Dataset>> {
        match p.dataset.kind.as_str() {
            "NuScenes" => {
                let ds = nuscenes::NuScenes::open(parse_canonical(&p.dataset.config)?)
                    .context("opening the NuScenes dataset")?;
                for w in &ds.warnings {
                    eprintln!("warning: {w}");
                }
                Ok(Box::new(ds))
            }
            "Dgp" => {
                Ok(Box::new(dgp::Dgp::open(parse_canonical(&p.dataset.config)?).context("opening the DGP dataset")?))
            }
            other => Err(anyhow!("unknown dataset kind {other}")),
        }
    }

    /// One operator per pipeline node (None for sources).
    pub fn operators(&self, p: &Pipeline) -> Result<Vec<Option<Box<dyn Operator>>>> {
        p.nodes
            .iter()
            .map(|n| match n.stage() {
                None => Ok(None),
                Some(s) => {
                    let def = self
                        .stages
                        .iter()
                        .find(|d| d.kind == s.kind)
                        .ok_or_else(|| anyhow!("unknown stage kind {}", s.kind))?;
                    let wired: Vec<&str> = s.inputs.iter().map(|i| i.port.as_str()).collect();
                    def.build(&s.params, &wired).with_context(|| format!("stage `{}`", n.name)).map(Some)
                }
            })
            .collect()
    }
}

impl Catalog for Registry {
    fn stage(&self, kind: &str) -> Option<&dyn StageSchema> {
        self.stages.iter().find(|s| s.kind == kind).map(|s| s as &dyn StageSchema)
    }
    fn stage_kinds(&self) -> Vec<&'static str> {
        self.stages.iter().map(|s| s.kind).collect()
    }
    fn dataset(&self, kind: &str) -> Option<&dyn DatasetSchema> {
        match kind {
            "NuScenes" => Some(&self.nuscenes),
            "Dgp" => Some(&self.dgp),
            _ => None,
        }
    }
    fn dataset_kinds(&self) -> Vec<&'static str> {
        vec!["NuScenes", "Dgp"]
    }
    fn exportable(&self, ty: &str) -> bool {
        ty == artifact::File::TYPE
    }
}

use artifact::Artifact as _;
