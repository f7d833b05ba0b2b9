//! [`CellProjection`]: how a camera draws cells, and its extraction into the
//! render world.

use bevy::prelude::*;
use bevy::render::Extract;
use bevy::render::sync_world::RenderEntity;

use crate::cell_batch::CellBatch;
use crate::quality::EffectiveQuality;

/// How a camera draws nebel's cells. A camera without it draws as the
/// [`NebelQuality`](crate::NebelQuality) preset says
/// ([`QualityPreset::cell_projection`](crate::QualityPreset::cell_projection)).
///
/// [`CellProjection::EXACT`] is the method of the papers: every cell at full
/// resolution, every ray to its end. The default, [`CellProjection::HIGH`],
/// draws at half resolution where that changes the image by no more than
/// about one 8-bit step, and stops shading opaque pixels.
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Debug, Clone)]
#[require(Camera3d)]
pub struct CellProjection {
    /// The resolution the cells are drawn at: a fraction of the view's,
    /// mixed with full resolution where the fraction would be off (see
    /// [`CellResolution`]). Default [`CellResolution::Half`].
    pub resolution: CellResolution,
    /// Below full resolution, the largest interpolation error a pixel may
    /// take from the lower resolution, in linear RGB and transmittance:
    /// the error of the bilinear mix of its four low-resolution neighbours
    /// at its weights `w`, estimated from their second differences along
    /// each axis (`w (1 − w) h² |f''| / 2` for samples `h` apart, the
    /// leading term of the error). A pixel beyond it is drawn at full
    /// resolution. 0 draws every pixel whose neighbours are not exactly
    /// linear at full resolution; larger values trade fine detail for
    /// speed. A value that is not finite and ≥ 0 counts as 0. Default
    /// 0.004, about one 8-bit step.
    pub upsample_tolerance: f32,
    /// Stop shading a pixel once its transmittance has fallen below
    /// [`CellProjection::TERMINATION_TRANSMITTANCE`]: cells go front to back
    /// and, between groups of them, a full-screen pass marks such pixels in
    /// a stencil that the later cells' fragments are tested against. What
    /// the skipped cells would have added is at most the threshold times
    /// their radiance. MIP cells are not skipped (their maximum is not
    /// attenuated). Default true.
    pub early_termination: bool,
}

/// The resolution of [`CellProjection`].
///
/// At a fraction `1/k` of the view's resolution, the cells are drawn into a
/// target of `1/k²` the pixels, clipped by the mean opaque depth of each
/// `k × k` block. A full-resolution pixel then takes the bilinear mix of the
/// four low-resolution pixels around it where (1) the mix of their depths
/// predicts its own depth within [`CellResolution::DEPTH_TOLERANCE`]
/// (relative), (2) the interpolation error estimated from the second
/// differences around them is within [`CellProjection::upsample_tolerance`]
/// and (3) it lies at least `1.5 k` pixels inside the view. Every other
/// pixel, along the edges of opaque geometry, of the volume and of the
/// view, is drawn again at full resolution, exact.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Reflect)]
#[reflect(Default, Debug, Clone)]
pub enum CellResolution {
    /// Every pixel, exact.
    Full,
    /// Half the view's width and height, mixed with full resolution.
    #[default]
    Half,
    /// A quarter of the view's width and height, mixed with full
    /// resolution.
    Quarter,
}

impl CellResolution {
    /// Largest relative difference between a pixel's opaque depth and the
    /// one its low-resolution neighbours predict for the mix to be used.
    pub const DEPTH_TOLERANCE: f32 = 1.0e-3;

    /// The factor `k` the view's width and height are divided by.
    pub fn divisor(self) -> u32 {
        match self {
            Self::Full => 1,
            Self::Half => 2,
            Self::Quarter => 4,
        }
    }
}

impl CellProjection {
    /// The transmittance below which early termination stops shading a
    /// pixel: 1/512, half an 8-bit step for radiance up to 1.
    pub const TERMINATION_TRANSMITTANCE: f32 = 1.0 / 512.0;

    /// Every cell at full resolution, every ray to its end.
    pub const EXACT: Self = Self {
        resolution: CellResolution::Full,
        upsample_tolerance: 0.0,
        early_termination: false,
    };

    /// The `High` preset and the default: half resolution where the image
    /// changes by about one 8-bit step at most, early termination.
    pub const HIGH: Self = Self {
        resolution: CellResolution::Half,
        upsample_tolerance: 0.004,
        early_termination: true,
    };

    /// The `Medium` preset: half resolution where the image changes by
    /// 0.05 at most.
    pub const MEDIUM: Self = Self {
        upsample_tolerance: 0.05,
        ..Self::HIGH
    };

    /// The `Low` preset: a quarter of the resolution where the image
    /// changes by 0.2 at most.
    pub const LOW: Self = Self {
        resolution: CellResolution::Quarter,
        upsample_tolerance: 0.2,
        early_termination: true,
    };

    /// The upsample tolerance the shader uses: a value that is not finite
    /// and ≥ 0 counts as 0.
    pub fn checked_upsample_tolerance(&self) -> f32 {
        if self.upsample_tolerance.is_finite() && self.upsample_tolerance >= 0.0 {
            self.upsample_tolerance
        } else {
            0.0
        }
    }
}

impl Default for CellProjection {
    fn default() -> Self {
        Self::HIGH
    }
}

/// Gives every 3D camera's render entity the [`CellProjection`] it draws
/// with: its own, or the quality preset's; nothing while no cells are drawn.
pub fn extract_cell_projection(
    mut commands: Commands,
    cameras: Extract<Query<(RenderEntity, Option<&CellProjection>), With<Camera3d>>>,
    batches: Extract<Query<(), With<CellBatch>>>,
    quality: Extract<Option<Res<EffectiveQuality>>>,
) {
    if batches.is_empty() {
        return;
    }
    let preset = quality
        .as_ref()
        .map_or_else(CellProjection::default, |quality| {
            quality.preset.cell_projection()
        });
    for (entity, settings) in &cameras {
        commands
            .entity(entity)
            .insert(settings.copied().unwrap_or(preset));
    }
}
