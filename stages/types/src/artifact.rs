//! Artifact types and their byte encodings (what travels between tasks and sits in the cache).
//!
//! Each encoding starts with a 4-byte tag and is little-endian; decoding checks sizes and never
//! panics on bad bytes.

use crate::geometry::{BoxTest, Se3};
use anyhow::{bail, ensure, Context, Result};

/// A type that can be a port's artifact.
pub trait Artifact: Sized {
    const TYPE: &'static str;
    fn encode(&self) -> Vec<u8>;
    fn decode(bytes: &[u8]) -> Result<Self>;
}

struct Reader<'a>(&'a [u8], &'static str);

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8], tag: &[u8; 4], ty: &'static str) -> Result<Self> {
        ensure!(bytes.len() >= 4 && &bytes[..4] == tag, "not a {ty} artifact");
        Ok(Reader(&bytes[4..], ty))
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        if self.0.len() < n {
            bail!("{} artifact is truncated", self.1);
        }
        let (a, b) = self.0.split_at(n);
        self.0 = b;
        Ok(a)
    }
    fn remaining(&self) -> usize {
        self.0.len()
    }
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into()?))
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into()?))
    }
    fn i64(&mut self) -> Result<i64> {
        Ok(i64::from_le_bytes(self.take(8)?.try_into()?))
    }
    fn f32s(&mut self, n: usize) -> Result<Vec<f32>> {
        let b = self.take(n.checked_mul(4).context("size overflow")?)?;
        Ok(b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect())
    }
}

/// Appends `xs` as little-endian f32 (written chunk by chunk into a sized buffer, which compiles
/// to a plain copy on little-endian machines; artifacts of image size are megabytes).
fn put_f32s(out: &mut Vec<u8>, xs: &[f32]) {
    let start = out.len();
    out.resize(start + xs.len() * 4, 0);
    for (c, x) in out[start..].chunks_exact_mut(4).zip(xs) {
        c.copy_from_slice(&x.to_le_bytes());
    }
}

/// Points with xyz and intensity, in the frame of the sensor that measured them (or the frame
/// the stage that made them says), with optional per-point semantic labels (nuScenes-lidarseg
/// indices) when the dataset has them, and optional colours (points from RGB-D).
#[derive(Clone, Debug, PartialEq, Default)]
pub struct PointCloud {
    /// x, y, z, intensity per point.
    pub points: Vec<[f32; 4]>,
    /// One label per point, or empty.
    pub labels: Vec<u8>,
    /// One RGB8 colour per point, or empty.
    pub rgb: Vec<[u8; 3]>,
}

impl Artifact for PointCloud {
    const TYPE: &'static str = "PointCloud";
    fn encode(&self) -> Vec<u8> {
        let mut out = b"PCL2".to_vec();
        out.extend_from_slice(&(self.points.len() as u32).to_le_bytes());
        put_f32s(&mut out, self.points.as_flattened());
        out.push(!self.labels.is_empty() as u8);
        out.extend_from_slice(&self.labels);
        // Colours after the labels, only when there are any: clouds without them keep the bytes
        // (and so the digests) they had before colours existed.
        if !self.rgb.is_empty() {
            out.push(1);
            out.extend_from_slice(self.rgb.as_flattened());
        }
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader::new(bytes, b"PCL2", Self::TYPE)?;
        let n = r.u32()? as usize;
        let flat = r.f32s(n * 4)?;
        let labels = if r.take(1)?[0] != 0 { r.take(n)?.to_vec() } else { Vec::new() };
        let rgb = if r.remaining() > 0 && r.take(1)?[0] != 0 {
            r.take(n.checked_mul(3).context("size overflow")?)?.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        } else {
            Vec::new()
        };
        Ok(PointCloud { points: flat.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]).collect(), labels, rgb })
    }
}

/// An RGB8 image, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Artifact for Image {
    const TYPE: &'static str = "Image";
    fn encode(&self) -> Vec<u8> {
        let mut out = b"IMG1".to_vec();
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        out.extend_from_slice(&self.rgb);
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader::new(bytes, b"IMG1", Self::TYPE)?;
        let (width, height) = (r.u32()?, r.u32()?);
        let rgb = r.take((width as usize * height as usize).checked_mul(3).context("size overflow")?)?.to_vec();
        Ok(Image { width, height, rgb })
    }
}

