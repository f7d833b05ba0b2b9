//! Volumes in scene files: where the scalar field comes from, its box, its
//! transfer function and its optical mode.
//!
//! ```ron
//! volumes: [
//!     (
//!         source: Procedural((dims: (33, 17, 33), kind: Fbm, seed: 7, octaves: 4, frequency: 0.5, coverage: 0.6)),
//!         // or Uniform((value: 1.0)), Ramp((axis: Y, from: 1.0, to: 0.0)),
//!         // or Cells([(positions: ((0,0,0), (1,0,0), (0,1,0), (0,0,1)), scalars: (1, 1, 1, 1)), ...]),
//!         min: (-4.0, 0.0, -4.0),          // the grid's box, metres; default (-1, -1, -1)
//!         max: (4.0, 2.0, 4.0),            // default (1, 1, 1)
//!         transfer: Preset(Cloud),         // or Points([(s: 0.0, kappa: (1, 1, 1), rho: 0.0), ...])
//!                                          // or Strip((path: "ramps/fire.png", max_density: 2.0))
//!         density_scale: 1.0,              // multiplies ρ; default 1
//!         mode: Sorted,                    // Sorted, Emissive or Mip; default Sorted
//!         lod: (image_error: 0.1, min_accuracy: 4.0), // octree C-LOD by the screen error (or
//!                                          // `accuracy: 16.0`: the distance criterion);
//!                                          // default none (full resolution)
//!         lighting: (ambient: 0.3, diffuse: 0.7, shadow_extinction: 0.0, model: Isotropic),
//!                                          // lit cloud (Röttger and Ertl 2003 §5); default none
//!     ),
//!     (
//!         // Procedural cumulus after Schpok et al. 2003, drifting with the wind.
//!         source: Cloud((dims: (65, 17, 65), seed: 3, coverage: 0.5, octaves: 5,
//!                        wavelength: 40.0, wind: (2.0, 0.0, 0.0), detail_wind: 1.5)),
//!         min: (-32.0, 10.0, -32.0), max: (32.0, 26.0, 32.0),
//!         lighting: (shadow_extinction: 0.2),
//!     ),
//! ]
//! ```
//!
//! Grid sources sample the box `min..max` at `dims` points per axis (corners
//! included), trilinear in between. A volume with `lighting`, and a `Cloud`
//! source, is drawn through the octree, with `lod` or the default (the screen
//! error at 0.1, `C = 4`), unless `full_resolution` draws it ray cast at full
//! resolution, a lit one with its light field at the grid's points (projected
//! cells carry no light field: a lit volume may not have both); its light field
//! uses the first directional light of the scene as the sun (straight up when
//! there is none) and its transfer function defaults to `Preset(CloudLight)`
//! for the `Isotropic` model (colour over light, opacity from the density)
//! and `Preset(Cloud)` for `NonPhysical`. `Cells` gives tetrahedra in world space
//! and ignores the box. A transfer-function strip path is relative to the scene
//! file. Building a volume ([`VolumeDescription::build`]) generates or loads its
//! data; a scene file's validation checks only what is cheap.
//!
//! That includes the memory budget (`nebel_core::budget`): validation refuses,
//! naming the field that sizes it, a volume any of whose structures would
//! exceed it: the density grid of `dims`; for a volume drawn through the
//! octree the grid padded to `2^n + 1` points per
//! axis (and its light field, of the same size) and the octree over it; for
//! one drawn at full resolution as projected cells its cell batch (Kuhn's six
//! tetrahedra per voxel); a search light's cells; a
//! `Cells` list.

use std::path::Path;
use std::sync::Arc;

use glam::{DQuat, DVec3};
use serde::{Deserialize, Serialize};

use super::InvalidField;
use nebel_core::budget::{BudgetError, Dims, check_allocation};
use nebel_core::cell::{KUHN_TETRAHEDRA, Tetrahedron};
use nebel_core::field::effects::{
    CAMPFIRE_DIMS, CAMPFIRE_MAX, CAMPFIRE_MIN, SEARCH_LIGHT_SEGMENTS, campfire_density,
    check_search_light_budget, search_light_cells,
};
use nebel_core::field::{
    CloudEllipsoid, CloudKind, CloudLighting, CloudNoise, CloudShape, CloudWeather, DensityGrid,
    FieldError, NoiseKind, ProceduralNoise, WeatherMap, power_of_two_plus_one,
};
use nebel_core::fog_sunlight::FogSunlight;
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{ControlPoint, TransferError, TransferFunction, TransferPreset};
use nebel_lod::octree::LodCriterion;
use nebel_lod::octree::keyframe::{keyframe_index, keyframe_time};
use nebel_lod::{GpuCell, OctreeSettings, VolumeHierarchy};

/// One volume of a scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeDescription {
    /// Where the scalar field comes from.
    pub source: SourceDescription,
    /// Minimum corner of the grid's box, metres. Default `(-1, -1, -1)`.
    #[serde(default = "default_min")]
    pub min: [f32; 3],
    /// Maximum corner of the grid's box, metres, above `min` on every axis.
    /// Default `(1, 1, 1)`.
    #[serde(default = "default_max")]
    pub max: [f32; 3],
    /// κ and ρ over the scalar. Default: `Preset(Fire)` for a campfire,
    /// `Preset(SearchLight)` for a search light, `Preset(Cloud)` otherwise.
    #[serde(default)]
    pub transfer: Option<TransferDescription>,
    /// Factor on ρ, finite and ≥ 0. Default 1.
    #[serde(default = "default_density_scale")]
    pub density_scale: f32,
    /// How segments combine. Default: `Emissive` for a campfire or a search
    /// light, `Sorted` otherwise.
    #[serde(default)]
    pub mode: Option<OpticalMode>,
    /// Draw a grid source through the octree level of detail (Röttger and Ertl 2003)
    /// instead of at full resolution. Default: none (full resolution, but
    /// the octree's default for a lit volume or a `Cloud`, see the module
    /// docs).
    #[serde(default)]
    pub lod: Option<LodDescription>,
    /// Light a grid volume as a cloud (Röttger and Ertl 2003 §5). Default: none (unlit).
    #[serde(default)]
    pub lighting: Option<LightingDescription>,
    /// Draw a grid at full resolution as its tetrahedra projected in
    /// visibility order (Röttger 2004 §8) instead of ray casting them; both
    /// are exact. Ignored through the octree. Default false.
    #[serde(default)]
    pub projected_cells: bool,
    /// Draw a lit volume or a `Cloud` at full resolution instead of through
    /// the octree's default (module docs); not with `lod`. Default false.
    #[serde(default)]
    pub full_resolution: bool,
    /// How a sorted volume scatters the scene's volumetric point and spot
    /// lights: `(asymmetry: g, strength: s)`, the Henyey-Greenstein
    /// asymmetry in (−1, 1) and a factor ≥ 0 on its colour. Default
    /// `(asymmetry: 0.0, strength: 1.0)`.
    #[serde(default)]
    pub light_response: LightResponse,
}

/// Which field of a lit cloud gives the colour and which the opacity (paper
/// Röttger and Ertl 2003 §5), or single scattering (Nes 2008).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub enum LightModel {
    /// §5.1: colour from the light γ (transfer function over γ), opacity from
    /// the density, `l' = l · f`. The default.
    #[default]
    Isotropic,
    /// §5.2: colour and opacity from the density (transfer function over the
    /// density), segment length scaled by γ.
    NonPhysical,
    /// Single scattering of the sun (Nes 2008): γ is the transmittance
    /// toward the sun, colour over γ (default `Preset(Transmittance)`),
    /// opacity from the density, and each pixel weighs the sunlight by the
    /// Henyey-Greenstein phase of its ray; `ambient` and `diffuse` are the
    /// sky's and the sun's strength. `Scattering(asymmetry: 0.7)`.
    Scattering {
        /// Henyey-Greenstein `g`, in (−1, 1).
        asymmetry: f32,
    },
}

/// Lighting of a grid volume: `γ = ambient · T_sky + diffuse · T_sun ·
/// lambert` per grid point (`nebel_core::field::light_field`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightingDescription {
    /// Ambient light, in [0, 1]. Default 0.3.
    #[serde(default = "default_ambient")]
    pub ambient: f32,
    /// Sunlight strength, in [0, 1]. Default 0.7.
    #[serde(default = "default_diffuse")]
    pub diffuse: f32,
    /// Optical density per metre at density 1 of the shadow toward the sun,
    /// ≥ 0; 0 casts none. Default 0.
    #[serde(default)]
    pub shadow_extinction: f32,
    /// Which field gives colour and which opacity. Default `Isotropic`.
    #[serde(default)]
    pub model: LightModel,
    /// Seconds between the light field's keyframes while the sun turns,
    /// > 0 (`nebel_volume::VolumeLighting::keyframe_interval`). Default 2.
    #[serde(default = "default_keyframe_interval")]
    pub keyframe_interval: f32,
    /// Octaves of multiple scattering of the sunlight, 1 to 8
    /// (`nebel_volume::VolumeLighting::scattering_octaves`). Default 1.
    #[serde(default = "default_scattering_octaves")]
    pub scattering_octaves: u32,
    /// The cloud above a point dims its sky light
    /// (`nebel_volume::VolumeLighting::sky_occlusion`). Default false.
    #[serde(default)]
    pub sky_occlusion: bool,
    /// The cloud's shadow falls on the scene's meshes and terrain below it
    /// (`nebel_volume::CloudShadowCaster`; a grid volume with a shadow
    /// extinction). Default false.
    #[serde(default)]
    pub ground_shadow: bool,
}

