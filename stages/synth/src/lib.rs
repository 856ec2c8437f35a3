//! The synthetic world: a procedural urban street, rendered by ray casting and written as a
//! complete nuScenes v1.0 dataset, with the ground truth real data lacks (dense depth, semantics,
//! and a renderer for any pose and time).
//!
//! Everything is a pure function of [`SynthConfig`]: the same config gives byte-identical files.

pub mod material;
pub mod render;
pub mod shapes;
pub mod world;
mod writer;

pub use render::{CameraImage, LidarModel, LidarSweep, PinholeCamera, Snapshot};
pub use world::{World, WorldParams};
pub use writer::{lidarseg_index, write_dataset};

use anyhow::{Context, Result};
use dist4d_types::geometry::Se3;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Bumped whenever the same config would produce different data. 2: ground-truth depth EXRs
/// have their channel named `Y` (which OpenCV reads), not `Z`.
pub const GENERATOR_VERSION: u32 = 2;

/// Where the ground truth sits inside a synthetic dataset root.
pub const GROUND_TRUTH_DIR: &str = "groundtruth";

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SynthConfig {
    pub seed: u64,
    pub scenes: u32,
    /// Keyframes (2 Hz samples) per scene.
    pub keyframes: u32,
    /// Image size; intrinsics scale with it (the real ones are for 1600 x 900).
    pub width: u32,
    pub height: u32,
    /// Write the 20 Hz LiDAR sweeps between keyframes.
    pub lidar_sweeps: bool,
    /// Write the 12 Hz camera sweeps between keyframes.
    pub camera_sweeps: bool,
    /// Dense depth EXR and semantic PNG for every camera image.
    pub ground_truth: bool,
    pub jpeg_quality: u8,
    pub world: WorldParams,
    pub lidar: LidarModel,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            seed: 0,
            scenes: 1,
            keyframes: 40,
            width: 1600,
            height: 900,
            lidar_sweeps: true,
            camera_sweeps: false,
            ground_truth: true,
            jpeg_quality: 90,
            world: WorldParams::default(),
            lidar: LidarModel::default(),
        }
    }
}

impl SynthConfig {
    /// The seed of scene `i`: scenes are independent worlds.
    pub fn scene_seed(&self, i: u32) -> u64 {
        dist4d_types::rng::mix(self.seed.wrapping_mul(0x1000_0000_01B3) ^ (i as u64 + 1))
    }

    /// The world of scene `i`, long enough for its keyframes.
    pub fn world(&self, i: u32) -> World {
        let params = WorldParams { duration: self.keyframes as f64 * 0.5 + 1.0, ..self.world.clone() };
        World::generate(self.scene_seed(i), &params)
    }
}

/// The nuScenes sensor rig of the shared real keyframe (scene-0061): mounting (sensor -> ego,
/// quaternion `[w, x, y, z]`, metres) and, for cameras, intrinsics at 1600 x 900.
pub struct RigSensor {
    pub channel: &'static str,
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
    pub focal: f64,
    pub principal: [f64; 2],
}

pub const LIDAR_TOP: RigSensor = RigSensor {
    channel: "LIDAR_TOP",
    translation: [0.943713, 0.0, 1.84023],
    rotation: [0.7077955119163518, -0.006492242056004365, 0.010646214713995808, -0.7063073142877817],
    focal: 0.0,
    principal: [0.0, 0.0],
};

pub const CAMERA_RIG: [RigSensor; 6] = [
    RigSensor {
        channel: "CAM_FRONT",
        translation: [1.70079118954, 0.0159456324149, 1.51095763913],
        rotation: [0.4998015430569128, -0.5030316162024876, 0.4997798114386805, -0.49737083824542755],
        focal: 1266.417203046554,
        principal: [816.2670197447984, 491.50706579294757],
    },
    RigSensor {
        channel: "CAM_FRONT_RIGHT",
        translation: [1.5508477543, -0.493404796419, 1.49574800619],
        rotation: [0.2060347966337182, -0.2026940577919598, 0.6824507824531167, -0.6713610884174485],
        focal: 1260.8474446004698,
        principal: [807.968244525554, 495.3344268742088],
    },
    RigSensor {
        channel: "CAM_BACK_RIGHT",
        translation: [1.0148780988, -0.480568219723, 1.56239545128],
        rotation: [0.12280980120078765, -0.132400842670559, -0.7004305821388234, 0.690496031265798],
        focal: 1259.5137405846733,
        principal: [807.2529053838625, 501.19579884916527],
    },
    RigSensor {
        channel: "CAM_BACK",
        translation: [0.0283260309358, 0.00345136761476, 1.57910346144],
        rotation: [0.5037872666382278, -0.49740249788611096, -0.4941850223835201, 0.5045496097725578],
        focal: 809.2209905677063,
        principal: [829.2196003259838, 481.77842384512485],
    },
    RigSensor {
        channel: "CAM_BACK_LEFT",
        translation: [1.03569100218, 0.484795032713, 1.59097014818],
        rotation: [0.6924185592174665, -0.7031619420114925, -0.11648342771943819, 0.11203317912370753],
        focal: 1256.7414812095406,
        principal: [792.1125740759628, 492.7757465151356],
    },
    RigSensor {
        channel: "CAM_FRONT_LEFT",
        translation: [1.52387798135, 0.494631336551, 1.50932822144],
        rotation: [0.6757265034669446, -0.6736266522251881, 0.21214015046209478, -0.21122827103904068],
        focal: 1272.5979470598488,
        principal: [826.6154927353808, 479.75165386361925],
    },
];

impl RigSensor {
    pub fn sensor_to_ego(&self) -> Se3 {
        Se3::from_wxyz_t(self.rotation, self.translation)
    }

