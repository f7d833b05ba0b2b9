//! Building a terrain's quadtree in the background.
//!
//! `build_terrains` notices a new terrain, a changed source or one of
//! `spacing`, `vertical_scale`, `min_accuracy` (compared bit for bit, so a
//! NaN setting is not rebuilt every frame), and a height asset that was
//! added, loaded or modified; it takes the unit heights (the asset's shared
//! values, or a procedural source's settings) and starts `build_quadtree` on
//! the task pool. One build runs per terrain at a time; settings that change
//! meanwhile are built next. It takes the result when it is ready (at once
//! under `HeavyBuilds::Blocking`): the new quadtree replaces the old one,
//! which was drawn meanwhile, or the failure is recorded in
//! [`TerrainStatus::Failed`], logged once and the mesh removed. A failed
//! terrain is not built again until its settings or its asset change.
//!
//! The build checks the settings, scales the unit heights (every height must
//! be finite), centres the grid on the entity, pads it to `2^k + 1` points
//! per side and computes the quadtree's roughness ([`TerrainHierarchy::new`]).

use std::sync::Arc;
use std::time::Instant;

use bevy::camera::primitives::Aabb;
use bevy::camera::visibility::NoAutoAabb;
use bevy::diagnostic::Diagnostics;
use bevy::math::DVec2;
use bevy::prelude::*;
use nebel_core::field::{HeightField, TerrainNoise};
use nebel_lod::quadtree::TerrainRefiner;
use nebel_lod::quadtree::{MAX_TERRAIN_SIDE, pad_to_power_of_two_plus_one};
use nebel_lod::{TerrainHierarchy, TerrainMesh};
use nebel_render::{GrayscaleMap, HeavyBuild, HeavyBuilds, InvalidSetting};

use crate::error::TerrainBuildError;
use crate::terrain::{Terrain, TerrainLodStats, TerrainPlugin, TerrainSource, TerrainStatus};
use crate::update::Refined;

/// The settings a quadtree is built from, bit for bit: the quadtree is
/// rebuilt when they change.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct BuildKey {
    /// The height asset, or the procedural source's settings.
    source: Result<AssetId<GrayscaleMap>, [u64; 7]>,
    /// `spacing`, `vertical_scale`, `min_accuracy`.
    settings: [u32; 3],
}

impl BuildKey {
    fn of(terrain: &Terrain) -> Self {
        let source = match &terrain.source {
            TerrainSource::Heights(handle) => Ok(handle.id()),
            TerrainSource::Procedural { size, noise } => Err([
                u64::from(*size),
                noise.kind as u64,
                u64::from(noise.seed),
                noise.octaves as u64,
                noise.wavelength.to_bits(),
                noise.persistence.to_bits(),
                noise.exponent.to_bits(),
            ]),
        };
        Self {
            source,
            settings: [
                terrain.spacing,
                terrain.vertical_scale,
                terrain.min_accuracy,
            ]
            .map(f32::to_bits),
        }
    }
}

/// Where a build takes its unit heights from.
enum UnitHeights {
    /// A height asset's values, shared.
    Asset {
        dims: [usize; 2],
        values: Arc<Vec<f32>>,
    },
    /// A procedural source, generated on the task pool.
    Procedural { size: u32, noise: TerrainNoise },
}

/// Everything `build_quadtree` needs, owned, so it runs on another thread.
pub(crate) struct BuildInput {
    heights: UnitHeights,
    spacing: f32,
    vertical_scale: f32,
    min_accuracy: f32,
}

#[cfg(test)]
impl BuildInput {
    /// The input of a procedural terrain.
    pub fn of(terrain: &Terrain) -> Self {
        let TerrainSource::Procedural { size, noise } = terrain.source.clone() else {
            panic!("a procedural terrain");
        };
        Self {
            heights: UnitHeights::Procedural { size, noise },
            spacing: terrain.spacing,
            vertical_scale: terrain.vertical_scale,
            min_accuracy: terrain.min_accuracy,
        }
    }
}

