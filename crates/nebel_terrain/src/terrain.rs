//! The [`Terrain`] component, its status and statistics, and
//! [`TerrainPlugin`].
//!
//! A terrain's heights come from a [`GrayscaleMap`] asset (a 16-bit PNG
//! through the `AssetServer`, or one built in memory) or from the
//! procedural generator `nebel_core::field::HeightField::terrain`. They are
//! unit heights: `vertical_scale` multiplies them, `spacing` places the grid
//! points. The grid is centred on the entity: point `(i, j)` of an `nx × nz`
//! map lies at local `x = (i − (nx − 1)/2) · spacing`, `z = (j − (nz − 1)/2)
//! · spacing`, its height at local `y = vertical_scale · unit`. A map whose
//! sides are not `2^k + 1` points (or that is not square) is padded at its
//! high x and z ends by replicating the edge
//! ([`nebel_lod::quadtree::pad_to_power_of_two_plus_one`]); the centre stays
//! the centre of the map as given.
//!
//! Building the quadtree ([`nebel_lod::TerrainHierarchy`]) happens when the
//! terrain appears, when its source or one of `spacing`, `vertical_scale`
//! and `min_accuracy` changes, and when its height asset is modified
//! ([`crate::build`]). For large maps that takes longer than a frame (plus
//! the generator's time for a procedural one), so it runs on Bevy's
//! `AsyncComputeTaskPool` and the terrain appears (or changes) in the first
//! frame after it is done ([`HeavyBuilds`] can make the frame wait instead).
//! What happens every frame is in [`crate::update`].

use bevy::diagnostic::DiagnosticPath;
use bevy::prelude::*;
use nebel_core::field::{DEFAULT_TERRAIN_SPACING, DEFAULT_TERRAIN_VERTICAL_SCALE, TerrainNoise};
use nebel_lod::quadtree::{DEFAULT_ACCURACY, DEFAULT_MIN_RESOLUTION};
use nebel_render::{
    EffectStatus, GrayscaleMap, GrayscaleMapPlugin, HeavyBuilds, LodCamera, NebelSystems,
    cpu_timed, register_diagnostics,
};

use crate::build::{TerrainLod, build_terrains};
use crate::error::TerrainBuildError;
use crate::map::TerrainMapLod;
use crate::update::{measure_terrains, update_terrain_meshes};

/// Adds [`Terrain`], the [`GrayscaleMap`] asset and its PNG loader, and the
/// terrain's systems (in [`PostUpdate`], see [`crate::build`] and
/// [`crate::update`]) and diagnostics.
///
/// Needs Bevy's `AssetPlugin` before it (part of `DefaultPlugins`); the
/// terrain's mesh and material live in `Assets<Mesh>` and
/// `Assets<StandardMaterial>` (Bevy's `PbrPlugin`). A world without a
/// [`Terrain`] runs no terrain work: every system returns at once.
#[derive(Default)]
pub struct TerrainPlugin;

impl TerrainPlugin {
    /// Terrains in the world.
    pub const TERRAINS: DiagnosticPath = DiagnosticPath::const_new("nebel/terrain/terrains");
    /// Triangles of the level of detail, all terrains.
    pub const TRIANGLES: DiagnosticPath = DiagnosticPath::const_new("nebel/terrain/triangles");
    /// Vertices of the level of detail, all terrains.
    pub const VERTICES: DiagnosticPath = DiagnosticPath::const_new("nebel/terrain/vertices");
    /// Mesh rebuilds so far, all terrains.
    pub const UPDATES: DiagnosticPath = DiagnosticPath::const_new("nebel/terrain/updates");
    /// Time of the mesh rebuilds of a frame that rebuilt one (refinement,
    /// morphing, triangle output and the copy into the Bevy mesh), ms.
    pub const UPDATE_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/terrain/update_ms");
    /// The part of it the quadtree's refinement and triangle output took, ms.
    pub const REFINE_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/terrain/refine_ms");
    /// Time of the last quadtree build (on the task pool), ms.
    pub const BUILD_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/terrain/build_ms");
    /// Grid points of all quadtrees.
    pub const POINTS: DiagnosticPath = DiagnosticPath::const_new("nebel/terrain/points");
    /// Bytes the quadtrees hold per grid point.
    pub const BYTES_PER_POINT: DiagnosticPath =
        DiagnosticPath::const_new("nebel/terrain/bytes_per_point");
}

