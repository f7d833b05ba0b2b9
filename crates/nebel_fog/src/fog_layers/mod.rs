//! Fog layers: height fog drawn exactly in one full-screen pass, the far
//! and cheap partner of ground fog (Röttger, "Volumetric Methods for the
//! Real-Time Display of Natural Gaseous Phenomena", 2004, §5.3, layered
//! fog).
//!
//! Put [`FogLayers`] on a 3D camera. When the fog's density depends on the
//! altitude only, the optical depth from the eye to any point has a closed
//! form, `τ = L · (T(h₁) − T(h₀)) / (h₁ − h₀)` with `T` the prefix integral
//! of the density over altitude (`nebel_core::height_fog`, which takes the
//! limit for level rays), so one pass over the depth buffer is exact per
//! pixel: each pixel gets `(c α, α)`, `α = 1 − e^{−τ}` over the fog's
//! stretch of its ray, blended over the scene. Pixels with nothing opaque
//! (the sky) integrate to [`FogLayers::max_distance`], where bounded layers
//! have long ended.
//!
//! The fog glows with [`FogLayers::color`] and scatters the sunlight
//! [`FogLayers::sun_color`] of the first `DirectionalLight` once, with the
//! Henyey-Greenstein phase function (`4π p_HG`, 1 on average) at the ray's
//! angle to the sun, dimmed by the fog between the sun and each point: a
//! point at altitude `h` sees the sun through `C(h)/μ`, `C(h) = ∫_h^∞ ρ` the
//! fog above it and `μ` the sine of the sun's elevation. Along the ray `ρ dt
//! = −dC/d_y`, so the scattered light is closed form for any profile
//! (`nebel_core::height_fog`): `τ e^{−τ − s₁} (e^x − 1)/x`, `x = τ − (s₀ −
//! s₁)`, with `s₀`, `s₁` the sun's optical depths at the stretch's ends.
//! Deep fog is darker than its top, and the sun at or below the horizon
//! lights none of it. Clouds that cast shadows (`nebel_render`'s
//! `CloudShadowMaps`) hold back `c 4π p_HG ∫ ρ e^{−τ(0, t) − C(h)/μ} w (1 −
//! T_map) dt` of it over the stretch of each ray whose line toward the sun
//! crosses a map below the clouds' top: a piece of three Gauss-Legendre
//! nodes per four texels the crossing moves over, at most 64. The first
//! terrain's shadow heights for that sun ([`FogLayersTerrainShadow`], built
//! in the background) take the sunlight of every stretch of the ray below
//! them, exactly for the map's bilinear heights: the pass walks the map
//! along the ray, crossing blocks whole where the ray passes above or below
//! all their heights, and holds back each shaded stretch's closed form.
//! Beyond the map's extent the terrain casts nothing. A sun that casts
//! shadows (`shadow_maps_enabled`) is hidden by opaque meshes too, through
//! Bevy's cascaded shadow map of it (`nebel_render::light_shadows`, with
//! the light's depth and normal biases): its visibility is read at 32 equal
//! steps of the stretch the cascades reach, each change bisected, and each
//! stretch of one visibility `V` holds back `1 − V` of its closed form
//! (where the terrain has not). Beyond the cascades' reach no mesh shades
//! the fog.
//!
//! # Point and spot lights
//!
//! Lights with Bevy's `VolumetricLight` add their single scattering,
//! `s c ∫ ρ(h(t)) e^{−τ(0, t) − τ(x(t), p)} E(t) 4π p_HG dt` over each
//! light's stretch of the ray (`nebel_core::local_light`;
//! [`FogLayers::light_response`] gives `s` and the phase), with the fog's
//! attenuation both to the eye and from the light at `p`, each in closed
//! form. The stretch is cut where the density has a jump or a kink, each
//! part into equal pieces, one per 0.5 of its optical depth plus
//! exponential falloff times the altitude crossed (at most 64), each piece
//! by Gauss-Legendre quadrature in the angle the light sees; a light with a
//! shadow map is cut where its visibility changes. A volume inside the fog
//! is conjugated by the fog's glow and sunlight alone: the lights' part of
//! the fog in front of a cell, and the clouds' and the terrain's shadow on
//! it, are not in its conjugation. The lights take a variant of
//! the pass; without them it runs as before.
//!
//! # Volumes inside the fog
//!
//! The cell projection draws after this pass and sees every cell segment
//! through the fog in front of it (the segment conjugated by the fog from
//! the eye to its middle; `nebel_render::cell_projection`), so a cloud inside
//! or behind the fog is fogged by the fog in front of it only, and hides the
//! fog behind it. The splitting of the fog inside a segment errs to second
//! order in the optical depths of the fog and the cell.
//!
//! # Handoff with ground fog
//!
//! [`FogLayers::start_distance`] begins the layers that far along each ray;
//! a [`GroundFog`](crate::GroundFog) draws the fog nearer, so neither counts
//! it twice.
//!
//! # Cost
//!
//! One full-screen pass of a few dozen arithmetic operations per layer per
//! pixel, no compute and no storage buffer (it fits WebGL2-class devices:
//! one uniform block, `nebel_render::fog_layers`). A camera without
//! `FogLayers`, or whose layers are all of zero density, runs no pass.

