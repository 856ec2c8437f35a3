//! Checks on what a dataset's metadata says, shared by the nuScenes and DGP readers: file
//! references stay inside the dataset root, and poses and calibrations are finite rigid
//! transforms and pinhole cameras within documented bounds.
//!
//! Every check returns its problem as one line that starts with the [`Place`] the value was read
//! from (file, row or object, token) and names the field, so a reader can store it as the error of
//! just the items that use the bad row and the user can find the row without a debugger.

use dist4d_types::geometry::Se3;
use std::collections::BTreeMap;
use std::fmt;
use std::path::{Component, Path, PathBuf};

/// Largest distance (m) of an ego pose (or a DGP sensor pose, also in the world frame) from the
/// world origin. 1e7 m covers UTM coordinates (northings reach 1e7 m) and every city-local frame
/// the datasets use (nuScenes and DDAD stay within a few km); a translation beyond it is a broken
/// row, and in f64 it would also leave too few bits for centimetres.
pub const MAX_EGO_TRANSLATION_M: f64 = 1e7;

/// Largest distance (m) of a sensor from the ego origin (sensor -> ego mounting). Sensors sit on
/// the vehicle, a few metres from its origin; 100 m leaves room for trucks and odd conventions
/// but catches a translation in millimetres or a world pose written into the calibration.
pub const MAX_MOUNT_TRANSLATION_M: f64 = 100.0;

/// A quaternion whose norm differs from 1 by more than this is not a rotation: an error.
/// Within it the quaternion is normalised, with a warning (a writer that rounded its values).
pub const QUATERNION_NORM_TOLERANCE: f64 = 1e-2;

/// Norm errors up to this size are float printing and are normalised without a warning.
const QUATERNION_NORM_ROUNDING: f64 = 1e-6;

/// Largest width or height of a camera image (px). Driving cameras are 1-4 k px wide; 16384
/// leaves room for panoramas while bounding every buffer a stage sizes from the metadata.
pub const MAX_IMAGE_SIDE: u32 = 16_384;

/// Largest number of pixels of a camera image: 64 Mpx (an 8K frame is 33 Mpx). A depth map of
/// it is 256 MB of f32, which a stage may hold a few of per task.
pub const MAX_IMAGE_PIXELS: u64 = 64 << 20;

/// Largest image file read (bytes): a JPEG or PNG of [`MAX_IMAGE_PIXELS`] stays well below it.
pub const MAX_IMAGE_FILE_BYTES: u64 = 512 << 20;

/// Largest sensor file read (bytes): a LiDAR sweep (nuScenes `.pcd.bin`, DGP `.npz`), its
/// lidarseg labels, a ground-truth sidecar, a map mask. 1 GiB is 50 M points of 20 bytes, 200
/// times a 128-beam sweep.
pub const MAX_SENSOR_FILE_BYTES: u64 = 1 << 30;

/// Largest array inflated from an `.npz` member (bytes), whatever its zip header claims.
pub const MAX_NPZ_MEMBER_BYTES: u64 = 1 << 30;

/// Largest metadata file read (bytes): a nuScenes table or a DGP scene JSON. The largest real
/// one, nuScenes v1.0-trainval's `sample_data.json`, is about 1.3 GB.
pub const MAX_TABLE_FILE_BYTES: u64 = 16 << 30;

/// Checks an image size read from metadata or a file header: both sides positive, each at most
/// [`MAX_IMAGE_SIDE`], the area at most [`MAX_IMAGE_PIXELS`]. `at` names where it was read and
/// `field` the field(s).
pub fn image_size(at: &str, field: &str, width: u32, height: u32) -> Result<(), String> {
    let why = if width == 0 || height == 0 {
        "has a zero side".to_string()
    } else if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        format!("has a side over MAX_IMAGE_SIDE ({MAX_IMAGE_SIDE} px)")
    } else if width as u64 * height as u64 > MAX_IMAGE_PIXELS {
        format!("has more than MAX_IMAGE_PIXELS ({MAX_IMAGE_PIXELS}) pixels")
    } else {
        return Ok(());
    };
    Err(format!("{at}: {field} {width}x{height} {why}"))
}