/// One annotated 3D box, in the world frame (like nuScenes `sample_annotation`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Box3D {
    pub center: [f64; 3],
    /// Width, length, height (nuScenes order), metres.
    pub size: [f64; 3],
    /// `[w, x, y, z]`, box to world.
    pub rotation: [f64; 4],
    /// World-frame velocity, m/s; NaN components when unknown (a track of one annotation).
    pub velocity: [f64; 3],
    /// The track this box belongs to (nuScenes instance token, DGP instance id).
    pub instance: String,
    /// Category name in the dataset's own taxonomy (`vehicle.car`, `Car`).
    pub category: String,
    pub attributes: Vec<String>,
    /// LiDAR points inside, as annotated (0 when interpolated or unknown).
    pub num_lidar_pts: u32,
    /// Whether the box was interpolated between two annotations (sweeps, camera rounds, images).
    pub interpolated: bool,
    /// Whether the box was extrapolated from one annotation with its velocity (a track annotated
    /// on only one of the keyframes around the box's time).
    #[serde(default)]
    pub extrapolated: bool,
}

impl Box3D {
    /// A point-inside test of this box in another frame (see [`BoxTest`]).
    pub fn test(&self, frame_from_world: &Se3, margin: f64, ground_clearance: f64) -> BoxTest {
        BoxTest::new(
            self.size,
            &Se3::from_wxyz_t(self.rotation, self.center),
            frame_from_world,
            margin,
            ground_clearance,
        )
    }

    /// Moving by attribute (`*.moving`), or faster than `min_speed` m/s.
    pub fn is_moving(&self, min_speed: f64) -> bool {
        self.attributes.iter().any(|a| a.ends_with(".moving")) || self.speed() > min_speed
    }

    /// Speed over the ground (m/s): NaN when the velocity is unknown, so never faster than a bound.
    pub fn speed(&self) -> f64 {
        self.velocity[0].hypot(self.velocity[1])
    }

    /// The centre `seconds` later along the velocity; an unknown component stays where it is.
    pub fn advanced(&self, seconds: f64) -> [f64; 3] {
        [0, 1, 2].map(|i| self.center[i] + if self.velocity[i].is_finite() { self.velocity[i] * seconds } else { 0.0 })
    }
}

/// Everything a training index records about one camera item: which image it is (the item's
/// labels, the dataset's token, file relative to the dataset root, time), how it was taken
/// (intrinsics, camera -> ego, ego -> world at its time) and the boxes at its time. An item whose
/// image is missing (a dropped frame) has `missing` set and nothing else.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct ImageInfo {
    pub scene: String,
    pub frame: String,
    pub camera: String,
    /// Why the item has no image, when it has none.
    pub missing: Option<String>,
    /// nuScenes `sample_data` token, DGP datum key.
    pub token: String,
    /// Relative to the dataset root.
    pub file: String,
    /// The image's row when `file` is a table of images (a py123d log's camera file: the encoded
    /// image is that row's `<camera>.data`); `None` when `file` is the image.
    pub row: Option<u64>,
    pub timestamp_us: i64,
    pub width: u32,
    pub height: u32,
    pub intrinsics: Option<[[f64; 3]; 3]>,
    pub camera_to_ego: Se3,
    pub ego_to_world: Se3,
    pub boxes: Boxes3D,
    /// The recording vehicle, where the dataset names it apart from its file names (py123d's
    /// `vehicle_name`); empty otherwise.
    pub vehicle: String,
}

/// `ImageInfo` without its boxes and transforms, as JSON.
#[derive(serde::Serialize, serde::Deserialize)]
struct ImageInfoOnDisk {
    scene: String,
    frame: String,
    camera: String,
    missing: Option<String>,
    token: String,
    file: String,
    timestamp_us: i64,
    width: u32,
    height: u32,
    intrinsics: Option<[[f64; 3]; 3]>,
    // Left out when empty: the bytes of every dataset that names no vehicle stay as they were.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    vehicle: String,
    // Left out when none, for the same reason.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    row: Option<u64>,
}