impl Plugin for TerrainPlugin {
    fn build(&self, app: &mut App) {
        GrayscaleMapPlugin::add_once(app);
        app.init_resource::<HeavyBuilds>()
            .register_type::<Terrain>()
            .register_type::<TerrainStatus>()
            .register_type::<TerrainLodStats>()
            .register_type::<LodCamera>()
            .register_type::<HeavyBuilds>()
            .register_type::<TerrainMapLod>()
            .add_systems(
                PostUpdate,
                (
                    cpu_timed(build_terrains).in_set(TerrainSystems::Build),
                    cpu_timed(update_terrain_meshes).in_set(TerrainSystems::Refine),
                    cpu_timed(measure_terrains),
                )
                    .chain()
                    .in_set(NebelSystems)
                    // This frame's camera: after its transform and projection.
                    .after(TransformSystems::Propagate)
                    .after(bevy::camera::CameraUpdateSystems)
                    .after(bevy::camera::visibility::VisibilitySystems::VisibilityPropagate)
                    .before(bevy::camera::visibility::VisibilitySystems::CheckVisibility),
            );
        register_diagnostics(
            app,
            &[
                (Self::TERRAINS, ""),
                (Self::TRIANGLES, ""),
                (Self::VERTICES, ""),
                (Self::UPDATES, ""),
                (Self::UPDATE_MS, " ms"),
                (Self::REFINE_MS, " ms"),
                (Self::BUILD_MS, " ms"),
                (Self::POINTS, ""),
                (Self::BYTES_PER_POINT, " B"),
            ],
        );
    }
}

/// The terrain's systems in [`PostUpdate`], for effects that read or extend
/// its level of detail.
#[derive(SystemSet, Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TerrainSystems {
    /// Quadtree builds start and land.
    Build,
    /// The level of detail is refined for the camera and the mesh written.
    Refine,
}

/// Where a terrain's unit heights come from.
#[derive(Clone, Debug, PartialEq, Reflect)]
#[reflect(Clone)]
pub enum TerrainSource {
    /// A height map asset, e.g. `asset_server.load::<GrayscaleMap>("h.png")`.
    Heights(Handle<GrayscaleMap>),
    /// Seeded fractal noise rescaled to [0, 1]
    /// (`nebel_core::field::HeightField::terrain`).
    Procedural {
        /// Grid points per side, 2 to 8193; `2^k + 1` needs no padding.
        size: u32,
        /// Noise kind, seed, octaves, first wavelength (local units),
        /// persistence and the valley exponent; see [`TerrainNoise`].
        noise: TerrainNoise,
    },
}

/// Debug views of the terrain's triangles. Both replace the default
/// material's height and slope colours; both work with a custom material
/// too (its base colour multiplies them).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Reflect)]
#[reflect(Default, Clone)]
pub struct TerrainDebug {
    /// Colour each triangle by its quadtree level (a hue per level, coarse
    /// to fine). Default false.
    pub lod_colours: bool,
    /// Darken each triangle's edges, wireframe-like: every triangle is drawn
    /// as an inner triangle and a dark border (seven triangles each; the
    /// `terrain` counters still count the LOD's triangles). Default false.
    pub edges: bool,
}

