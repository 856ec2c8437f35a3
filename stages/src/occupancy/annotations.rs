//! `Occ3dAnnotations`: a scene's part of Occ3D-nuScenes' `annotations.json`, with the schema of
//! the Occ3D README (CVPR2023-3D-Occupancy-Prediction, "annotations.json"): per frame (keyed by its
//! sample token, in time order) its `timestamp`, `camera_sensor` (per camera, keyed by the image's
//! `sample_data` token: `img_path`, `intrinsic`, `extrinsic` and `ego_pose`, each pose as
//! `translation` and a `[w, x, y, z]` `rotation`), the frame's `ego_pose`, `gt_path` (the
//! exported `labels.npz`, relative to the output folder) and `prev` / `next` (the neighbouring
//! frames' tokens, "" at the scene's ends; the README's comments swap the two, its converter
//! does not).
//!
//! Occ3D has one file for a whole split: `dist4d occ3d-annotations OUT` merges the scenes' parts
//! into `OUT/annotations.json` and writes the splits.

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, ImageInfo, Pose};
use dist4d_types::geometry::Se3;
use serde::{Deserialize, Serialize};
use serde_json::{json, Map, Value};
use std::collections::BTreeMap;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The export path of the frames' `labels.npz` (one of the pipeline's export templates:
    /// `{scene}` and `{frame.token}` are filled in).
    pub gt_path: String,
}

impl Default for Params {
    fn default() -> Self {
        Params { gt_path: "gts/{scene}/{frame.token}/labels.npz".into() }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.check(self.gt_path.contains("{scene}") && self.gt_path.contains("{frame.token}"), "gt_path", || {
            format!("must hold {{scene}} and {{frame.token}}, found `{}`", self.gt_path)
        });
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// every frame's token (`All("dataset.frame_token")`)
        tokens: Many<File>,
        /// every frame's ego pose (`All("dataset.lidar_pose")`), by frame like `tokens`
        poses: Many<Pose>,
        /// every camera image's info (`All("dataset.image_info")`)
        infos: Many<ImageInfo>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// JSON: `{"scene_infos": {<scene>: {<token>: {..}}}}`
        json: One<File>,
    }
}

pub struct Occ3dAnnotations(Params);

impl Stage for Occ3dAnnotations {
    const KIND: &'static str = "Occ3dAnnotations";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "a scene's part of Occ3D's annotations.json: frames, cameras, poses, gt paths, prev/next";
    const GRAINS: &'static [&'static str] = &["scene"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["tokens", "poses"]];
    const EXPORT_TEMPLATE_PARAMS: &'static [&'static str] = &["gt_path"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(Occ3dAnnotations(params))
    }

    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        ensure!(
            i.tokens.len() == i.poses.len(),
            "`tokens` and `poses` hold {} and {} frames: wire both with All(..)",
            i.tokens.len(),
            i.poses.len()
        );
        let mut frames: Vec<(i64, String, &Pose)> = Vec::new();
        for ((pt, File(t)), (pp, pose)) in i.tokens.iter().zip(&i.poses) {
            ensure!(pt == pp, "`tokens` and `poses` must be wired with the same selector");
            let token = String::from_utf8(t.clone()).context("a frame token is not UTF-8")?;
            ensure!(!token.is_empty(), "frame {pt} has no token in this dataset");
            frames.push((*pt, token, pose));
        }
        frames.sort_by_key(|f| f.0);
        // Cameras by frame label ("003" is frame 3).
        let mut cameras: BTreeMap<usize, Vec<&ImageInfo>> = BTreeMap::new();
        let mut scene = String::new();
        for (_, info) in &i.infos {
            scene.clone_from(&info.scene);
            if info.missing.is_some() {
                continue;
            }
            let frame: usize = info.frame.parse().with_context(|| format!("frame label {:?} is not a number", info.frame))?;
            cameras.entry(frame).or_default().push(info);
        }
        let pose = |s: &Se3| json!({ "translation": s.translation.to_array(), "rotation": s.wxyz() });
        let mut infos = Map::new();
        for (k, (_, token, ego)) in frames.iter().enumerate() {
            let mut sensors = Map::new();
            for info in cameras.get(&k).map(Vec::as_slice).unwrap_or_default() {
                sensors.insert(
                    info.token.clone(),
                    json!({
                        "img_path": info.file,
                        "intrinsic": info.intrinsics,
                        "extrinsic": pose(&info.camera_to_ego),
                        "ego_pose": pose(&info.ego_to_world),
                    }),
                );
            }
            let neighbour = |d: isize| {
                let j = k as isize + d;
                (j >= 0).then(|| frames.get(j as usize)).flatten().map_or(String::new(), |f| f.1.clone())
            };
            infos.insert(
                token.clone(),
                json!({
                    "timestamp": ego.timestamp_us.to_string(),
                    "camera_sensor": sensors,
                    "ego_pose": pose(&ego.ego_to_world),
                    "gt_path": self.0.gt_path.replace("{scene}", &scene).replace("{frame.token}", token),
                    "prev": neighbour(-1),
                    "next": neighbour(1),
                }),
            );
        }
        let out = json!({ "scene_infos": { scene: Value::Object(infos) } });
        Ok(Outputs { json: File(serde_json::to_vec(&out)?) }.into())
    }
}

/// Merges the scenes' parts found under `dir` (`*.json` with a `scene_infos` object) into Occ3D's
/// `annotations.json`: `train_split`, `val_split` (the scenes named in `val`, the others train)
/// and `scene_infos`.
pub fn merge(parts: &[Value], val: &[String]) -> Result<Value> {
    let mut scene_infos = Map::new();
    for p in parts {
        let infos = p["scene_infos"].as_object().context("a part without `scene_infos`")?;
        for (scene, frames) in infos {
            ensure!(!scene_infos.contains_key(scene), "scene {scene} is in two parts");
            scene_infos.insert(scene.clone(), frames.clone());
        }
    }
    for v in val {
        ensure!(scene_infos.contains_key(v), "--val names scene {v}, which no part holds");
    }
    let (val_split, train_split): (Vec<&String>, Vec<&String>) = scene_infos.keys().partition(|s| val.contains(s));
    Ok(json!({ "train_split": train_split, "val_split": val_split, "scene_infos": scene_infos }))
}
