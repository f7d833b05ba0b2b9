//! The [`Terrain`] component, its status and statistics, and
//! [`TerrainPlugin`].
//!
//! A terrain's heights come from a [`TerrainHeights`] asset (a 16-bit PNG
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
//! and `min_accuracy` changes, and when its height asset is modified. It runs
//! on the main thread in the frame it is needed (about 4 ms for 513², 16 ms
//! for 1025², 65 ms for 2049² plus the generator's time), so the first frame
//! already shows the terrain. What happens every frame is in
//! [`crate::update`].

use std::sync::Arc;

use bevy::prelude::*;
use nebel_core::field::{HeightField, TerrainNoise};
use nebel_lod::TerrainHierarchy;
use nebel_lod::quadtree::{
    DEFAULT_ACCURACY, DEFAULT_MIN_RESOLUTION, MAX_TERRAIN_SIDE, pad_to_power_of_two_plus_one,
};
use nebel_render::NebelSystems;

use crate::heights::{TerrainHeights, TerrainHeightsLoader};
use crate::update::TerrainLod;

/// Adds [`Terrain`], the [`TerrainHeights`] asset and its PNG loader, and the
/// terrain's system (in [`PostUpdate`], see [`crate::update`]).
///
/// Needs Bevy's `AssetPlugin` before it (part of `DefaultPlugins`); the
/// terrain's mesh and material live in `Assets<Mesh>` and
/// `Assets<StandardMaterial>` (Bevy's `PbrPlugin`). A world without a
/// [`Terrain`] runs no terrain work: the system returns at once.
#[derive(Default)]
pub struct TerrainPlugin;

impl Plugin for TerrainPlugin {
    fn build(&self, app: &mut App) {
        app.init_asset::<TerrainHeights>()
            .register_asset_loader(TerrainHeightsLoader)
            .register_type::<Terrain>()
            .register_type::<TerrainStatus>()
            .register_type::<TerrainLodStats>()
            .add_systems(
                PostUpdate,
                crate::update::update_terrains
                    .in_set(NebelSystems)
                    // This frame's camera: after its transform and projection.
                    .after(TransformSystems::Propagate)
                    .after(bevy::camera::CameraUpdateSystems)
                    .after(bevy::camera::visibility::VisibilitySystems::VisibilityPropagate)
                    .before(bevy::camera::visibility::VisibilitySystems::CheckVisibility),
            );
    }
}

/// Where a terrain's unit heights come from.
#[derive(Clone, Debug, PartialEq, Reflect)]
pub enum TerrainSource {
    /// A height map asset, e.g. `asset_server.load::<TerrainHeights>("h.png")`.
    Heights(Handle<TerrainHeights>),
    /// Seeded fractal noise rescaled to [0, 1]
    /// (`nebel_core::field::HeightField::terrain`).
    Procedural {
        /// Grid points per side, 2 to 8193; `2^k + 1` needs no padding.
        size: u32,
        /// Noise kind, seed, octaves, first wavelength (local units),
        /// persistence and the valley exponent; see [`TerrainNoise`].
        #[reflect(ignore)]
        noise: TerrainNoise,
    },
}

/// Debug views of the terrain's triangles. Both replace the default
/// material's height and slope colours; both work with a custom material
/// too (its base colour multiplies them).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Reflect)]
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
#[reflect(Component, Default)]
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
    /// Minimum resolution `C`, finite and ≥ 1.6: a node is refined within
    /// `C` node sizes of the eye whatever its roughness. Changing it rebuilds
    /// the quadtree. Default 2.
    pub min_accuracy: f32,
    /// Geomorphing: new vertices blend in from the coarse mesh, so nothing
    /// pops. Default true.
    pub morph: bool,
    /// How far the eye may move, in grid spacings, before the mesh is
    /// rebuilt; also the margin the culling frustum is widened by. Default
    /// 0.25 (see [`crate::update`] for the bound this keeps).
    pub update_distance: f32,
    /// How far the camera may turn, degrees, before the mesh is rebuilt; the
    /// culling frustum is widened by this angle. Default 3.
    pub view_margin_degrees: f32,
    /// The material; `None` gives the default terrain material (a rough,
    /// white `StandardMaterial` under vertex colours by height and slope).
    /// A material given here gets no height and slope colours. Default
    /// `None`.
    pub material: Option<Handle<StandardMaterial>>,
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
            spacing: 10.0,
            vertical_scale: 400.0,
            accuracy: DEFAULT_ACCURACY,
            min_accuracy: DEFAULT_MIN_RESOLUTION,
            morph: true,
            update_distance: 0.25,
            view_margin_degrees: 3.0,
            material: None,
            debug: TerrainDebug::default(),
        }
    }
}

