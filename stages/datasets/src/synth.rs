//! `Synth(..)`: the synthetic world as a dataset kind. A pipeline names the world (seed, size,
//! clock) instead of a folder `dist4d synth` wrote first: the first open generates it into `root`
//! (atomically: a partial folder renamed into place), later opens find the same world there and
//! read it as they are; a folder holding another world is refused. The files are a nuScenes v1.0
//! dataset with its exact ground truth (`groundtruth/`), read by the nuScenes reader, so every
//! port, including `gt_depth` and `synth_world`, is the one `NuScenes(root: ..)` gives on them.
//!
//! `--set 'dataset=Synth(seed: 7)'` runs a shipped pipeline on a held-out world in one line.

use crate::nuscenes::{FrameMode, NuScenes, NuScenesConfig};
use anyhow::{Context, Result};
use dist4d_graph::{DatasetSchema, ParamsSpec, ParamsValue};
use dist4d_synth::SynthConfig;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Serialize, Deserialize, Clone, Debug)]
#[serde(deny_unknown_fields, default)]
pub struct SynthDatasetConfig {
    /// Where the world's files are kept: made on the first open; relative paths are resolved
    /// against the pipeline file's folder. Unset: a folder named by the settings under `data/`
    /// of the working directory, so that every world has its own.
    pub root: Option<String>,
    pub seed: u64,
    pub scenes: u32,
    /// Keyframes (2 Hz samples) per scene.
    pub keyframes: u32,
    /// Image size (intrinsics scale with it).
    pub width: u32,
    pub height: u32,
    /// Write the 20 Hz LiDAR sweeps between keyframes (for `frames: Sweeps`).
    pub lidar_sweeps: bool,
    /// Write the 12 Hz camera images between keyframes (for `frames: Camera`).
    pub camera_sweeps: bool,
    /// The clock: `Keyframes`, `Sweeps` or `Camera`, as for `NuScenes(..)`.
    pub frames: FrameMode,
}

impl Default for SynthDatasetConfig {
    fn default() -> Self {
        SynthDatasetConfig {
            root: None,
            seed: 0,
            scenes: 1,
            keyframes: 4,
            width: 640,
            height: 360,
            lidar_sweeps: true,
            camera_sweeps: false,
            frames: FrameMode::Keyframes,
        }
    }
}

impl SynthDatasetConfig {
    /// The folder of the world: `root`, or `data/synth-seed7-1x4-640x360-sweeps` named by the
    /// settings that change its files (not `frames`, which reads the same files another way).
    pub fn root(&self) -> PathBuf {
        match &self.root {
            Some(root) => PathBuf::from(root),
            None => PathBuf::from(format!(
                "data/synth-seed{}-{}x{}-{}x{}{}{}",
                self.seed,
                self.scenes,
                self.keyframes,
                self.width,
                self.height,
                if self.lidar_sweeps { "-sweeps" } else { "" },
                if self.camera_sweeps { "-12hz" } else { "" }
            )),
        }
    }

    /// The generator's config of this world.
    pub fn world(&self) -> SynthConfig {
        SynthConfig {
            seed: self.seed,
            scenes: self.scenes,
            keyframes: self.keyframes,
            width: self.width,
            height: self.height,
            lidar_sweeps: self.lidar_sweeps,
            camera_sweeps: self.camera_sweeps,
            ..SynthConfig::default()
        }
    }
}

impl dist4d_graph::Validate for SynthDatasetConfig {
    fn validate(&self) -> Vec<dist4d_graph::ParamProblem> {
        let mut checks = dist4d_graph::ParamChecks::new();
        // Bounded so that a typo cannot ask for terabytes: 100 scenes x 400 keyframes at 4K.
        checks
            .count("scenes", self.scenes as u64, 1, 100)
            .count("keyframes", self.keyframes as u64, 1, 400)
            .count("width", self.width as u64, 16, 4096)
            .count("height", self.height as u64, 16, 4096)
            .check(self.frames != FrameMode::Sweeps || self.lidar_sweeps, "frames", || {
                "frames: Sweeps needs the LiDAR sweeps (lidar_sweeps: true)".into()
            })
            .check(self.frames != FrameMode::Camera || self.camera_sweeps, "frames", || {
                "frames: Camera needs the 12 Hz camera images (camera_sweeps: true)".into()
            })
            .done()
    }
}

/// The `Synth(..)` dataset kind.
pub const DATASET: crate::DatasetDef =
    crate::DatasetDef { schema, open: open_checked, root: root_of, recognises, makes_root: true };

