//! dist4d-stages: every stage, each a module with its params, ports and a plain function that
//! does the work, grouped by family (`curation`, `novel_view`, `generation`, `occupancy`, `eval`,
//! `output`); the library modules the families share (`views`, `lift`, `camera`, `polygons`, ..);
//! and the registry that offers them with the dataset readers to the graph and the runtime.

pub mod box_sum;
pub mod camera;
pub mod curation;
pub mod eval;
pub mod generation;
pub mod hull;
pub mod lift;
pub mod lone_points;
pub mod middlebury;
pub mod model_worker;
pub mod novel_view;
pub mod occupancy;
pub mod output;
pub mod polygons;
pub mod reference;
pub mod stage;
pub mod stereo;
pub mod views;
pub mod voxel_hash;

use anyhow::{anyhow, Context, Result};
use dist4d_datasets::{DatasetDef, DATASETS};
use dist4d_graph::{Catalog, DatasetSchema, Pipeline, StageSchema};
use dist4d_runtime::{Dataset, Operator};
use stage::StageDef;

/// Every stage kind and dataset kind dist4d has.
pub struct Registry {
    stages: Vec<StageDef>,
    /// Each dataset kind's schema beside how to open it, in [`DATASETS`] order.
    datasets: Vec<(DatasetSchema, &'static DatasetDef)>,
}

impl Default for Registry {
    fn default() -> Self {
        Registry {
            stages: [
                curation::stages(),
                eval::stages(),
                generation::stages(),
                novel_view::stages(),
                occupancy::stages(),
                output::stages(),
            ]
            .into_iter()
            .flatten()
            .collect(),
            datasets: DATASETS.iter().map(|d| ((d.schema)(), d)).collect(),
        }
    }
}

impl Registry {
    /// Every dataset kind, in registry order.
    pub fn dataset_schemas(&self) -> impl Iterator<Item = &DatasetSchema> {
        self.datasets.iter().map(|(s, _)| s)
    }

    pub fn stage_defs(&self) -> &[StageDef] {
        &self.stages
    }

    /// What a look at the pipeline's dataset root finds wrong before opening it: it does not
    /// exist, or it holds another kind's data (the message says which, and how to read it).
    pub fn dataset_root_problem(&self, p: &Pipeline) -> Option<dist4d_datasets::registry::RootProblem> {
        let (_, def) = self.datasets.iter().find(|(s, _)| s.kind == p.dataset.kind)?;
        let root = (def.root)(&p.dataset.config)?;
        dist4d_datasets::registry::root_problem(DATASETS, &p.dataset.kind, &root)
    }

    /// Opens the dataset a pipeline names (with the pipeline's variants under its items, when
    /// a stage declares them).
    pub fn open_dataset(&self, p: &Pipeline) -> Result<Box<dyn Dataset>> {
        let inner = self.open_dataset_only(p)?;
        if p.variants.is_empty() {
            return Ok(inner);
        }
        Ok(Box::new(dist4d_runtime::WithVariants { inner, depth: p.dims.len() - 1, labels: p.variants.clone() }))
    }

    fn open_dataset_only(&self, p: &Pipeline) -> Result<Box<dyn Dataset>> {
        let kind = p.dataset.kind.as_str();
        let (_, def) =
            self.datasets.iter().find(|(s, _)| s.kind == kind).ok_or_else(|| anyhow!("unknown dataset kind {kind}"))?;
        if let Some(problem) = self.dataset_root_problem(p) {
            anyhow::bail!("{problem}");
        }
        let opened = (def.open)(&p.dataset.config)?;
        for w in &opened.warnings {
            eprintln!("warning: {w}");
        }
        for w in occupancy::geometry_only_warnings(p, opened.has_point_labels, &opened.description) {
            eprintln!("warning: {w}");
        }
        for w in occupancy::encode_occ3d_waymo::grid_mismatch_warnings(p) {
            eprintln!("warning: {w}");
        }
        for w in curation::ego_mask::unmasked_warnings(p, opened.dataset.as_ref()) {
            eprintln!("warning: {w}");
        }
        Ok(opened.dataset)
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
                        .find(|d| d.schema.kind == s.kind)
                        .ok_or_else(|| anyhow!("unknown stage kind {}", s.kind))?;
                    let wired: Vec<&str> = s.inputs.iter().map(|i| i.port.as_str()).collect();
                    def.build(&s.params, &wired).with_context(|| format!("stage `{}`", n.name)).map(Some)
                }
            })
            .collect()
    }
}

impl Catalog for Registry {
    fn stage(&self, kind: &str) -> Option<&StageSchema> {
        self.stages.iter().map(|s| &s.schema).find(|s| s.kind == kind)
    }
    fn stage_kinds(&self) -> Vec<&'static str> {
        self.stages.iter().map(|s| s.schema.kind).collect()
    }
    fn dataset(&self, kind: &str) -> Option<&DatasetSchema> {
        self.dataset_schemas().find(|d| d.kind == kind)
    }
    fn dataset_kinds(&self) -> Vec<&'static str> {
        self.dataset_schemas().map(|d| d.kind).collect()
    }
    fn exportable(&self, ty: &str) -> bool {
        ty == dist4d_types::artifact::File::TYPE
    }
}