fn default_scattering_octaves() -> u32 {
    1
}

fn default_keyframe_interval() -> f32 {
    2.0
}

fn default_ambient() -> f32 {
    CloudLighting::DEFAULT_AMBIENT
}

fn default_diffuse() -> f32 {
    CloudLighting::DEFAULT_DIFFUSE
}

/// Procedural cumulus clouds with the artist controls of Schpok et al. 2003
/// (`nebel_core::field::CloudNoise`; defaults as there).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CloudSource {
    /// Grid points per axis, each ≥ 2.
    pub dims: [usize; 3],
    /// Seed. Default 0.
    #[serde(default)]
    pub seed: u32,
    /// Fraction of the box covered by cloud, in [0, 1]. Default 0.5.
    #[serde(default)]
    pub coverage: Option<f32>,
    /// Detail octaves, 1 to 16. Default 5.
    #[serde(default)]
    pub octaves: Option<usize>,
    /// Wavelength of the first octave, metres (the size of the clouds).
    /// Default 2000.
    #[serde(default)]
    pub wavelength: Option<f64>,
    /// Drift of the first octave, metres per second. Default zero (static).
    #[serde(default)]
    pub wind: [f64; 3],
    /// Each finer octave drifts (and turns) this much faster than the
    /// previous. Default 1.5.
    #[serde(default)]
    pub detail_wind: Option<f64>,
    /// Axis times the first octave's turn, radians per second, about the
    /// box's centre (Schpok et al. 2003's torque). Default zero.
    #[serde(default)]
    pub torque: [f64; 3],
    /// Height fraction over which the base fades in. Default 0.15.
    #[serde(default)]
    pub base_fade: Option<f32>,
    /// Height fraction over which the tops round off. Default 0.5.
    #[serde(default)]
    pub top_fade: Option<f32>,
    /// Fraction of the width and depth over which the coverage falls to 0
    /// toward the box's sides, in [0, 0.5]. Default 0.1.
    #[serde(default)]
    pub side_fade: Option<f32>,
    /// How sharply the density rises from a cloud's edge, in [0, 1).
    /// Default 0 (0.4 for stratus).
    #[serde(default)]
    pub sharpness: Option<f32>,
    /// The kind of cloud whose settings the unset fields take: `Cumulus`
    /// (the defaults above), `Stratus`, `Cirrus` or `Wispy`
    /// (`nebel_core::field::CloudNoise::of_kind`). Default `Cumulus`.
    #[serde(default)]
    pub kind: CloudKind,
    /// Elongation of the clouds' features along x, y and z, each > 0.
    /// Default (1, 1, 1) (the kind's).
    #[serde(default)]
    pub stretch: Option<[f64; 3]>,
    /// Ridged octaves: thin, torn filaments. Default false (the kind's).
    #[serde(default)]
    pub wisps: Option<bool>,
    /// Seconds between the keyframes a windy cloud is blended from, > 0
    /// (see `nebel_volume::CloudVolume::keyframe_interval`). Default 2.
    #[serde(default)]
    pub keyframe_interval: Option<f32>,
    /// Weather over the box: coverage and cloud type per column. Default
    /// none.
    #[serde(default)]
    pub weather: Option<WeatherDescription>,
    /// Implicit ellipsoids that shape the cloud (Schpok et al. 2003). Default
    /// none.
    #[serde(default)]
    pub primitives: Vec<PrimitiveDescription>,
}

/// An implicit ellipsoid of a cloud (`nebel_core::field::CloudEllipsoid`),
/// metres in the volume's frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PrimitiveDescription {
    /// Centre at time 0.
    pub centre: [f64; 3],
    /// Radii along its axes at time 0, each > 0.
    pub radii: [f64; 3],
    /// Turn of its axes about y, degrees. Default 0.
    #[serde(default)]
    pub yaw_degrees: f64,
    /// Weight of its field, ≥ 0. Default 1.
    #[serde(default)]
    pub density: Option<f32>,
    /// Drift of its centre, metres per second. Default zero.
    #[serde(default)]
    pub velocity: [f64; 3],
    /// Growth of its radii per second. Default 0.
    #[serde(default)]
    pub growth: f64,
}

/// A cloud's weather (`nebel_core::field::CloudWeather` and `WeatherMap`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum WeatherDescription {
    /// Procedural weather; unset fields take `CloudWeather`'s defaults.
    Procedural(ProceduralWeatherDescription),
    /// Grayscale PNGs over the box's footprint, relative to the scene file.
    Map(WeatherMapDescription),
}

/// Procedural weather (`nebel_core::field::CloudWeather`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProceduralWeatherDescription {
    /// Size of the weather's regions, metres, ≥ 0 (0: no weather).
    pub wavelength: f64,
    /// Seed. Default 0.
    #[serde(default)]
    pub seed: u32,
    /// Fraction of the sky without cloud. Default 0.3.
    #[serde(default)]
    pub clear: Option<f32>,
    /// Fraction of the sky at the full coverage. Default 0.2.
    #[serde(default)]
    pub overcast: Option<f32>,
    /// Fraction of the columns of stratus. Default 0.3.
    #[serde(default)]
    pub stratus: Option<f32>,
    /// Top of a stratus column, a fraction of the box's height. Default 0.35.
    #[serde(default)]
    pub stratus_top: Option<f32>,
}

/// A weather map from grayscale PNGs stretched over the box's footprint
/// (the image's left column at the minimum x, its top row at the minimum z).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WeatherMapDescription {
    /// Coverage: black no cloud, white the cloud's full coverage.
    pub coverage: String,
    /// Cloud type: black stratus, white cumulus. Default cumulus everywhere.
    #[serde(default)]
    pub kind: Option<String>,
    /// Top of a stratus column, a fraction of the box's height. Default 0.35.
    #[serde(default)]
    pub stratus_top: Option<f32>,
}

impl CloudSource {
    /// The generator settings, defaults filled in.
    pub fn noise(&self) -> CloudNoise {
        let defaults = CloudNoise::of_kind(self.kind);
        CloudNoise {
            seed: self.seed,
            coverage: self.coverage.unwrap_or(defaults.coverage),
            octaves: self.octaves.unwrap_or(defaults.octaves),
            wavelength: self.wavelength.unwrap_or(defaults.wavelength),
            wind: DVec3::from(self.wind),
            detail_wind: self.detail_wind.unwrap_or(defaults.detail_wind),
            torque: DVec3::from(self.torque),
            base_fade: self.base_fade.unwrap_or(defaults.base_fade),
            top_fade: self.top_fade.unwrap_or(defaults.top_fade),
            side_fade: self.side_fade.unwrap_or(defaults.side_fade),
            sharpness: self.sharpness.unwrap_or(defaults.sharpness),
            stretch: self.stretch.map_or(defaults.stretch, DVec3::from),
            wisps: self.wisps.unwrap_or(defaults.wisps),
            weather: match &self.weather {
                Some(WeatherDescription::Procedural(weather)) => {
                    let defaults = CloudWeather::default();
                    CloudWeather {
                        wavelength: weather.wavelength,
                        seed: weather.seed,
                        clear: weather.clear.unwrap_or(defaults.clear),
                        overcast: weather.overcast.unwrap_or(defaults.overcast),
                        stratus: weather.stratus.unwrap_or(defaults.stratus),
                        stratus_top: weather.stratus_top.unwrap_or(defaults.stratus_top),
                    }
                }
                _ => CloudWeather::default(),
            },
            ..defaults
        }
    }

    /// The cloud's shape: its weather map (loaded, if the weather is one,
    /// its paths resolved against `scene_dir`) and its ellipsoids. Errors
    /// name the field.
    fn shape(&self, scene_dir: &Path) -> Result<CloudShape, InvalidField> {
        Ok(CloudShape {
            weather_map: self.weather_map(scene_dir)?,
            primitives: self
                .primitives
                .iter()
                .map(|p| CloudEllipsoid {
                    centre: DVec3::from(p.centre),
                    radii: DVec3::from(p.radii),
                    rotation: DQuat::from_rotation_y(p.yaw_degrees.to_radians()),
                    density: p.density.unwrap_or(1.0),
                    velocity: DVec3::from(p.velocity),
                    growth: p.growth,
                })
                .collect(),
        })
    }

