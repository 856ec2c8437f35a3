//! `ClipIndex`: the training clips of a scene as JSON lines, one record per clip, for a video
//! model's loader (DiST-T trains on surround RGB-D clips at 12 Hz).
//!
//! A clip is `frames` consecutive frames (camera rounds with `frames: Camera`), clips starting
//! every `stride` frames. Its record holds, per frame and camera, everything a loader needs without
//! redoing any matching: the image (file relative to the dataset root, token, timestamp), the
//! intrinsics, camera -> ego, ego -> world at the image's time, the boxes at that time, and the
//! curated depth and its confidence (paths relative to the output folder, from the `depth` and
//! `confidence` templates, which must be the pipeline's export templates of those files: `check`
//! refuses one that no export has); and the
//! clip's ego trajectory (the first camera's ego pose at each frame). Everything comes from the
//! dataset's `image_info` port, which answers for a missing image too (a dropped frame): clips
//! holding one are left out, not the scene. A scene with no clip at all has nothing to make
//! (no file, and the run says why once) rather than an empty file nobody is told about. Record
//! layout and a numpy-only loader: docs/datasets.md, "Training clips".

use crate::stage::Stage;
use anyhow::Result;
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::{Made, TaskContext};
use dist4d_types::artifact::{File, ImageInfo};
use dist4d_types::geometry::Se3;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Frames per clip.
    pub frames: u32,
    /// Frames from one clip's start to the next's (= `frames`: clips do not overlap).
    pub stride: u32,
    /// Where the curated depth of an image is, relative to the output folder: the pipeline's
    /// export template of it (`{scene}`, `{frame}`, `{camera}` are the item's labels; a template
    /// that no export of the pipeline has is a pipeline error).
    pub depth: String,
    /// Where its confidence (the completion's support distance) is, the same way.
    pub confidence: String,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            frames: 16,
            stride: 8,
            depth: "{scene}/{camera}/{frame}_depth.npy".into(),
            confidence: "{scene}/{camera}/{frame}_support.npy".into(),
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.count("frames", self.frames as u64, 1, 100_000).count("stride", self.stride as u64, 1, 100_000);
        for (field, template) in [("depth", &self.depth), ("confidence", &self.confidence)] {
            c.check(["{scene}", "{frame}", "{camera}"].iter().all(|p| template.contains(p)), field, || {
                format!("must hold {{scene}}, {{frame}} and {{camera}} (one file per image), found `{template}`")
            });
        }
        c.done()
    }
}

fn transform(t: &Se3) -> Value {
    json!({ "translation": t.translation.to_array(), "rotation": t.wxyz() })
}

fn render(template: &str, info: &ImageInfo) -> String {
    template.replace("{scene}", &info.scene).replace("{frame}", &info.frame).replace("{camera}", &info.camera)
}

/// One image of a clip: what it is, where it is seen from, what is in it, and its curated files.
fn image_record(p: &Params, info: &ImageInfo) -> Value {
    let boxes: Vec<Value> = info
        .boxes
        .boxes
        .iter()
        .map(|b| {
            json!({
                "instance": b.instance,
                "category": b.category,
                "attributes": b.attributes,
                "center": b.center,
                "size": b.size,
                "rotation": b.rotation,
                // JSON has no NaN: an unknown velocity is null.
                "velocity": b.velocity.map(|v| v.is_finite().then_some(v)),
                "interpolated": b.interpolated,
                "extrapolated": b.extrapolated,
            })
        })
        .collect();
    let mut record = json!({
        "camera": info.camera,
        "token": info.token,
        "image": info.file,
        "timestamp_us": info.timestamp_us,
        "width": info.width,
        "height": info.height,
        "intrinsics": info.intrinsics,
        "camera_to_ego": transform(&info.camera_to_ego),
        "ego_to_world": transform(&info.ego_to_world),
        "boxes_timestamp_us": info.boxes.timestamp_us,
        "boxes": boxes,
        "depth": render(&p.depth, info),
        "confidence": render(&p.confidence, info),
    });
    // A py123d log keeps its images inside its camera files: `image` is that file, this its row.
    if let Some(row) = info.row {
        record["image_row"] = row.into();
    }
    record
}

