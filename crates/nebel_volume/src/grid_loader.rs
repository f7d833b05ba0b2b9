//! Loads [`VolumeGrid`]s from raw files through the `AssetServer`.
//!
//! A raw file holds the samples without a header, x fastest, then y, then z,
//! little-endian ([`RawSampleType`]: 8- or 16-bit unsigned, scaled to [0, 1],
//! or f32 as stored), so its size must be given in the loader settings
//! ([`VolumeGridSettings`]), with the spacing and origin of the grid in the
//! volume's local frame:
//!
//! ```no_run
//! use bevy::prelude::*;
//! use nebel_volume::{VolumeGrid, VolumeGridSettings};
//!
//! fn load(assets: Res<AssetServer>) -> Handle<VolumeGrid> {
//!     assets
//!         .load_builder()
//!         .with_settings(|settings: &mut VolumeGridSettings| {
//!             settings.dims = UVec3::new(64, 32, 64);
//!             settings.spacing = Vec3::splat(0.25);
//!         })
//!         .load("smoke.raw")
//! }
//! ```
//!
//! The loader takes files ending in `.raw`. The grid is checked against the
//! memory budget before the file is read, at most the expected number of
//! bytes (and one more) is read, and a wrong length is an error naming the
//! file; nothing is decoded before both checks.

use bevy::asset::io::Reader;
use bevy::asset::{AssetLoader, LoadContext};
use bevy::prelude::*;
use bevy::tasks::futures_lite::AsyncReadExt;
use nebel_core::budget::BudgetError;
use nebel_core::field::{DensityGrid, FieldError, Normalization, RawSampleType};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::grid::VolumeGrid;

/// How to read a raw density file (see the module docs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VolumeGridSettings {
    /// Grid points per axis. Default 2 × 2 × 2 (set it: the file has no
    /// header).
    pub dims: UVec3,
    /// The samples' type. Default [`RawSampleType::U8`].
    pub sample_type: RawSampleType,
    /// How samples become densities in [0, 1]. Default
    /// [`Normalization::None`] (they must be in [0, 1] already).
    pub normalization: Normalization,
    /// Distance between neighbouring points per axis, local units, finite
    /// and > 0. Default 1.
    pub spacing: Vec3,
    /// Position of point (0, 0, 0), local units. Default the origin.
    pub origin: Vec3,
}

impl Default for VolumeGridSettings {
    fn default() -> Self {
        Self {
            dims: UVec3::splat(2),
            sample_type: RawSampleType::U8,
            normalization: Normalization::None,
            spacing: Vec3::ONE,
            origin: Vec3::ZERO,
        }
    }
}

/// Why a density file could not be loaded.
#[derive(Debug, Error)]
pub enum VolumeGridLoadError {
    /// The file could not be read.
    #[error("cannot read the density grid: {0}")]
    Io(#[from] std::io::Error),
    /// The bytes do not make a grid of the settings' size.
    #[error(transparent)]
    Field(#[from] FieldError),
    /// The grid of the settings' size would exceed the memory budget.
    #[error("{path}: {error}")]
    OverBudget {
        /// The asset path.
        path: String,
        /// The budget's refusal.
        error: BudgetError,
    },
}

/// Loads [`VolumeGrid`]s from `.raw` files (see the module docs).
#[derive(Clone, Copy, Debug, Default, TypePath)]
pub struct VolumeGridLoader;

impl AssetLoader for VolumeGridLoader {
    type Asset = VolumeGrid;
    type Settings = VolumeGridSettings;
    type Error = VolumeGridLoadError;

    async fn load(
        &self,
        reader: &mut dyn Reader,
        settings: &VolumeGridSettings,
        load_context: &mut LoadContext<'_>,
    ) -> Result<VolumeGrid, VolumeGridLoadError> {
        let name = load_context.path().to_string();
        let dims = settings.dims.to_array().map(|n| n as usize);
        DensityGrid::check_budget(dims).map_err(|error| VolumeGridLoadError::OverBudget {
            path: name.clone(),
            error,
        })?;
        // Within the budget: the samples are at most 4 bytes each, like the
        // grid's f32 values. One byte more shows a file that is too long.
        let expected = dims.iter().product::<usize>() * settings.sample_type.bytes();
        let mut bytes = Vec::new();
        reader
            .take(expected as u64 + 1)
            .read_to_end(&mut bytes)
            .await?;
        let grid = DensityGrid::from_raw_bytes(
            &name,
            &bytes,
            dims,
            settings.sample_type,
            settings.normalization,
            settings.spacing.as_dvec3(),
            settings.origin.as_dvec3(),
        )?;
        Ok(grid.into())
    }

    fn extensions(&self) -> &[&str] {
        &["raw"]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::asset::{AssetPlugin, LoadState};

    #[test]
    fn a_raw_file_loads_as_a_grid_and_a_wrong_size_fails_naming_the_file() {
        let dir = std::env::temp_dir().join(format!("nebel-grid-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let bytes = [0u8, 51, 102, 153, 204, 255, 0, 255];
        std::fs::write(dir.join("ramp.raw"), bytes).unwrap();
        // The asset server loads a path once: the wrong size gets a file of its own.
        std::fs::write(dir.join("short.raw"), bytes).unwrap();
        let mut app = App::new();
        app.add_plugins((
            MinimalPlugins,
            AssetPlugin {
                file_path: dir.to_string_lossy().into_owned(),
                ..default()
            },
        ))
        .init_asset::<VolumeGrid>()
        .register_asset_loader(VolumeGridLoader);
        let server = app.world().resource::<AssetServer>().clone();
        let good: Handle<VolumeGrid> = server
            .load_builder()
            .with_settings(|s: &mut VolumeGridSettings| s.spacing = Vec3::splat(0.5))
            .load("ramp.raw");
        let bad: Handle<VolumeGrid> = server
            .load_builder()
            .with_settings(|s: &mut VolumeGridSettings| s.dims = UVec3::new(3, 3, 3))
            .load("short.raw");
        for _ in 0..1000 {
            app.update();
            let done = |id| {
                matches!(
                    server.get_load_state(id),
                    Some(LoadState::Loaded | LoadState::Failed(_))
                )
            };
            if done(good.id()) && done(bad.id()) {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        let grids = app.world().resource::<Assets<VolumeGrid>>();
        let grid = grids.get(&good).expect("loaded");
        assert_eq!(grid.dims(), [2, 2, 2]);
        assert_eq!(grid.values()[1], 0.2);
        assert_eq!(grid.spacing(), bevy::math::DVec3::splat(0.5));
        let Some(LoadState::Failed(error)) = server.get_load_state(bad.id()) else {
            panic!("a wrong size fails");
        };
        let message = error.to_string();
        assert!(
            message.contains("short.raw") && message.contains("27"),
            "{message}"
        );
    }
}