    fn weather_map(&self, scene_dir: &Path) -> Result<Option<Arc<WeatherMap>>, InvalidField> {
        let Some(WeatherDescription::Map(map)) = &self.weather else {
            return Ok(None);
        };
        let load = |field: &str, path: &str| InvalidField::load_map(scene_dir, path, field);
        let coverage = load("source.Cloud.weather.coverage", &map.coverage)?;
        let kind = map
            .kind
            .as_deref()
            .map(|path| load("source.Cloud.weather.kind", path))
            .transpose()?;
        let stratus_top = map
            .stratus_top
            .unwrap_or(CloudWeather::default().stratus_top);
        WeatherMap::new(coverage, kind, stratus_top)
            .map(|map| Some(Arc::new(map)))
            .map_err(|error| InvalidField::new("source.Cloud.weather", error.to_string()))
    }
}

/// Level-of-detail settings of a grid volume: the octree refined by the
/// screen error (`image_error`, the default) or by the distance criterion
/// (`accuracy`); at most one of the two.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LodDescription {
    /// The screen error's tolerance: the RMSE over the image (linear RGB)
    /// that one node's error alone may cause, > 0. Default 0.1 when
    /// `accuracy` is not given.
    #[serde(default)]
    pub image_error: Option<f64>,
    /// The distance criterion's global accuracy `c`, ≥ 0: higher draws more
    /// cells (16 was the default before the screen error).
    #[serde(default)]
    pub accuracy: Option<f64>,
    /// Minimum accuracy `C`, > √3. Default 4.
    #[serde(default = "default_lod_min_accuracy")]
    pub min_accuracy: f64,
}

impl Default for LodDescription {
    /// The screen error at its default tolerance, `C = 4`.
    fn default() -> Self {
        Self {
            image_error: None,
            accuracy: None,
            min_accuracy: default_lod_min_accuracy(),
        }
    }
}

impl LodDescription {
    /// The distance criterion at accuracy `c`.
    pub fn distance(accuracy: f64) -> Self {
        Self {
            accuracy: Some(accuracy),
            ..Self::default()
        }
    }

    /// The screen error at `image_error`.
    pub fn screen_error(image_error: f64) -> Self {
        Self {
            image_error: Some(image_error),
            ..Self::default()
        }
    }

    /// The refinement criterion described (validated: at most one of the two
    /// is given).
    pub fn criterion(&self) -> LodCriterion {
        match (self.image_error, self.accuracy) {
            (_, Some(accuracy)) => LodCriterion::distance(accuracy),
            (Some(image_error), None) => LodCriterion::screen_error(image_error),
            (None, None) => LodCriterion::default(),
        }
    }
}

fn default_lod_min_accuracy() -> f64 {
    OctreeSettings::DEFAULT_MIN_ACCURACY
}

fn default_min() -> [f32; 3] {
    [-1.0; 3]
}

fn default_max() -> [f32; 3] {
    [1.0; 3]
}

fn default_density_scale() -> f32 {
    1.0
}

/// Where a volume's scalar field comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum SourceDescription {
    /// The same scalar everywhere in the box.
    Uniform(UniformSource),
    /// A scalar linear along one axis of the box.
    Ramp(RampSource),
    /// Seeded Perlin noise.
    Procedural(ProceduralSource),
    /// Tetrahedra in world space with a scalar per vertex.
    Cells(Vec<TetrahedronDescription>),
    /// An animated campfire (Röttger 2004 §10.4): the flame box
    /// [`CAMPFIRE_MIN`]..[`CAMPFIRE_MAX`] stretched onto `min..max`, its
    /// density changing every frame. Emissive with the `Fire` preset unless
    /// the volume says otherwise.
    Campfire(CampfireSource),
    /// Procedural cumulus clouds after Schpok et al. 2003 (coverage, detail octaves,
    /// wind), sampled over the box.
    Cloud(Box<CloudSource>),
    /// A search-light cone (Röttger 2004 §10.4), placed by its own position and
    /// direction (the box is not used). Emissive with the `SearchLight` preset
    /// unless the volume says otherwise.
    SearchLight(SearchLightSource),
}

/// An animated campfire.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CampfireSource {
    /// Noise seed. Default 0.
    #[serde(default)]
    pub seed: u32,
    /// Grid points per axis, each in [2, 257] (at full resolution 238³ at
    /// most fits the memory budget, see the module docs). Default
    /// `(17, 17, 17)` (16³ cells).
    #[serde(default = "default_campfire_dims")]
    pub dims: [usize; 3],
}

fn default_campfire_dims() -> [usize; 3] {
    CAMPFIRE_DIMS
}

/// A search-light cone.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SearchLightSource {
    /// The cone's apex (the lamp), metres.
    pub position: [f32; 3],
    /// The beam's direction; non-zero.
    pub direction: [f32; 3],
    /// Length of the beam, metres, > 0.
    pub length: f32,
    /// Half the opening angle, degrees, in (0, 85].
    pub half_angle_degrees: f32,
    /// Cells around × radial × along the beam, each in [1, 256] (around even).
    /// Default `(16, 4, 32)`.
    #[serde(default = "default_search_light_segments")]
    pub segments: [usize; 3],
}

fn default_search_light_segments() -> [usize; 3] {
    SEARCH_LIGHT_SEGMENTS
}

/// The same scalar everywhere.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UniformSource {
    /// The scalar, in [0, 1].
    pub value: f32,
    /// Grid points per axis, each ≥ 2. Default `(2, 2, 2)`.
    #[serde(default = "default_small_dims")]
    pub dims: [usize; 3],
}

/// A coordinate axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Axis {
    /// World X.
    X,
    /// World Y (up).
    Y,
    /// World Z.
    Z,
}

/// A scalar linear along one axis: `from` at the box's minimum, `to` at its maximum.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RampSource {
    /// The axis the scalar changes along.
    pub axis: Axis,
    /// Scalar at `min` along the axis, in [0, 1].
    pub from: f32,
    /// Scalar at `max` along the axis, in [0, 1].
    pub to: f32,
    /// Grid points per axis, each ≥ 2. Default `(2, 2, 2)`: the ramp is exact
    /// with two points.
    #[serde(default = "default_small_dims")]
    pub dims: [usize; 3],
}

fn default_small_dims() -> [usize; 3] {
    [2; 3]
}

/// Seeded fractal Perlin noise over the box.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProceduralSource {
    /// Grid points per axis, each ≥ 2.
    pub dims: [usize; 3],
    /// Fractal kind. Default `Fbm`.
    #[serde(default)]
    pub kind: NoiseKind,
    /// Seed. Default 0.
    #[serde(default)]
    pub seed: u32,
    /// Octaves, 1 to 32. Default 4.
    #[serde(default = "default_octaves")]
    pub octaves: usize,
    /// First-octave frequency, cycles per metre, > 0. Default 1.
    #[serde(default = "default_frequency")]
    pub frequency: f32,
    /// Share of the noise range kept, in (0, 1]: a noise value `n` in [0, 1]
    /// becomes `clamp((n − (1 − coverage)) / coverage, 0, 1)`, so a smaller
    /// coverage leaves more empty space. Default 1 (the noise as it is).
    #[serde(default = "default_coverage")]
    pub coverage: f32,
    /// Multiply the noise by `max(0, 1 − r²)`, `r` the distance from the box
    /// centre with the box scaled to the unit sphere, so the volume fades to
    /// nothing before its box ends (an implicit ellipsoid, Schpok et al. 2003). Default false.
    #[serde(default)]
    pub ellipsoid: bool,
}

fn default_octaves() -> usize {
    4
}

fn default_frequency() -> f32 {
    1.0
}

fn default_coverage() -> f32 {
    1.0
}

/// A tetrahedron in world space.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TetrahedronDescription {
    /// The four vertices, metres.
    pub positions: [[f32; 3]; 4],
    /// The scalar at each vertex, in [0, 1].
    pub scalars: [f32; 4],
}

/// A transfer function in a scene file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum TransferDescription {
    /// A named preset.
    Preset(TransferPreset),
    /// Control points, piecewise linear.
    Points(Vec<ControlPoint>),
    /// A 1-pixel-high PNG strip, see [`TransferFunction::from_png_strip`].
    Strip(TransferStrip),
}

impl TransferDescription {
    /// The transfer function: the preset, the points, or the strip loaded
    /// from its path relative to `scene_dir`.
    pub fn build(&self, scene_dir: &Path) -> Result<TransferFunction, TransferError> {
        match self {
            Self::Preset(preset) => Ok(TransferFunction::preset(*preset)),
            Self::Points(points) => TransferFunction::new(points.clone()),
            Self::Strip(strip) => {
                TransferFunction::from_png_strip(scene_dir.join(&strip.path), strip.max_density)
            }
        }
    }

    /// The transfer function of `description`, or `preset` without one, its
    /// density scaled by `scale`; errors name the field `transfer`.
    pub(crate) fn scaled(
        description: Option<&Self>,
        preset: TransferPreset,
        scene_dir: &Path,
        scale: f32,
    ) -> Result<TransferFunction, InvalidField> {
        let built = match description {
            Some(description) => description.build(scene_dir),
            None => Ok(TransferFunction::preset(preset)),
        };
        built
            .and_then(|tf| tf.scale_density(scale))
            .map_err(|error| InvalidField::new("transfer", error.to_string()))
    }
}

