//! `OccupancySheet`: a window of occupancy frames on one image, to see a sequence the way a 4D
//! model sees it: the frames' bird's-eye views ([`super::preview`]) in rows of `columns`, in time
//! order, one sheet per window start (the pipeline's `every` on the stage, as the DiT's windows).

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::Image;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Frames per window; wire `views` with `Window(.., frame, 0, frames - 1)`.
    pub frames: u32,
    /// Views per row.
    pub columns: u32,
}

impl Default for Params {
    fn default() -> Self {
        Params { frames: 16, columns: 4 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.count("frames", self.frames as u64, 1, 1024).count(
            "columns",
            self.columns as u64,
            1,
            64,
        );
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the window's bird's-eye views (`Window("preview.bev", frame, 0, 15)`)
        views: Many<Image>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the sheet
        sheet: One<Image>,
    }
}

pub struct OccupancySheet(Params);

impl Stage for OccupancySheet {
    const KIND: &'static str = "OccupancySheet";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "a window of occupancy frames' bird's-eye views on one sheet, in time order";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(OccupancySheet(params))
    }

    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let t = self.0.frames as usize;
        let views = crate::or_nothing!(super::window("views", &i.views, t)?);
        let (w, h) = (views[0].width as usize, views[0].height as usize);
        ensure!(views.iter().all(|v| (v.width as usize, v.height as usize) == (w, h)), "the views differ in size");
        let cols = (self.0.columns as usize).min(t);
        let rows = t.div_ceil(cols);
        let gap = 4;
        let (sw, sh) = (cols * w + (cols - 1) * gap, rows * h + (rows - 1) * gap);
        let mut rgb = vec![255u8; sw * sh * 3];
        for (k, v) in views.iter().enumerate() {
            let (x0, y0) = ((k % cols) * (w + gap), (k / cols) * (h + gap));
            for y in 0..h {
                let src = &v.rgb[3 * y * w..3 * (y + 1) * w];
                let at = 3 * ((y0 + y) * sw + x0);
                rgb[at..at + 3 * w].copy_from_slice(src);
            }
        }
        Ok(Outputs { sheet: Image { width: sw as u32, height: sh as u32, rgb } }.into())
    }
}
