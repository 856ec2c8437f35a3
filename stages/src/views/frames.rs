//! A dataset's frames as views: the camera an `ImageInfo` gives (checked against the image and
//! depth it comes with), a frame's cameras wired with `Across(.., camera)`, and what a record
//! says of a frame.

use super::splat::PinholeView;
use anyhow::{bail, ensure, Context, Result};
use dist4d_types::artifact::{DepthMap, Image, ImageInfo};
use serde_json::json;

/// A frame's camera images wired with `Across(.., camera)` as three inputs (images, their depths
/// and infos), matched by position; cameras without an image (a dropped frame) are left out.
/// `what` names the inputs in errors.
pub fn camera_views<'a>(
    images: &'a [(i64, Image)],
    depths: &'a [(i64, DepthMap)],
    infos: &'a [(i64, ImageInfo)],
    what: &str,
) -> Result<Vec<(&'a Image, &'a DepthMap, &'a ImageInfo)>> {
    ensure!(
        images.len() == depths.len() && images.len() == infos.len(),
        "{what} hold {}, {} and {} items: wire them with the same selector (Across(.., camera))",
        images.len(),
        depths.len(),
        infos.len()
    );
    let mut out = Vec::with_capacity(images.len());
    for (((pi, image), (pd, depth)), (pn, info)) in images.iter().zip(depths).zip(infos) {
        ensure!(pi == pd && pd == pn, "{what} must be wired with the same selector");
        if info.missing.is_none() {
            out.push((image, depth, info));
        }
    }
    Ok(out)
}

/// The camera of an image, as its info gives it.
pub fn info_view(info: &ImageInfo) -> Result<PinholeView> {
    if let Some(why) = &info.missing {
        bail!("{}/{}/{} has no image: {why}", info.scene, info.frame, info.camera);
    }
    let k = info.intrinsics.with_context(|| format!("{}/{}/{}: no intrinsics", info.scene, info.frame, info.camera))?;
    Ok(PinholeView {
        k,
        width: info.width,
        height: info.height,
        world_from_cam: info.ego_to_world.then_from(&info.camera_to_ego),
    })
}

/// The camera of an image, checked against the image and depth it comes with.
pub fn view_of(info: &ImageInfo, image: &Image, depth: &DepthMap) -> Result<PinholeView> {
    let view = info_view(info)?;
    ensure!(
        (image.width, image.height) == (info.width, info.height)
            && (depth.width, depth.height) == (info.width, info.height),
        "{}/{}/{}: image {}x{} and depth {}x{} do not match the camera's {}x{}",
        info.scene,
        info.frame,
        info.camera,
        image.width,
        image.height,
        depth.width,
        depth.height,
        info.width,
        info.height
    );
    Ok(view)
}

/// What a pair's record says of one of its frames: which image, when, and the camera as the
/// pair's files see it (intrinsics at the model size for the target).
pub fn frame_record(info: &ImageInfo, view: &PinholeView) -> serde_json::Value {
    let t = |s: &dist4d_types::geometry::Se3| json!({ "translation": s.translation.to_array(), "rotation": s.wxyz() });
    json!({
        "camera": info.camera,
        "frame": info.frame,
        "token": info.token,
        "image": info.file,
        "timestamp_us": info.timestamp_us,
        "intrinsics": view.k,
        "size": [view.height, view.width],
        "camera_to_ego": t(&info.camera_to_ego),
        "ego_to_world": t(&info.ego_to_world),
    })
}