/// A finished build: the quadtree and how long it took.
pub(crate) struct BuiltQuadtree {
    pub hierarchy: Arc<TerrainHierarchy>,
    /// The sides of the heights' own rectangle along x and z (before the
    /// padding to the quadtree's square), world units.
    extent: Vec2,
    build_ms: f32,
}

/// Checks the settings, scales the unit heights and builds the quadtree (see
/// the module docs).
pub(crate) fn build_quadtree(input: BuildInput) -> Result<BuiltQuadtree, TerrainBuildError> {
    let started = Instant::now();
    let BuildInput {
        heights,
        spacing,
        vertical_scale,
        min_accuracy,
    } = input;
    let valid = spacing.is_finite() && spacing > 0.0;
    InvalidSetting::check(valid, "spacing", spacing, "finite and positive")?;
    let valid = vertical_scale.is_finite();
    InvalidSetting::check(valid, "vertical_scale", vertical_scale, "finite")?;
    let (dims, values) = match heights {
        UnitHeights::Asset { dims, values } => (dims, values),
        UnitHeights::Procedural { size, noise } => {
            let side = size as usize;
            if !(2..=MAX_TERRAIN_SIDE).contains(&side) {
                return Err(TerrainBuildError::ProceduralSize { size });
            }
            let field = HeightField::terrain([side; 2], f64::from(spacing), &noise)?;
            ([side; 2], Arc::new(field.heights().to_vec()))
        }
    };
    let [nx, nz] = dims;
    if nx < 2 || nz < 2 {
        return Err(TerrainBuildError::TooSmall { nx, nz });
    }
    if nx.max(nz) > MAX_TERRAIN_SIDE {
        return Err(TerrainBuildError::TooLarge { nx, nz });
    }
    if values.len() != nx * nz {
        return Err(TerrainBuildError::ValueCount {
            nx,
            nz,
            count: values.len(),
        });
    }
    let mut scaled = Vec::with_capacity(nx * nz);
    for (index, &unit) in values.iter().enumerate() {
        let height = unit * vertical_scale;
        if !height.is_finite() {
            return Err(TerrainBuildError::NonFiniteHeight {
                i: index % nx,
                j: index / nx,
                height,
                unit,
                scale: vertical_scale,
            });
        }
        scaled.push(height);
    }
    let spacing = f64::from(spacing);
    let half = DVec2::new((nx - 1) as f64, (nz - 1) as f64) * spacing / 2.0;
    let field = HeightField::new([nx, nz], DVec2::splat(spacing), -half, scaled)?;
    let padded = pad_to_power_of_two_plus_one(&field)?;
    let hierarchy = TerrainHierarchy::new(padded, min_accuracy)?;
    Ok(BuiltQuadtree {
        hierarchy: Arc::new(hierarchy),
        extent: (half * 2.0).as_vec2(),
        build_ms: started.elapsed().as_secs_f32() * 1e3,
    })
}

/// A terrain's quadtree, the build in flight, its level of detail and its
/// mesh, kept by the terrain's systems; effects on the terrain's entity read
/// the quadtree and the level of detail's mesh.
#[derive(Component, Default)]
pub struct TerrainLod {
    /// What the quadtree (or the failure) was built from.
    key: Option<BuildKey>,
    /// The build in flight and what it builds from.
    build: Option<(
        BuildKey,
        HeavyBuild<Result<BuiltQuadtree, TerrainBuildError>>,
    )>,
    pub(crate) hierarchy: Option<Arc<TerrainHierarchy>>,
    /// The level of detail of the last refinement done.
    pub(crate) refiner: TerrainRefiner,
    /// The refinement running on a worker, if any.
    pub(crate) refining: Option<HeavyBuild<Refined>>,
    /// Something the mesh depends on changed since the last refinement
    /// started: refine again even if the view did not move.
    pub(crate) stale: bool,
    /// The latency the next refinement's culling allows for (see
    /// [`crate::update`]).
    pub(crate) latency: (f64, f64),
    pub(crate) mesh: Option<Handle<Mesh>>,
    /// The sides of the heights' rectangle along x and z (the mesh's UVs
    /// run from 0 to 1 over it).
    pub(crate) extent: Vec2,
    /// The `StandardMaterial` the terrain inserted on the entity, if any
    /// (not one of the user's own).
    pub(crate) material_inserted: Option<Handle<StandardMaterial>>,
    /// The mapped quadtree the last refinement used, if any.
    pub(crate) mapped: Option<Arc<TerrainHierarchy>>,
}

