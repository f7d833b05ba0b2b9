//! The [`GroundFog`] component, its status and statistics, and
//! [`GroundFogPlugin`].
//!
//! A ground fog lies on the [`Terrain`](nebel_terrain::Terrain) of its
//! entity. Its thickness above the ground (metres, per terrain grid point)
//! comes from a [`FogThickness`]: a grayscale fog map through the
//! `AssetServer` (the terrain's [`GrayscaleMap`] asset: black 0, white 1,
//! times `scale`), seeded noise patches ([`FogNoise`]), or the valleys
//! filled up to an altitude with a noisy edge ([`ValleyFog`], the default).
//! A map of any size covers the terrain's grid from corner to corner and is
//! sampled bilinearly at its points (`nebel_lod::quadtree::TerrainMap::resample`);
//! for a terrain whose heights were padded to `2^k + 1` points, that is the
//! padded grid.
//!
//! Every triangle of the terrain's level of detail carries a vertical prism
//! up to the fog's top, morphed with the terrain (the method of Röttger and
//! Ertl 2003 §6; the cells are [`nebel_lod::ground_fog`]'s), drawn by the
//! cell projection with the fog's transfer function, mode and vertical
//! profile.

use std::sync::Arc;

use bevy::diagnostic::DiagnosticPath;
use bevy::prelude::*;
use nebel_core::field::{FogNoise, ValleyFog};
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_render::{EffectStatus, GrayscaleMap, NebelSystems, cpu_timed, register_diagnostics};
use nebel_terrain::TerrainSystems;

use crate::batch::{GroundFogBatch, measure_fogs, remove_fogs, update_fog_batches};
use crate::error::GroundFogError;
use crate::map::{GroundFogMap, build_ground_fog_maps};
use crate::sunlight::{GroundFogSun, update_fog_sunlight};

/// Adds [`GroundFog`] and its systems (in [`PostUpdate`], around the
/// terrain's: the fog's map is built after the terrain's quadtree, its
/// cells after the terrain's refinement) and diagnostics.
///
/// Needs the terrain plugin (`nebel_terrain::TerrainPlugin`) and the cell
/// projection (`nebel_render::CellProjectionPlugin`) to draw; a world
/// without a [`GroundFog`] runs no fog work.
#[derive(Default)]
pub struct GroundFogPlugin;

impl GroundFogPlugin {
    /// Ground fogs in the world that draw cells.
    pub const FOGS: DiagnosticPath = DiagnosticPath::const_new("nebel/fog/fogs");
    /// Fogged terrain triangles (prism columns), all fogs.
    pub const PRISMS: DiagnosticPath = DiagnosticPath::const_new("nebel/fog/prisms");
    /// Tetrahedra drawn, all fogs.
    pub const TETRAHEDRA: DiagnosticPath = DiagnosticPath::const_new("nebel/fog/tetrahedra");
    /// Time of the prism updates of a frame that updated one (prisms, order
    /// and the batch), ms; the terrain's refinement is in
    /// `nebel/terrain/refine_ms`.
    pub const UPDATE_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/fog/update_ms");
    /// Time of the last fog layer build (thickness and roughness, on the
    /// task pool), ms.
    pub const BUILD_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/fog/build_ms");
    /// Time of the last sun map build (the terrain's shadow, on the task
    /// pool; [`crate::sunlight`]), ms.
    pub const SUN_MAP_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/fog/sun_map_ms");
}

impl Plugin for GroundFogPlugin {
    fn build(&self, app: &mut App) {
        app.register_type::<GroundFog>()
            .register_type::<GroundFogStatus>()
            .register_type::<GroundFogStats>()
            .add_systems(
                PostUpdate,
                (
                    cpu_timed(build_ground_fog_maps)
                        .after(TerrainSystems::Build)
                        .before(TerrainSystems::Refine),
                    (
                        cpu_timed(remove_fogs),
                        cpu_timed(update_fog_batches),
                        cpu_timed(update_fog_sunlight),
                        cpu_timed(measure_fogs),
                    )
                        .chain()
                        .after(TerrainSystems::Refine),
                )
                    .in_set(NebelSystems),
            );
        register_diagnostics(
            app,
            &[
                (Self::FOGS, ""),
                (Self::PRISMS, ""),
                (Self::TETRAHEDRA, ""),
                (Self::UPDATE_MS, " ms"),
                (Self::BUILD_MS, " ms"),
                (Self::SUN_MAP_MS, " ms"),
            ],
        );
    }
}

/// Where a ground fog's thickness above the ground comes from.
#[derive(Clone, Debug, PartialEq, Reflect)]
#[reflect(Clone)]
pub enum FogThickness {
    /// A grayscale map asset (`asset_server.load::<GrayscaleMap>("fog.png")`:
    /// black 0, white 1), times `scale` metres, resampled bilinearly onto
    /// the terrain's grid.
    Map {
        /// The map.
        map: Handle<GrayscaleMap>,
        /// Metres of a white pixel, finite and ≥ 0.
        scale: f32,
    },
    /// Seeded noise patches.
    Noise(FogNoise),
    /// The valleys filled up to an altitude with a noisy edge.
    Valley(ValleyFog),
}

impl Default for FogThickness {
    fn default() -> Self {
        Self::Valley(ValleyFog::default())
    }
}

/// Debug views of the fog's cells.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Reflect)]
#[reflect(Default, Clone)]
pub struct GroundFogDebug {
    /// Draw every tetrahedron's edges as lines (the prisms over the terrain's
    /// triangles, like Röttger 2004 Fig. 12.1), in a separate line mesh
    /// entity. Default false.
    pub wireframe: bool,
}

