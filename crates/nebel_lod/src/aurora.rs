//! The aurora as a layer between two surfaces (Röttger 2004 §10.4: the
//! "polar light" drawn as emissive prisms between two height fields).
//!
//! An [`AuroraShape`] places a footprint of curtain strengths in [0, 1]
//! (`nebel_core::field::AuroraCurtains::map`, or a map) over a square of
//! `extent` centred on the origin of its frame: the bottom surface is the
//! plane at altitude `bottom`, the top is `bottom + strength · (top −
//! bottom)`, so a curtain rises as high as it is strong and ends where its
//! strength does (at zero thickness: no cells). The cells' scalar is the
//! altitude above the bottom over the full span `top − bottom`
//! ([`PrismScalar::Height`]), so the transfer function colours by altitude
//! (the green of oxygen's 557.7 nm line low, its red 630.0 nm line high)
//! the same way in weak and strong curtains: weak ones stay green, strong
//! ones reach into the red.

use glam::DVec2;
use nebel_core::field::HeightField;

use crate::ground_fog::{FogProfile, PrismScalar};
use crate::quadtree::TerrainError;
use crate::surface_layer::{LayerTop, SurfaceLayer, SurfaceLayerError};

/// Where an aurora's curtains stand (see the [module docs](self)); lengths
/// in world units (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AuroraShape {
    /// Side of the square footprint, finite and > 0.
    pub extent: f64,
    /// Altitude of the curtains' bottom, finite.
    pub bottom: f64,
    /// Altitude the strongest curtains reach, finite and above `bottom`.
    pub top: f64,
}

impl AuroraShape {
    /// Checks the shape's ranges.
    pub fn validate(&self) -> Result<(), TerrainError> {
        let (extent, bottom, top) = (self.extent, self.bottom, self.top);
        let check = TerrainError::check;
        check(
            extent.is_finite() && extent > 0.0,
            "aurora extent",
            extent,
            "finite and > 0",
        )?;
        check(bottom.is_finite(), "aurora bottom", bottom, "finite")?;
        let requirement = "finite and above the bottom";
        check(
            top.is_finite() && top > bottom,
            "aurora top",
            top,
            requirement,
        )
    }

    /// The curtains' layer over `strength` (`side × side` values in [0, 1],
    /// `side = 2^k + 1`, index `i + side · j` along x and z; values outside
    /// [0, 1] are clamped), its quadtree built for the minimum resolution
    /// `min_resolution` with the thickness's roughness weighted by
    /// `roughness_weight`.
    pub fn layer(
        &self,
        side: usize,
        strength: &[f32],
        min_resolution: f32,
        roughness_weight: f32,
    ) -> Result<SurfaceLayer, SurfaceLayerError> {
        self.validate()?;
        TerrainError::check_map_length(side, strength.len())?;
        let span = self.top - self.bottom;
        let thickness: Vec<f32> = strength
            .iter()
            .map(|s| (f64::from(s.clamp(0.0, 1.0)) * span) as f32)
            .collect();
        // A NaN strength survives the clamp: the layer refuses it, naming it.
        let spacing = self.extent / (side - 1) as f64;
        let bottom = HeightField::new(
            [side, side],
            DVec2::splat(spacing),
            DVec2::splat(-self.extent / 2.0),
            vec![self.bottom as f32; side * side],
        )
        .map_err(TerrainError::from)?;
        SurfaceLayer::new(
            bottom,
            LayerTop::Thickness(&thickness),
            None,
            min_resolution,
            roughness_weight,
        )
    }

    /// The cells' scalar: the altitude above the bottom over `top − bottom`.
    pub fn scalar(&self) -> PrismScalar {
        PrismScalar::Height {
            span: (self.top - self.bottom) as f32,
        }
    }

    /// One prism per column (the scalar is linear in height, so one level
    /// carries it exactly).
    pub fn profile() -> FogProfile {
        FogProfile::new(vec![[0.0, 0.0], [1.0, 1.0]]).expect("a valid profile")
    }
}
