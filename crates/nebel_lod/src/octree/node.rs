//! [`Node`]: one octree node, addressed by its level and minimum grid point.

/// One node of the volume octree: the cube of `2^level` voxels per edge whose
/// minimum corner is grid point `origin` (each coordinate a multiple of
/// `2^level`).
///
/// Level 0 is a single voxel, the finest leaf, which has no points but its
/// corners. Every node of level ≥ 1 has a unique centre grid point
/// `origin + 2^(level−1)`, whose three coordinates have exactly `level − 1`
/// trailing zero bits; the hierarchy stores the node's Δ and e' there.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Node {
    /// `log2` of the edge length in voxels; 0 for a voxel.
    pub level: u32,
    /// Grid point of the minimum corner.
    pub origin: [usize; 3],
}

impl Node {
    /// Edge length in voxels, `2^level`.
    pub fn size(&self) -> usize {
        1 << self.level
    }

    /// Grid point of corner `v = x + 2y + 4z` (corner bits `x, y, z ∈ {0, 1}`,
    /// numbered as in [`nebel_core::cell::Hexahedron`]).
    pub fn corner(&self, v: usize) -> [usize; 3] {
        let s = self.size();
        std::array::from_fn(|a| self.origin[a] + s * ((v >> a) & 1))
    }

    /// The centre grid point; `None` for a voxel (level 0).
    pub fn centre(&self) -> Option<[usize; 3]> {
        (self.level >= 1).then(|| self.origin.map(|o| o + (1 << (self.level - 1))))
    }

    /// The node of the next level up that contains this one. The caller
    /// checks that this node is below the roots' level.
    pub fn parent(&self) -> Node {
        let mask = !((1usize << (self.level + 1)) - 1);
        Node {
            level: self.level + 1,
            origin: self.origin.map(|o| o & mask),
        }
    }

    /// The eight children, child `x + 2y + 4z` at the node's corner `v` side;
    /// `None` for a voxel.
    pub fn children(&self) -> Option<[Node; 8]> {
        let level = self.level.checked_sub(1)?;
        let half = 1 << level;
        Some(std::array::from_fn(|v| Node {
            level,
            origin: std::array::from_fn(|a| self.origin[a] + half * ((v >> a) & 1)),
        }))
    }
}
