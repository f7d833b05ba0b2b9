//! An animated campfire (paper 001 §10.4): a [`Volume`] whose density grid is
//! regenerated every frame from 3D Perlin noise rising with time
//! ([`nebel_core::field::effects::campfire_density`]).
//!
//! The grid lives in the flame box `[−0.5, 0.5] × [0, 1.5] × [−0.5, 0.5]` of
//! the entity's local space; scale and move the entity's [`Transform`] to place
//! it. The volume is emissive with the `Fire` preset by default, so it needs no
//! sorting and the rebuild each frame is only the 16³ grid and its cells.

use std::sync::Arc;

use bevy::prelude::*;
use nebel_core::field::effects::{CAMPFIRE_DIMS, campfire_density};
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};

use crate::volume::{Volume, VolumeField};

/// Makes a [`Volume`] an animated campfire.
#[derive(Component, Clone, Copy, Debug, Reflect)]
#[reflect(Component, Default)]
#[require(Volume = campfire_volume())]
pub struct Campfire {
    /// Noise seed: two fires with different seeds flicker differently. Default 0.
    pub seed: u32,
    /// Grid points per axis, each 2 to 257. Default `[17, 17, 17]` (16³ cells).
    pub dims: [usize; 3],
}

impl Default for Campfire {
    fn default() -> Self {
        Self {
            seed: 0,
            dims: CAMPFIRE_DIMS,
        }
    }
}

fn campfire_volume() -> Volume {
    Volume {
        field: VolumeField::Grid(Arc::new(campfire_density(CAMPFIRE_DIMS, 0.0, 0))),
        transfer_function: Arc::new(TransferFunction::preset(TransferPreset::Fire)),
        mode: OpticalMode::Emissive,
    }
}

/// Regenerates every campfire's grid for the current time.
pub(crate) fn animate_campfires(time: Res<Time>, mut fires: Query<(&Campfire, &mut Volume)>) {
    for (campfire, mut volume) in &mut fires {
        let grid = campfire_density(campfire.dims, time.elapsed_secs_f64(), campfire.seed);
        volume.field = VolumeField::Grid(Arc::new(grid));
    }
}