/// A transfer function from a PNG strip.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferStrip {
    /// The PNG, relative to the scene file.
    pub path: String,
    /// ρ where the strip's alpha is 1, 1/metre.
    pub max_density: f32,
}

/// A volume ready to render: its field and its transfer function.
#[derive(Clone, Debug, PartialEq)]
pub struct BuiltVolume {
    /// The scalar field.
    pub field: SceneField,
    /// κ and ρ, `density_scale` applied.
    pub transfer_function: TransferFunction,
    /// How segments combine.
    pub mode: OpticalMode,
    /// Level-of-detail settings, the octree's default where the volume is
    /// drawn through it without them (module docs); `None` draws at full
    /// resolution.
    pub lod: Option<LodDescription>,
    /// Cloud lighting; `None` for an unlit volume.
    pub lighting: Option<LightingDescription>,
    /// A grid at full resolution is drawn as projected cells, not ray cast.
    pub projected_cells: bool,
    /// Ground fog: the scene's fog layers take it over from their start
    /// distance, where its rays end (as the GPU's cell batch of ground fog).
    pub ends_where_fog_layers_begin: bool,
    /// How it scatters volumetric point and spot lights.
    pub light_response: LightResponse,
    /// Ground fog lit by the sun: the terrain's shadow, the fog's column and
    /// the sun (`nebel_core::fog_sunlight`); `None` for anything else.
    pub fog_sunlight: Option<FogSunlight>,
}

/// A volume's scalar field.
#[derive(Clone, Debug, PartialEq)]
pub enum SceneField {
    /// A trilinear grid over a box.
    Grid(DensityGrid),
    /// Tetrahedra with a scalar per vertex.
    Cells(Vec<Tetrahedron>),
    /// A campfire whose grid changes with time, see [`AnimatedCampfire::grid_at`].
    Campfire(AnimatedCampfire),
    /// Procedural clouds drifting with the wind, see [`AnimatedCloud::grid_at`].
    Cloud(AnimatedCloud),
}

/// Procedural clouds over a box: their density at any time.
#[derive(Clone, Debug, PartialEq)]
pub struct AnimatedCloud {
    /// The generator settings.
    pub noise: CloudNoise,
    /// Seconds between the keyframes a windy cloud is drawn from.
    pub keyframe_interval: f32,
    /// The weather map over the box and the ellipsoids.
    pub shape: CloudShape,
    /// Grid points per axis.
    pub dims: [usize; 3],
    /// Minimum corner of the box, metres.
    pub min: DVec3,
    /// Maximum corner of the box, metres.
    pub max: DVec3,
}

impl AnimatedCloud {
    /// The density grid at `time` seconds, in world space. Errors name the
    /// generator setting that is out of range.
    pub fn grid_at(&self, time: f64) -> Result<DensityGrid, FieldError> {
        let spacing = (self.max - self.min) / (DVec3::from(self.dims.map(|n| n as f64)) - 1.0);
        DensityGrid::cloud_shaped(self.dims, spacing, self.min, &self.noise, &self.shape, time)
    }

    /// The keyframes a windy cloud is drawn between at `time`: their times
    /// `k·T` and `(k + 1)·T` and the blend factor toward the second
    /// (`nebel_lod::octree::keyframe`); `None` without wind, torque or
    /// moving ellipsoids (the cloud is its grid at `time`).
    pub fn keyframes_at(&self, time: f64) -> Option<([f64; 2], f64)> {
        if !self.noise.animates() && !self.shape.animates() {
            return None;
        }
        let interval = f64::from(self.keyframe_interval).max(1e-3);
        let index = keyframe_index(time, interval);
        let start = keyframe_time(index, interval);
        let times = [start, keyframe_time(index + 1, interval)];
        Some((times, ((time - start) / interval).clamp(0.0, 1.0)))
    }
}

/// A campfire placed in a box: its density at any time.
#[derive(Clone, Debug, PartialEq)]
pub struct AnimatedCampfire {
    /// Noise seed.
    pub seed: u32,
    /// Grid points per axis.
    pub dims: [usize; 3],
    /// Minimum corner of the box the flame box is stretched onto, metres.
    pub min: DVec3,
    /// Maximum corner of that box, metres.
    pub max: DVec3,
}

impl AnimatedCampfire {
    /// How the flame box maps onto `min..max`: per-axis scale and offset.
    pub fn placement(&self) -> (DVec3, DVec3) {
        let scale = (self.max - self.min) / (CAMPFIRE_MAX - CAMPFIRE_MIN);
        (scale, self.min - CAMPFIRE_MIN * scale)
    }

    /// The density grid at `time` seconds, in world space.
    pub fn grid_at(&self, time: f64) -> DensityGrid {
        let flame = campfire_density(self.dims, time, self.seed);
        let (scale, _) = self.placement();
        DensityGrid::new(
            flame.dims(),
            flame.spacing() * scale,
            self.min,
            flame.values().to_vec(),
        )
        .expect("a campfire grid scaled by a positive factor stays valid")
    }
}

/// The cone of `light` in world space: apex at its position, opening along
/// its direction. Errors name the segments when the cells exceed the memory
/// budget.
fn search_light(light: &SearchLightSource) -> Result<Vec<Tetrahedron>, InvalidField> {
    let direction = DVec3::from(light.direction.map(f64::from)).normalize();
    let rotation = DQuat::from_rotation_arc(DVec3::NEG_Z, direction);
    let position = DVec3::from(light.position.map(f64::from));
    let cells = search_light_cells(
        f64::from(light.length),
        f64::from(light.half_angle_degrees).to_radians(),
        light.segments,
    )
    .map_err(over_budget("source.SearchLight.segments"))?;
    Ok(cells
        .into_iter()
        .map(|cell| Tetrahedron {
            positions: cell.positions.map(|p| position + rotation * p),
            scalars: cell.scalars,
        })
        .collect())
}

/// Turns a [`BudgetError`] into an [`InvalidField`] naming `field`, the
/// field that sizes what was to be built.
fn over_budget(field: &str) -> impl FnOnce(BudgetError) -> InvalidField + '_ {
    move |error| InvalidField::new(field, error.to_string())
}

fn source_error(error: FieldError) -> InvalidField {
    InvalidField::new("source", error.to_string())
}

impl VolumeDescription {
    /// Generates or loads the field and builds the transfer function.
    /// `scene_dir` resolves a strip's relative path. Errors name the field
    /// (relative to this volume) and the reason.
    pub fn build(&self, scene_dir: &Path) -> Result<BuiltVolume, InvalidField> {
        let field = match &self.source {
            SourceDescription::Cells(cells) => SceneField::Cells(
                cells
                    .iter()
                    .map(|cell| Tetrahedron {
                        positions: cell.positions.map(|p| DVec3::from(p.map(f64::from))),
                        scalars: cell.scalars.map(f64::from),
                    })
                    .collect(),
            ),
            SourceDescription::Uniform(uniform) => SceneField::Grid(self.uniform_grid(uniform)?),
            SourceDescription::Ramp(ramp) => SceneField::Grid(self.ramp_grid(ramp)?),
            SourceDescription::Procedural(procedural) => {
                SceneField::Grid(self.procedural_grid(procedural)?)
            }
            SourceDescription::Campfire(campfire) => SceneField::Campfire(AnimatedCampfire {
                seed: campfire.seed,
                dims: campfire.dims,
                min: self.min_corner(),
                max: self.max_corner(),
            }),
            SourceDescription::SearchLight(light) => SceneField::Cells(search_light(light)?),
            SourceDescription::Cloud(cloud) => {
                if let Some(interval) = cloud.keyframe_interval
                    && !(interval.is_finite() && interval > 0.0)
                {
                    return Err(InvalidField::new(
                        "source.Cloud.keyframe_interval",
                        format!("must be finite and > 0, got {interval}"),
                    ));
                }
                let animated = AnimatedCloud {
                    noise: cloud.noise(),
                    shape: cloud.shape(scene_dir)?,
                    keyframe_interval: cloud.keyframe_interval.unwrap_or(2.0),
                    dims: cloud.dims,
                    min: self.min_corner(),
                    max: self.max_corner(),
                };
                // Checks every generator setting now, not at the first frame.
                animated.grid_at(0.0).map_err(source_error)?;
                SceneField::Cloud(animated)
            }
        };
        let light_model = self.lighting.map(|lighting| lighting.model);
        let (default_preset, default_mode) = match (&self.source, light_model) {
            (SourceDescription::Campfire(_), _) => (TransferPreset::Fire, OpticalMode::Emissive),
            (SourceDescription::SearchLight(_), _) => {
                (TransferPreset::SearchLight, OpticalMode::Emissive)
            }
            (_, Some(LightModel::Isotropic)) => (TransferPreset::CloudLight, OpticalMode::Sorted),
            (_, Some(LightModel::Scattering { .. })) => {
                (TransferPreset::Transmittance, OpticalMode::Sorted)
            }
            _ => (TransferPreset::Cloud, OpticalMode::Sorted),
        };
        let transfer = TransferDescription::scaled(
            self.transfer.as_ref(),
            default_preset,
            scene_dir,
            self.density_scale,
        )?;
        Ok(BuiltVolume {
            field,
            transfer_function: transfer,
            mode: self.mode.unwrap_or(default_mode),
            lod: self.drawn_lod(),
            lighting: self.lighting,
            projected_cells: self.projected_cells,
            ends_where_fog_layers_begin: false,
            light_response: self.light_response,
            fog_sunlight: None,
        })
    }