impl Artifact for ImageInfo {
    const TYPE: &'static str = "ImageInfo";
    // The JSON's length and bytes, the two transforms, then the boxes as Boxes3D encodes them.
    fn encode(&self) -> Vec<u8> {
        let head = ImageInfoOnDisk {
            scene: self.scene.clone(),
            frame: self.frame.clone(),
            camera: self.camera.clone(),
            missing: self.missing.clone(),
            token: self.token.clone(),
            file: self.file.clone(),
            timestamp_us: self.timestamp_us,
            width: self.width,
            height: self.height,
            intrinsics: self.intrinsics,
            vehicle: self.vehicle.clone(),
            row: self.row,
        };
        let json = serde_json::to_vec(&head).unwrap_or_default();
        let mut out = b"IMI1".to_vec();
        out.extend_from_slice(&(json.len() as u64).to_le_bytes());
        out.extend_from_slice(&json);
        self.camera_to_ego.encode_into(&mut out);
        self.ego_to_world.encode_into(&mut out);
        out.extend_from_slice(&self.boxes.encode());
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader::new(bytes, b"IMI1", Self::TYPE)?;
        let n = usize::try_from(r.i64()?).context("ImageInfo artifact is malformed")?;
        let head: ImageInfoOnDisk = serde_json::from_slice(r.take(n)?).context("ImageInfo artifact is malformed")?;
        let camera_to_ego = Se3::decode_from(&mut |n| r.take(n))?;
        let ego_to_world = Se3::decode_from(&mut |n| r.take(n))?;
        let boxes = Boxes3D::decode(r.0)?;
        Ok(ImageInfo {
            scene: head.scene,
            frame: head.frame,
            camera: head.camera,
            missing: head.missing,
            token: head.token,
            file: head.file,
            row: head.row,
            timestamp_us: head.timestamp_us,
            width: head.width,
            height: head.height,
            intrinsics: head.intrinsics,
            camera_to_ego,
            ego_to_world,
            boxes,
            vehicle: head.vehicle,
        })
    }
}

/// The annotated boxes of one frame.
#[derive(Clone, Debug, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct Boxes3D {
    pub timestamp_us: i64,
    pub boxes: Vec<Box3D>,
}

impl Artifact for Boxes3D {
    const TYPE: &'static str = "Boxes3D";
    fn encode(&self) -> Vec<u8> {
        // JSON: boxes are few and small, and NaN velocities are written as null.
        let mut out = b"BOX1".to_vec();
        out.extend_from_slice(&serde_json::to_vec(&BoxesOnDisk::from(self)).unwrap_or_default());
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let r = Reader::new(bytes, b"BOX1", Self::TYPE)?;
        let on_disk: BoxesOnDisk = serde_json::from_slice(r.0).context("Boxes3D artifact is malformed")?;
        Ok(on_disk.into())
    }
}

/// `Boxes3D` with NaN as `None`, since JSON has no NaN.
#[derive(serde::Serialize, serde::Deserialize)]
struct BoxesOnDisk {
    timestamp_us: i64,
    boxes: Vec<(Box3D, [Option<f64>; 3])>,
}

impl From<&Boxes3D> for BoxesOnDisk {
    fn from(b: &Boxes3D) -> Self {
        BoxesOnDisk {
            timestamp_us: b.timestamp_us,
            boxes: b
                .boxes
                .iter()
                .map(|x| {
                    let v = x.velocity.map(|c| c.is_finite().then_some(c));
                    (Box3D { velocity: [0.0; 3], ..x.clone() }, v)
                })
                .collect(),
        }
    }
}

impl From<BoxesOnDisk> for Boxes3D {
    fn from(b: BoxesOnDisk) -> Self {
        Boxes3D {
            timestamp_us: b.timestamp_us,
            boxes: b
                .boxes
                .into_iter()
                .map(|(x, v)| Box3D { velocity: v.map(|c| c.unwrap_or(f64::NAN)), ..x })
                .collect(),
        }
    }
}

/// A dense or sparse metric depth map: f32 metres along the optical axis, 0 = no depth.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

impl DepthMap {
    pub fn new(width: u32, height: u32) -> DepthMap {
        DepthMap { width, height, data: vec![0.0; width as usize * height as usize] }
    }
}

