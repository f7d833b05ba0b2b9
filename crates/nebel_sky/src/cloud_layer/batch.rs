//! The cloud layer as a [`SkyLayer`]: its layer between two surfaces, built
//! once per source and settings, sorted back to front for the eye and lit
//! through the cloud above each point.

use std::sync::Arc;

use bevy::diagnostic::DiagnosticPath;
use bevy::math::DVec3;
use bevy::prelude::*;
use nebel_core::field::FogNoise;
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::TransferFunction;
use nebel_lod::quadtree::DEFAULT_MIN_RESOLUTION;
use nebel_lod::{
    CellOrder, CloudLayerShape, FogProfile, LayerTop, PrismScalar, SurfaceLayer, SurfaceLayerError,
};
use nebel_render::GrayscaleMap;

use super::{CloudLayer, CloudLayerPlugin, CloudLayerSource};
use crate::SkyLayerError;
use crate::sky_layer::{SkyLayer, SkyLayerState, map_values};

/// A cloud layer's quadtree, buffers and caches.
pub type CloudLayerState = SkyLayerState<CloudLayer>;

/// What a cloud layer's layer was built from.
#[derive(Clone, Debug, PartialEq)]
pub struct CloudLayerKey {
    source: CloudLayerSource,
    shape: CloudLayerShape,
    resolution: u32,
    /// The maps' values (by identity), for map surfaces.
    maps: [Option<usize>; 2],
}

/// What a build makes the two surfaces from: noise, or two maps' unit
/// values with the metres of a white pixel.
pub enum SurfacesInput {
    Noise(FogNoise),
    Maps {
        bottom: Vec<f32>,
        top: Vec<f32>,
        scale: f32,
    },
}

impl SkyLayer for CloudLayer {
    type LayerKey = CloudLayerKey;
    type LayerInput = SurfacesInput;
    const NAME: &'static str = "cloud layer";
    const DRAWN: DiagnosticPath = CloudLayerPlugin::LAYERS;
    const TETRAHEDRA: DiagnosticPath = CloudLayerPlugin::TETRAHEDRA;
    const UPDATE_MS: DiagnosticPath = CloudLayerPlugin::UPDATE_MS;
    const MODE: OpticalMode = OpticalMode::Sorted;
    const SUNLIT: bool = true;

    fn validate(&self) -> Result<(), SkyLayerError> {
        CloudLayer::validate(self)
    }

    fn is_dark(&self) -> bool {
        self.density == 0.0 || self.transfer_function.is_transparent(0.0, 1.0)
    }

    fn layer_key(&self, _seconds: f64, maps: &Assets<GrayscaleMap>) -> CloudLayerKey {
        CloudLayerKey {
            source: self.source.clone(),
            shape: CloudLayerShape {
                extent: f64::from(self.extent),
                base: f64::from(self.base),
                sag: f64::from(self.sag),
                edge_fade: f64::from(self.edge_fade),
            },
            resolution: self.resolution,
            maps: match &self.source {
                CloudLayerSource::Maps { bottom, top, .. } => [bottom, top]
                    .map(|map| maps.get(map).map(|map| Arc::as_ptr(&map.values) as usize)),
                CloudLayerSource::Noise(_) => [None, None],
            },
        }
    }

    fn layer_input(
        key: &CloudLayerKey,
        maps: &Assets<GrayscaleMap>,
        asset_server: &AssetServer,
    ) -> Result<Option<SurfacesInput>, SkyLayerError> {
        let side = key.resolution as usize;
        Ok(match &key.source {
            CloudLayerSource::Noise(noise) => Some(SurfacesInput::Noise(*noise)),
            CloudLayerSource::Maps { bottom, top, scale } => match (
                map_values(Self::NAME, bottom, side, maps, asset_server)?,
                map_values(Self::NAME, top, side, maps, asset_server)?,
            ) {
                (Some(bottom), Some(top)) => Some(SurfacesInput::Maps {
                    bottom,
                    top,
                    scale: *scale,
                }),
                _ => None,
            },
        })
    }

    fn build_layer(
        key: &CloudLayerKey,
        input: SurfacesInput,
    ) -> Result<SurfaceLayer, SkyLayerError> {
        let side = key.resolution as usize;
        let shape = &key.shape;
        match input {
            SurfacesInput::Noise(noise) => {
                let thickness = noise.thickness(side, shape.extent / (side - 1) as f64)?;
                Ok(shape.layer(side, &thickness, DEFAULT_MIN_RESOLUTION, 1.0)?)
            }
            SurfacesInput::Maps { bottom, top, scale } => {
                let base = shape.base as f32;
                let surface = |unit: Vec<f32>| -> Vec<f32> {
                    unit.iter().map(|u| base + scale * u).collect()
                };
                let bottom = shape
                    .field(side, surface(bottom))
                    .map_err(|error| SkyLayerError::from(SurfaceLayerError::from(error)))?;
                let top = surface(top);
                Ok(SurfaceLayer::new(
                    bottom,
                    LayerTop::Surface(&top),
                    None,
                    DEFAULT_MIN_RESOLUTION,
                    1.0,
                )?)
            }
        }
    }

    fn transfer(&self) -> (&TransferFunction, f32) {
        (&self.transfer_function, self.density)
    }

    fn accuracy(&self) -> f32 {
        self.accuracy
    }

    fn light_response(&self) -> LightResponse {
        self.light_response
    }

    fn drawing(&self, _key: &CloudLayerKey, sun: DVec3) -> (FogProfile, PrismScalar, CellOrder) {
        (
            CloudLayerShape::profile(),
            PrismScalar::Sunlit {
                extinction: self.shadow_extinction,
                sun_height: sun.y as f32,
                ambient: self.ambient,
                diffuse: self.diffuse,
                octaves: self.scattering_octaves,
                sky_occlusion: self.sky_occlusion,
            },
            CellOrder::BackToFront,
        )
    }
}