/// Where a value was read: a metadata file and the row or object in it, e.g.
/// `v1.0-mini/ego_pose.json row 3 (token X)`.
#[derive(Clone, Debug)]
pub struct Place {
    pub file: PathBuf,
    pub item: String,
}

impl Place {
    pub fn new(file: &Path, item: impl Into<String>) -> Place {
        Place { file: file.to_path_buf(), item: item.into() }
    }

    /// Row `row` (0-based, as in the JSON list) of a table, with its token.
    pub fn row(file: &Path, row: usize, token: &str) -> Place {
        Place::new(file, format!("row {row} (token {token})"))
    }
}

impl fmt::Display for Place {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}", self.file.display(), self.item)
    }
}

/// Checks a file reference read from dataset metadata: a non-empty relative path without `..`
/// or NUL, so that joined to a folder inside the dataset root it stays inside the root.
///
/// The check is lexical. A symlink inside the root is followed wherever it points: the files
/// under the root are the user's, and a link among them is their choice, not metadata's.
pub fn check_reference(at: &Place, field: &str, value: &str) -> Result<(), String> {
    let why = if value.is_empty() {
        Some("is empty")
    } else if value.contains('\0') {
        Some("contains a NUL byte")
    } else {
        Path::new(value).components().find_map(|c| match c {
            Component::Normal(_) | Component::CurDir => None,
            Component::ParentDir => Some("leaves the dataset root (a `..` component)"),
            Component::RootDir | Component::Prefix(_) => Some("leaves the dataset root (an absolute path)"),
        })
    };
    match why {
        None => Ok(()),
        Some(why) => Err(format!("{at}: field {field} {value:?} {why}")),
    }
}

/// `base.join(value)` once [`check_reference`] accepts `value`; `base` is the dataset root or a
/// folder inside it.
pub fn join_inside(base: &Path, at: &Place, field: &str, value: &str) -> Result<PathBuf, String> {
    check_reference(at, field, value)?;
    Ok(base.join(value))
}

/// What a rigid transform maps, which sets the bound on its translation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Transform {
    /// Ego (or sensor) -> world: within [`MAX_EGO_TRANSLATION_M`].
    Pose,
    /// Sensor -> ego: within [`MAX_MOUNT_TRANSLATION_M`].
    Mount,
}

impl Transform {
    fn bound(self) -> (f64, &'static str) {
        match self {
            Transform::Pose => (MAX_EGO_TRANSLATION_M, "a pose in the world (MAX_EGO_TRANSLATION_M)"),
            Transform::Mount => (MAX_MOUNT_TRANSLATION_M, "a sensor mounting (MAX_MOUNT_TRANSLATION_M)"),
        }
    }
}

/// The field names of a transform's two parts, e.g. `rotation` and `translation`.
pub struct Fields<'a> {
    pub rotation: &'a str,
    pub translation: &'a str,
}

/// Quaternions a little off unit norm that were normalised: one warning per file, naming the
/// worst, so a table of 30,000 rounded poses gives one line and not 30,000.
#[derive(Default)]
pub struct Renormalised {
    /// file -> (where, field) -> norm; a BTreeMap so the warnings come out in a stable order and
    /// a calibration read once per sample counts once.
    by_file: BTreeMap<PathBuf, BTreeMap<String, f64>>,
}

impl Renormalised {
    fn note(&mut self, at: &Place, field: &str, norm: f64) {
        self.by_file.entry(at.file.clone()).or_default().insert(format!("{} field {field}", at.item), norm);
    }

    pub fn warnings(&self) -> Vec<String> {
        self.by_file
            .iter()
            .map(|(file, notes)| {
                let (worst, norm) = notes
                    .iter()
                    .max_by(|a, b| (a.1 - 1.0).abs().total_cmp(&(b.1 - 1.0).abs()))
                    .map(|(w, n)| (w.as_str(), *n))
                    .unwrap_or(("?", 1.0));
                format!(
                    "{}: {} quaternion(s) off unit norm were normalised (worst: {worst}, norm {})",
                    file.display(),
                    notes.len(),
                    num(norm)
                )
            })
            .collect()
    }
}