impl Artifact for DepthMap {
    const TYPE: &'static str = "DepthMap";
    /// A map with depth at half its pixels or more is an NPY file (v1.0, float32, H x W): the very
    /// bytes [`crate::npy::npy_f32`] exports, so a dense map and its NPY export are one blob
    /// in the store (and a blob a user can `numpy.load`). A sparser one is `DEP2`: width, height,
    /// then runs of (zeros: u32, values: u32, the values as f32); a projected sweep fills ~2% of the
    /// pixels and shrinks ~30x, which matters because every artifact is hashed and stored.
    fn encode(&self) -> Vec<u8> {
        let d = &self.data;
        if 2 * d.iter().filter(|&&z| z != 0.0).count() >= d.len()
            && d.len() == self.width as usize * self.height as usize
        {
            return crate::npy::npy_f32(&[self.height as usize, self.width as usize], d);
        }
        let mut out = Vec::with_capacity(12 + 4 * self.data.len() + 8);
        out.extend_from_slice(b"DEP2");
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        let mut i = 0;
        while i < d.len() {
            let zeros = d[i..].iter().take_while(|&&z| z == 0.0).count();
            let start = i + zeros;
            let values = d[start..].iter().take_while(|&&z| z != 0.0).count();
            out.extend_from_slice(&(zeros as u32).to_le_bytes());
            out.extend_from_slice(&(values as u32).to_le_bytes());
            put_f32s(&mut out, &d[start..start + values]);
            i = start + values;
        }
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        if bytes.starts_with(b"\x93NUMPY") {
            let (shape, data) = crate::npy::read_npy_f32(bytes).context("DepthMap artifact (NPY)")?;
            let [height, width] = shape[..] else { bail!("DepthMap artifact (NPY) has shape {shape:?}, not H x W") };
            let (width, height) = (u32::try_from(width)?, u32::try_from(height)?);
            return Ok(DepthMap { width, height, data });
        }
        if bytes.starts_with(b"DEP1") {
            let mut r = Reader::new(bytes, b"DEP1", Self::TYPE)?;
            let (width, height) = (r.u32()?, r.u32()?);
            let data = r.f32s(width as usize * height as usize)?;
            return Ok(DepthMap { width, height, data });
        }
        let mut r = Reader::new(bytes, b"DEP2", Self::TYPE)?;
        let (width, height) = (r.u32()?, r.u32()?);
        let n = (width as usize).checked_mul(height as usize).context("size overflow")?;
        let mut data = Vec::with_capacity(n);
        while data.len() < n {
            let (zeros, values) = (r.u32()? as usize, r.u32()? as usize);
            ensure!(data.len() + zeros + values <= n, "{} artifact has more pixels than {width}x{height}", Self::TYPE);
            data.resize(data.len() + zeros, 0.0);
            data.extend(r.f32s(values)?);
        }
        Ok(DepthMap { width, height, data })
    }
}

/// Per-pixel semantic class ids (Cityscapes ids, as any segmenter writes them), row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Segmentation {
    pub width: u32,
    pub height: u32,
    pub ids: Vec<u8>,
}

impl Segmentation {
    /// Cityscapes id of sky.
    pub const SKY: u8 = 23;
}

impl Artifact for Segmentation {
    const TYPE: &'static str = "Segmentation";
    fn encode(&self) -> Vec<u8> {
        encode_byte_map(b"SEG1", self.width, self.height, &self.ids)
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let (width, height, ids) = decode_byte_map(bytes, b"SEG1", Self::TYPE)?;
        Ok(Segmentation { width, height, ids })
    }
}

/// One frame's semantic occupancy, as Occ3D stores it: three volumes of one byte a voxel, axes
/// x, y, z in C order (`dims` = [X, Y, Z]): the class of every voxel, and whether the LiDAR and
/// the cameras observed it (0/1).
#[derive(Clone, Debug, PartialEq)]
pub struct OccupancyGrid {
    pub dims: [u32; 3],
    pub semantics: Vec<u8>,
    pub mask_lidar: Vec<u8>,
    pub mask_camera: Vec<u8>,
}

impl OccupancyGrid {
    pub fn voxels(&self) -> usize {
        self.dims.iter().map(|&d| d as usize).product()
    }
}

