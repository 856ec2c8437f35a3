//! Items: keys along a dataset's dimensions, outermost first.

use std::fmt;

/// The most dimensions an item key may have.
pub const MAX_DIMS: usize = 4;

/// A key of `depth` coordinates, outermost first. A depth-2 key names an item of the second
/// dimension under an outer item; a depth-3 key names an item of the third under that one.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct ItemKey {
    pub depth: u8,
    pub idx: [u32; MAX_DIMS],
}

impl ItemKey {
    pub fn new(coords: &[u32]) -> ItemKey {
        let mut idx = [0; MAX_DIMS];
        idx[..coords.len()].copy_from_slice(coords);
        ItemKey { depth: coords.len() as u8, idx }
    }

    pub fn coords(&self) -> &[u32] {
        &self.idx[..self.depth as usize]
    }

    /// The enclosing key of depth `depth`.
    pub fn prefix(&self, depth: usize) -> ItemKey {
        let mut k = ItemKey { depth: depth as u8, idx: [0; MAX_DIMS] };
        k.idx[..depth].copy_from_slice(&self.idx[..depth]);
        k
    }

    /// This key extended by one coordinate.
    pub fn child(&self, i: u32) -> ItemKey {
        let mut k = *self;
        k.idx[k.depth as usize] = i;
        k.depth += 1;
        k
    }

    pub fn to_bytes(&self) -> [u8; 1 + 4 * MAX_DIMS] {
        let mut b = [0u8; 1 + 4 * MAX_DIMS];
        b[0] = self.depth;
        for (i, x) in self.idx.iter().enumerate() {
            b[1 + 4 * i..5 + 4 * i].copy_from_slice(&x.to_le_bytes());
        }
        b
    }

    pub fn from_bytes(b: &[u8]) -> Option<ItemKey> {
        if b.len() < 1 + 4 * MAX_DIMS || b[0] as usize > MAX_DIMS {
            return None;
        }
        let mut idx = [0; MAX_DIMS];
        for (i, x) in idx.iter_mut().enumerate() {
            *x = u32::from_le_bytes(b[1 + 4 * i..5 + 4 * i].try_into().ok()?);
        }
        Some(ItemKey { depth: b[0], idx })
    }
}

impl fmt::Debug for ItemKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}", self.coords())
    }
}

/// The items of a dataset, as a tree: the items of the outermost dimension, the items of the
/// second under each of them, and so on.
pub trait ItemSpace: Send + Sync {
    /// How many children `prefix` has along the next dimension (outer items for the empty key).
    fn count(&self, prefix: &ItemKey) -> u32;
    /// The printable name of the last coordinate of `item` (`s0`, `003`, `cam2`).
    fn label(&self, item: &ItemKey) -> String;

    /// The labels of every coordinate joined by `/`: `s0/003/cam2`.
    fn path(&self, item: &ItemKey) -> String {
        (1..=item.depth as usize).map(|d| self.label(&item.prefix(d))).collect::<Vec<_>>().join("/")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prefixes_children_and_bytes() {
        let k = ItemKey::new(&[3, 7, 2]);
        assert_eq!(k.prefix(2), ItemKey::new(&[3, 7]));
        assert_eq!(k.prefix(2).child(2), k);
        assert_eq!(ItemKey::from_bytes(&k.to_bytes()), Some(k));
        assert!(ItemKey::new(&[1]) < ItemKey::new(&[1, 0]));
    }
}