/// The records of a scene's clips, one JSON object per line, from its camera items in order
/// (frame by frame, the cameras of a frame together, as `All(...)` gives them). A clip with a
/// missing image (a dropped frame) is left out; the others keep their numbers.
pub fn clip_index(p: &Params, images: &[ImageInfo]) -> Result<Vec<u8>> {
    // Frames in order, each with the indices of its cameras' items.
    let mut frames: Vec<(String, Vec<usize>)> = Vec::new();
    for (i, info) in images.iter().enumerate() {
        match frames.last_mut() {
            Some((label, items)) if *label == info.frame => items.push(i),
            _ => frames.push((info.frame.clone(), vec![i])),
        }
    }
    let mut out = Vec::new();
    let (length, stride) = (p.frames as usize, p.stride as usize);
    if frames.len() < length {
        return Ok(out);
    }
    for (clip, start) in (0..=frames.len() - length).step_by(stride).enumerate() {
        let window = &frames[start..start + length];
        if window.iter().flat_map(|(_, items)| items).any(|&i| images[i].missing.is_some()) {
            continue;
        }
        let trajectory: Vec<Value> = window
            .iter()
            .map(|(label, items)| {
                let first = &images[items[0]];
                json!({
                    "frame": label,
                    "camera": first.camera,
                    "timestamp_us": first.timestamp_us,
                    "ego_to_world": transform(&first.ego_to_world),
                })
            })
            .collect();
        let frame_records: Vec<Value> = window
            .iter()
            .map(|(label, items)| {
                let cameras: Vec<Value> = items.iter().map(|&i| image_record(p, &images[i])).collect();
                json!({ "frame": label, "cameras": cameras })
            })
            .collect();
        let record = json!({
            "scene": images[window[0].1[0]].scene,
            "clip": clip,
            "frames": frame_records,
            "ego_trajectory": trajectory,
        });
        serde_json::to_writer(&mut out, &record)?;
        out.push(b'\n');
    }
    Ok(out)
}

/// Why [`clip_index`] gave no clip for a scene of `images`.
fn why_no_clips(p: &Params, images: &[ImageInfo]) -> String {
    let mut frames: Vec<&str> = images.iter().map(|i| i.frame.as_str()).collect();
    frames.dedup();
    if frames.len() < p.frames as usize {
        format!("no clip: the scene has {} frame(s), fewer than a clip's {} (`frames`)", frames.len(), p.frames)
    } else {
        format!("no clip: every clip of {} frames holds a dropped image", p.frames)
    }
}

crate::inputs! {
    pub struct Inputs {
        /// every camera item's image, calibration, poses and boxes: All("dataset.image_info")
        images: Many<ImageInfo>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the clips, one JSON object per line
        jsonl: One<File>,
    }
}

/// The artifacts of a `Many` input without their positions (All gives them in item order).
fn strip<A>(mut v: Vec<(i64, A)>) -> Vec<A> {
    v.sort_by_key(|(position, _)| *position);
    v.into_iter().map(|(_, a)| a).collect()
}

pub struct ClipIndex(Params);

