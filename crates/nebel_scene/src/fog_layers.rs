//! The scene's fog layers: height fog seen by the camera
//! (`nebel_fog::FogLayers` in Bevy, [`nebel_reference::ReferenceFog`] in the
//! reference), after Röttger 2004 §5.3.

use glam::DVec3;
use nebel_core::height_fog::{HeightFog, HeightFogLayer};
use nebel_core::local_light::{LightResponse, LocalLight};
use nebel_core::occluder::Occluder;
use nebel_reference::{FogSunlight, ReferenceFog};
use serde::{Deserialize, Serialize};

use crate::{InvalidField, colour, finite, non_negative};

/// Fog layers over the whole scene: density over altitude (world y) as a sum
/// of layers, with one colour per ray.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FogLayersDescription {
    /// The layers, summed: `Exponential(base: m, density: 1/m, falloff:
    /// 1/m)`, `Constant(bottom: m, top: m, density: 1/m)` or
    /// `Linear([(altitude, density), ...])`. At most 8 layers and 32 linear
    /// points.
    pub layers: Vec<HeightFogLayer>,
    /// The colour dense fog converges to without sunlight, linear RGB (not
    /// sRGB: it is radiance). Default `(0.5, 0.56, 0.64)`.
    #[serde(default = "default_color")]
    pub color: [f32; 3],
    /// Sunlight scattered toward the eye, linear RGB, from the scene's
    /// directional light (none: ignored), dimmed by the fog toward the sun.
    /// Default `(0, 0, 0)`.
    #[serde(default)]
    pub sun_color: [f32; 3],
    /// Henyey-Greenstein asymmetry of the sunlight, in (−1, 1). Default 0.6.
    #[serde(default = "default_asymmetry")]
    pub sun_asymmetry: f32,
    /// Where the layers begin along each ray, metres (ground fog draws the
    /// fog nearer). Default 0.
    #[serde(default)]
    pub start_distance: f32,
    /// Where the fog ends along each ray, metres (the sky integrates to
    /// here). Default 100000.
    #[serde(default = "default_max_distance")]
    pub max_distance: f32,
    /// How the fog scatters the scene's volumetric point and spot lights,
    /// its colour being its look under a light as bright as the reference
    /// sun. Default `(asymmetry: 0.0, strength: 1.0)`.
    #[serde(default)]
    pub light_response: LightResponse,
}

fn default_color() -> [f32; 3] {
    [0.5, 0.56, 0.64]
}

fn default_asymmetry() -> f32 {
    0.6
}

fn default_max_distance() -> f32 {
    100_000.0
}

impl FogLayersDescription {
    /// Checks every field.
    pub(crate) fn validate(&self) -> Result<(), InvalidField> {
        HeightFog::new(self.layers.clone())
            .map_err(|error| InvalidField::new("layers", error.to_string()))?;
        colour("color", self.color)?;
        colour("sun_color", self.sun_color)?;
        if !(self.sun_asymmetry > -1.0 && self.sun_asymmetry < 1.0) {
            return Err(InvalidField::new(
                "sun_asymmetry",
                format!("must be in (−1, 1), got {}", self.sun_asymmetry),
            ));
        }
        InvalidField::check_light_response(&self.light_response)?;
        non_negative("start_distance", self.start_distance)?;
        finite("max_distance", &[self.max_distance])?;
        if self.max_distance <= self.start_distance {
            return Err(InvalidField::new(
                "max_distance",
                format!(
                    "must be greater than start_distance ({}), got {}",
                    self.start_distance, self.max_distance
                ),
            ));
        }
        Ok(())
    }

    /// The checked density over altitude.
    pub fn height_fog(&self) -> Result<HeightFog, InvalidField> {
        HeightFog::new(self.layers.clone())
            .map_err(|error| InvalidField::new("layers", error.to_string()))
    }

    /// The fog for the reference integrator; `sun` is the unit direction
    /// toward the scene's directional light, if it has one, and whether it
    /// casts shadows, `lights` the scene's volumetric point and spot lights,
    /// `occluders` what shades those, and the sun, that cast shadows.
    pub fn reference(
        &self,
        sun: Option<(DVec3, bool)>,
        lights: Vec<LocalLight>,
        occluders: Vec<Occluder>,
    ) -> Result<ReferenceFog, InvalidField> {
        let linear = |c: [f32; 3]| DVec3::from(c.map(f64::from));
        Ok(ReferenceFog {
            fog: self.height_fog()?,
            colour: linear(self.color),
            sun: sun.map(|(direction, shadows)| FogSunlight {
                direction,
                colour: linear(self.sun_color),
                asymmetry: f64::from(self.sun_asymmetry),
                shadows,
            }),
            start_distance: f64::from(self.start_distance),
            max_distance: f64::from(self.max_distance),
            lights,
            light_response: self.light_response,
            occluders,
            clouds: Vec::new(),
            terrain: None,
        })
    }
}
