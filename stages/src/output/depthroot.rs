//! `nus_sampletoken2depthroot.json`, the index DiST-4D's loaders start from: sample token ->
//! the folder (relative to the depth root) holding `<CAMERA>/refined_depth.npz` and
//! `semantic_oneformer.npz`. Made from the files an export wrote (`pipelines/dist4d_layout.ron`),
//! so it lists exactly the samples that have them, keyframes and 12 Hz samples alike, whatever
//! shards or runs wrote them.

use anyhow::{anyhow, bail, Context, Result};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

pub const INDEX: &str = "nus_sampletoken2depthroot.json";
const DEPTH_FILE: &str = "refined_depth.npz";

/// What [`write_depthroot`] indexed.
#[derive(Debug)]
pub struct DepthRoots {
    pub samples: usize,
    pub files: usize,
}

/// The index of the `<relative root>/<CAMERA>/refined_depth.npz` files under `out`: each sample
/// token (the relative root's last folder) to its relative root, `/`-separated without a leading
/// slash (the loaders join it to the root as a path, or concatenate it to a root that ends in `/`).
pub fn depth_roots(out: &Path) -> Result<(BTreeMap<String, String>, usize)> {
    let mut roots: BTreeMap<String, String> = BTreeMap::new();
    let mut files = 0;
    let mut stack = vec![out.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).with_context(|| format!("reading {}", dir.display()))? {
            let path = entry.with_context(|| format!("reading {}", dir.display()))?.path();
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.file_name().and_then(|n| n.to_str()) != Some(DEPTH_FILE) {
                continue;
            }
            let rel = path.strip_prefix(out).map_err(|_| anyhow!("{} is outside {}", path.display(), out.display()))?;
            let parts: Vec<&str> = rel.iter().map(|p| p.to_str().unwrap_or("")).collect();
            // <relative root (at least the token)>/<CAMERA>/refined_depth.npz
            if parts.len() < 3 || parts.iter().any(|p| p.is_empty()) {
                bail!("{}: not <relative root>/<CAMERA>/{DEPTH_FILE} (DiST-4D's layout)", path.display());
            }
            let root = parts[..parts.len() - 2].join("/");
            let token = parts[parts.len() - 3].to_string();
            if let Some(other) = roots.get(&token).filter(|r| **r != root) {
                bail!("sample {token} has depth under two roots, {other} and {root}: one sample, one folder");
            }
            roots.insert(token, root);
            files += 1;
        }
    }
    Ok((roots, files))
}

/// Writes `out/nus_sampletoken2depthroot.json` (whole or not at all).
pub fn write_depthroot(out: &Path) -> Result<DepthRoots> {
    let (roots, files) = depth_roots(out)?;
    if roots.is_empty() {
        bail!(
            "{} holds no <relative root>/<CAMERA>/{DEPTH_FILE}: run pipelines/dist4d_layout.ron with --out there first",
            out.display()
        );
    }
    let target = out.join(INDEX);
    let tmp = out.join(format!(".{INDEX}.tmp-{}", std::process::id()));
    let written = (|| -> Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(&serde_json::to_vec_pretty(&roots)?)?;
        f.sync_all()?;
        Ok(std::fs::rename(&tmp, &target)?)
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(e).with_context(|| format!("writing {}", target.display()));
    }
    Ok(DepthRoots { samples: roots.len(), files })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_map_to_their_folders_and_strays_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        for rel in ["scene-1/tok_a/CAM_FRONT", "scene-1/tok_a/CAM_BACK", "scene-2/tok_b1/CAM_FRONT"] {
            std::fs::create_dir_all(dir.path().join(rel)).unwrap();
            std::fs::write(dir.path().join(rel).join(DEPTH_FILE), b"x").unwrap();
        }
        let r = write_depthroot(dir.path()).unwrap();
        assert_eq!((r.samples, r.files), (2, 3));
        let index: BTreeMap<String, String> =
            serde_json::from_slice(&std::fs::read(dir.path().join(INDEX)).unwrap()).unwrap();
        assert_eq!(index["tok_a"], "scene-1/tok_a");
        assert_eq!(index["tok_b1"], "scene-2/tok_b1");
        std::fs::create_dir_all(dir.path().join("scene-3/tok_a/CAM_FRONT")).unwrap();
        std::fs::write(dir.path().join("scene-3/tok_a/CAM_FRONT").join(DEPTH_FILE), b"x").unwrap();
        let e = write_depthroot(dir.path()).unwrap_err().to_string();
        assert!(e.contains("tok_a") && e.contains("two roots"), "{e}");
    }
}