    /// The octree's settings the volume is drawn with: its `lod`, or the
    /// default for a lit volume or a cloud without `full_resolution`.
    fn drawn_lod(&self) -> Option<LodDescription> {
        let octree_by_default =
            self.lighting.is_some() || matches!(self.source, SourceDescription::Cloud(_));
        self.lod
            .or_else(|| (octree_by_default && !self.full_resolution).then(LodDescription::default))
    }

    fn spacing(&self, dims: [usize; 3]) -> DVec3 {
        let steps = DVec3::from(dims.map(|n| (n.max(2) - 1) as f64));
        (self.max_corner() - self.min_corner()) / steps
    }

    fn min_corner(&self) -> DVec3 {
        DVec3::from(self.min.map(f64::from))
    }

    fn max_corner(&self) -> DVec3 {
        DVec3::from(self.max.map(f64::from))
    }

    fn uniform_grid(&self, uniform: &UniformSource) -> Result<DensityGrid, InvalidField> {
        DensityGrid::check_budget(uniform.dims).map_err(over_budget("source.Uniform.dims"))?;
        let count = uniform.dims.iter().product();
        DensityGrid::new(
            uniform.dims,
            self.spacing(uniform.dims),
            self.min_corner(),
            vec![uniform.value; count],
        )
        .map_err(source_error)
    }