use dist4d_types::artifact::Artifact as _;

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_graph::source::Sources;
    use dist4d_graph::syntax::parse;
    use dist4d_graph::ParamsError;

    /// The range problems of `kind`'s params written as `text`, as `field: message` lines.
    fn problems(catalog: &Registry, kind: &str, text: &str) -> Vec<String> {
        let mut sources = Sources::default();
        let id = sources.add("t", text);
        let value = parse(text, id).unwrap();
        let spec = match catalog.stage(kind) {
            Some(s) => &s.params,
            None => &catalog.dataset(kind).unwrap().config,
        };
        match spec.check(Some(&value)) {
            Ok(_) => Vec::new(),
            Err(ParamsError::Range(p)) => p.iter().map(|p| format!("{}: {}", p.field, p.message)).collect(),
            Err(ParamsError::Type(e)) => panic!("{kind} {text}: {e}"),
        }
    }

    #[test]
    fn every_default_is_in_range() {
        let r = Registry::default();
        for kind in r.stage_kinds() {
            assert!(r.stage(kind).unwrap().params.check(None).is_ok(), "{kind}");
        }
        for kind in r.dataset_kinds() {
            assert!(r.dataset(kind).unwrap().config.check(None).is_ok(), "{kind}");
        }
    }

    #[test]
    fn params_that_size_buffers_or_that_every_task_would_refuse_are_out_of_range() {
        let r = Registry::default();
        // (kind, params, the fields at fault)
        let cases: &[(&str, &str, &[&str])] = &[
            ("MultiViewStereo", "(max_planes: 1000000000, plane_step_px: 0.000001)", &["max_planes", "plane_step_px"]),
            ("MultiViewStereo", "(downscale: 0)", &["downscale"]),
            ("MultiViewStereo", "(min_depth: 50, max_depth: 10)", &["min_depth"]),
            ("MultiViewStereo", "(p1: 9, p2: 8)", &["p1"]),
            ("MultiViewStereo", "(p2: 60000)", &["p2"]),
            ("MultiViewStereo", "(uniqueness: 1.0, consistency_px: inf)", &["uniqueness", "consistency_px"]),
            ("AggregateLidar", "(holdout: NaN)", &["holdout"]),
            ("AggregateLidar", "(holdout: 2)", &["holdout"]),
            ("AggregateLidar", "(ego_box_min: [0, 0, 5], min_distance: -1)", &["min_distance", "ego_box_min"]),
            ("FusePoints", "(cell_px: 0)", &["cell_px"]),
            ("FusePoints", "(cell_px: 100000)", &["cell_px"]),
            ("CompleteDepth", "(grow: inf, sky_depth: 0, row_gap: 4000000000)", &["row_gap", "sky_depth", "grow"]),
            (
                "HiddenPointRemoval",
                "(radius_factor: 0.5, restore_window: [1, 1e9])",
                &["radius_factor", "restore_window"],
            ),
            ("StaticMvsPoints", "(support_radius: 100000)", &["support_radius"]),
            ("StaticMvsPoints", "(support_radius: 1, min_support: 9)", &["min_support"]),
            ("StaticMvsPoints", "(min_confidence: -0.1, voxel: NaN)", &["min_confidence", "voxel"]),
            ("DepthSheet", "(scale: 1000)", &["scale"]),
            ("DepthSheet", "(scale: 0)", &["scale"]),
            ("DepthSheet", "(error_cap: 0, sky_threshold: NaN)", &["sky_threshold", "error_cap"]),
            ("EncodeDepth", "(preview_max_depth: 0)", &["preview_max_depth"]),
            ("EvalDepth", "(min_depth: 0)", &["min_depth"]),
            // Below the scored range's end and the structure range's end: two relations broken.
            ("EvalDepth", "(min_depth: 90)", &["min_depth", "min_depth"]),
            // The edge search visits pi * max^2 offsets per edge pixel.
            ("EvalDepth", "(structure_depth: 120, edge_max_distance: 1000)", &["structure_depth", "edge_max_distance"]),
            ("EvalDepth", "(edge_low_step: 1, edge_high_step: 1.05)", &["edge_low_step"]),
            ("DepthPrompt", "(max_depth: NaN)", &["max_depth"]),
            ("ProjectLidar", "(border_px: -1)", &["border_px"]),
            (
                "AboveLidarFov",
                "(outlier_share: 1, top_elevation_deg: Some(91))",
                &["top_elevation_deg", "outlier_share"],
            ),
            ("NuScenes", "(cameras: [])", &["cameras"]),
            ("NuScenes", r#"(cameras: ["CAM_FRONT", "CAM_FRONT"])"#, &["cameras"]),
            ("NuScenes", r#"(cameras: ["../x", "a/b", "a\\b", ".", "..", "", "/abs", "n\u{0}ul"])"#, &["cameras"; 8]),
            ("NuScenes", r#"(lidar: "..", version: "../../etc")"#, &["lidar", "version"]),
            ("Dgp", r#"(cameras: ["CAMERA_01", "../CAMERA_05"], lidar: "")"#, &["cameras", "lidar"]),
        ];
        for (kind, text, fields) in cases {
            let found = problems(&r, kind, text);
            let at: Vec<&str> = found.iter().map(|p| p.split(':').next().unwrap()).collect();
            assert_eq!(&at, fields, "{kind} {text}: {found:?}");
        }
        // What the shipped pipelines use, and the sane edges, pass.
        for (kind, text) in [
            ("MultiViewStereo", "(downscale: 1, max_planes: 1024, plane_step_px: 0.5, p1: 8, p2: 8)"),
            ("AggregateLidar", "(holdout: 0.2)"),
            ("AggregateLidar", "(holdout: 1)"),
            ("FusePoints", "(cell_px: 1)"),
            ("StaticMvsPoints", "(support_radius: 1, min_support: 8)"),
            // Above every confidence: MVS points off.
            ("StaticMvsPoints", "(min_confidence: 2)"),
            ("NuScenes", r#"(cameras: ["CAM_FRONT"], version: "v1.0-trainval")"#),
        ] {
            assert_eq!(problems(&r, kind, text), Vec::<String>::new(), "{kind} {text}");
        }
    }
}
