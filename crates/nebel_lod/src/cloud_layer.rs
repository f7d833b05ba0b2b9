//! A cloud layer between two surfaces (Röttger 2004 §10.4 and Fig. 10.6:
//! a cloud layer drawn as prisms between two height fields, with the ground
//! fog's machinery), sorted back to front and lit by the sun through the
//! layer above each point.
//!
//! A [`CloudLayerShape`] turns a thickness per grid point (procedural noise
//! patches, `nebel_core::field::FogNoise`, or a map) into the layer's two
//! surfaces over a square of `extent` centred on the origin of its frame:
//! the base hangs `sag · t` below the altitude `base` and the top rises
//! `(1 − sag) · t` above it, so thick clouds also reach lower, and where `t`
//! is 0 the surfaces meet and there is no cloud. Two maps give the surfaces
//! directly ([`SurfaceLayer::new`]). The cells' scalar is the sunlight that
//! reaches each level ([`PrismScalar::Sunlit`](crate::PrismScalar::Sunlit)), sampled on
//! [`CloudLayerShape::profile`]'s levels, for a transfer function over
//! light (the `CloudLight` preset): bright tops, darker bases, as the cloud
//! volume's light field gives them.

use glam::DVec2;
use nebel_core::field::{HeightField, side_fade_factors};

use crate::ground_fog::FogProfile;
use crate::quadtree::TerrainError;
use crate::surface_layer::{LayerTop, SurfaceLayer, SurfaceLayerError};

/// Where a cloud layer lies (see the [module docs](self)); lengths in world
/// units (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudLayerShape {
    /// Side of the square layer, finite and > 0.
    pub extent: f64,
    /// The altitude the clouds grow from, finite.
    pub base: f64,
    /// The part of each cloud's thickness below `base`, in [0, 1].
    pub sag: f64,
    /// Fraction of the side, in [0, 0.5], over which the thickness of
    /// [`CloudLayerShape::layer`] falls to 0 toward the square's four edges
    /// (`nebel_core::field::side_fade_factors`), so no cloud is cut flat by
    /// them; 0 keeps the thickness as given.
    pub edge_fade: f64,
}

impl CloudLayerShape {
    /// Checks the shape's ranges.
    pub fn validate(&self) -> Result<(), TerrainError> {
        let (extent, base, sag, fade) = (self.extent, self.base, self.sag, self.edge_fade);
        let check = TerrainError::check;
        let extent_ok = extent.is_finite() && extent > 0.0;
        check(extent_ok, "cloud layer extent", extent, "finite and > 0")?;
        check(base.is_finite(), "cloud layer base", base, "finite")?;
        check(
            (0.0..=1.0).contains(&sag),
            "cloud layer sag",
            sag,
            "in [0, 1]",
        )?;
        let fade_ok = (0.0..=0.5).contains(&fade);
        check(fade_ok, "cloud layer edge fade", fade, "in [0, 0.5]")
    }

    /// The layer of `thickness` (`side × side` values ≥ 0, `side = 2^k + 1`,
    /// index `i + side · j` along x and z) faded toward the edges
    /// ([`CloudLayerShape::edge_fade`]), its quadtree built for the
    /// minimum resolution `min_resolution` with both surfaces' roughness,
    /// the thickness's weighted by `roughness_weight`.
    pub fn layer(
        &self,
        side: usize,
        thickness: &[f32],
        min_resolution: f32,
        roughness_weight: f32,
    ) -> Result<SurfaceLayer, SurfaceLayerError> {
        self.validate()?;
        TerrainError::check_map_length(side, thickness.len())?;
        if let Some(index) = thickness.iter().position(|t| !t.is_finite()) {
            return Err(TerrainError::NonFiniteMapValue {
                index,
                value: thickness[index],
            }
            .into());
        }
        let fade = side_fade_factors(self.edge_fade as f32, side);
        let thickness: Vec<f64> = thickness
            .iter()
            .enumerate()
            .map(|(n, t)| f64::from(t.max(0.0)) * fade[n % side] * fade[n / side])
            .collect();
        let below = |t: f64| (self.base - self.sag * t) as f32;
        let above = |t: f64| (self.base + (1.0 - self.sag) * t) as f32;
        let bottom = self.field(side, thickness.iter().map(|t| below(*t)).collect())?;
        let top: Vec<f32> = thickness.iter().map(|t| above(*t)).collect();
        SurfaceLayer::new(
            bottom,
            LayerTop::Surface(&top),
            None,
            min_resolution,
            roughness_weight,
        )
    }

    /// The height field of `heights` (`side²`) over the layer's square.
    pub fn field(&self, side: usize, heights: Vec<f32>) -> Result<HeightField, TerrainError> {
        self.validate()?;
        let spacing = self.extent / (side.max(2) - 1) as f64;
        if let Some(index) = heights.iter().position(|h| !h.is_finite()) {
            return Err(TerrainError::NonFiniteHeight {
                i: index % side.max(1),
                j: index / side.max(1),
                index,
                value: heights[index],
            });
        }
        Ok(HeightField::new(
            [side, side],
            DVec2::splat(spacing),
            DVec2::splat(-self.extent / 2.0),
            heights,
        )?)
    }

    /// Four stacked prisms per column, at relative heights 0, ¼, ½, ¾ and 1,
    /// on which the sunlight is sampled.
    pub fn profile() -> FogProfile {
        FogProfile::new((0..=4).map(|k| [k as f32 / 4.0, 0.0]).collect()).expect("a valid profile")
    }
}