    fn ramp_grid(&self, ramp: &RampSource) -> Result<DensityGrid, InvalidField> {
        DensityGrid::check_budget(ramp.dims).map_err(over_budget("source.Ramp.dims"))?;
        let [nx, ny, nz] = ramp.dims;
        let axis = ramp.axis as usize;
        let mut values = Vec::with_capacity(nx * ny * nz);
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let t = [i, j, k][axis] as f32 / (ramp.dims[axis] - 1) as f32;
                    values.push(ramp.from + (ramp.to - ramp.from) * t);
                }
            }
        }
        DensityGrid::new(
            ramp.dims,
            self.spacing(ramp.dims),
            self.min_corner(),
            values,
        )
        .map_err(source_error)
    }

    fn procedural_grid(&self, procedural: &ProceduralSource) -> Result<DensityGrid, InvalidField> {
        let noise = ProceduralNoise {
            kind: procedural.kind,
            seed: procedural.seed,
            octaves: procedural.octaves,
            frequency: f64::from(procedural.frequency),
            ..ProceduralNoise::default()
        };
        let spacing = self.spacing(procedural.dims);
        let grid = DensityGrid::procedural(procedural.dims, spacing, self.min_corner(), &noise)
            .map_err(source_error)?;
        let coverage = procedural.coverage;
        let [nx, ny, nz] = procedural.dims;
        let unit = |i: usize, n: usize| 2.0 * i as f32 / (n - 1) as f32 - 1.0;
        let values = grid
            .values()
            .iter()
            .enumerate()
            .map(|(index, n)| {
                let covered = ((n - (1.0 - coverage)) / coverage).clamp(0.0, 1.0);
                if !procedural.ellipsoid {
                    return covered;
                }
                let (i, j, k) = (index % nx, (index / nx) % ny, index / (nx * ny));
                let r2 = unit(i, nx).powi(2) + unit(j, ny).powi(2) + unit(k, nz).powi(2);
                covered * (1.0 - r2).max(0.0)
            })
            .collect();
        DensityGrid::new(procedural.dims, spacing, self.min_corner(), values).map_err(source_error)
    }

    /// Checks what is cheap to check; [`VolumeDescription::build`] checks the rest.
    pub(super) fn validate(&self) -> Result<(), InvalidField> {
        for (name, corner) in [("min", self.min), ("max", self.max)] {
            if let Some(value) = corner.iter().find(|c| !c.is_finite()) {
                return Err(InvalidField::new(
                    name,
                    format!("must be finite, got {value}"),
                ));
            }
        }
        if (0..3).any(|a| self.max[a] <= self.min[a]) {
            return Err(InvalidField::new(
                "max",
                format!(
                    "must exceed min on every axis, got min {:?} max {:?}",
                    self.min, self.max
                ),
            ));
        }
        InvalidField::check_light_response(&self.light_response)?;
        if self.full_resolution && self.lod.is_some() {
            return Err(InvalidField::new(
                "full_resolution",
                "draws the volume without the octree: give it or lod, not both",
            ));
        }
        if self.full_resolution && self.lighting.is_some() && self.projected_cells {
            return Err(InvalidField::new(
                "projected_cells",
                "projected cells at full resolution carry no light field: a lit volume with full_resolution is ray cast",
            ));
        }
        if let Some(lod) = &self.lod {
            match (lod.image_error, lod.accuracy) {
                (Some(_), Some(_)) => {
                    return Err(InvalidField::new(
                        "lod",
                        "give either image_error (the screen error) or accuracy (the distance criterion), not both",
                    ));
                }
                (Some(image_error), None) if !(image_error.is_finite() && image_error > 0.0) => {
                    return Err(InvalidField::new(
                        "lod.image_error",
                        format!("must be finite and > 0, got {image_error}"),
                    ));
                }
                (None, Some(accuracy)) if accuracy.is_nan() || accuracy < 0.0 => {
                    return Err(InvalidField::new(
                        "lod.accuracy",
                        format!("must be >= 0, got {accuracy}"),
                    ));
                }
                _ => {}
            }
            if !(lod.min_accuracy.is_finite() && lod.min_accuracy > 3f64.sqrt()) {
                return Err(InvalidField::new(
                    "lod.min_accuracy",
                    format!("must be finite and > √3, got {}", lod.min_accuracy),
                ));
            }
        }
        if let Some(lighting) = &self.lighting {
            for (field, value) in [
                ("lighting.ambient", lighting.ambient),
                ("lighting.diffuse", lighting.diffuse),
            ] {
                if !(0.0..=1.0).contains(&value) {
                    return Err(InvalidField::new(
                        field,
                        format!("must be in [0, 1], got {value}"),
                    ));
                }
            }
            if let LightModel::Scattering { asymmetry } = lighting.model
                && !(asymmetry > -1.0 && asymmetry < 1.0)
            {
                return Err(InvalidField::new(
                    "lighting.model.Scattering.asymmetry",
                    format!("must be in (-1, 1), got {asymmetry}"),
                ));
            }
            if !(lighting.shadow_extinction.is_finite() && lighting.shadow_extinction >= 0.0) {
                return Err(InvalidField::new(
                    "lighting.shadow_extinction",
                    format!(
                        "must be finite and >= 0, got {}",
                        lighting.shadow_extinction
                    ),
                ));
            }
            if lighting.ground_shadow && lighting.shadow_extinction == 0.0 {
                return Err(InvalidField::new(
                    "lighting.ground_shadow",
                    "casts no shadow without a shadow_extinction above 0",
                ));
            }
            let interval = lighting.keyframe_interval;
            if !(interval.is_finite() && interval > 0.0) {
                return Err(InvalidField::new(
                    "lighting.keyframe_interval",
                    format!("must be finite and > 0, got {interval}"),
                ));
            }
            let octaves = lighting.scattering_octaves;
            if !(1..=CloudLighting::MAX_SCATTERING_OCTAVES).contains(&octaves) {
                return Err(InvalidField::new(
                    "lighting.scattering_octaves",
                    format!("must be between 1 and 8, got {octaves}"),
                ));
            }
            if matches!(
                self.source,
                SourceDescription::Cells(_)
                    | SourceDescription::Campfire(_)
                    | SourceDescription::SearchLight(_)
            ) {
                return Err(InvalidField::new(
                    "lighting",
                    "only grid sources (Uniform, Ramp, Procedural, Cloud) can be lit",
                ));
            }
        }
        if !(self.density_scale.is_finite() && self.density_scale >= 0.0) {
            return Err(InvalidField::new(
                "density_scale",
                format!("must be finite and >= 0, got {}", self.density_scale),
            ));
        }
        let unit = |field: &str, value: f32| {
            if (0.0..=1.0).contains(&value) {
                Ok(())
            } else {
                Err(InvalidField::new(
                    field,
                    format!("must be in [0, 1], got {value}"),
                ))
            }
        };
        let dims = |field: &str, dims: [usize; 3]| {
            if dims.iter().all(|n| (2..=4097).contains(n)) {
                Ok(())
            } else {
                Err(InvalidField::new(
                    field,
                    format!("each must be in [2, 4097], got {dims:?}"),
                ))
            }
        };
        match &self.source {
            SourceDescription::Uniform(uniform) => {
                unit("source.Uniform.value", uniform.value)?;
                dims("source.Uniform.dims", uniform.dims)
            }
            SourceDescription::Ramp(ramp) => {
                unit("source.Ramp.from", ramp.from)?;
                unit("source.Ramp.to", ramp.to)?;
                dims("source.Ramp.dims", ramp.dims)
            }
            SourceDescription::Procedural(procedural) => {
                dims("source.Procedural.dims", procedural.dims)?;
                if !(procedural.coverage > 0.0 && procedural.coverage <= 1.0) {
                    return Err(InvalidField::new(
                        "source.Procedural.coverage",
                        format!("must be in (0, 1], got {}", procedural.coverage),
                    ));
                }
                Ok(())
            }
            SourceDescription::Cloud(cloud) => dims("source.Cloud.dims", cloud.dims),
            SourceDescription::Campfire(campfire) => dims("source.Campfire.dims", campfire.dims)
                .and_then(|()| {
                    if campfire.dims.iter().all(|n| *n <= 257) {
                        Ok(())
                    } else {
                        Err(InvalidField::new(
                            "source.Campfire.dims",
                            format!("each must be in [2, 257], got {:?}", campfire.dims),
                        ))
                    }
                }),
            SourceDescription::SearchLight(light) => {
                let field = "source.SearchLight";
                if light
                    .position
                    .iter()
                    .chain(&light.direction)
                    .any(|c| !c.is_finite())
                {
                    return Err(InvalidField::new(
                        field,
                        "position and direction must be finite",
                    ));
                }
                if light.direction.iter().all(|c| *c == 0.0) {
                    return Err(InvalidField::new(
                        format!("{field}.direction"),
                        "must not be zero",
                    ));
                }
                if !(light.length.is_finite() && light.length > 0.0) {
                    return Err(InvalidField::new(
                        format!("{field}.length"),
                        format!("must be finite and > 0, got {}", light.length),
                    ));
                }
                if !(light.half_angle_degrees > 0.0 && light.half_angle_degrees <= 85.0) {
                    return Err(InvalidField::new(
                        format!("{field}.half_angle_degrees"),
                        format!("must be in (0, 85], got {}", light.half_angle_degrees),
                    ));
                }
                let [around, radial, along] = light.segments;
                if !(around % 2 == 0
                    && [around, radial, along]
                        .iter()
                        .all(|n| (1..=256).contains(n)))
                {
                    return Err(InvalidField::new(
                        format!("{field}.segments"),
                        format!(
                            "each must be in [1, 256] and `around` even, got {:?}",
                            light.segments
                        ),
                    ));
                }
                Ok(())
            }
            SourceDescription::Cells(cells) => {
                if cells.is_empty() {
                    return Err(InvalidField::new("source.Cells", "needs at least one cell"));
                }
                for (index, cell) in cells.iter().enumerate() {
                    if cell.positions.iter().flatten().any(|c| !c.is_finite()) {
                        return Err(InvalidField::new(
                            format!("source.Cells[{index}].positions"),
                            "must be finite",
                        ));
                    }
                    for scalar in cell.scalars {
                        unit(&format!("source.Cells[{index}].scalars"), scalar)?;
                    }
                }
                Ok(())
            }
        }?;
        self.check_budget()
    }

    /// Checks that every structure built for the volume fits the memory
    /// budget (see the module docs); errors name the field that sizes it.
    fn check_budget(&self) -> Result<(), InvalidField> {
        let (field, dims) = match &self.source {
            SourceDescription::Uniform(uniform) => ("source.Uniform.dims", uniform.dims),
            SourceDescription::Ramp(ramp) => ("source.Ramp.dims", ramp.dims),
            SourceDescription::Procedural(procedural) => {
                ("source.Procedural.dims", procedural.dims)
            }
            SourceDescription::Cloud(cloud) => ("source.Cloud.dims", cloud.dims),
            SourceDescription::Campfire(campfire) => ("source.Campfire.dims", campfire.dims),
            SourceDescription::SearchLight(light) => {
                return check_search_light_budget(light.segments)
                    .map(drop)
                    .map_err(over_budget("source.SearchLight.segments"));
            }
            SourceDescription::Cells(cells) => {
                return check_allocation(
                    || format!("cell list of {} tetrahedra", cells.len()),
                    &[cells.len()],
                    size_of::<Tetrahedron>() as u64,
                )
                .map(drop)
                .map_err(over_budget("source.Cells"));
            }
        };
        DensityGrid::check_budget(dims).map_err(over_budget(field))?;
        if self.drawn_lod().is_some() {
            // The octree's grid, its light field and the octree itself.
            let padded = dims.map(power_of_two_plus_one);
            let padded_error = |error: BudgetError| {
                InvalidField::new(
                    field,
                    format!("padded to 2^n+1 points per axis for the octree, the {error}"),
                )
            };
            DensityGrid::check_budget(padded).map_err(padded_error)?;
            VolumeHierarchy::check_budget(padded, self.lighting.is_some()).map_err(padded_error)?;
        } else if self.projected_cells {
            // Projected cells; a ray-cast grid needs only the grid itself
            // (and a lit one its light field, of the same size).
            let voxels = dims.map(|n| n - 1);
            check_allocation(
                || {
                    format!(
                        "full-resolution batch of {} voxels ({} tetrahedra each)",
                        Dims(&voxels),
                        KUHN_TETRAHEDRA.len()
                    )
                },
                &[KUHN_TETRAHEDRA.len(), voxels[0], voxels[1], voxels[2]],
                size_of::<GpuCell>() as u64,
            )
            .map_err(over_budget(field))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_transfer_function_is_validated_when_deserialized() {
        let tf: TransferFunction =
            ron::from_str("(points: [(s: 1.0, kappa: (1.0, 1.0, 1.0), rho: 2.0), (s: 0.0, kappa: (0.0, 0.0, 0.0), rho: 0.0)])")
                .unwrap();
        assert_eq!(tf.points()[0].s, 0.0);
        let error = ron::from_str::<TransferFunction>("(points: [])").unwrap_err();
        assert!(
            error.to_string().contains("at least one control point"),
            "{error}"
        );
    }

    fn volume(source: SourceDescription) -> VolumeDescription {
        VolumeDescription {
            source,
            min: [0.0; 3],
            max: [2.0, 4.0, 8.0],
            transfer: None,
            density_scale: 2.0,
            mode: Some(OpticalMode::Emissive),
            lod: None,
            lighting: None,
            projected_cells: false,
            full_resolution: false,
            light_response: LightResponse::default(),
        }
    }

    #[test]
    fn a_cloud_takes_its_weather_from_noise_or_from_maps() {
        let dir = std::env::temp_dir().join(format!("nebel-scene-weather-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // Coverage: black (clear) on the left, white on the right.
        image::ImageBuffer::<image::Luma<u8>, _>::from_fn(4, 4, |x, _| {
            image::Luma([if x < 2 { 0 } else { 255 }])
        })
        .save(dir.join("coverage.png"))
        .unwrap();
        let source = |weather: &str| {
            let ron = format!(
                "(source: Cloud((dims: (13, 7, 13), coverage: 1.0, wavelength: 6.0, \
                 side_fade: 0.0, weather: {weather})))"
            );
            ron::Options::default()
                .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME)
                .from_str::<VolumeDescription>(&ron)
                .unwrap()
        };
        let built = source("Map((coverage: \"coverage.png\"))")
            .build(&dir)
            .unwrap();
        let SceneField::Cloud(cloud) = built.field else {
            panic!("a cloud source is an animated cloud");
        };
        let grid = cloud.grid_at(0.0).unwrap();
        let [nx, ny, nz] = grid.dims();
        let column = || (0..nz).flat_map(|k| (0..ny).map(move |j| (j, k)));
        // The image's two left pixels span the box's first third: clear.
        assert!(column().all(|(j, k)| grid.value(0, j, k) == 0.0));
        assert!(column().any(|(j, k)| grid.value(nx - 1, j, k) > 0.0));

        let stratus = ron::Options::default()
            .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME)
            .from_str::<VolumeDescription>(
                "(source: Cloud((dims: (5, 5, 5), kind: Stratus, coverage: 0.6, \
                 stretch: (2.0, 1.0, 3.0))))",
            )
            .unwrap();
        let SourceDescription::Cloud(stratus) = &stratus.source else {
            panic!("a cloud source");
        };
        let noise = stratus.noise();
        assert_eq!((noise.coverage, noise.sharpness), (0.6, 0.4));
        assert_eq!(noise.stretch, DVec3::new(2.0, 1.0, 3.0));

        let procedural = source("Procedural((wavelength: 20.0, clear: 0.5, stratus_top: 0.5))");
        let SceneField::Cloud(cloud) = procedural.build(&dir).unwrap().field else {
            panic!("a cloud source is an animated cloud");
        };
        assert_eq!(cloud.noise.weather.clear, 0.5);
        assert_eq!(
            cloud.noise.weather.overcast,
            CloudWeather::default().overcast
        );
        assert!(cloud.shape.weather_map.is_none());

        let error = source("Map((coverage: \"missing.png\"))")
            .build(&dir)
            .unwrap_err();
        assert_eq!(error.field, "source.Cloud.weather.coverage");
        assert!(error.reason.contains("missing.png"), "{}", error.reason);
        let error = source("Map((coverage: \"coverage.png\", stratus_top: 0.0))")
            .build(&dir)
            .unwrap_err();
        assert_eq!(error.field, "source.Cloud.weather");
        let error = source("Procedural((wavelength: 20.0, clear: 2.0))")
            .build(&dir)
            .unwrap_err();
        assert_eq!(error.field, "source");
        assert!(error.reason.contains("weather.clear"), "{}", error.reason);
    }

    #[test]
    fn a_cloud_is_shaped_by_its_primitives_and_animates_when_they_move() {
        let source = |velocity: &str| {
            let ron = format!(
                "(source: Cloud((dims: (13, 7, 13), coverage: 1.0, wavelength: 6.0, \
                 side_fade: 0.0, primitives: [(centre: (0.0, 0.0, 0.0), radii: (0.6, 0.5, 0.4), \
                 yaw_degrees: 90.0, density: 2.0, velocity: {velocity})])))"
            );
            ron::Options::default()
                .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME)
                .from_str::<VolumeDescription>(&ron)
                .unwrap()
        };
        let SceneField::Cloud(still) = source("(0.0, 0.0, 0.0)")
            .build(Path::new("."))
            .unwrap()
            .field
        else {
            panic!("a cloud source is an animated cloud");
        };
        let [e] = still.shape.primitives.as_slice() else {
            panic!("one primitive");
        };
        assert_eq!((e.radii, e.density), (DVec3::new(0.6, 0.5, 0.4), 2.0));
        // A quarter turn about y: the ellipsoid's x axis lies along −z.
        assert!((e.rotation * DVec3::X - DVec3::NEG_Z).length() < 1e-12);
        assert_eq!(still.keyframes_at(1.0), None);
        // Nothing outside the ellipsoid (the box is ±1 on each axis).
        let grid = still.grid_at(0.0).unwrap();
        assert_eq!(grid.value(0, 3, 6), 0.0);
        assert!(grid.values().iter().any(|&v| v > 0.0));

        let SceneField::Cloud(rising) = source("(0.0, 0.5, 0.0)")
            .build(Path::new("."))
            .unwrap()
            .field
        else {
            panic!("a cloud source is an animated cloud");
        };
        assert!(rising.keyframes_at(1.0).is_some());
        assert_ne!(
            rising.grid_at(0.0).unwrap().values(),
            rising.grid_at(1.0).unwrap().values()
        );
    }

    #[test]
    fn a_cloud_under_torque_animates_and_turns_its_detail() {
        let cloud = |torque: &str| {
            let ron = format!(
                "(source: Cloud((dims: (13, 7, 13), coverage: 0.6, wavelength: 6.0, \
                 torque: {torque})))"
            );
            let volume = ron::Options::default()
                .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME)
                .from_str::<VolumeDescription>(&ron)
                .unwrap();
            match volume.build(Path::new(".")).unwrap().field {
                SceneField::Cloud(cloud) => cloud,
                _ => panic!("a cloud source is an animated cloud"),
            }
        };
        let still = cloud("(0.0, 0.0, 0.0)");
        let turning = cloud("(0.0, 0.8, 0.0)");
        assert_eq!(still.noise.torque, DVec3::ZERO);
        assert_eq!(turning.noise.torque, DVec3::new(0.0, 0.8, 0.0));
        assert_eq!(still.keyframes_at(1.0), None);
        assert!(turning.keyframes_at(1.0).is_some());
        // At time 0 nothing has turned yet; a second later the detail has.
        let grid = |cloud: &AnimatedCloud, time| cloud.grid_at(time).unwrap();
        let (before, after) = (grid(&turning, 0.0), grid(&turning, 1.0));
        let most = |a: &DensityGrid, b: &DensityGrid| {
            let pairs = a.values().iter().zip(b.values());
            pairs.map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max)
        };
        assert!(most(&grid(&still, 0.0), &before) <= 1e-6);
        assert!(most(&before, &after) > 0.1);
    }

    #[test]
    fn a_lit_cloud_defaults_to_the_light_preset_and_checks_its_settings() {
        let source = SourceDescription::Cloud(Box::new(CloudSource {
            dims: [9, 5, 9],
            seed: 2,
            coverage: Some(0.6),
            octaves: Some(3),
            wavelength: Some(4.0),
            wind: [1.0, 0.0, 0.5],
            detail_wind: None,
            torque: [0.0; 3],
            base_fade: None,
            top_fade: None,
            side_fade: None,
            sharpness: None,
            kind: CloudKind::Cumulus,
            stretch: None,
            wisps: None,
            keyframe_interval: Some(1.5),
            weather: None,
            primitives: Vec::new(),
        }));
        let mut lit = VolumeDescription {
            mode: None,
            density_scale: 1.0,
            lighting: Some(LightingDescription {
                ambient: 0.3,
                diffuse: 0.7,
                shadow_extinction: 0.0,
                model: LightModel::Isotropic,
                keyframe_interval: 2.0,
                scattering_octaves: 1,
                sky_occlusion: false,
                ground_shadow: false,
            }),
            ..volume(source)
        };
        lit.validate().unwrap();
        let built = lit.build(Path::new(".")).unwrap();
        assert_eq!(
            built.transfer_function,
            TransferFunction::preset(TransferPreset::CloudLight)
        );
        let SceneField::Cloud(cloud) = built.field else {
            panic!("a cloud source is an animated cloud");
        };
        // The wind moves the field, drawn between keyframes 1.5 s apart.
        assert_eq!(cloud.keyframes_at(4.0), Some(([3.0, 4.5], 1.0 / 1.5)));
        let (now, later) = (cloud.grid_at(0.0).unwrap(), cloud.grid_at(3.0).unwrap());
        assert_eq!(now.dims(), [9, 5, 9]);
        assert_ne!(now.values(), later.values());

        if let Some(lighting) = &mut lit.lighting {
            lighting.model = LightModel::NonPhysical;
        }
        assert_eq!(
            lit.build(Path::new(".")).unwrap().transfer_function,
            TransferFunction::preset(TransferPreset::Cloud)
        );
        if let Some(lighting) = &mut lit.lighting {
            lighting.model = LightModel::Scattering { asymmetry: 0.7 };
        }
        assert_eq!(
            lit.build(Path::new(".")).unwrap().transfer_function,
            TransferFunction::preset(TransferPreset::Transmittance)
        );
        if let Some(lighting) = &mut lit.lighting {
            lighting.model = LightModel::Scattering { asymmetry: 1.0 };
        }
        assert_eq!(
            lit.validate().unwrap_err().field,
            "lighting.model.Scattering.asymmetry"
        );
        if let Some(lighting) = &mut lit.lighting {
            lighting.model = LightModel::Isotropic;
            lighting.ambient = 1.5;
        }
        assert_eq!(lit.validate().unwrap_err().field, "lighting.ambient");
        if let Some(lighting) = &mut lit.lighting {
            lighting.ambient = 0.3;
            lighting.shadow_extinction = 0.0;
            lighting.ground_shadow = true;
        }
        assert_eq!(lit.validate().unwrap_err().field, "lighting.ground_shadow");
        let cells = VolumeDescription {
            lighting: Some(LightingDescription {
                ambient: 0.3,
                diffuse: 0.7,
                shadow_extinction: 0.0,
                model: LightModel::Isotropic,
                keyframe_interval: 2.0,
                scattering_octaves: 1,
                sky_occlusion: false,
                ground_shadow: false,
            }),
            ..volume(SourceDescription::Cells(Vec::new()))
        };
        assert_eq!(cells.validate().unwrap_err().field, "lighting");
    }

    fn grid(built: BuiltVolume) -> DensityGrid {
        match built.field {
            SceneField::Grid(grid) => grid,
            other => panic!("expected a grid, got {other:?}"),
        }
    }

    #[test]
    fn ramp_is_linear_along_its_axis_and_spans_the_box() {
        let ramp = volume(SourceDescription::Ramp(RampSource {
            axis: Axis::Y,
            from: 0.2,
            to: 0.8,
            dims: [3, 5, 2],
        }));
        let built = ramp.build(Path::new(".")).unwrap();
        assert_eq!(built.mode, OpticalMode::Emissive);
        let grid = grid(built);
        assert_eq!(grid.max_corner(), DVec3::new(2.0, 4.0, 8.0));
        for y in [0.0, 1.0, 2.5, 4.0] {
            let expected = 0.2 + 0.6 * y / 4.0;
            assert!((grid.sample(DVec3::new(1.3, y, 5.0)) - expected).abs() < 1e-6);
        }
    }

    #[test]
    fn density_scale_multiplies_rho() {
        let built = volume(SourceDescription::Uniform(UniformSource {
            value: 1.0,
            dims: [2; 3],
        }))
        .build(Path::new("."))
        .unwrap();
        let cloud = TransferFunction::preset(TransferPreset::Cloud);
        assert_eq!(
            built.transfer_function.evaluate(1.0).rho,
            2.0 * cloud.evaluate(1.0).rho
        );
    }

    #[test]
    fn a_lit_volume_or_a_cloud_takes_the_octree_unless_drawn_at_full_resolution() {
        let procedural = SourceDescription::Procedural(ProceduralSource {
            dims: [9; 3],
            kind: NoiseKind::Fbm,
            seed: 3,
            octaves: 2,
            frequency: 0.4,
            coverage: 1.0,
            ellipsoid: true,
        });
        let cloud = SourceDescription::Cloud(Box::new(CloudSource {
            dims: [9, 5, 9],
            seed: 2,
            coverage: Some(0.6),
            octaves: Some(3),
            wavelength: Some(4.0),
            wind: [0.0; 3],
            detail_wind: None,
            torque: [0.0; 3],
            base_fade: None,
            top_fade: None,
            side_fade: None,
            sharpness: None,
            kind: CloudKind::Cumulus,
            stretch: None,
            wisps: None,
            keyframe_interval: None,
            weather: None,
            primitives: Vec::new(),
        }));
        let lighting = Some(LightingDescription {
            ambient: 0.3,
            diffuse: 0.7,
            shadow_extinction: 0.5,
            model: LightModel::Isotropic,
            keyframe_interval: 2.0,
            scattering_octaves: 1,
            sky_occlusion: false,
            ground_shadow: false,
        });
        let lod = Some(LodDescription {
            accuracy: Some(8.0),
            ..LodDescription::default()
        });
        let drawn = |description: &VolumeDescription| {
            description.validate().unwrap();
            description.build(Path::new(".")).unwrap().lod
        };
        let unlit = volume(procedural.clone());
        let lit = VolumeDescription {
            lighting,
            ..volume(procedural)
        };
        let cloud = volume(cloud);
        assert_eq!(drawn(&unlit), None);
        for octree_by_default in [&lit, &cloud] {
            assert_eq!(drawn(octree_by_default), Some(LodDescription::default()));
            let full = VolumeDescription {
                full_resolution: true,
                ..octree_by_default.clone()
            };
            assert_eq!(drawn(&full), None);
            let given = VolumeDescription {
                lod,
                ..octree_by_default.clone()
            };
            assert_eq!(drawn(&given), lod);
            // Not both.
            let both = VolumeDescription {
                full_resolution: true,
                ..given
            };
            assert_eq!(both.validate().unwrap_err().field, "full_resolution");
        }
        // Projected cells carry no light field.
        let lit_projected = VolumeDescription {
            full_resolution: true,
            projected_cells: true,
            ..lit
        };
        assert_eq!(
            lit_projected.validate().unwrap_err().field,
            "projected_cells"
        );
        let projected = VolumeDescription {
            full_resolution: true,
            projected_cells: true,
            ..unlit
        };
        assert_eq!(drawn(&projected), None);
    }

    #[test]
    fn coverage_empties_low_noise() {
        let source = |coverage| {
            SourceDescription::Procedural(ProceduralSource {
                dims: [9; 3],
                kind: NoiseKind::Fbm,
                seed: 3,
                octaves: 3,
                frequency: 0.4,
                coverage,
                ellipsoid: false,
            })
        };
        let full = grid(volume(source(1.0)).build(Path::new(".")).unwrap());
        let half = grid(volume(source(0.5)).build(Path::new(".")).unwrap());
        for (n, h) in full.values().iter().zip(half.values()) {
            assert!((h - ((n - 0.5) / 0.5).clamp(0.0, 1.0)).abs() < 1e-6);
        }
        assert!(
            half.values().iter().filter(|v| **v == 0.0).count()
                > full.values().iter().filter(|v| **v == 0.0).count()
        );
    }

    #[test]
    fn ellipsoid_vanishes_at_the_box_faces_and_keeps_the_centre() {
        let source = |ellipsoid| {
            SourceDescription::Procedural(ProceduralSource {
                dims: [5; 3],
                kind: NoiseKind::Fbm,
                seed: 1,
                octaves: 2,
                frequency: 0.7,
                coverage: 1.0,
                ellipsoid,
            })
        };
        let plain = grid(volume(source(false)).build(Path::new(".")).unwrap());
        let shaped = grid(volume(source(true)).build(Path::new(".")).unwrap());
        assert_eq!(shaped.value(2, 2, 2), plain.value(2, 2, 2));
        for (i, j, k) in [(0, 2, 2), (4, 2, 2), (2, 0, 2), (2, 2, 4), (0, 0, 0)] {
            assert_eq!(shaped.value(i, j, k), 0.0);
        }
        assert!((shaped.value(1, 2, 2) - 0.75 * plain.value(1, 2, 2)).abs() < 1e-6);
    }

    #[test]
    fn cells_keep_world_positions() {
        let cell = TetrahedronDescription {
            positions: [[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            scalars: [0.0, 0.5, 1.0, 0.25],
        };
        let built = volume(SourceDescription::Cells(vec![cell]))
            .build(Path::new("."))
            .unwrap();
        let SceneField::Cells(cells) = built.field else {
            panic!("expected cells");
        };
        assert_eq!(cells[0].positions[1], DVec3::X);
        assert_eq!(cells[0].scalars[2], 1.0);
    }

    #[test]
    fn campfire_is_emissive_fire_and_fills_its_box() {
        let mut fire = volume(SourceDescription::Campfire(CampfireSource {
            seed: 2,
            dims: [9, 9, 9],
        }));
        fire.mode = None;
        let built = fire.build(Path::new(".")).unwrap();
        assert_eq!(built.mode, OpticalMode::Emissive);
        assert_eq!(
            built.transfer_function,
            TransferFunction::preset(TransferPreset::Fire)
                .scale_density(2.0)
                .unwrap()
        );
        let SceneField::Campfire(campfire) = built.field else {
            panic!("expected a campfire");
        };
        let early = campfire.grid_at(0.0);
        assert_eq!(early.origin(), DVec3::ZERO);
        assert!((early.max_corner() - DVec3::new(2.0, 4.0, 8.0)).length() < 1e-9);
        assert_ne!(early.values(), campfire.grid_at(0.5).values());
    }

    #[test]
    fn search_light_points_along_its_direction() {
        let mut light = volume(SourceDescription::SearchLight(SearchLightSource {
            position: [1.0, 2.0, 3.0],
            direction: [1.0, 0.0, 0.0],
            length: 10.0,
            half_angle_degrees: 10.0,
            segments: [8, 2, 8],
        }));
        light.mode = None;
        let built = light.build(Path::new(".")).unwrap();
        assert_eq!(built.mode, OpticalMode::Emissive);
        let SceneField::Cells(cells) = built.field else {
            panic!("expected cells");
        };
        let far = cells
            .iter()
            .flat_map(|c| c.positions)
            .map(|p| p.x)
            .fold(f64::NEG_INFINITY, f64::max);
        assert!((far - 11.0).abs() < 1e-9, "beam ends at x = {far}");
    }

    #[test]
    fn missing_strip_names_the_file() {
        let mut strip = volume(SourceDescription::Uniform(UniformSource {
            value: 1.0,
            dims: [2; 3],
        }));
        strip.transfer = Some(TransferDescription::Strip(TransferStrip {
            path: String::from("ramps/none.png"),
            max_density: 1.0,
        }));
        let error = strip.build(Path::new("scenes")).unwrap_err();
        assert_eq!(error.field, "transfer");
        assert!(
            error.reason.contains("scenes/ramps/none.png"),
            "{}",
            error.reason
        );
    }

    #[test]
    fn building_checks_the_memory_budget_too() {
        for (source, field) in [
            (
                SourceDescription::Uniform(UniformSource {
                    value: 0.5,
                    dims: [4097; 3],
                }),
                "source.Uniform.dims",
            ),
            (
                SourceDescription::Ramp(RampSource {
                    axis: Axis::X,
                    from: 0.0,
                    to: 1.0,
                    dims: [4097; 3],
                }),
                "source.Ramp.dims",
            ),
            (
                SourceDescription::SearchLight(SearchLightSource {
                    position: [0.0; 3],
                    direction: [0.0, 0.0, -1.0],
                    length: 1.0,
                    half_angle_degrees: 10.0,
                    segments: [256; 3],
                }),
                "source.SearchLight.segments",
            ),
        ] {
            let error = volume(source).build(Path::new(".")).unwrap_err();
            assert_eq!(error.field, field);
            assert!(error.reason.contains("memory budget"), "{}", error.reason);
        }
        let error = volume(SourceDescription::Procedural(ProceduralSource {
            dims: [4097; 3],
            kind: NoiseKind::Fbm,
            seed: 0,
            octaves: 1,
            frequency: 1.0,
            coverage: 1.0,
            ellipsoid: false,
        }))
        .build(Path::new("."))
        .unwrap_err();
        assert_eq!(error.field, "source");
        assert!(
            error.reason.contains(
                "DensityGrid::procedural: density grid of 4097 × 4097 × 4097 points needs"
            ),
            "{}",
            error.reason
        );
    }
}