fn open_checked(checked: &ParamsValue) -> Result<crate::Opened> {
    let config = crate::registry::config::<SynthDatasetConfig>(checked)?;
    let root = config.root();
    let made =
        dist4d_synth::write_dataset(&config.world(), &root, &|m| eprintln!("synth: {m}")).with_context(|| {
            format!("making the synthetic world of dataset Synth(seed: {}) in {}", config.seed, root.display())
        })?;
    if let Some(s) = made {
        eprintln!(
            "synth: {} written ({} scenes, {} samples, {} camera images) in {:.1}s",
            root.display(),
            s.scenes,
            s.samples,
            s.camera_images,
            s.seconds
        );
    }
    let ds = NuScenes::open(NuScenesConfig {
        root: root.display().to_string(),
        frames: config.frames,
        ..NuScenesConfig::default()
    })
    .with_context(|| format!("reading the synthetic world in {}", root.display()))?;
    Ok(crate::Opened {
        description: format!("Synth(seed: {}) at {}", config.seed, root.display()),
        warnings: ds.warnings.clone(),
        has_point_labels: ds.has_point_labels,
        dataset: Box::new(crate::surround::Surround(ds)),
    })
}

fn root_of(checked: &ParamsValue) -> Option<PathBuf> {
    checked.get::<SynthDatasetConfig>().map(SynthDatasetConfig::root)
}

/// A folder `dist4d synth` wrote: its world's config in `groundtruth/synth.json`.
fn recognises(folder: &Path) -> bool {
    folder.join(dist4d_synth::GROUND_TRUTH_DIR).join("synth.json").is_file()
}

pub fn schema() -> DatasetSchema {
    DatasetSchema {
        kind: "Synth",
        summary:
            "the synthetic street world, generated into `root` on first use (nuScenes files with exact ground truth)",
        dims: crate::surround::DIMS.to_vec(),
        ports: crate::surround::PORTS.to_vec(),
        config: ParamsSpec::of::<SynthDatasetConfig>(),
        path_fields: vec!["root"],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn checked(config: SynthDatasetConfig) -> ParamsValue {
        ParamsValue::new(config).unwrap()
    }

    #[test]
    fn the_first_open_makes_the_world_and_later_opens_read_it_as_it_is() {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("w");
        let config = SynthDatasetConfig {
            root: Some(root.display().to_string()),
            keyframes: 2,
            width: 64,
            height: 36,
            lidar_sweeps: false,
            ..Default::default()
        };
        let opened = (DATASET.open)(&checked(config.clone())).unwrap();
        assert_eq!(opened.dataset.count(&dist4d_runtime::ItemKey::new(&[])), 1);
        assert_eq!(opened.dataset.count(&dist4d_runtime::ItemKey::new(&[0])), 2);
        assert!(recognises(&root));
        let stamp = std::fs::metadata(root.join("v1.0-mini/scene.json")).unwrap().modified().unwrap();
        (DATASET.open)(&checked(config.clone())).unwrap();
        assert_eq!(std::fs::metadata(root.join("v1.0-mini/scene.json")).unwrap().modified().unwrap(), stamp);
        // Another world in the same folder is refused, naming both.
        let e = (DATASET.open)(&checked(SynthDatasetConfig { seed: 5, ..config })).err().unwrap();
        let e = format!("{e:#}");
        assert!(e.contains("Synth(seed: 5)") && e.contains("other settings"), "{e}");
    }

    #[test]
    fn worlds_without_a_root_each_get_their_own_folder() {
        let seven = SynthDatasetConfig { seed: 7, ..Default::default() };
        assert_eq!(seven.root(), PathBuf::from("data/synth-seed7-1x4-640x360-sweeps"));
        let roots: std::collections::HashSet<PathBuf> = [
            SynthDatasetConfig::default(),
            seven.clone(),
            SynthDatasetConfig { keyframes: 8, ..seven.clone() },
            SynthDatasetConfig { camera_sweeps: true, ..seven.clone() },
        ]
        .iter()
        .map(SynthDatasetConfig::root)
        .collect();
        assert_eq!(roots.len(), 4);
        // The clock reads the same files.
        assert_eq!(SynthDatasetConfig { frames: FrameMode::Sweeps, ..seven.clone() }.root(), seven.root());
    }

    #[test]
    fn a_clock_without_its_files_is_a_config_error() {
        let problems =
            |c: SynthDatasetConfig| dist4d_graph::Validate::validate(&c).iter().map(|p| p.field).collect::<Vec<_>>();
        assert_eq!(problems(SynthDatasetConfig { frames: FrameMode::Camera, ..Default::default() }), ["frames"]);
        assert!(problems(SynthDatasetConfig { frames: FrameMode::Camera, camera_sweeps: true, ..Default::default() })
            .is_empty());
        assert_eq!(problems(SynthDatasetConfig { scenes: 0, width: 8, ..Default::default() }), ["scenes", "width"]);
    }
}