mod node;
mod resources;
mod terrain_shadow;

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use bevy::diagnostic::{Diagnostic, DiagnosticPath, Diagnostics, RegisterDiagnostic};
use bevy::prelude::*;
use bevy::render::extract_resource::ExtractResourcePlugin;
use nebel_core::height_fog::{HeightFog, HeightFogError, HeightFogLayer};
use nebel_core::local_light::LightResponse;
use nebel_render::EffectStatus;
use nebel_render::fog_layers::{FogLayersLimitError, FogLayersLook, FogLayersUniform};
use thiserror::Error;

pub use resources::FogLayersRenderPlugin;
pub use terrain_shadow::FogLayersTerrainShadow;

/// Height fog seen by a 3D camera (see the module docs). Put it on the
/// camera entity; [`FogLayersStatus`] says whether it draws.
#[derive(Component, Clone, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Debug, Clone)]
#[require(FogLayersStatus, PreparedFogLayers)]
pub struct FogLayers {
    /// The density over altitude (world y, metres; densities in 1/m) as a
    /// sum of layers: exponential, constant between two altitudes, or
    /// piecewise linear. Overlapping layers add. At most 8 layers and 32
    /// points of linear profiles together. Empty, or every density zero:
    /// no fog and no pass. Default: one exponential layer, 0.0015/m at 0 m,
    /// falling off by e every 250 m.
    pub layers: Vec<HeightFogLayer>,
    /// The colour dense fog converges to without sunlight (the ambient light
    /// it scatters toward the eye), linear HDR. Default a pale blue grey,
    /// linear (0.5, 0.56, 0.64).
    pub color: Color,
    /// Sunlight the fog scatters toward the eye, linear HDR, added to
    /// [`Self::color`] on average over all directions where the sun reaches
    /// undimmed, scaled by the Henyey-Greenstein phase at each ray's angle to
    /// the first `DirectionalLight` (none: no sunlight) and dimmed by the
    /// fog toward the sun (see the module docs). Default black (none).
    pub sun_color: Color,
    /// The Henyey-Greenstein asymmetry of the sunlight's scattering, in
    /// (−1, 1) (clamped to ±0.99): 0 isotropic, toward 1 a bright halo
    /// around the sun. Default 0.6.
    pub sun_asymmetry: f32,
    /// Where the fog begins along each ray, metres, finite and ≥ 0. Nearer,
    /// a ground fog draws it. Default 0.
    pub start_distance: f32,
    /// Where the fog ends along each ray, metres, finite and greater than
    /// `start_distance`: rays that meet nothing opaque (the sky) are
    /// integrated to here. Set it to the extent of a finite world to keep
    /// the fog off the horizon beyond it. Default 100 km.
    pub max_distance: f32,
    /// How the fog scatters the point and spot lights with Bevy's
    /// `VolumetricLight` (`nebel_render::local_lights`; the brightest eight
    /// at the camera): the phase's asymmetry and a factor on
    /// [`Self::color`], which is the fog's look under a light as bright as
    /// the reference sun. Default: isotropic, 1.
    pub light_response: LightResponse,
}

impl Default for FogLayers {
    fn default() -> Self {
        Self {
            layers: vec![HeightFogLayer::Exponential {
                base: 0.0,
                density: 0.0015,
                falloff: 1.0 / 250.0,
            }],
            color: Color::linear_rgb(0.5, 0.56, 0.64),
            sun_color: Color::BLACK,
            sun_asymmetry: 0.6,
            start_distance: 0.0,
            max_distance: 100_000.0,
            light_response: LightResponse::default(),
        }
    }
}

