//! The hasher of the integer keys of voxel sets and cell maps: `FramePair`'s thinning,
//! `SurroundCloud`'s voxels, the cells of [`crate::lone_points`].

/// A multiply-rotate hasher for voxel keys (the FxHash recipe): the default SipHash cost more
/// than the thinning itself. Keys come from our own geometry, not from an adversary.
#[derive(Default)]
pub struct VoxelHasher(u64);

impl std::hash::Hasher for VoxelHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.write_u64(*b as u64);
        }
    }
    fn write_u64(&mut self, x: u64) {
        self.0 = (self.0.rotate_left(5) ^ x).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
    fn write_i64(&mut self, x: i64) {
        self.write_u64(x as u64);
    }
}
