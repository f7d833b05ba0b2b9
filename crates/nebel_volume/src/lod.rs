//! View-dependent level of detail for grid volumes: the volumetric C-LOD of
//! Röttger and Ertl 2003 §2-3.
//!
//! Add [`VolumeLod`] to a [`Volume`](crate::Volume) with a grid field and its
//! batch comes from the octree instead of the full-resolution grid: the
//! hierarchy ([`nebel_lod::VolumeHierarchy`], built once per grid, 4 bytes per point) is
//! refined every time the eye moves with `e = s · C · max(c · Δ, 1) / d`, and
//! the leaves become morphed, conforming tetrahedra in back-to-front order
//! ([`nebel_lod::octree::lod_batch`]). A grid whose sides are not `2^n + 1`
//! points is padded with zero density up to the next such size (the volume's
//! box grows on the positive side; zero density adds nothing).
//!
//! The render system is unchanged: the LOD only changes which cells the
//! [`CellBatch`](nebel_render::CellBatch) holds.

use bevy::prelude::*;
use nebel_lod::OctreeSettings;
use nebel_lod::octree::RefinementSettings;

/// Draws a grid [`Volume`](crate::Volume) through the octree C-LOD.
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct VolumeLod {
    /// Global accuracy `c` (Röttger and Ertl 2003 Eq. 1), 1/density units, ≥ 0: higher
    /// draws more cells. Default 16.
    pub accuracy: f64,
    /// Minimum accuracy `C` (Röttger and Ertl 2003 Eq. 1), > √3: how many node sizes away
    /// a node must be before it may stay coarse; it also sets the deviation
    /// propagation `K_max = C / (2C − √3/2)`. Default 4.
    pub min_accuracy: f64,
}

impl Default for VolumeLod {
    fn default() -> Self {
        Self {
            accuracy: RefinementSettings::DEFAULT_ACCURACY,
            min_accuracy: OctreeSettings::DEFAULT_MIN_ACCURACY,
        }
    }
}