/// A rotation `[w, x, y, z]` and translation checked and made into a transform: all values
/// finite, the quaternion of unit norm within [`QUATERNION_NORM_TOLERANCE`] (normalised, and noted
/// in `notes` when off by more than rounding), the translation within the bound of `kind`.
pub fn rigid(
    at: &Place,
    fields: Fields,
    q: [f64; 4],
    t: [f64; 3],
    kind: Transform,
    notes: &mut Renormalised,
) -> Result<Se3, String> {
    if q.iter().any(|v| !v.is_finite()) {
        return Err(format!("{at}: field {} {} is not finite", fields.rotation, list(&q)));
    }
    if t.iter().any(|v| !v.is_finite()) {
        return Err(format!("{at}: field {} {} is not finite", fields.translation, list(&t)));
    }
    // hypot, not a sum of squares: a finite 1e300 must not overflow to inf.
    let norm = q.iter().fold(0.0, |n: f64, v| n.hypot(*v));
    if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        let what = if norm == 0.0 { "a rotation" } else { "a unit quaternion" };
        return Err(format!(
            "{at}: field {} {} is not {what} (norm {}; allowed 1 +- {QUATERNION_NORM_TOLERANCE})",
            fields.rotation,
            list(&q),
            num(norm)
        ));
    }
    if (norm - 1.0).abs() > QUATERNION_NORM_ROUNDING {
        notes.note(at, fields.rotation, norm);
    }
    let distance = t.iter().fold(0.0, |n: f64, v| n.hypot(*v));
    let (max, what) = kind.bound();
    if distance > max {
        return Err(format!(
            "{at}: field {} {} is {} m from the origin, beyond the {} m bound of {what}",
            fields.translation,
            list(&t),
            num(distance),
            num(max)
        ));
    }
    Ok(Se3::from_wxyz_t(q.map(|v| v / norm), t))
}

/// Largest distance (m) of a LiDAR return from its sensor: automotive LiDARs reach 200-300 m; a
/// coordinate beyond 2 km is a unit error or garbage (1e30), which would spread through voxel
/// grids and hulls.
pub const MAX_LIDAR_RANGE_M: f32 = 2000.0;

/// Checks a sweep's points `[x, y, z, intensity]` (sensor frame): every value finite, each
/// coordinate within [`MAX_LIDAR_RANGE_M`]. The error names the file, its metadata (`what`), the
/// first bad point and field, and how many points are bad.
pub fn lidar_points(file: &Path, what: &str, points: &[[f32; 4]]) -> Result<(), String> {
    const FIELDS: [&str; 4] = ["x", "y", "z", "intensity"];
    let bad = |p: &[f32; 4]| -> Option<usize> {
        (0..4).find(|&f| !p[f].is_finite() || (f < 3 && p[f].abs() > MAX_LIDAR_RANGE_M))
    };
    let Some((first, field)) = points.iter().enumerate().find_map(|(i, p)| bad(p).map(|f| (i, f))) else {
        return Ok(());
    };
    let count = points.iter().filter(|p| bad(p).is_some()).count();
    let value = points[first][field];
    let why = if value.is_finite() {
        format!("beyond MAX_LIDAR_RANGE_M ({MAX_LIDAR_RANGE_M} m)")
    } else {
        "not finite".into()
    };
    Err(format!(
        "{} ({what}): point {first}, field {}, is {value} ({why}); {count} of its {} points are bad",
        file.display(),
        FIELDS[field],
        points.len()
    ))
}

/// Largest side of a 3D box (m): a road train is 50 m; a side beyond this is a unit error.
pub const MAX_BOX_SIZE_M: f64 = 1000.0;

/// A 3D box annotation's centre, size and rotation `[w, x, y, z]` checked: every value finite,
/// every side positive and at most [`MAX_BOX_SIZE_M`], the centre within
/// [`MAX_EGO_TRANSLATION_M`] of the origin, the quaternion of unit norm (normalised as [`rigid`]
/// does). Returns the normalised rotation. A zero quaternion would become NaN in every stage that
/// rotates by it.
pub fn box_values(
    at: &Place,
    center: [f64; 3],
    size: [f64; 3],
    rotation: [f64; 4],
    notes: &mut Renormalised,
) -> Result<[f64; 4], String> {
    if size.iter().any(|v| !v.is_finite()) {
        return Err(format!("{at}: field size {} is not finite", list(&size)));
    }
    if size.iter().any(|v| *v <= 0.0) {
        return Err(format!("{at}: field size {} has a side that is not positive", list(&size)));
    }
    if size.iter().any(|v| *v > MAX_BOX_SIZE_M) {
        return Err(format!("{at}: field size {} has a side over MAX_BOX_SIZE_M ({MAX_BOX_SIZE_M} m)", list(&size)));
    }
    let fields = Fields { rotation: "rotation", translation: "translation" };
    let se3 = rigid(at, fields, rotation, center, Transform::Pose, notes)?;
    // Within float printing of unit norm the row is kept to the bit (its boxes' bytes unchanged).
    let norm = rotation.iter().fold(0.0, |n: f64, v| n.hypot(*v));
    if (norm - 1.0).abs() <= QUATERNION_NORM_ROUNDING {
        return Ok(rotation);
    }
    let q = se3.rotation;
    Ok([q.w, q.x, q.y, q.z])
}