impl Artifact for OccupancyGrid {
    const TYPE: &'static str = "OccupancyGrid";
    fn encode(&self) -> Vec<u8> {
        let mut out = b"OCC1".to_vec();
        for d in self.dims {
            out.extend_from_slice(&d.to_le_bytes());
        }
        out.extend_from_slice(&self.semantics);
        out.extend_from_slice(&self.mask_lidar);
        out.extend_from_slice(&self.mask_camera);
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader::new(bytes, b"OCC1", Self::TYPE)?;
        let dims = [r.u32()?, r.u32()?, r.u32()?];
        let n = dims.iter().try_fold(1usize, |n, &d| n.checked_mul(d as usize)).context("size overflow")?;
        let semantics = r.take(n)?.to_vec();
        let mask_lidar = r.take(n)?.to_vec();
        let mask_camera = r.take(n)?.to_vec();
        Ok(OccupancyGrid { dims, semantics, mask_lidar, mask_camera })
    }
}

/// The points of each tracked object gathered over a scene, in the object's own box frame (x
/// along its length, z up, origin at its centre), with the object's class: placed at a frame's
/// box pose, they draw the object densely wherever it is then.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct TrackClouds {
    pub tracks: Vec<TrackCloud>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TrackCloud {
    /// The track's id (nuScenes instance token, DGP instance id).
    pub instance: String,
    pub class: u8,
    pub points: Vec<[f32; 3]>,
}

impl Artifact for TrackClouds {
    const TYPE: &'static str = "TrackClouds";
    fn encode(&self) -> Vec<u8> {
        let mut out = b"TRK1".to_vec();
        out.extend_from_slice(&(self.tracks.len() as u32).to_le_bytes());
        for t in &self.tracks {
            out.extend_from_slice(&(t.instance.len() as u32).to_le_bytes());
            out.extend_from_slice(t.instance.as_bytes());
            out.push(t.class);
            out.extend_from_slice(&(t.points.len() as u32).to_le_bytes());
            put_f32s(&mut out, t.points.as_flattened());
        }
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader::new(bytes, b"TRK1", Self::TYPE)?;
        let n = r.u32()? as usize;
        let mut tracks = Vec::with_capacity(n.min(1 << 16));
        for _ in 0..n {
            let len = r.u32()? as usize;
            let instance = String::from_utf8(r.take(len)?.to_vec()).context("TrackClouds: an instance is not UTF-8")?;
            let class = r.take(1)?[0];
            let count = r.u32()? as usize;
            let flat = r.f32s(count.checked_mul(3).context("size overflow")?)?;
            tracks.push(TrackCloud {
                instance,
                class,
                points: flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
            });
        }
        Ok(TrackClouds { tracks })
    }
}

/// A map of one byte a pixel: magic, width and height (u32 LE), then the bytes row-major.
fn encode_byte_map(magic: &[u8; 4], width: u32, height: u32, bytes: &[u8]) -> Vec<u8> {
    let mut out = magic.to_vec();
    out.extend_from_slice(&width.to_le_bytes());
    out.extend_from_slice(&height.to_le_bytes());
    out.extend_from_slice(bytes);
    out
}

fn decode_byte_map(bytes: &[u8], magic: &[u8; 4], ty: &'static str) -> Result<(u32, u32, Vec<u8>)> {
    let mut r = Reader::new(bytes, magic, ty)?;
    let (width, height) = (r.u32()?, r.u32()?);
    let data = r.take(width as usize * height as usize)?.to_vec();
    Ok((width, height, data))
}

/// A per-pixel yes/no map (e.g. sky), row-major, one byte a pixel: 1 = yes, 0 = no.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Mask {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl Artifact for Mask {
    const TYPE: &'static str = "Mask";
    fn encode(&self) -> Vec<u8> {
        encode_byte_map(b"MSK1", self.width, self.height, &self.data)
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let (width, height, data) = decode_byte_map(bytes, b"MSK1", Self::TYPE)?;
        Ok(Mask { width, height, data })
    }
}

/// Points projected into an image: (u, v, depth) rows in the order of the source points.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct ProjectedPoints {
    pub rows: Vec<[f32; 3]>,
}

impl Artifact for ProjectedPoints {
    const TYPE: &'static str = "ProjectedPoints";
    fn encode(&self) -> Vec<u8> {
        let mut out = b"UVZ1".to_vec();
        out.extend_from_slice(&(self.rows.len() as u32).to_le_bytes());
        put_f32s(&mut out, self.rows.as_flattened());
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader::new(bytes, b"UVZ1", Self::TYPE)?;
        let n = r.u32()? as usize;
        let flat = r.f32s(n * 3)?;
        Ok(ProjectedPoints { rows: flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect() })
    }
}