impl TerrainLod {
    /// Removes the terrain's mesh and the material it inserted from its
    /// entity (a user's own material stays).
    pub(crate) fn remove_mesh(&mut self, commands: &mut Commands, entity: Entity) {
        if self.mesh.take().is_some() {
            commands
                .entity(entity)
                .remove::<(Mesh3d, Aabb, NoAutoAabb)>();
        }
        self.remove_material(commands, entity);
    }

    /// Removes the material the terrain inserted, if the entity still
    /// carries it (one the user put in its place stays).
    pub(crate) fn remove_material(&mut self, commands: &mut Commands, entity: Entity) {
        if let Some(inserted) = self.material_inserted.take() {
            commands
                .entity(entity)
                .queue(move |mut entity: EntityWorldMut| {
                    if entity
                        .get::<MeshMaterial3d<StandardMaterial>>()
                        .is_some_and(|material| material.0 == inserted)
                    {
                        entity.remove::<MeshMaterial3d<StandardMaterial>>();
                    }
                });
        }
    }
}

impl TerrainLod {
    /// The terrain's own quadtree, once built (its field holds the padded,
    /// scaled heights in the entity's frame).
    pub fn quadtree(&self) -> Option<&Arc<TerrainHierarchy>> {
        self.hierarchy.as_ref()
    }

    /// The mesh of the last refinement, in the quadtree's frame (relative
    /// to its origin), front to back, with grid points per vertex and, when
    /// the terrain carries a [`TerrainMapLod`](crate::TerrainMapLod),
    /// the map's morphed values.
    pub fn mesh(&self) -> &Arc<TerrainMesh> {
        self.refiner.mesh()
    }
}

/// The unit heights of `terrain`'s source, `Ok(None)` while its asset
/// loads.
fn unit_heights(
    terrain: &Terrain,
    heights: &Assets<GrayscaleMap>,
    asset_server: &AssetServer,
) -> Result<Option<UnitHeights>, TerrainBuildError> {
    match &terrain.source {
        TerrainSource::Procedural { size, noise } => Ok(Some(UnitHeights::Procedural {
            size: *size,
            noise: *noise,
        })),
        TerrainSource::Heights(handle) => match heights.get(handle) {
            Some(asset) => Ok(Some(UnitHeights::Asset {
                dims: [asset.dims.x as usize, asset.dims.y as usize],
                values: asset.values.clone(),
            })),
            None => match GrayscaleMap::load_failure(handle, asset_server) {
                Some((path, error)) => Err(TerrainBuildError::HeightsNotLoaded { path, error }),
                None => Ok(None),
            },
        },
    }
}

/// Records a failure: the status, one log line per entity and new reason,
/// no mesh.
fn fail(
    commands: &mut Commands,
    entity: Entity,
    status: &mut TerrainStatus,
    state: &mut TerrainLod,
    error: TerrainBuildError,
) {
    TerrainStatus::fail(&mut *status, "terrain", entity, error);
    state.hierarchy = None;
    state.refiner = TerrainRefiner::new();
    state.refining = None;
    state.remove_mesh(commands, entity);
}