/// Focal lengths (px) a pinhole camera may have: 1 px is a field of view near 180 degrees for any
/// image, 1e7 px a telescope's fraction of a degree at [`MAX_IMAGE_SIDE`]. Outside it (1e-300,
/// 1e300) every projection overflows or collapses to one pixel.
pub const FOCAL_PX: std::ops::RangeInclusive<f64> = 1.0..=1e7;

/// A pinhole matrix `[[fx, s, cx], [0, fy, cy], [0, 0, 1]]` checked: finite, positive focal
/// lengths, and the shape every projection in dist4d assumes.
pub fn pinhole(at: &Place, field: &str, k: [[f64; 3]; 3]) -> Result<[[f64; 3]; 3], String> {
    let flat: Vec<f64> = k.iter().flatten().copied().collect();
    let bad = |why: String| Err(format!("{at}: field {field} {} {why}", matrix(&k)));
    if flat.iter().any(|v| !v.is_finite()) {
        return bad("is not finite".into());
    }
    if k[0][0] <= 0.0 || k[1][1] <= 0.0 {
        return bad(format!("has focal lengths fx {} and fy {}; both must be positive", num(k[0][0]), num(k[1][1])));
    }
    if !(FOCAL_PX.contains(&k[0][0]) && FOCAL_PX.contains(&k[1][1])) {
        return bad(format!(
            "has focal lengths fx {} and fy {}; both must be within {} to {} px (FOCAL_PX)",
            num(k[0][0]),
            num(k[1][1]),
            num(*FOCAL_PX.start()),
            num(*FOCAL_PX.end())
        ));
    }
    if k[1][0] != 0.0 || k[2] != [0.0, 0.0, 1.0] {
        return bad("is not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]".into());
    }
    Ok(k)
}

/// The principal point of a checked pinhole matrix lies inside its `width` x `height` image
/// (pixel-area convention: 0 <= cx <= width); skipped when the size is unknown (0).
pub fn principal_point_inside(
    at: &Place,
    field: &str,
    k: &[[f64; 3]; 3],
    width: u32,
    height: u32,
) -> Result<(), String> {
    if width == 0 || height == 0 {
        return Ok(());
    }
    let (cx, cy) = (k[0][2], k[1][2]);
    if (0.0..=width as f64).contains(&cx) && (0.0..=height as f64).contains(&cy) {
        return Ok(());
    }
    Err(format!(
        "{at}: field {field} has its principal point ({}, {}) outside the {width}x{height} image",
        num(cx),
        num(cy)
    ))
}

/// A number as a person reads it: `0`, `1.5`, `1e300` (not 301 digits).
fn num(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-4..1e7).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

fn list(v: &[f64]) -> String {
    format!("[{}]", v.iter().map(|x| num(*x)).collect::<Vec<_>>().join(", "))
}

