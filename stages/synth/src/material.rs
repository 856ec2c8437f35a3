//! What the world's surfaces are: their semantic class (Cityscapes ids, as the ground truth
//! writes them) and their material (how the renderer colours them and the LiDAR sees them).

/// Cityscapes ids of the ground-truth semantic PNGs.
pub mod class {
    pub const ROAD: u8 = 7;
    pub const SIDEWALK: u8 = 8;
    pub const BUILDING: u8 = 11;
    pub const POLE: u8 = 17;
    pub const VEGETATION: u8 = 21;
    pub const TERRAIN: u8 = 22;
    pub const SKY: u8 = 23;
    pub const PERSON: u8 = 24;
    pub const CAR: u8 = 26;
    /// Only in LiDAR labels: the ego vehicle's own body.
    pub const EGO: u8 = 255;
}

/// What a surface looks like; [`crate::render`] turns it into colour and LiDAR intensity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Material {
    Road,
    Sidewalk,
    Kerb,
    Facade { hue: [f32; 3], floor_height: f32, window_width: f32 },
    Roof,
    Metal,
    Bark,
    Foliage,
    CarPaint([f32; 3]),
    Glass,
    Cloth([f32; 3]),
    Skin,
    EgoBody,
}
