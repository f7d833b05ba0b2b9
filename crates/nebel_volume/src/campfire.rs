//! An animated campfire (Röttger, "Volumetric Methods for the Real-Time
//! Display of Natural Gaseous Phenomena", 2004, §10.4): a [`Volume`] whose
//! density grid asset is regenerated every frame from 3D Perlin noise rising with time
//! ([`nebel_core::field::effects::campfire_density`]).
//!
//! The grid lives in the flame box `[−0.5, 0.5] × [0, 1.5] × [−0.5, 0.5]` of
//! the entity's local space; scale and move the entity's [`Transform`] to place
//! it. The volume is emissive with the `Fire` preset by default, so it needs no
//! sorting and the rebuild each frame is only the 16³ grid and its cells.
//!
//! The grid is made on the `AsyncComputeTaskPool` and written into the asset
//! in the first frame after: the fire drawn is a frame old, the next grid
//! already on its way (under [`HeavyBuilds::Blocking`] each frame waits for
//! its own time's grid).

use std::sync::Arc;

use bevy::prelude::*;
use nebel_core::field::DensityGrid;
use nebel_core::field::effects::{CAMPFIRE_DIMS, campfire_density};
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_render::{HeavyBuild, HeavyBuilds};

use crate::grid::VolumeGrid;
use crate::volume::{Volume, VolumeField};

/// Makes a [`Volume`] an animated campfire.
#[derive(Component, Clone, Copy, Debug, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(Volume = campfire_volume(), CampfireAnimation)]
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
        ..default()
    }
}

/// A campfire's next grid in the making.
#[derive(Component, Default)]
pub(crate) struct CampfireAnimation(Option<HeavyBuild<DensityGrid>>);

/// Writes every visible campfire's newest grid into its grid asset (added on
/// the first frame) and starts the next one for the current time (see the
/// module docs).
pub(crate) fn animate_campfires(
    time: Res<Time>,
    mode: Res<HeavyBuilds>,
    mut fires: Query<(
        &Campfire,
        &InheritedVisibility,
        &mut Volume,
        &mut CampfireAnimation,
    )>,
    mut grids: ResMut<Assets<VolumeGrid>>,
) {
    let at = time.elapsed_secs_f64();
    for (campfire, visibility, mut volume, mut animation) in &mut fires {
        let building = &mut animation.0;
        if !visibility.get() {
            *building = None;
            continue;
        }
        let Campfire { seed, dims } = *campfire;
        let start = || HeavyBuild::spawn(move || campfire_density(dims, at, seed));
        let Some(grid) = building.get_or_insert_with(start).poll(*mode) else {
            continue;
        };
        *building = (*mode != HeavyBuilds::Blocking).then(start);
        match &volume.field {
            VolumeField::Grid(handle) if let Some(mut asset) = grids.get_mut(handle) => {
                *asset = grid.into();
            }
            _ => volume.field = VolumeField::Grid(grids.add(VolumeGrid::from(grid))),
        }
    }
}