fn matrix(k: &[[f64; 3]; 3]) -> String {
    format!("[{}]", k.iter().map(|r| list(r)).collect::<Vec<_>>().join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at() -> Place {
        Place::row(Path::new("v1.0-mini/ego_pose.json"), 3, "X")
    }

    const RT: Fields = Fields { rotation: "rotation", translation: "translation" };

    #[test]
    fn references_must_stay_inside_the_root() {
        let root = Path::new("/data/nuscenes");
        assert_eq!(join_inside(root, &at(), "filename", "samples/a.jpg").unwrap(), root.join("samples/a.jpg"));
        assert!(join_inside(root, &at(), "filename", "./samples/a.jpg").is_ok());
        for (bad, why) in [
            ("../outside/x.pcd.bin", "leaves the dataset root"),
            ("samples/../../x", "leaves the dataset root"),
            ("../../../../etc/passwd", "leaves the dataset root"),
            ("/etc/passwd", "leaves the dataset root (an absolute path)"),
            ("", "is empty"),
            ("a\0b", "contains a NUL byte"),
        ] {
            let e = join_inside(root, &at(), "filename", bad).unwrap_err();
            assert!(e.starts_with("v1.0-mini/ego_pose.json row 3 (token X): field filename"), "{e}");
            assert!(e.contains(why), "{bad:?}: {e}");
        }
    }

    #[test]
    fn rotations_translations_and_intrinsics_are_checked() {
        let mut notes = Renormalised::default();
        let ok = rigid(&at(), RT, [1.0, 0.0, 0.0, 0.0], [3e6, 5e6, 10.0], Transform::Pose, &mut notes);
        assert!(ok.is_ok() && notes.warnings().is_empty());
        let e = rigid(&at(), RT, [0.0; 4], [0.0; 3], Transform::Pose, &mut notes).unwrap_err();
        assert_eq!(
            e,
            "v1.0-mini/ego_pose.json row 3 (token X): field rotation [0, 0, 0, 0] is not a rotation \
             (norm 0; allowed 1 +- 0.01)"
        );
        let e = rigid(&at(), RT, [1.0, 0.0, 0.0, 0.0], [1e300, 0.0, 0.0], Transform::Pose, &mut notes).unwrap_err();
        assert!(e.contains("field translation [1e300, 0, 0] is 1e300 m from the origin, beyond the 1e7 m"), "{e}");
        let e = rigid(&at(), RT, [1.0, 0.0, 0.0, 0.0], [150.0, 0.0, 0.0], Transform::Mount, &mut notes).unwrap_err();
        assert!(e.contains("beyond the 100 m bound of a sensor mounting"), "{e}");
        let e = rigid(&at(), RT, [f64::NAN, 0.0, 0.0, 0.0], [0.0; 3], Transform::Pose, &mut notes).unwrap_err();
        assert!(e.contains("field rotation [NaN, 0, 0, 0] is not finite"), "{e}");
        assert!(rigid(&at(), RT, [1.5, 0.0, 0.0, 0.0], [0.0; 3], Transform::Pose, &mut notes).is_err());
        // Slightly off: normalised, one warning for the file however many rows.
        let q = rigid(&at(), RT, [0.999, 0.0, 0.0, 0.0], [0.0; 3], Transform::Pose, &mut notes).unwrap();
        assert!((q.rotation.length() - 1.0).abs() < 1e-12);
        let other = Place::row(Path::new("v1.0-mini/ego_pose.json"), 4, "Y");
        rigid(&other, RT, [0.995, 0.0, 0.0, 0.0], [0.0; 3], Transform::Pose, &mut notes).unwrap();
        let w = notes.warnings();
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].contains("2 quaternion(s)") && w[0].contains("row 4 (token Y) field rotation, norm 0.995"),
            "{w:?}"
        );

        let k = [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]];
        assert!(pinhole(&at(), "camera_intrinsic", k).is_ok());
        assert!(principal_point_inside(&at(), "camera_intrinsic", &k, 1600, 900).is_ok());
        assert!(principal_point_inside(&at(), "camera_intrinsic", &k, 0, 0).is_ok());
        let e = principal_point_inside(&at(), "camera_intrinsic", &k, 800, 450).unwrap_err();
        assert!(e.contains("principal point (816.3, 491.5) outside the 800x450 image"), "{e}");
        let e = pinhole(&at(), "camera_intrinsic", [[0.0; 3]; 3]).unwrap_err();
        assert!(e.contains("has focal lengths fx 0 and fy 0; both must be positive"), "{e}");
        let mut skewed = k;
        skewed[2] = [0.0, 0.0, 0.0];
        assert!(pinhole(&at(), "camera_intrinsic", skewed).unwrap_err().contains("is not a pinhole matrix"));
        skewed = k;
        skewed[0][1] = f64::INFINITY;
        assert!(pinhole(&at(), "camera_intrinsic", skewed).unwrap_err().contains("is not finite"));
    }
}