/// Volumetric fog lying on the [`Terrain`](nebel_terrain::Terrain) of the
/// same entity (see the module docs).
#[derive(Component, Clone, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(
    GroundFogStatus,
    GroundFogStats,
    GroundFogMap,
    GroundFogBatch,
    GroundFogSun
)]
pub struct GroundFog {
    /// The thickness above the ground. Default: [`ValleyFog::default()`]
    /// (filled up to 60 m in the terrain's frame, ±8 m edge).
    pub thickness: FogThickness,
    /// Multiplies the transfer function's density ρ, finite and ≥ 0 (else
    /// the status is `Failed`); 0 draws nothing and leaves the terrain
    /// refining without the fog's map. With the default transfer function
    /// (ρ = 1 at the ground) it is the extinction at the ground, 1/m.
    /// Default 0.03 (about 100 m to fade to 5 %).
    pub density: f32,
    /// κ and ρ over the scalar (1 at the ground, 0 at the top with the
    /// default profile). Default: the `GroundFog` preset.
    #[reflect(ignore, default = "ground_fog_transfer_function")]
    pub transfer_function: Arc<TransferFunction>,
    /// How segments combine: [`OpticalMode::Sorted`] (emission and
    /// absorption, back to front; the terrain refines whenever the eye
    /// moves, since the order depends on it), or the unsorted
    /// [`OpticalMode::Emissive`] and [`OpticalMode::Mip`]. Default Sorted.
    pub mode: OpticalMode,
    /// With [`OpticalMode::Emissive`], saturate each segment's emission
    /// (Röttger and Ertl 2003 §6 Eq. 10): `ε = 1 − e^{−τ l}` and `I' = κ̄ ε +
    /// (1 − ε) I`, still unsorted, so dense fog tends to its colour instead
    /// of brightening without bound. That is the sorted model composited in
    /// the cells' own order: exact where κ is constant along a ray,
    /// otherwise off by the order of its colours. Ignored in the other modes.
    /// Default false.
    pub saturate: bool,
    /// The scalar over relative height inside the fog, `(height, scalar)`
    /// points from 0 (the ground) to 1 (the top), piecewise linear (see
    /// `nebel_lod::FogProfile`): each interval is a stack of prisms. Default
    /// `[(0, 1), (1, 0)]`: dense at the ground, clear at the top.
    pub profile: Vec<[f32; 2]>,
    /// Weight of the thickness's roughness in the terrain quadtree's d2,
    /// finite and ≥ 0: larger refines more where the fog's top varies.
    /// Changing it rebuilds the map. Default 1.
    pub roughness_weight: f32,
    /// How a sorted fog scatters the point and spot lights with Bevy's
    /// `VolumetricLight` that reach it (`nebel_render::local_lights`): the
    /// phase's asymmetry and a factor on its colour. Default: isotropic, 1.
    pub light_response: LightResponse,
    /// Sunlight a sorted fog scatters toward the eye, linear RGB, relative
    /// to the light the transfer function's colour stands for (which is the
    /// fog's glow in the shade): the fog adds `sun_color ⊙ κ` times the
    /// Henyey-Greenstein phase at each ray's angle to the first
    /// `DirectionalLight` (none: no sunlight), dimmed by the fog above each
    /// point and cut by the terrain's shadow ([`crate::sunlight`]). Default
    /// black: no sunlight, the fog is its colour in sun and shade alike.
    pub sun_color: Color,
    /// The Henyey-Greenstein asymmetry of the sunlight's scattering, in
    /// (−1, 1) (clamped to ±0.99): 0 isotropic, toward 1 a bright halo
    /// around the sun. Default 0.6.
    pub sun_asymmetry: f32,
    /// Debug views. Default: none.
    pub debug: GroundFogDebug,
}

impl GroundFog {
    /// The mode the cells are drawn in: [`OpticalMode::Sorted`]'s segments
    /// for a saturated emissive fog (in the unsorted order), else
    /// [`GroundFog::mode`].
    pub fn drawn_mode(&self) -> OpticalMode {
        if self.saturate && self.mode == OpticalMode::Emissive {
            OpticalMode::Sorted
        } else {
            self.mode
        }
    }
}

fn ground_fog_transfer_function() -> Arc<TransferFunction> {
    Arc::new(TransferFunction::preset(TransferPreset::GroundFog))
}

impl Default for GroundFog {
    fn default() -> Self {
        Self {
            thickness: FogThickness::default(),
            density: 0.03,
            transfer_function: ground_fog_transfer_function(),
            mode: OpticalMode::Sorted,
            saturate: false,
            profile: vec![[0.0, 1.0], [1.0, 0.0]],
            roughness_weight: 1.0,
            light_response: LightResponse::default(),
            sun_color: Color::BLACK,
            sun_asymmetry: 0.6,
            debug: GroundFogDebug::default(),
        }
    }
}

/// What became of a [`GroundFog`]: pending, ready, or failed and why.
pub type GroundFogStatus = EffectStatus<GroundFogError>;

/// Statistics of a [`GroundFog`], updated by the plugin.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct GroundFogStats {
    /// Fogged terrain triangles in the last update (each a column of
    /// prisms).
    pub prisms: u32,
    /// Tetrahedra drawn.
    pub tetrahedra: u32,
    /// Prism updates so far.
    pub updates: u64,
    /// Time of the last prism update (prisms, order and the batch), ms.
    pub update_ms: f32,
    /// Time of the last map build (thickness and roughness), ms.
    pub build_ms: f32,
    /// The largest thickness, metres.
    pub max_thickness: f32,
}