/// A height-field terrain drawn through Röttger's quadtree C-LOD with
/// geomorphing (see the crate docs).
#[derive(Component, Clone, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(Transform, Visibility, TerrainStatus, TerrainLodStats, TerrainLod)]
pub struct Terrain {
    /// The unit heights. Default: 257 × 257 points of
    /// `TerrainNoise::default()` (fBm, 2000 m first wavelength).
    pub source: TerrainSource,
    /// Horizontal distance between neighbouring grid points, local units
    /// (metres), finite and > 0. Default 10.
    pub spacing: f32,
    /// Height of a unit value, local units (metres), finite. Default 400.
    pub vertical_scale: f32,
    /// Global accuracy `c` of `f = l² / (d² · max(c · d2, C)²)`, finite and
    /// positive: larger draws more triangles; a detail the mesh leaves out
    /// subtends at most about `1/(2c)` radian. Default 300 (about two pixels
    /// at 1080 lines and 60°).
    pub accuracy: f32,
    /// A tolerance in pixels that replaces `accuracy` when given: each frame
    /// `c` is derived from the LOD camera's projection and viewport so that
    /// no detail the mesh leaves out (of the ground, and of the top of fog
    /// lying on it) moves by more than this many pixels anywhere in the view
    /// ([`nebel_lod::quadtree::accuracy_for_pixel_error`]; for a 1080-line,
    /// 60°, 16:9 view 2 px is `c` ≈ 740). Finite and > 0; needs a
    /// perspective camera (an orthographic one is a `Failed` status). Default
    /// `None`: `accuracy` is used.
    pub pixel_error: Option<f32>,
    /// Minimum resolution `C`, finite and ≥ 1.6: a node is refined within
    /// `C` node sizes of the eye whatever its roughness. Changing it rebuilds
    /// the quadtree. Default 2.
    pub min_accuracy: f32,
    /// Geomorphing: new vertices blend in from the coarse mesh, so nothing
    /// pops. Default true.
    pub morph: bool,
    /// How far the eye may move, in grid spacings, before the mesh is
    /// rebuilt; also the margin the culling frustum is widened by. Default
    /// 0.25 (see [`nebel_lod::quadtree::TerrainRefiner`] for the bound this
    /// keeps).
    pub update_distance: f32,
    /// How far the camera may turn, degrees, before the mesh is rebuilt; the
    /// culling frustum is widened by this angle. Default 3.
    pub view_margin_degrees: f32,
    /// The material the terrain is drawn with; see [`TerrainMaterial`].
    /// Default [`TerrainMaterial::HeightAndSlope`].
    pub material: TerrainMaterial,
    /// Debug views. Default: none.
    pub debug: TerrainDebug,
}

impl Default for Terrain {
    fn default() -> Self {
        Self {
            source: TerrainSource::Procedural {
                size: 257,
                noise: TerrainNoise::default(),
            },
            spacing: DEFAULT_TERRAIN_SPACING,
            vertical_scale: DEFAULT_TERRAIN_VERTICAL_SCALE,
            accuracy: DEFAULT_ACCURACY,
            pixel_error: None,
            min_accuracy: DEFAULT_MIN_RESOLUTION,
            morph: true,
            update_distance: 0.25,
            view_margin_degrees: 3.0,
            material: TerrainMaterial::HeightAndSlope,
            debug: TerrainDebug::default(),
        }
    }
}

/// The material of a [`Terrain`]. Every terrain mesh carries UVs (`u` along
/// x, `v` along z, 0 to 1 over the height map, beyond 1 where the quadtree's
/// square pads it; unchanged by geomorphing, which moves vertices only up
/// and down), so textures map onto it (tile them with
/// `StandardMaterial::uv_transform` and a repeating sampler).
#[derive(Clone, Debug, Default, PartialEq, Reflect)]
#[reflect(Default, Clone)]
pub enum TerrainMaterial {
    /// A rough, white `StandardMaterial` under vertex colours by the morphed
    /// height and slope (grass, rock and snow).
    #[default]
    HeightAndSlope,
    /// This `StandardMaterial` (with textures, say); no vertex colours.
    Standard(Handle<StandardMaterial>),
    /// The material the entity carries itself: a `MeshMaterial3d<M>` of any
    /// Bevy `Material` `M`, inserted by the user (a texture-splatting
    /// extension of `StandardMaterial`, say). The terrain inserts and removes
    /// no material and writes no vertex colours.
    Own,
}

/// What became of a [`Terrain`]: pending, ready, or failed and why.
pub type TerrainStatus = EffectStatus<TerrainBuildError>;

/// Statistics of a [`Terrain`]'s level of detail, updated by the plugin.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct TerrainLodStats {
    /// Grid points per side of the quadtree (after padding).
    pub points_per_side: u32,
    /// Bytes the quadtree holds per grid point (heights and d2 codes).
    pub bytes_per_point: f32,
    /// Time the last quadtree build took (heights, padding, d2), ms.
    pub build_ms: f32,
    /// Mesh rebuilds so far.
    pub updates: u64,
    /// Time of the last mesh rebuild (refinement, morphing, triangle output
    /// and the copy into the Bevy mesh), ms.
    pub update_ms: f32,
    /// The part of it the quadtree's refinement and triangle output took
    /// (`TerrainHierarchy::update`), ms.
    pub refine_ms: f32,
    /// Triangles of the level of detail in the mesh.
    pub triangles: u32,
    /// Vertices of the level of detail in the mesh.
    pub vertices: u32,
    /// Deepest quadtree level drawn (0 = the root).
    pub deepest_level: u32,
    /// Nodes skipped with their subtree by frustum culling.
    pub culled_nodes: u32,
}
