//! A cloud layer between two surfaces in a scene file (Röttger 2004 §10.4,
//! Fig. 10.6): noise patches growing from a base, or two grayscale maps for
//! the bottom and the top, sorted and lit by the scene's sun through the
//! cloud above each point; and the exact cells the reference integrates.
//!
//! ```ron
//! cloud_layer: (
//!     noise: (noise: (kind: Fbm, seed: 0, octaves: 5, wavelength: 4000.0, persistence: 0.5, exponent: 1.0),
//!             thickness: 700.0, coverage: 0.45),
//!     // or maps: (bottom: "base.png", top: "tops.png", scale: 800.0): two grayscale
//!     // surfaces at base + scale · value, relative to the scene file
//!     center: (0.0, 0.0, 0.0),   // the layer's centre; the base is above it
//!     extent: 40000.0,           // side of the square layer, m
//!     base: 1500.0,              // the altitude the clouds grow from, m
//!     sag: 0.2,                  // part of a cloud's thickness below the base, [0, 1]
//!     edge_fade: 0.1,            // noise: thickness to 0 at the edges over this part of the side, [0, 0.5]
//!     resolution: 257,           // points per side, 2^k + 1 from 9 to 2049
//!     density: 0.01,             // extinction of the view rays, times ρ; ≥ 0
//!     ambient: 0.3, diffuse: 0.7, // light without and of the unshadowed sun, [0, 1]
//!     shadow_extinction: 0.004,  // extinction toward the sun, 1/m
//!     scattering_octaves: 1,     // multiple scattering of the sunlight, 1 to 8
//!     sky_occlusion: false,      // the cloud above dims the sky's light
//!     light_response: (asymmetry: 0.0, strength: 1.0), // scattering of volumetric lights
//!     transfer: Preset(CloudLight), // κ and ρ over the light; default this
//!     accuracy: 40.0,            // the quadtree's c
//! ),
//! ```
//!
//! Every field has the default shown; the sun is the scene's first
//! `Directional` light (straight up without one). The reference draws the
//! layer as the cells the plugin draws for the reference camera (the same
//! surfaces, quadtree, refinement, light and order, without culling),
//! integrated exactly.

use std::path::Path;

use glam::DVec3;
use serde::{Deserialize, Serialize};

use nebel_core::field::{CloudLighting, FogNoise, HeightField, TerrainNoise};
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_lod::quadtree::DEFAULT_MIN_RESOLUTION;
use nebel_lod::{CellOrder, CloudLayerShape, LayerTop, PrismScalar, SurfaceLayer, TerrainMap};

use super::sky_layer::{LayerDrawing, layer_reference};
use super::{
    BuiltVolume, InvalidField, TransferDescription, finite, in_range, layer_side, non_negative,
    positive, shape_error,
};

/// A cloud layer over the scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CloudLayerDescription {
    /// The procedural clouds' thickness (ignored with `maps`).
    pub noise: FogNoise,
    /// Two grayscale surfaces instead of the noise. Default none.
    pub maps: Option<CloudLayerMaps>,
    /// The layer's centre, world space; the base is above it.
    pub center: [f32; 3],
    /// Side of the square layer, m, finite and > 0.
    pub extent: f32,
    /// The altitude the clouds grow from, m, finite.
    pub base: f32,
    /// The part of a procedural cloud's thickness below `base`, in [0, 1].
    pub sag: f32,
    /// Part of the side, in [0, 0.5], over which the noise's thickness
    /// falls to 0 toward the layer's edges (`nebel_lod::CloudLayerShape`).
    pub edge_fade: f32,
    /// Points per side, `2^k + 1` from 9 to 2049.
    pub resolution: u32,
    /// Multiplies the transfer function's ρ, finite and ≥ 0.
    pub density: f32,
    /// Light every point receives, in [0, 1].
    pub ambient: f32,
    /// Light of the unshadowed sun, in [0, 1].
    pub diffuse: f32,
    /// Extinction toward the sun, 1/m, finite and ≥ 0.
    pub shadow_extinction: f32,
    /// Octaves of multiple scattering of the sunlight, 1 to 8.
    pub scattering_octaves: u32,
    /// Whether the cloud above a point dims its sky light.
    pub sky_occlusion: bool,
    /// How it scatters the scene's volumetric point and spot lights.
    /// Default `(asymmetry: 0.0, strength: 1.0)`.
    pub light_response: LightResponse,
    /// κ and ρ over the light. Default `Preset(CloudLight)`.
    pub transfer: Option<TransferDescription>,
    /// Accuracy `c` of the quadtree's criterion, finite and > 0.
    pub accuracy: f32,
}

/// A cloud layer's two map surfaces.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CloudLayerMaps {
    /// The bottom surface's PNG, relative to the scene file.
    pub bottom: String,
    /// The top surface's PNG, relative to the scene file.
    pub top: String,
    /// Metres of a white pixel, finite and ≥ 0.
    pub scale: f32,
}

impl Default for CloudLayerDescription {
    fn default() -> Self {
        Self {
            noise: FogNoise {
                noise: TerrainNoise {
                    octaves: 5,
                    wavelength: 4000.0,
                    ..TerrainNoise::default()
                },
                thickness: 700.0,
                coverage: 0.45,
            },
            maps: None,
            center: [0.0; 3],
            extent: 40e3,
            base: 1500.0,
            sag: 0.2,
            edge_fade: 0.1,
            resolution: 257,
            density: 0.01,
            ambient: CloudLighting::DEFAULT_AMBIENT,
            diffuse: CloudLighting::DEFAULT_DIFFUSE,
            shadow_extinction: 0.004,
            scattering_octaves: 1,
            sky_occlusion: false,
            light_response: LightResponse::default(),
            transfer: None,
            accuracy: 40.0,
        }
    }
}