/// Takes finished quadtree builds and starts new ones for every terrain whose
/// heights or build settings changed (see the module docs).
pub(crate) fn build_terrains(
    mut commands: Commands,
    mut terrains: Query<(
        Entity,
        &Terrain,
        &mut TerrainStatus,
        &mut TerrainLodStats,
        &mut TerrainLod,
    )>,
    heights: Res<Assets<GrayscaleMap>>,
    mut height_events: MessageReader<AssetEvent<GrayscaleMap>>,
    asset_server: Res<AssetServer>,
    mode: Res<HeavyBuilds>,
    mut diagnostics: Diagnostics,
) {
    let changed = GrayscaleMap::changed(&mut height_events);
    for (entity, terrain, mut status, mut stats, mut state) in &mut terrains {
        let state = &mut *state;
        let mut land = |state: &mut TerrainLod, status: &mut TerrainStatus| {
            let result = poll_build(state, *mode);
            let built = result.and_then(|result| {
                put_in_place(&mut commands, entity, status, &mut stats, state, result)
            });
            if let Some(build_ms) = built {
                diagnostics.add_measurement(&TerrainPlugin::BUILD_MS, || f64::from(build_ms));
            }
        };
        land(state, &mut status);
        if state.build.is_some() {
            continue;
        }
        let key = BuildKey::of(terrain);
        let asset_changed = matches!(&terrain.source,
            TerrainSource::Heights(handle) if changed.contains(&handle.id()));
        if state.key.as_ref() == Some(&key) && !asset_changed {
            continue;
        }
        match unit_heights(terrain, &heights, &asset_server) {
            // Still loading: ask again next frame.
            Ok(None) => *status = TerrainStatus::Pending,
            Ok(Some(unit)) => {
                let input = BuildInput {
                    heights: unit,
                    spacing: terrain.spacing,
                    vertical_scale: terrain.vertical_scale,
                    min_accuracy: terrain.min_accuracy,
                };
                state.build = Some((key, HeavyBuild::spawn(move || build_quadtree(input))));
                if state.hierarchy.is_none() {
                    *status = TerrainStatus::Pending;
                }
                land(state, &mut status);
            }
            Err(error) => {
                state.key = Some(key);
                fail(&mut commands, entity, &mut status, state, error);
            }
        }
    }
}

/// The result of the build in flight if it is done (waiting for it under
/// `HeavyBuilds::Blocking`); its key becomes the terrain's.
fn poll_build(
    state: &mut TerrainLod,
    mode: HeavyBuilds,
) -> Option<Result<BuiltQuadtree, TerrainBuildError>> {
    let (key, build) = state.build.as_mut()?;
    let result = build.poll(mode)?;
    state.key = Some(key.clone());
    state.build = None;
    Some(result)
}

/// Puts a finished build in place: the quadtree (returning how long its
/// build took, ms), or the failure.
fn put_in_place(
    commands: &mut Commands,
    entity: Entity,
    status: &mut TerrainStatus,
    stats: &mut TerrainLodStats,
    state: &mut TerrainLod,
    result: Result<BuiltQuadtree, TerrainBuildError>,
) -> Option<f32> {
    match result {
        Ok(BuiltQuadtree {
            hierarchy,
            extent,
            build_ms,
        }) => {
            *stats = TerrainLodStats {
                points_per_side: hierarchy.size() as u32,
                bytes_per_point: hierarchy.bytes_per_point() as f32,
                build_ms,
                updates: stats.updates,
                ..default()
            };
            if state.mesh.is_some() {
                // A new extent: new bounds.
                commands.entity(entity).insert(bounds(&hierarchy));
            }
            state.hierarchy = Some(hierarchy);
            state.extent = extent;
            state.refiner = TerrainRefiner::new();
            state.refining = None;
            state.mapped = None;
            *status = TerrainStatus::Ready;
            Some(build_ms)
        }
        Err(error) => {
            fail(commands, entity, status, state, error);
            None
        }
    }
}

/// The bounds of every mesh the quadtree can produce, in the entity's frame:
/// the grid's square and the height range (morphed heights stay inside it).
pub(crate) fn bounds(hierarchy: &TerrainHierarchy) -> Aabb {
    let origin = hierarchy.origin().as_vec3();
    let spacing = hierarchy.field().spacing().as_vec2();
    let extent = (hierarchy.size() - 1) as f32 * spacing;
    let [low, high] = hierarchy.height_range();
    Aabb::from_min_max(
        Vec3::new(origin.x, low, origin.z),
        Vec3::new(origin.x + extent.x, high, origin.z + extent.y),
    )
}
