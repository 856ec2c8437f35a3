//! `EncodePly`: a point cloud as a binary little-endian PLY file, the format Open3D
//! (`read_point_cloud`), CloudCompare, MeshLab and PCL open: `x y z` (float32), then `red green
//! blue` (uint8) when the cloud has colours, `intensity` (float32) when any point has one, and
//! `label` (uint8) when it has labels. Coordinates are in the cloud's own frame, as its stage
//! documents.

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::Validate;
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, PointCloud};
use serde::{Deserialize, Serialize};
use std::io::Write;

#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Params {}

impl Validate for Params {}

crate::inputs! {
    pub struct Inputs {
        /// the cloud
        points: One<PointCloud>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// binary little-endian PLY
        ply: One<File>,
    }
}

pub struct EncodePly;

impl Stage for EncodePly {
    const KIND: &'static str = "EncodePly";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "PointCloud -> binary PLY (xyz, and rgb, intensity, label when it has them)";
    const GRAINS: &'static [&'static str] = &["variant", "camera", "frame", "scene"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(_: Params) -> Result<Self> {
        Ok(EncodePly)
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        Ok(Outputs { ply: File(ply(&i.points)?) }.into())
    }
}

/// The PLY bytes of `cloud`.
pub fn ply(cloud: &PointCloud) -> Result<Vec<u8>> {
    let n = cloud.points.len();
    let rgb = !cloud.rgb.is_empty();
    let labels = !cloud.labels.is_empty();
    ensure!(!rgb || cloud.rgb.len() == n, "the cloud has {n} points and {} colours", cloud.rgb.len());
    ensure!(!labels || cloud.labels.len() == n, "the cloud has {n} points and {} labels", cloud.labels.len());
    let intensity = cloud.points.iter().any(|p| p[3] != 0.0);
    let mut out = Vec::with_capacity(256 + n * (12 + 3 * rgb as usize + 4 * intensity as usize + labels as usize));
    write!(out, "ply\nformat binary_little_endian 1.0\ncomment made by dist4d\nelement vertex {n}\n")?;
    write!(out, "property float x\nproperty float y\nproperty float z\n")?;
    if rgb {
        write!(out, "property uchar red\nproperty uchar green\nproperty uchar blue\n")?;
    }
    if intensity {
        write!(out, "property float intensity\n")?;
    }
    if labels {
        write!(out, "property uchar label\n")?;
    }
    write!(out, "end_header\n")?;
    for (k, p) in cloud.points.iter().enumerate() {
        for c in &p[..3] {
            out.extend_from_slice(&c.to_le_bytes());
        }
        if rgb {
            out.extend_from_slice(&cloud.rgb[k]);
        }
        if intensity {
            out.extend_from_slice(&p[3].to_le_bytes());
        }
        if labels {
            out.push(cloud.labels[k]);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_header_names_the_columns_the_cloud_has_and_the_body_holds_them_in_order() {
        let cloud = PointCloud {
            points: vec![[1.0, 2.0, 3.0, 0.0], [4.0, 5.0, 6.0, 0.0]],
            labels: vec![7, 9],
            rgb: vec![[10, 20, 30], [40, 50, 60]],
        };
        let bytes = ply(&cloud).unwrap();
        let end = b"end_header\n";
        let at = bytes.windows(end.len()).position(|w| w == end).unwrap() + end.len();
        let header = std::str::from_utf8(&bytes[..at]).unwrap();
        assert!(header.contains("element vertex 2\n") && header.contains("property uchar red\n"));
        assert!(header.contains("property uchar label\n") && !header.contains("intensity"), "{header}");
        let body = &bytes[at..];
        assert_eq!(body.len(), 2 * (12 + 3 + 1));
        assert_eq!(&body[..4], &1.0f32.to_le_bytes());
        assert_eq!(&body[12..16], &[10, 20, 30, 7]);
        assert_eq!(&body[16 + 8..16 + 12], &6.0f32.to_le_bytes());
        let bad = PointCloud { rgb: vec![[0, 0, 0]], ..cloud };
        assert!(ply(&bad).is_err());
    }
}