/// A scene's cloud layer with its files read: the maps' unit values and
/// the density-scaled transfer function.
#[derive(Clone, Debug, PartialEq)]
pub struct BuiltCloudLayer {
    /// The bottom and top maps (black 0, white 1), `None` for the noise.
    pub maps: Option<(HeightField, HeightField)>,
    /// κ and ρ, `density` applied.
    pub transfer_function: TransferFunction,
}

impl CloudLayerDescription {
    /// The layer's shape.
    pub fn shape(&self) -> CloudLayerShape {
        CloudLayerShape {
            extent: f64::from(self.extent),
            base: f64::from(self.base),
            sag: f64::from(self.sag),
            edge_fade: f64::from(self.edge_fade),
        }
    }

    /// Checks every setting against its documented range.
    pub(super) fn validate(&self) -> Result<(), InvalidField> {
        self.shape()
            .validate()
            .map_err(|error| shape_error(error, "cloud layer "))?;
        finite("center", &self.center)?;
        layer_side("resolution", self.resolution)?;
        non_negative("density", self.density)?;
        InvalidField::check_light_response(&self.light_response)?;
        non_negative("shadow_extinction", self.shadow_extinction)?;
        positive("accuracy", self.accuracy)?;
        in_range("ambient", self.ambient, 0.0, 1.0)?;
        in_range("diffuse", self.diffuse, 0.0, 1.0)?;
        let octaves = self.scattering_octaves;
        if !(1..=CloudLighting::MAX_SCATTERING_OCTAVES).contains(&octaves) {
            return Err(InvalidField::new(
                "scattering_octaves",
                format!("must be between 1 and 8, got {octaves}"),
            ));
        }
        if let Some(maps) = &self.maps {
            if maps.bottom.trim().is_empty() || maps.top.trim().is_empty() {
                return Err(InvalidField::new(
                    "maps",
                    "must name two PNG files (relative to the scene file)",
                ));
            }
            non_negative("maps.scale", maps.scale)?;
        }
        Ok(())
    }

    /// Loads the maps (if any) and builds the transfer function with ρ times
    /// `density`; `scene_dir` resolves their paths.
    pub fn build(&self, scene_dir: &Path) -> Result<BuiltCloudLayer, InvalidField> {
        let load = |path: &str, field: &str| InvalidField::load_map(scene_dir, path, field);
        let maps = self
            .maps
            .as_ref()
            .map(|maps| {
                Ok((
                    load(&maps.bottom, "maps.bottom")?,
                    load(&maps.top, "maps.top")?,
                ))
            })
            .transpose()?;
        let transfer_function = TransferDescription::scaled(
            self.transfer.as_ref(),
            TransferPreset::CloudLight,
            scene_dir,
            self.density,
        )?;
        Ok(BuiltCloudLayer {
            maps,
            transfer_function,
        })
    }

    /// The layer between its two surfaces.
    pub fn layer(&self, built: &BuiltCloudLayer) -> Result<SurfaceLayer, InvalidField> {
        let side = self.resolution as usize;
        let shape = self.shape();
        let invalid = |field: &str| {
            let field = field.to_owned();
            move |error: nebel_lod::SurfaceLayerError| InvalidField::new(&field, error.to_string())
        };
        match (&built.maps, &self.maps) {
            (Some((bottom, top)), Some(maps)) => {
                let surface = |map: &HeightField, field: &str| {
                    TerrainMap::resample(map.heights(), map.dims(), side)
                        .map(|unit| {
                            unit.values()
                                .iter()
                                .map(|u| self.base + maps.scale * u)
                                .collect::<Vec<f32>>()
                        })
                        .map_err(|error| InvalidField::new(field, error.to_string()))
                };
                let bottom = shape
                    .field(side, surface(bottom, "maps.bottom")?)
                    .map_err(|error| InvalidField::new("maps.bottom", error.to_string()))?;
                let top = surface(top, "maps.top")?;
                SurfaceLayer::new(
                    bottom,
                    LayerTop::Surface(&top),
                    None,
                    DEFAULT_MIN_RESOLUTION,
                    1.0,
                )
                .map_err(invalid("maps"))
            }
            _ => {
                let thickness = self
                    .noise
                    .thickness(side, shape.extent / (side - 1) as f64)
                    .map_err(|error| InvalidField::new("noise", error.to_string()))?;
                shape
                    .layer(side, &thickness, DEFAULT_MIN_RESOLUTION, 1.0)
                    .map_err(invalid("noise"))
            }
        }
    }

    /// The layer's cells for an eye at `eye` (world space) and the sun in
    /// the unit direction `toward_sun`, as the plugin draws them (without
    /// culling), back to front, as a sorted volume for the reference;
    /// `None` when it has none.
    pub fn reference(
        &self,
        built: &BuiltCloudLayer,
        eye: DVec3,
        toward_sun: DVec3,
    ) -> Result<Option<BuiltVolume>, InvalidField> {
        let layer = self.layer(built)?;
        let drawing = LayerDrawing {
            center: self.center,
            accuracy: self.accuracy,
            profile: &CloudLayerShape::profile(),
            scalar: PrismScalar::Sunlit {
                extinction: self.shadow_extinction,
                sun_height: toward_sun.normalize_or(DVec3::Y).y as f32,
                ambient: self.ambient,
                diffuse: self.diffuse,
                octaves: self.scattering_octaves,
                sky_occlusion: self.sky_occlusion,
            },
            order: CellOrder::BackToFront,
            light_response: self.light_response,
            transfer_function: &built.transfer_function,
            mode: OpticalMode::Sorted,
        };
        layer_reference(&layer, &drawing, eye)
    }
}