impl Stage for ClipIndex {
    const KIND: &'static str = "ClipIndex";
    // 2: a scene with no clip has nothing to make, instead of an empty file.
    const VERSION: u32 = 2;
    const SUMMARY: &'static str =
        "A scene's camera items -> its training clips (frames x cameras: image, calibration, poses, boxes, depth paths) as JSON lines";
    const GRAINS: &'static [&'static str] = &["scene"];
    const EXPORT_TEMPLATE_PARAMS: &'static [&'static str] = &["depth", "confidence"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(ClipIndex(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let images = strip(i.images);
        let jsonl = clip_index(&self.0, &images)?;
        if jsonl.is_empty() {
            return Ok(Made::Nothing(why_no_clips(&self.0, &images)));
        }
        Ok(Outputs { jsonl: File(jsonl) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::{Artifact, Box3D, Boxes3D};

    /// `frames` x `cameras` items as All(..) gives them, frame by frame.
    fn scene(frames: usize, cameras: usize) -> Vec<ImageInfo> {
        let mut out = Vec::new();
        for f in 0..frames {
            for c in 0..cameras {
                let t = (f * 83_333 + c * 8_000) as i64;
                let car = Box3D {
                    center: [f as f64, 5.0, 0.8],
                    size: [1.8, 4.4, 1.5],
                    rotation: [1.0, 0.0, 0.0, 0.0],
                    velocity: [f64::NAN; 3],
                    instance: "car".into(),
                    category: "vehicle.car".into(),
                    attributes: vec![],
                    num_lidar_pts: 0,
                    interpolated: true,
                    extrapolated: false,
                };
                out.push(ImageInfo {
                    scene: "s".into(),
                    frame: format!("{f:03}"),
                    camera: format!("CAM{c}"),
                    missing: None,
                    token: format!("tok{f}-{c}"),
                    file: format!("sweeps/CAM{c}/{t}.jpg"),
                    row: (c == 1).then_some(f as u64),
                    timestamp_us: t,
                    width: 1600,
                    height: 900,
                    intrinsics: Some([[500.0, 0.0, 800.0], [0.0, 500.0, 450.0], [0.0, 0.0, 1.0]]),
                    camera_to_ego: Se3::default(),
                    ego_to_world: Se3::from_wxyz_t([1.0, 0.0, 0.0, 0.0], [f as f64, 0.0, 0.0]),
                    boxes: Boxes3D { timestamp_us: t, boxes: vec![car] },
                    vehicle: String::new(),
                });
            }
        }
        out
    }

    fn records(bytes: Vec<u8>) -> Vec<Value> {
        String::from_utf8(bytes).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
    }

    #[test]
    fn clips_are_windows_of_frames_with_every_cameras_files_and_the_ego_trajectory() {
        let images = scene(7, 2);
        let p = Params { frames: 3, stride: 2, ..Params::default() };
        let clips = records(clip_index(&p, &images).unwrap());
        // Starts 0, 2, 4 (a clip from 6 would run past the 7 frames).
        assert_eq!(clips.len(), 3);
        let frame_labels = |c: &Value| -> Vec<String> {
            c["frames"].as_array().unwrap().iter().map(|f| f["frame"].as_str().unwrap().to_string()).collect()
        };
        assert_eq!(frame_labels(&clips[2]), ["004", "005", "006"]);
        let image = &clips[1]["frames"][0]["cameras"][1];
        assert_eq!(image["camera"], "CAM1");
        assert_eq!(image["token"], "tok2-1");
        // An image inside a table (a py123d camera file) names its row; a file of its own does not.
        assert_eq!(image["image_row"], 2);
        assert!(clips[1]["frames"][0]["cameras"][0].get("image_row").is_none());
        assert_eq!(image["depth"], "s/CAM1/002_depth.npy");
        assert_eq!(image["confidence"], "s/CAM1/002_support.npy");
        assert_eq!(image["timestamp_us"], 2 * 83_333 + 8_000);
        assert_eq!(image["boxes_timestamp_us"], image["timestamp_us"]);
        assert_eq!(image["ego_to_world"]["translation"][0], 2.0);
        assert!(image["boxes"][0]["velocity"][0].is_null(), "an unknown velocity is null, not NaN");
        // The trajectory: the first camera's ego pose at each frame.
        let trajectory = clips[1]["ego_trajectory"].as_array().unwrap();
        assert_eq!(trajectory.len(), 3);
        assert_eq!((trajectory[2]["frame"].as_str(), trajectory[2]["camera"].as_str()), (Some("004"), Some("CAM0")));
        // Fewer frames than a clip: no clips, and why.
        let long = Params { frames: 8, ..p.clone() };
        assert!(clip_index(&long, &images).unwrap().is_empty());
        assert_eq!(why_no_clips(&long, &images), "no clip: the scene has 7 frame(s), fewer than a clip's 8 (`frames`)");
    }

    #[test]
    fn a_dropped_image_loses_the_clips_that_hold_it_and_no_others() {
        let mut images = scene(7, 2);
        images[2 * 5 + 1].missing = Some("a dropped frame".into()); // frame 5, camera 1
        let p = Params { frames: 3, stride: 2, ..Params::default() };
        let clips = records(clip_index(&p, &images).unwrap());
        let numbers: Vec<u64> = clips.iter().map(|c| c["clip"].as_u64().unwrap()).collect();
        assert_eq!(numbers, [0, 1], "clip 2 (frames 4-6) holds it");
        let one = Params { frames: 7, ..p };
        assert!(clip_index(&one, &images).unwrap().is_empty());
        assert_eq!(why_no_clips(&one, &images), "no clip: every clip of 7 frames holds a dropped image");
    }

    #[test]
    fn image_info_survives_its_encoding() {
        let info = scene(2, 1).remove(1);
        let mut back = ImageInfo::decode(&info.encode()).unwrap();
        assert_eq!(back.boxes.boxes[0].center, info.boxes.boxes[0].center);
        assert!(back.boxes.boxes[0].velocity[0].is_nan(), "NaN, stored as null, comes back NaN");
        // (NaN is not equal to itself: the rest compared without the boxes.)
        back.boxes = Boxes3D::default();
        assert_eq!(back, ImageInfo { boxes: Boxes3D::default(), ..info });
    }

    #[test]
    fn a_path_template_must_name_every_item() {
        let bad = Params { depth: "{scene}/{frame}_depth.npy".into(), ..Params::default() };
        assert_eq!(bad.validate().len(), 1);
        assert!(Params::default().validate().is_empty());
    }
}
