//! `ShiftView`: the ego pose of a camera image moved sideways, one variant per shift: the novel
//! trajectories of DiST-4D's self-supervised cycle consistency (paper Sec. 3.4: a lateral shift
//! tau in [-3, 3] m) and of its novel-view evaluation (Table 5: +-1, +-2, +-4 m). A shift is along
//! the ego vehicle's left axis (+y: positive = left), and every camera of a frame gets the same
//! one: the rig moves together and keeps its orientation (each camera from its own ego pose, at
//! its own time). A variant gives a fixed `lateral` shift or a `range` to draw it from: the draw is
//! seeded by the frame (the item's scene and frame), the variant and `seed`, so a rerun gives the
//! same shifts and another `seed` new ones.

use dist4d_runtime::Made;
use crate::stage::{variant_of, Stage};
use anyhow::Result;
use dist4d_graph::{ParamChecks, ParamProblem, Validate, Variants};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::Pose;
use dist4d_types::rng::{mix, Rng};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// One shift.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct Shift {
    /// Metres to the ego's left (negative: right).
    pub lateral: f64,
    /// Draw the shift uniformly from `[lo, hi]` metres instead (per image, seeded).
    pub range: Option<[f64; 2]>,
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Changes every drawn shift (fixed ones stay).
    pub seed: u64,
    pub variants: BTreeMap<String, Shift>,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            seed: 0,
            variants: [("random".to_string(), Shift { lateral: 0.0, range: Some([-3.0, 3.0]) })].into_iter().collect(),
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        let labels: Vec<String> = self.variants.keys().cloned().collect();
        c.path_names("variants", &labels);
        for (label, s) in &self.variants {
            c.check(s.lateral.is_finite() && s.lateral.abs() <= 100.0, "variants", || {
                format!("`{label}`: `lateral` must be within +-100 m, found {}", s.lateral)
            });
            if let Some([lo, hi]) = s.range {
                c.check(lo.is_finite() && hi.is_finite() && lo < hi && lo >= -100.0 && hi <= 100.0, "variants", || {
                    format!("`{label}`: `range` must be [lo, hi] with lo < hi within +-100 m, found [{lo}, {hi}]")
                });
                c.check(s.lateral == 0.0, "variants", || format!("`{label}`: give `lateral` or `range`, not both"));
            }
        }
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the ego pose at the image's time
        pose: One<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the same pose moved sideways (same time)
        pose: One<Pose>,
    }
}

pub struct ShiftView(Params);

impl Stage for ShiftView {
    const KIND: &'static str = "ShiftView";
    // 2: one drawn shift per frame, shared by its cameras.
    const VERSION: u32 = 2;
    const SUMMARY: &'static str = "an image's ego pose moved sideways by a fixed or seeded lateral shift, per variant";
    const GRAINS: &'static [&'static str] = &["variant"];
    const SEEDED: bool = true;
    const VARIANTS: bool = true;
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(ShiftView(params))
    }
    fn variants(params: &Params) -> Option<Variants> {
        Variants::split(params, |p| std::mem::take(&mut p.variants))
    }
    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let (label, shift) = variant_of(ctx, &self.0.variants)?;
        let tau = match shift.range {
            Some([lo, hi]) => {
                // One draw per frame, shared by its cameras: the item's scene and frame
                // coordinates (not its camera), the variant and the seed.
                let c = ctx.item.coords();
                let mut seed = mix(self.0.seed ^ 0x5348_4946_5456_4945);
                for &x in c.iter().take(2) {
                    seed = mix(seed ^ x as u64);
                }
                // The label, not the variant's index: adding a variant leaves the others' draws.
                let label_hash = blake3::hash(label.as_bytes());
                let mut first = [0u8; 8];
                first.copy_from_slice(&label_hash.as_bytes()[..8]);
                seed = mix(seed ^ u64::from_le_bytes(first));
                Rng::new(seed).range(lo, hi)
            }
            None => shift.lateral,
        };
        Ok(Outputs { pose: shifted(&i.pose, tau) }.into())
    }
}

/// `pose` moved `tau` metres along its own left axis.
pub fn shifted(pose: &Pose, tau: f64) -> Pose {
    let mut p = pose.clone();
    p.ego_to_world.translation += pose.ego_to_world.matrix() * DVec3::new(0.0, tau, 0.0);
    p
}

/// How far `shifted` lies to the left of `pose` (the inverse of [`shifted`]).
pub fn lateral_of(pose: &Pose, shifted: &Pose) -> f64 {
    (pose.ego_to_world.matrix().transpose() * (shifted.ego_to_world.translation - pose.ego_to_world.translation)).y
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::geometry::Se3;

    #[test]
    fn a_shift_moves_the_ego_to_its_left_and_is_read_back() {
        let pose = Pose {
            ego_to_world: Se3::from_yaw(std::f64::consts::FRAC_PI_2, DVec3::new(10.0, 5.0, 0.0)),
            timestamp_us: 7,
        };
        let s = shifted(&pose, 2.0);
        // Facing +y, the ego's left is -x.
        assert!((s.ego_to_world.translation - DVec3::new(8.0, 5.0, 0.0)).length() < 1e-12);
        assert!((lateral_of(&pose, &s) - 2.0).abs() < 1e-12);
        assert_eq!(s.timestamp_us, 7);
    }
}