    /// Intrinsics for an image of `width` x `height` (scaled from 1600 x 900, pixel-area convention).
    pub fn intrinsics(&self, width: u32, height: u32) -> [[f64; 3]; 3] {
        let (sx, sy) = (width as f64 / 1600.0, height as f64 / 900.0);
        [
            [self.focal * sx, 0.0, self.principal[0] * sx],
            [0.0, self.focal * sy, self.principal[1] * sy],
            [0.0, 0.0, 1.0],
        ]
    }
}

/// Exact rendering of a synthetic dataset's world at any pose and time: what novel-view
/// evaluation compares against. Rebuilt from the dataset's `groundtruth/synth.json`.
pub struct Renderer {
    pub config: SynthConfig,
    worlds: Vec<World>,
}

impl Renderer {
    pub fn new(config: SynthConfig) -> Renderer {
        let worlds = (0..config.scenes).map(|i| config.world(i)).collect();
        Renderer { config, worlds }
    }

    /// Opens the renderer of a dataset written by `dist4d synth`.
    pub fn open(root: &Path) -> Result<Renderer> {
        let path = root.join(GROUND_TRUTH_DIR).join("synth.json");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("reading {} (is this a dist4d synthetic dataset?)", path.display()))?;
        let value: serde_json::Value =
            serde_json::from_str(&text).with_context(|| format!("malformed {}", path.display()))?;
        Renderer::from_json(value).with_context(|| path.display().to_string())
    }

    /// The renderer of a `groundtruth/synth.json`'s content.
    pub fn from_json(value: serde_json::Value) -> Result<Renderer> {
        let file: writer::SynthFile = serde_json::from_value(value).context("malformed synth.json")?;
        anyhow::ensure!(
            file.generator_version == GENERATOR_VERSION,
            "written by generator version {}, this build renders version {}",
            file.generator_version,
            GENERATOR_VERSION
        );
        Ok(Renderer::new(file.config))
    }

    /// The renderer of a dataset port `synth_world`'s bytes (`{"synth": <synth.json>}`), built once
    /// per process and world: generating a world takes longer than rendering a view, and every
    /// stage that scores against the world (novel views, clouds, occupancy) asks for it.
    pub fn shared(world: &[u8]) -> Result<std::sync::Arc<Renderer>> {
        use std::collections::HashMap;
        use std::sync::{Arc, Mutex, OnceLock};
        static CACHE: OnceLock<Mutex<HashMap<[u8; 32], Arc<Renderer>>>> = OnceLock::new();
        let key = *blake3::hash(world).as_bytes();
        let cache = CACHE.get_or_init(Default::default);
        if let Some(r) = cache.lock().map_err(|_| anyhow::anyhow!("renderer cache poisoned"))?.get(&key) {
            return Ok(r.clone());
        }
        let value: serde_json::Value = serde_json::from_slice(world).context("`world` is not JSON")?;
        let r = Arc::new(Renderer::from_json(value["synth"].clone())?);
        cache.lock().map_err(|_| anyhow::anyhow!("renderer cache poisoned"))?.insert(key, r.clone());
        Ok(r)
    }

    /// The index of the scene the dataset names `name` (`synth-0003` -> 3).
    pub fn scene_index(&self, name: &str) -> Option<u32> {
        let i: u32 = name.strip_prefix("synth-")?.parse().ok()?;
        (i < self.config.scenes).then_some(i)
    }

    pub fn world(&self, scene: u32) -> Option<&World> {
        self.worlds.get(scene as usize)
    }

    /// RGB, depth and semantics of `camera` in scene `scene` at `t` seconds from its start
    /// (timestamps: `(timestamp_us - scene_start_us) / 1e6`, see [`writer::scene_start_us`]).
    pub fn render(&self, scene: u32, t: f64, camera: &PinholeCamera) -> Result<CameraImage> {
        let w = self.worlds.get(scene as usize).with_context(|| format!("no scene {scene}"))?;
        Ok(Snapshot::new(w, t).render(camera))
    }

    /// The exact semantic occupancy of a grid around an ego pose at a nuScenes timestamp
    /// ([`Snapshot::occupancy`]): Cityscapes ids, 0 = free.
    #[allow(clippy::too_many_arguments)]
    pub fn occupancy_at_timestamp(
        &self,
        scene: u32,
        timestamp_us: i64,
        ego_to_world: &dist4d_types::geometry::Se3,
        min: glam::DVec3,
        voxel: f64,
        dims: [usize; 3],
        samples: usize,
    ) -> Result<Vec<u8>> {
        let w = self.worlds.get(scene as usize).with_context(|| format!("no scene {scene}"))?;
        let t = (timestamp_us - writer::scene_start_us(scene)) as f64 * 1e-6;
        let grid = Snapshot::new(w, t).occupancy(ego_to_world, min, voxel, dims, samples);
        dist4d_types::cancel::check()?;
        Ok(grid)
    }

    /// The world of scene `scene` at a nuScenes timestamp (microseconds): to cast rays in.
    pub fn snapshot_at_timestamp(&self, scene: u32, timestamp_us: i64) -> Result<Snapshot<'_>> {
        let w = self.worlds.get(scene as usize).with_context(|| format!("no scene {scene}"))?;
        Ok(Snapshot::new(w, (timestamp_us - writer::scene_start_us(scene)) as f64 * 1e-6))
    }

    /// Like [`Renderer::render`] with a nuScenes timestamp (microseconds).
    pub fn render_at_timestamp(&self, scene: u32, timestamp_us: i64, camera: &PinholeCamera) -> Result<CameraImage> {
        self.render(scene, (timestamp_us - writer::scene_start_us(scene)) as f64 * 1e-6, camera)
    }
}
