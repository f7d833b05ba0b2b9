//! An animated campfire (Röttger, "Volumetric Methods for the Real-Time
//! Display of Natural Gaseous Phenomena", 2004, §10.4): a [`Volume`] whose
//! density grid asset is regenerated every frame from 3D Perlin noise rising with time
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

use crate::grid::VolumeGrid;
use crate::volume::{Volume, VolumeField};

/// Makes a [`Volume`] an animated campfire.
#[derive(Component, Clone, Copy, Debug, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(Volume = campfire_volume())]
pub struct Campfire {
    /// Noise seed: two fires with different seeds flicker differently. Default 0.
    pub seed: u32,
    /// Grid points per axis, each clamped to 2..=257 (its full-resolution
    /// batch must also fit the memory budget, about 238³ points: beyond, the
    /// volume fails with the reason). Default `[17, 17, 17]` (16³ voxels).
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

/// The volume a campfire starts with: no grid yet (the animation adds it),
/// the `Fire` preset, emissive.
fn campfire_volume() -> Volume {
    Volume {
        field: VolumeField::default(),
        transfer_function: Arc::new(TransferFunction::preset(TransferPreset::Fire)),
        mode: OpticalMode::Emissive,
    }
}

/// Regenerates every visible campfire's grid for the current time, in its
/// grid asset (added on the first frame).
pub(crate) fn animate_campfires(
    time: Res<Time>,
    mut fires: Query<(&Campfire, &InheritedVisibility, &mut Volume)>,
    mut grids: ResMut<Assets<VolumeGrid>>,
) {
    for (campfire, visibility, mut volume) in &mut fires {
        if !visibility.get() {
            continue;
        }
        let grid = campfire_density(campfire.dims, time.elapsed_secs_f64(), campfire.seed);
        match &volume.field {
            VolumeField::Grid(handle) if let Some(mut asset) = grids.get_mut(handle) => {
                *asset = grid.into();
            }
            _ => volume.field = VolumeField::Grid(grids.add(VolumeGrid::from(grid))),
        }
    }
}