/// A sensor's mounting on the ego vehicle, and for cameras the pinhole intrinsics and image size.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    pub sensor_to_ego: Se3,
    /// Row-major 3x3 camera matrix; `None` for non-camera sensors.
    pub intrinsics: Option<[[f64; 3]; 3]>,
    pub width: u32,
    pub height: u32,
}

impl Artifact for Calibration {
    const TYPE: &'static str = "Calibration";
    fn encode(&self) -> Vec<u8> {
        let mut out = b"CAL1".to_vec();
        self.sensor_to_ego.encode_into(&mut out);
        match &self.intrinsics {
            Some(k) => {
                out.push(1);
                for x in k.as_flattened() {
                    out.extend_from_slice(&x.to_le_bytes());
                }
            }
            None => out.push(0),
        }
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader::new(bytes, b"CAL1", Self::TYPE)?;
        let sensor_to_ego = Se3::decode_from(&mut |n| r.take(n))?;
        let intrinsics = match r.take(1)?[0] {
            0 => None,
            _ => {
                let mut k = [[0.0; 3]; 3];
                for row in k.iter_mut() {
                    for x in row.iter_mut() {
                        *x = r.f64()?;
                    }
                }
                Some(k)
            }
        };
        Ok(Calibration { sensor_to_ego, intrinsics, width: r.u32()?, height: r.u32()? })
    }
}

/// The ego vehicle's pose in the world at a sensor's timestamp.
#[derive(Clone, Debug, PartialEq)]
pub struct Pose {
    pub ego_to_world: Se3,
    /// Microseconds.
    pub timestamp_us: i64,
}

impl Artifact for Pose {
    const TYPE: &'static str = "Pose";
    fn encode(&self) -> Vec<u8> {
        let mut out = b"POS1".to_vec();
        self.ego_to_world.encode_into(&mut out);
        out.extend_from_slice(&self.timestamp_us.to_le_bytes());
        out
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        let mut r = Reader::new(bytes, b"POS1", Self::TYPE)?;
        let ego_to_world = Se3::decode_from(&mut |n| r.take(n))?;
        Ok(Pose { ego_to_world, timestamp_us: r.i64()? })
    }
}

/// An encoded file (EXR, PNG, NPY ...), written out by `export` as it is.
pub struct File(pub Vec<u8>);