/// What became of a [`Terrain`]'s heights: read it to show a loading screen
/// or an error.
#[derive(Component, Clone, Debug, Default, PartialEq, Eq, Reflect)]
#[reflect(Component, Default)]
pub enum TerrainStatus {
    /// Waiting for the height asset (or for the first frame with a camera).
    #[default]
    Pending,
    /// The quadtree is built; the entity has its mesh.
    Ready,
    /// The heights or settings are unusable: the reason. Logged once, the
    /// entity has no mesh; changing the terrain or its asset tries again.
    Failed(String),
}

/// Statistics of a [`Terrain`]'s level of detail, updated by the plugin.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Component, Default)]
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

/// The settings a quadtree is built from; the quadtree is rebuilt when they
/// change.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct BuildKey {
    pub source: TerrainSource,
    pub spacing: f32,
    pub vertical_scale: f32,
    pub min_accuracy: f32,
}

impl BuildKey {
    pub fn of(terrain: &Terrain) -> Self {
        Self {
            source: terrain.source.clone(),
            spacing: terrain.spacing,
            vertical_scale: terrain.vertical_scale,
            min_accuracy: terrain.min_accuracy,
        }
    }
}

/// Unit heights as the sources give them: points per axis and values.
pub(crate) struct UnitHeights<'a> {
    pub dims: [usize; 2],
    pub values: std::borrow::Cow<'a, [f32]>,
}

impl Terrain {
    /// The unit heights of a procedural source, or `None` for an asset.
    pub(crate) fn generate(&self) -> Option<Result<UnitHeights<'static>, String>> {
        let TerrainSource::Procedural { size, noise } = &self.source else {
            return None;
        };
        let size = *size as usize;
        if !(2..=MAX_TERRAIN_SIDE).contains(&size) {
            return Some(Err(format!(
                "a procedural terrain of {size} points per side: it must have 2 to {MAX_TERRAIN_SIDE}"
            )));
        }
        if !(self.spacing.is_finite() && self.spacing > 0.0) {
            return Some(Err(spacing_error(self.spacing)));
        }
        Some(
            HeightField::terrain([size; 2], f64::from(self.spacing), noise)
                .map(|field| UnitHeights {
                    dims: [size; 2],
                    values: field.heights().to_vec().into(),
                })
                .map_err(|error| error.to_string()),
        )
    }

    /// Checks the settings, scales `unit` and builds the quadtree (see the
    /// module docs). The error is a sentence naming the setting or the grid
    /// point at fault.
    pub(crate) fn build_hierarchy(&self, unit: &UnitHeights) -> Result<TerrainHierarchy, String> {
        if !(self.spacing.is_finite() && self.spacing > 0.0) {
            return Err(spacing_error(self.spacing));
        }
        if !self.vertical_scale.is_finite() {
            return Err(format!(
                "vertical_scale = {} is invalid: it must be finite",
                self.vertical_scale
            ));
        }
        if !(self.accuracy.is_finite() && self.accuracy > 0.0) {
            return Err(format!(
                "accuracy c = {} is invalid: it must be finite and positive",
                self.accuracy
            ));
        }
        let [nx, nz] = unit.dims;
        if nx < 2 || nz < 2 {
            return Err(format!(
                "the height map has {nx} × {nz} points; a terrain needs at least 2 × 2"
            ));
        }
        if nx.max(nz) > MAX_TERRAIN_SIDE {
            return Err(format!(
                "the height map has {nx} × {nz} points; the largest terrain side is {MAX_TERRAIN_SIDE}"
            ));
        }
        if unit.values.len() != nx * nz {
            return Err(format!(
                "the height map is {nx} × {nz} points but holds {} values",
                unit.values.len()
            ));
        }
        let scale = self.vertical_scale;
        let mut heights = Vec::with_capacity(nx * nz);
        for (index, &value) in unit.values.iter().enumerate() {
            let height = value * scale;
            if !height.is_finite() {
                return Err(format!(
                    "height at grid point ({}, {}) is {} ({value} × vertical_scale {scale}); every height must be finite",
                    index % nx,
                    index / nx,
                    height
                ));
            }
            heights.push(height);
        }
        let spacing = f64::from(self.spacing);
        let half = bevy::math::DVec2::new((nx - 1) as f64, (nz - 1) as f64) * spacing / 2.0;
        let field = HeightField::new([nx, nz], bevy::math::DVec2::splat(spacing), -half, heights)
            .map_err(|error| error.to_string())?;
        let padded = pad_to_power_of_two_plus_one(&field).map_err(|error| error.to_string())?;
        TerrainHierarchy::new(padded, self.min_accuracy).map_err(|error| error.to_string())
    }
}

fn spacing_error(spacing: f32) -> String {
    format!("spacing = {spacing} is invalid: it must be finite and positive")
}

/// A built quadtree, shared cheaply.
pub(crate) type SharedHierarchy = Arc<TerrainHierarchy>;