/// Why [`FogLayers`] draw nothing.
#[derive(Clone, Debug, Error, PartialEq, Reflect)]
#[reflect(opaque, Clone, Debug, PartialEq)]
pub enum FogLayersError {
    /// A layer is out of range (negative or NaN density, non-positive
    /// falloff, an empty or reversed range, unordered points).
    #[error(transparent)]
    Layer(#[from] HeightFogError),
    /// More layers or points than the GPU's uniform holds.
    #[error(transparent)]
    Limit(#[from] FogLayersLimitError),
    /// A colour, the asymmetry or a distance is out of range.
    #[error("fog layers: {setting} = {value} is invalid: it must be {requirement}")]
    InvalidSetting {
        /// The setting's name.
        setting: &'static str,
        /// The value given, formatted.
        value: String,
        /// What it must be.
        requirement: &'static str,
    },
}

/// What became of a camera's [`FogLayers`]: pending, ready, or failed and why.
pub type FogLayersStatus = EffectStatus<FogLayersError>;

/// The checked fog of a camera, packed for the GPU (`None`: nothing to
/// draw). Kept by [`FogLayersPlugin`]; the sun's direction is filled in
/// each frame.
#[derive(Component, Clone, Debug, Default, PartialEq)]
pub struct PreparedFogLayers(pub(crate) Option<FogLayersUniform>);

/// Adds [`FogLayers`]: checks them when they change, and draws them in one
/// pass in `Core3d` after the opaque pass and before the cell projection
/// ([`FogLayersRenderPlugin`]). Needs `nebel_render::CellProjectionPlugin`,
/// which loads the shaders' fog library (`NebelPlugins` adds both).
#[derive(Default)]
pub struct FogLayersPlugin;

impl FogLayersPlugin {
    /// Fog-layer passes run so far (one per camera with fog, per frame).
    pub const PASSES: DiagnosticPath = DiagnosticPath::const_new("nebel/fog_layers/passes");
    /// Milliseconds the last build of the terrain's shadow heights took
    /// ([`FogLayersTerrainShadow`]).
    pub const TERRAIN_SHADOW_MS: DiagnosticPath =
        DiagnosticPath::const_new("nebel/fog_layers/terrain_shadow_ms");
}

/// The number of fog-layer passes run, shared by the main and the render
/// world.
#[derive(Resource, Clone, Default, Debug)]
pub struct FogLayersPasses(pub(crate) Arc<AtomicU64>);

impl FogLayersPasses {
    /// Passes run so far.
    pub fn get(&self) -> u64 {
        self.0.load(Ordering::Relaxed)
    }
}

impl Plugin for FogLayersPlugin {
    fn build(&self, app: &mut App) {
        let passes = FogLayersPasses::default();
        app.register_type::<FogLayers>()
            .register_type::<FogLayersStatus>()
            .insert_resource(passes.clone())
            .register_diagnostic(Diagnostic::new(Self::PASSES))
            .register_diagnostic(Diagnostic::new(Self::TERRAIN_SHADOW_MS).with_suffix(" ms"))
            .init_resource::<FogLayersTerrainShadow>()
            .init_resource::<terrain_shadow::TerrainShadowBuild>()
            .add_plugins(ExtractResourcePlugin::<FogLayersTerrainShadow>::default())
            .add_systems(
                PostUpdate,
                (
                    prepare_fog_layers,
                    terrain_shadow::update_terrain_shadow.after(prepare_fog_layers),
                ),
            )
            .add_systems(Last, publish_passes)
            .add_plugins(FogLayersRenderPlugin { passes });
    }
}

/// Checks and packs the fog layers that changed.
fn prepare_fog_layers(
    mut fogs: Query<
        (
            Entity,
            &FogLayers,
            &mut FogLayersStatus,
            &mut PreparedFogLayers,
        ),
        Changed<FogLayers>,
    >,
) {
    for (entity, fog, mut status, mut prepared) in &mut fogs {
        match pack(fog) {
            Ok(uniform) => {
                *status = FogLayersStatus::Ready;
                prepared.0 = uniform;
            }
            Err(error) => {
                FogLayersStatus::fail(status.reborrow(), "fog layers of", entity, error);
                prepared.0 = None;
            }
        }
    }
}

/// The fog packed for the GPU, `None` when it has no density anywhere.
fn pack(fog: &FogLayers) -> Result<Option<FogLayersUniform>, FogLayersError> {
    let invalid = |setting, value: String, requirement| FogLayersError::InvalidSetting {
        setting,
        value,
        requirement,
    };
    for (setting, color) in [("color", fog.color), ("sun_color", fog.sun_color)] {
        let linear = color.to_linear().to_vec3();
        if !(linear.is_finite() && linear.min_element() >= 0.0) {
            return Err(invalid(setting, format!("{linear}"), "finite and ≥ 0"));
        }
    }
    if !fog.sun_asymmetry.is_finite() {
        return Err(invalid(
            "sun_asymmetry",
            fog.sun_asymmetry.to_string(),
            "finite",
        ));
    }
    if !(fog.start_distance.is_finite() && fog.start_distance >= 0.0) {
        return Err(invalid(
            "start_distance",
            fog.start_distance.to_string(),
            "finite and ≥ 0",
        ));
    }
    if !(fog.max_distance.is_finite() && fog.max_distance > fog.start_distance) {
        return Err(invalid(
            "max_distance",
            fog.max_distance.to_string(),
            "finite and greater than start_distance",
        ));
    }
    let height_fog = HeightFog::new(fog.layers.clone())?;
    let uniform = FogLayersUniform::new(
        &height_fog,
        &FogLayersLook {
            colour: fog.color.to_linear().to_vec3(),
            sun_colour: fog.sun_color.to_linear().to_vec3(),
            sun_direction: Vec3::Y,
            sun_asymmetry: fog.sun_asymmetry,
            start_distance: fog.start_distance,
            max_distance: fog.max_distance,
        },
    )?;
    Ok(height_fog.has_density().then_some(uniform))
}

/// Publishes the pass count as a diagnostic once a pass ran.
fn publish_passes(passes: Res<FogLayersPasses>, mut diagnostics: Diagnostics) {
    let count = passes.get();
    if count > 0 {
        diagnostics.add_measurement(&FogLayersPlugin::PASSES, || count as f64);
    }
}
