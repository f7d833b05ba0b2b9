//! View-dependent level of detail for grid volumes: the volumetric C-LOD of
//! Röttger and Ertl 2003 §2-3, refined by the estimated error on the screen.
//!
//! Add [`VolumeLod`] to a [`Volume`](crate::Volume) with a grid field and its
//! batch comes from the octree instead of the full-resolution grid: the
//! hierarchy ([`nebel_lod::VolumeHierarchy`], built once per grid, 4 bytes per
//! point) is refined every time the view changes, and the leaves become
//! morphed, conforming tetrahedra in back-to-front order
//! ([`nebel_lod::octree::lod_batch`]). The criterion
//! ([`VolumeLod::criterion`]) is by default the screen error
//! ([`LodCriterion::ScreenError`], `nebel_lod::octree::screen_error`): a node
//! is refined while the RMSE its error alone would cause in the image of the
//! LOD camera exceeds a tolerance, from its projected size, its deviation
//! through the transfer function over its path length and the opacity in
//! front of it; the distance criterion of the paper,
//! `e = s · C · max(c · Δ, 1) / d` ([`LodCriterion::Distance`]), stays
//! selectable. A grid whose sides are not `2^n + 1` points is padded with
//! zero density up to the next such size (the volume's box grows on the
//! positive side; zero density adds nothing).
//!
//! The render system is unchanged: the LOD only changes which cells the
//! [`CellBatch`](nebel_render::CellBatch) holds.

use bevy::prelude::*;
use nebel_lod::OctreeSettings;
pub use nebel_lod::octree::LodCriterion;

/// Draws a grid [`Volume`](crate::Volume) through the octree C-LOD.
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct VolumeLod {
    /// The refinement's error metric and tolerance: the screen error, the
    /// tolerated RMSE over the image (linear RGB) that one node's error
    /// alone may cause, > 0; or the distance criterion's global accuracy `c`
    /// (Röttger and Ertl 2003 Eq. 1), 1/density units, ≥ 0. The quality
    /// preset scales either (`image_error / s`, `c · s`). Default
    /// [`LodCriterion::ScreenError`] with
    /// [`LodCriterion::DEFAULT_IMAGE_ERROR`] (0.1).
    pub criterion: LodCriterion,
    /// Minimum accuracy `C` (Röttger and Ertl 2003 Eq. 1), > √3: the deviation
    /// propagation `K_max = C / (2C − √3/2)`, and for the distance criterion
    /// how many node sizes away a node must be before it may stay coarse.
    /// Default 4.
    pub min_accuracy: f64,
}

impl Default for VolumeLod {
    fn default() -> Self {
        Self {
            criterion: LodCriterion::default(),
            min_accuracy: OctreeSettings::DEFAULT_MIN_ACCURACY,
        }
    }
}
