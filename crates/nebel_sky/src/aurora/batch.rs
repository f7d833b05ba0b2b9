//! The aurora as a [`SkyLayer`]: the footprint at the animation time, the
//! layer between the plane and the curtains' tops ([`AuroraShape::layer`]),
//! emissive, unordered.
//!
//! The layer is built again when its footprint changed: every frame while a
//! procedural footprint is animated; when the settings or the map change
//! otherwise.

use std::sync::Arc;

use bevy::diagnostic::DiagnosticPath;
use bevy::math::DVec3;
use bevy::prelude::*;
use nebel_core::field::AuroraCurtains;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::TransferFunction;
use nebel_lod::quadtree::DEFAULT_MIN_RESOLUTION;
use nebel_lod::{AuroraShape, CellOrder, FogProfile, PrismScalar, SurfaceLayer};
use nebel_render::GrayscaleMap;

use super::{Aurora, AuroraFootprint, AuroraPlugin};
use crate::SkyLayerError;
use crate::sky_layer::{SkyLayer, SkyLayerState, map_values};

/// An aurora's layer, buffers and caches.
pub type AuroraState = SkyLayerState<Aurora>;

/// What an aurora's layer was built from.
#[derive(Clone, Debug, PartialEq)]
pub struct AuroraLayerKey {
    footprint: AuroraFootprint,
    shape: AuroraShape,
    resolution: u32,
    /// The animation time, seconds, for a procedural footprint.
    time: Option<u64>,
    /// The map's values (by identity), for a map footprint.
    map: Option<usize>,
}

/// The footprint a build samples: procedural curtains at a time, seconds,
/// or a map's values.
pub enum FootprintInput {
    Curtains(AuroraCurtains, f64),
    Map(Vec<f32>),
}

impl SkyLayer for Aurora {
    type LayerKey = AuroraLayerKey;
    type LayerInput = FootprintInput;
    const NAME: &'static str = "aurora";
    const DRAWN: DiagnosticPath = AuroraPlugin::AURORAS;
    const TETRAHEDRA: DiagnosticPath = AuroraPlugin::TETRAHEDRA;
    const UPDATE_MS: DiagnosticPath = AuroraPlugin::UPDATE_MS;
    const MODE: OpticalMode = OpticalMode::Emissive;
    const SUNLIT: bool = false;

    fn validate(&self) -> Result<(), SkyLayerError> {
        Aurora::validate(self)
    }

    fn is_dark(&self) -> bool {
        self.brightness == 0.0 || self.transfer_function.is_transparent(0.0, 1.0)
    }

    fn layer_key(&self, seconds: f64, maps: &Assets<GrayscaleMap>) -> AuroraLayerKey {
        let animated = matches!(self.footprint, AuroraFootprint::Curtains(_));
        AuroraLayerKey {
            footprint: self.footprint.clone(),
            shape: AuroraShape {
                extent: f64::from(self.extent),
                bottom: f64::from(self.bottom),
                top: f64::from(self.top),
            },
            resolution: self.resolution,
            time: animated.then_some((seconds * f64::from(self.speed)).to_bits()),
            map: match &self.footprint {
                AuroraFootprint::Map(handle) => maps
                    .get(handle)
                    .map(|map| Arc::as_ptr(&map.values) as usize),
                AuroraFootprint::Curtains(_) => None,
            },
        }
    }

    fn layer_input(
        key: &AuroraLayerKey,
        maps: &Assets<GrayscaleMap>,
        asset_server: &AssetServer,
    ) -> Result<Option<FootprintInput>, SkyLayerError> {
        match &key.footprint {
            AuroraFootprint::Curtains(curtains) => Ok(Some(FootprintInput::Curtains(
                *curtains,
                key.time.map_or(0.0, f64::from_bits),
            ))),
            AuroraFootprint::Map(handle) => {
                let side = key.resolution as usize;
                let values = map_values(Self::NAME, handle, side, maps, asset_server)?;
                Ok(values.map(FootprintInput::Map))
            }
        }
    }

    fn build_layer(
        key: &AuroraLayerKey,
        input: FootprintInput,
    ) -> Result<SurfaceLayer, SkyLayerError> {
        let side = key.resolution as usize;
        let strength = match input {
            FootprintInput::Curtains(curtains, time) => curtains.map(side, time)?,
            FootprintInput::Map(values) => values,
        };
        Ok(key
            .shape
            .layer(side, &strength, DEFAULT_MIN_RESOLUTION, 1.0)?)
    }

    fn transfer(&self) -> (&TransferFunction, f32) {
        (&self.transfer_function, self.brightness)
    }

    fn accuracy(&self) -> f32 {
        self.accuracy
    }

    fn drawing(&self, key: &AuroraLayerKey, _sun: DVec3) -> (FogProfile, PrismScalar, CellOrder) {
        (
            AuroraShape::profile(),
            key.shape.scalar(),
            CellOrder::Unordered,
        )
    }
}
