//! `PosesTxt`: a scene's ego poses as DynamicCity's (CarlaSC's) `poses.txt`: one line per frame
//! (row = frame number), the 3 x 4 world-from-ego matrix row-major, as `np.loadtxt` reads it; the
//! released loader takes x, y from entries 3 and 7 and the yaw as atan2(entry 4, entry 0)
//! (`dynamic_city/utils/data_utils.py`, `get_trajectory`).

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::Result;
use dist4d_graph::Validate;
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, Pose};
use serde::{Deserialize, Serialize};
use std::fmt::Write;

#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Params {}

impl Validate for Params {}

crate::inputs! {
    pub struct Inputs {
        /// every frame's ego pose, in frame order (`All("dataset.lidar_pose")`)
        poses: Many<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// poses.txt
        txt: One<File>,
    }
}

pub struct PosesTxt;

impl Stage for PosesTxt {
    const KIND: &'static str = "PosesTxt";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "a scene's ego poses as poses.txt: a line per frame, the 3x4 world-from-ego matrix row-major";
    const GRAINS: &'static [&'static str] = &["scene"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(_: Params) -> Result<Self> {
        Ok(PosesTxt)
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let mut poses: Vec<&(i64, Pose)> = i.poses.iter().collect();
        poses.sort_by_key(|(pos, _)| *pos);
        let mut text = String::new();
        for (_, p) in poses {
            let r = p.ego_to_world.matrix();
            let t = p.ego_to_world.translation;
            let rows = [[r.x_axis.x, r.y_axis.x, r.z_axis.x, t.x], [r.x_axis.y, r.y_axis.y, r.z_axis.y, t.y], [
                r.x_axis.z, r.y_axis.z, r.z_axis.z, t.z,
            ]];
            let line: Vec<String> = rows.iter().flatten().map(|v| format!("{v:.9e}")).collect();
            writeln!(text, "{}", line.join(" "))?;
        }
        Ok(Outputs { txt: File(text.into_bytes()) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::geometry::Se3;
    use glam::DVec3;

    #[test]
    fn poses_give_x_y_and_yaw_where_the_loader_reads_them() {
        let pose = |x: f64, yaw: f64| Pose { ego_to_world: Se3::from_yaw(yaw, DVec3::new(x, 2.0, 0.0)), timestamp_us: 0 };
        let txt = PosesTxt.run(&TaskContext { item: Default::default(), seed: 0, label: "t", unread: &[] }, Inputs { poses: vec![(1, pose(5.0, 0.5)), (0, pose(3.0, 0.0))] }).unwrap().unwrap();
        let text = String::from_utf8(txt.txt.0).unwrap();
        let rows: Vec<Vec<f64>> = text.lines().map(|l| l.split(' ').map(|v| v.parse().unwrap()).collect()).collect();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].len(), 12);
        assert!((rows[0][3] - 3.0).abs() < 1e-9 && (rows[1][3] - 5.0).abs() < 1e-9 && (rows[1][7] - 2.0).abs() < 1e-9);
        assert!((rows[1][4].atan2(rows[1][0]) - 0.5).abs() < 1e-9, "yaw = atan2(entry 4, entry 0)");
    }
}
