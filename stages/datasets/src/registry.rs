//! The dataset kinds, as one list: a reader is one module that exports a [`DatasetDef`], and one
//! line in [`crate::DATASETS`]. The stage crate's registry offers them to the graph (their
//! schemas) and opens the one a pipeline names; `dist4d check` uses [`DatasetDef::recognises`] to
//! say which kind a folder holds when a pipeline names another.

use anyhow::{anyhow, Result};
use dist4d_graph::{DatasetSchema, ParamsValue};
use dist4d_runtime::Dataset;
use std::path::{Path, PathBuf};

/// A dataset kind: how pipelines declare it and how it is opened.
pub struct DatasetDef {
    /// Its kind name, config, dimensions and source ports, as the graph checks pipelines.
    pub schema: fn() -> DatasetSchema,
    /// Opens the dataset a checked config (of the schema's config type) describes.
    pub open: fn(&ParamsValue) -> Result<Opened>,
    /// The folder a checked config reads (its `root`), for the checks before opening.
    pub root: fn(&ParamsValue) -> Option<PathBuf>,
    /// Whether `folder` holds this kind's data, from a cheap look at the names in it (no table
    /// is parsed): what lets `check` say "did you mean `Dgp(..)`".
    pub recognises: fn(&Path) -> bool,
    /// Whether opening makes the root when it is not there (a generated world): then a missing
    /// root is no problem.
    pub makes_root: bool,
}

/// An opened dataset and what opening it found.
pub struct Opened {
    pub dataset: Box<dyn Dataset>,
    /// Said once per run (rows left out, parts of the source that are missing).
    pub warnings: Vec<String>,
    /// Whether its LiDAR points carry semantic labels (lidarseg): the occupancy stages say when
    /// their semantics are geometry only.
    pub has_point_labels: bool,
    /// `NuScenes at /data/nuscenes`, for messages.
    pub description: String,
}

/// The typed config a graph-checked value holds.
pub fn config<C: 'static>(checked: &ParamsValue) -> Result<&C> {
    checked
        .get::<C>()
        .ok_or_else(|| anyhow!("the dataset config was checked as another type, not {}", std::any::type_name::<C>()))
}

/// Why a root cannot be read as the dataset kind a pipeline names, from a look at the folder.
#[derive(Debug, PartialEq)]
pub enum RootProblem {
    /// Nothing is there.
    Missing(PathBuf),
    /// It holds `other`'s data (`kinds`: every dataset kind, for the message).
    OtherKind { root: PathBuf, kind: String, other: &'static str, kinds: Vec<&'static str> },
}

impl std::fmt::Display for RootProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        match self {
            RootProblem::Missing(root) => {
                write!(f, "dataset root {} does not exist (set it with --set dataset.root=PATH)", root.display())
            }
            RootProblem::OtherKind { root, kind, other, kinds } => write!(
                f,
                "dataset root {} does not hold {kind} data; it looks like {other} data: did you mean \
                 `{other}(root: \"{}\")`? (--set 'dataset={other}(root: \"{}\")'; dataset kinds: {})",
                root.display(),
                root.display(),
                root.display(),
                kinds.join(", ")
            ),
        }
    }
}

/// What is wrong with reading `root` as a `kind` dataset that a look at the folder can tell
/// (no table is parsed): it does not exist, or it holds another kind's data and not this one's.
pub fn root_problem(defs: &[DatasetDef], kind: &str, root: &Path) -> Option<RootProblem> {
    let own = defs.iter().find(|d| (d.schema)().kind == kind)?;
    if !root.exists() {
        return (!own.makes_root).then(|| RootProblem::Missing(root.to_path_buf()));
    }
    if (own.recognises)(root) {
        return None;
    }
    let kinds: Vec<&'static str> = defs.iter().map(|d| (d.schema)().kind).collect();
    let other = kinds.iter().copied().find(|&k| k != kind && recognised_as(defs, k, root))?;
    Some(RootProblem::OtherKind { root: root.to_path_buf(), kind: kind.to_string(), other, kinds })
}

fn recognised_as(defs: &[DatasetDef], kind: &str, root: &Path) -> bool {
    defs.iter().any(|d| (d.schema)().kind == kind && (d.recognises)(root))
}

/// Whether `dir` has an entry whose name satisfies `name` (unreadable folders have none).
pub(crate) fn has_entry(dir: &Path, name: impl Fn(&str) -> bool) -> bool {
    std::fs::read_dir(dir)
        .map(|entries| entries.flatten().any(|e| e.file_name().to_str().is_some_and(&name)))
        .unwrap_or(false)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::DATASETS;

    #[test]
    fn every_kind_is_listed_once_and_opens_only_its_own_config() {
        let kinds: Vec<&str> = DATASETS.iter().map(|d| (d.schema)().kind).collect();
        let mut unique = kinds.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(unique.len(), kinds.len(), "{kinds:?}");
        // A config of another type is an error, not a panic.
        let wrong = ParamsValue::new(0u32).unwrap();
        for d in DATASETS {
            let e = (d.open)(&wrong).err().expect("a u32 is no dataset config");
            assert!(format!("{e:#}").contains("checked as another type"), "{e:#}");
            assert!((d.root)(&wrong).is_none());
        }
    }

    #[test]
    fn a_missing_root_does_not_exist_and_an_empty_folder_is_left_to_the_reader() {
        let tmp = tempfile::tempdir().unwrap();
        let missing = tmp.path().join("nope");
        let p = root_problem(DATASETS, "NuScenes", &missing).unwrap().to_string();
        assert!(p.contains("does not exist") && p.contains("nope"), "{p}");
        assert_eq!(root_problem(DATASETS, "NuScenes", tmp.path()), None);
        assert_eq!(root_problem(DATASETS, "Dgp", tmp.path()), None);
        // A generated world is made where it is not.
        assert_eq!(root_problem(DATASETS, "Synth", &missing), None);
    }

    #[test]
    fn a_folder_of_another_kind_says_which_kind_it_is() {
        let tmp = tempfile::tempdir().unwrap();
        let dgp = tmp.path().join("dgp");
        std::fs::create_dir_all(&dgp).unwrap();
        std::fs::write(dgp.join("scene_dataset_v1.0.json"), "{}").unwrap();
        let p = root_problem(DATASETS, "NuScenes", &dgp).unwrap().to_string();
        assert!(p.contains("did you mean `Dgp(root: "), "{p}");
        assert!(p.contains("dataset kinds: NuScenes, Dgp, Synth"), "{p}");
        assert_eq!(root_problem(DATASETS, "Dgp", &dgp), None);
        let nus = tmp.path().join("nus");
        std::fs::create_dir_all(nus.join("v1.0-mini")).unwrap();
        std::fs::write(nus.join("v1.0-mini/scene.json"), "[]").unwrap();
        let p = root_problem(DATASETS, "Dgp", &nus).unwrap().to_string();
        assert!(p.contains("did you mean `NuScenes(root: "), "{p}");
    }
}
