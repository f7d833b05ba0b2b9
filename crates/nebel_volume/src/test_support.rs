//! Helpers for the crate's tests.

use std::sync::Arc;

use bevy::prelude::*;
use nebel_core::field::DensityGrid;

use crate::{Volume, VolumeField, VolumeGrid};

/// The grid asset of `entity`'s volume, if it has one yet.
pub(crate) fn volume_grid(app: &App, entity: Entity) -> Option<Arc<DensityGrid>> {
    match &app.world().get::<Volume>(entity)?.field {
        VolumeField::Grid(handle) => Some(
            app.world()
                .resource::<Assets<VolumeGrid>>()
                .get(handle)?
                .0
                .clone(),
        ),
        VolumeField::Cells(_) => None,
    }
}