impl Artifact for File {
    const TYPE: &'static str = "File";
    fn encode(&self) -> Vec<u8> {
        self.0.clone()
    }
    fn decode(bytes: &[u8]) -> Result<Self> {
        Ok(File(bytes.to_vec()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn artifacts_round_trip_and_reject_bad_bytes() {
        let pc =
            PointCloud { points: vec![[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0]], labels: vec![], rgb: Vec::new() };
        assert_eq!(PointCloud::decode(&pc.encode()).unwrap(), pc);
        let pc = PointCloud { labels: vec![24, 17], ..pc };
        assert_eq!(PointCloud::decode(&pc.encode()).unwrap(), pc);
        let grid = OccupancyGrid {
            dims: [2, 1, 2],
            semantics: vec![17, 11, 4, 17],
            mask_lidar: vec![1, 1, 0, 0],
            mask_camera: vec![0, 1, 0, 0],
        };
        assert_eq!(OccupancyGrid::decode(&grid.encode()).unwrap(), grid);
        let tracks =
            TrackClouds { tracks: vec![TrackCloud { instance: "a".into(), class: 4, points: vec![[1.0, 2.0, 3.0]] }] };
        assert_eq!(TrackClouds::decode(&tracks.encode()).unwrap(), tracks);
        assert!(TrackClouds::decode(&tracks.encode()[..12]).is_err());
        let pc = PointCloud { rgb: vec![[1, 2, 3], [250, 251, 252]], ..pc };
        assert_eq!(PointCloud::decode(&pc.encode()).unwrap(), pc);
        let img = Image { width: 2, height: 1, rgb: vec![1, 2, 3, 4, 5, 6] };
        assert_eq!(Image::decode(&img.encode()).unwrap(), img);
        assert!(Image::decode(&img.encode()[..12]).is_err());
        let b = Box3D {
            center: [1.0, 2.0, 3.0],
            size: [2.0, 4.5, 1.6],
            rotation: [1.0, 0.0, 0.0, 0.0],
            velocity: [f64::NAN, f64::NAN, f64::NAN],
            instance: "i".into(),
            category: "vehicle.car".into(),
            attributes: vec!["vehicle.moving".into()],
            num_lidar_pts: 3,
            interpolated: false,
            extrapolated: false,
        };
        let boxes = Boxes3D { timestamp_us: 7, boxes: vec![b.clone(), Box3D { velocity: [1.0, 0.0, 0.0], ..b }] };
        let back = Boxes3D::decode(&boxes.encode()).unwrap();
        assert!(back.boxes[0].velocity[0].is_nan() && back.boxes[1].velocity == [1.0, 0.0, 0.0]);
        assert!(back.boxes[0].is_moving(10.0) && back.boxes[1].center == [1.0, 2.0, 3.0]);
        let d = DepthMap { width: 2, height: 1, data: vec![0.0, 3.5] };
        assert_eq!(DepthMap::decode(&d.encode()).unwrap(), d);
        let c = Calibration {
            sensor_to_ego: Se3::from_wxyz_t([1.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0]),
            intrinsics: Some([[1.0, 0.0, 2.0], [0.0, 1.0, 3.0], [0.0, 0.0, 1.0]]),
            width: 4,
            height: 3,
        };
        assert_eq!(Calibration::decode(&c.encode()).unwrap(), c);
        let p = Pose { ego_to_world: c.sensor_to_ego, timestamp_us: -5 };
        assert_eq!(Pose::decode(&p.encode()).unwrap(), p);
        assert!(DepthMap::decode(&d.encode()[..10]).is_err());
        assert!(DepthMap::decode(b"PCL1....").is_err());
        let m = Mask { width: 3, height: 1, data: vec![0, 1, 1] };
        assert_eq!(Mask::decode(&m.encode()).unwrap(), m);
        assert!(Mask::decode(&m.encode()[..13]).is_err(), "truncated");
        let seg = Segmentation { width: 1, height: 2, ids: vec![23, 7] };
        assert_eq!(Segmentation::decode(&seg.encode()).unwrap(), seg);
        assert!(Segmentation::decode(&m.encode()).is_err(), "a mask is not a segmentation");
    }
}

#[cfg(test)]
mod depth_map_tests {
    use super::*;

    #[test]
    fn depth_maps_round_trip_sparse_dense_and_empty_and_reject_overflow() {
        let mut sparse = DepthMap::new(100, 50);
        sparse.data[0] = 3.0;
        sparse.data[7] = 4.0;
        sparse.data[8] = 5.0;
        sparse.data[4999] = 6.0;
        let dense = DepthMap { width: 3, height: 2, data: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0] };
        for m in [sparse.clone(), dense, DepthMap::new(4, 4), DepthMap::new(0, 0)] {
            assert_eq!(DepthMap::decode(&m.encode()).unwrap(), m);
        }
        assert!(sparse.encode().len() < 100);
        let mut bad = DepthMap::new(2, 2).encode();
        bad[12..16].copy_from_slice(&9u32.to_le_bytes());
        assert!(DepthMap::decode(&bad).is_err());
        assert!(DepthMap::decode(&bad[..10]).is_err());
    }

    #[test]
    fn a_dense_map_is_the_npy_file_that_is_exported_and_a_sparse_one_stays_runs() {
        let dense = DepthMap { width: 3, height: 2, data: vec![1.0, 0.0, 3.0, 4.0, 0.0, 6.0] };
        assert_eq!(dense.encode(), crate::npy::npy_f32(&[2, 3], &dense.data));
        let sparse = DepthMap { width: 3, height: 2, data: vec![1.0, 0.0, 0.0, 0.0, 0.0, 6.0] };
        assert!(sparse.encode().starts_with(b"DEP2"));
        // An NPY of another dtype, order or rank is not a depth map.
        let npy = crate::npy::npy_f32(&[6], &dense.data);
        assert!(DepthMap::decode(&npy).is_err());
        let mut f64s = dense.encode();
        let at = f64s.windows(3).position(|w| w == b"<f4").unwrap();
        f64s[at + 2] = b'8';
        assert!(DepthMap::decode(&f64s).is_err());
        let mut truncated = dense.encode();
        truncated.pop();
        assert!(DepthMap::decode(&truncated).is_err());
    }
}
