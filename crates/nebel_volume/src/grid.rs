//! Density grids as Bevy assets: [`VolumeGrid`].
//!
//! A [`Volume`](crate::Volume) with a grid field holds a
//! `Handle<VolumeGrid>`, so one grid can serve several volumes, a generator
//! (a campfire, a cloud) can replace it in place, and a grid can come from a
//! file through the `AssetServer` ([`crate::grid_loader`]). The asset shares
//! its [`DensityGrid`] (an `Arc`): the background builds of the volume
//! plugin read it without a copy.

use std::sync::Arc;

use bevy::prelude::*;
use nebel_core::field::DensityGrid;

/// A density grid asset (see the module docs): values in [0, 1] at the
/// points `origin + (i, j, k) · spacing` of the volume's local frame,
/// trilinear in between.
#[derive(Asset, TypePath, Clone, Debug, Deref)]
pub struct VolumeGrid(pub Arc<DensityGrid>);

impl From<DensityGrid> for VolumeGrid {
    fn from(grid: DensityGrid) -> Self {
        Self(Arc::new(grid))
    }
}
