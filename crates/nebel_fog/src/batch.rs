//! The fog's cells frame after frame: after the terrain's refinement, the
//! prisms over the triangles it drew (`nebel_lod::fog_prisms`), in world
//! space, back to front for the eye in the sorted mode, as the entity's
//! [`CellBatch`]; and the debug wireframe.
//!
//! The prisms are built on the
//! [`AsyncComputeTaskPool`](bevy::tasks::AsyncComputeTaskPool), one build per
//! fog at a time, from the terrain's mesh of the frame that starts it; the
//! fog draws its last batch until the build is done and takes the new one in
//! the first frame after (the same frame under [`HeavyBuilds::Blocking`]).
//! A sorted fog's cells are then ordered for the eye of an earlier frame:
//! the order stays a visibility order while the eye keeps to the same side of
//! every face's plane, and only rays across a face whose plane the eye
//! crossed composite two cells out of order (`nebel_lod`'s ground-fog tests
//! measure the image cost of an order up to a grid spacing old).
//!
//! The cells are rebuilt when the terrain's mesh was rebuilt (for a sorted
//! fog the terrain refines after at most half a grid spacing, see
//! [`TerrainMapLod::max_update_distance`]) or the fog's drawing settings
//! (density, transfer function, mode, profile, debug view) or its placement
//! changed; otherwise the system compares a counter, a pointer and a few
//! change ticks per fog. A fog with no map (no thickness anywhere), no density, a
//! transparent transfer function, on a failed terrain, or that is hidden has
//! no `CellBatch`, so the cell projection runs no pass for it. The
//! wireframe is a child entity in the terrain's frame; removing the
//! `GroundFog` removes the batch, the terrain's map, the wireframe and the
//! fog's state.

use std::sync::Arc;
use std::time::Instant;

use bevy::asset::RenderAssetUsages;
use bevy::diagnostic::Diagnostics;
use bevy::math::DAffine3;
use bevy::mesh::PrimitiveTopology;
use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::TransferFunction;
use nebel_lod::{
    CellOrder, Cells, FogProfile, GpuCell, PrismInput, PrismScalar, PrismStats, TriangleOrder,
    fog_prisms,
};
use nebel_render::camera::to_double_affine;
use nebel_render::{
    CellBatch, CellFogSunlight, EffectiveQuality, HeavyBuild, HeavyBuilds, LodCameras,
};
use nebel_terrain::{Terrain, TerrainLod, TerrainLodStats, TerrainMapLod, TerrainStatus};

use crate::error::GroundFogError;
use crate::fog_layers::PreparedFogLayers;
use crate::ground_fog::{GroundFog, GroundFogPlugin, GroundFogStats, GroundFogStatus};
use crate::map::GroundFogMap;
use crate::sunlight::GroundFogSun;

/// What the fog's batch was built from.
#[derive(Clone, Debug, PartialEq)]
struct BatchKey {
    /// The terrain's mesh rebuilds.
    terrain_updates: u64,
    /// The mapped quadtree (by identity).
    quadtree: usize,
    /// The drawing settings as written (`Debug`).
    settings: String,
    transform: GlobalTransform,
    /// Where the camera's fog layers take over (bits of the distance), if
    /// they do.
    handoff: Option<u32>,
}

/// Prisms built on a worker, with what they were built from.
struct BuiltPrisms {
    cells: Vec<GpuCell>,
    counts: PrismStats,
    transfer: Arc<TransferFunction>,
    terrain_from_world: DAffine3,
    update_ms: f32,
}

/// The fog's batch state: what it was built from, the build in flight, the
/// density-scaled transfer function and the wireframe entity.
#[derive(Component, Default)]
pub struct GroundFogBatch {
    key: Option<BatchKey>,
    building: Option<(BatchKey, HeavyBuild<Result<BuiltPrisms, GroundFogError>>)>,
    transfer: Option<(u64, u32, Arc<TransferFunction>)>,
    wireframe: Option<(Entity, Handle<Mesh>)>,
}

/// The fog's transfer function with ρ times `density`, cached per input.
fn scaled_transfer(
    state: &mut GroundFogBatch,
    fog: &GroundFog,
) -> Result<Arc<TransferFunction>, GroundFogError> {
    let key = (fog.transfer_function.content_hash(), fog.density.to_bits());
    if let Some((hash, density, transfer)) = &state.transfer
        && (*hash, *density) == key
    {
        return Ok(transfer.clone());
    }
    let scaled = Arc::new(fog.transfer_function.scale_density(fog.density)?);
    state.transfer = Some((key.0, key.1, scaled.clone()));
    Ok(scaled)
}

/// The lines of every cell's six edges, in the frame `local_from_world`
/// maps the cells' world positions into.
fn wireframe_mesh(cells: &[GpuCell], local_from_world: &DAffine3) -> Mesh {
    let local = |cell: &GpuCell, v: usize| {
        local_from_world
            .transform_point3(cell.position(v).as_dvec3())
            .as_vec3()
            .to_array()
    };
    let mut positions = Vec::with_capacity(cells.len() * 12);
    for cell in cells {
        for (a, b) in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)] {
            positions.push(local(cell, a));
            positions.push(local(cell, b));
        }
    }
    Mesh::new(PrimitiveTopology::LineList, RenderAssetUsages::default())
        .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, positions)
}

/// Removes the fog's batch and wireframe.
fn clear(commands: &mut Commands, entity: Entity, state: &mut GroundFogBatch, has_batch: bool) {
    if has_batch {
        commands.entity(entity).remove::<CellBatch>();
    }
    if let Some((wireframe, _)) = state.wireframe.take() {
        commands.entity(wireframe).try_despawn();
    }
    state.key = None;
    state.building = None;
}

/// A `GroundFog` removed from an entity that lives on: its batch, the
/// terrain's map, the wireframe and the fog's state go with it (a
/// despawned entity takes them, the wireframe being its child).
pub(crate) fn remove_fogs(
    mut commands: Commands,
    mut removed: RemovedComponents<GroundFog>,
    mut states: Query<&mut GroundFogBatch>,
) {
    for entity in removed.read() {
        let Ok(mut state) = states.get_mut(entity) else {
            continue;
        };
        clear(&mut commands, entity, &mut state, true);
        commands.entity(entity).remove::<(
            TerrainMapLod,
            GroundFogBatch,
            GroundFogMap,
            GroundFogStatus,
            GroundFogStats,
            GroundFogSun,
            CellFogSunlight,
        )>();
    }
}

/// Writes every visible fog's cells after the terrain's refinement (see the
/// module docs).
pub(crate) fn update_fog_batches(
    mut commands: Commands,
    cameras: LodCameras,
    mut fogs: Query<(
        Entity,
        Ref<GroundFog>,
        &TerrainLod,
        &TerrainLodStats,
        Ref<TerrainStatus>,
        Option<Ref<TerrainMapLod>>,
        Ref<GlobalTransform>,
        Ref<InheritedVisibility>,
        Has<CellBatch>,
        &mut GroundFogBatch,
        &mut GroundFogStatus,
        &mut GroundFogStats,
        &Terrain,
    )>,
    fog_layers: Query<&PreparedFogLayers>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
    quality: Option<Res<EffectiveQuality>>,
    mode: Res<HeavyBuilds>,
    mut diagnostics: Diagnostics,
) {
    let Some(camera) = cameras.view() else {
        return;
    };
    let (prisms, quality_changed) = quality.as_ref().map_or((true, false), |quality| {
        (quality.ground_fog_prisms(), quality.is_changed())
    });
    // The camera's fog layers take the fog over from their start distance:
    // the prisms wholly beyond it are left out.
    let handoff = fog_layers
        .get(camera.camera)
        .ok()
        .and_then(|prepared| prepared.0)
        .map(|uniform| uniform.ranges.x)
        .filter(|start| *start > 0.0);
    let mut frame_ms = None;
    for (
        entity,
        fog,
        lod,
        terrain_stats,
        terrain_status,
        map,
        transform,
        visibility,
        has_batch,
        mut state,
        mut status,
        mut stats,
        terrain,
    ) in &mut fogs
    {
        let state = &mut *state;
        let mapped = map
            .as_deref()
            .and_then(|map| map.quadtree.as_ref())
            .filter(|mapped| {
                lod.quadtree()
                    .is_some_and(|own| Arc::ptr_eq(own, &mapped.base))
            });
        let quadtree = mapped.map_or(0, |mapped| Arc::as_ptr(&mapped.hierarchy) as usize);
        // Nothing changed since the batch was built.
        let unchanged = !fog.is_changed()
            && !quality_changed
            && !transform.is_changed()
            && !visibility.is_changed()
            && !terrain_status.is_changed()
            && state.key.as_ref().is_some_and(|key| {
                key.terrain_updates == terrain_stats.updates
                    && key.quadtree == quadtree
                    && key.handoff == handoff.map(f32::to_bits)
            });
        if unchanged && state.building.is_none() {
            continue;
        }
        let mesh = lod.mesh();
        let drawable = mapped.is_some()
            && prisms
            && visibility.get()
            && !matches!(*terrain_status, TerrainStatus::Failed(_))
            && fog.density > 0.0
            && !fog.transfer_function.is_transparent(0.0, 1.0)
            && !mesh.map.is_empty();
        let (Some(mapped), true) = (mapped, drawable) else {
            state.building = None;
            if has_batch || state.wireframe.is_some() {
                clear(&mut commands, entity, state, has_batch);
            }
            if stats.prisms != 0 || stats.tetrahedra != 0 {
                *stats = GroundFogStats {
                    prisms: 0,
                    tetrahedra: 0,
                    ..*stats
                };
            }
            continue;
        };
        let key = BatchKey {
            terrain_updates: terrain_stats.updates,
            quadtree,
            settings: format!(
                "{:?} {} {:?} {:?} {:?} {}",
                fog.mode,
                fog.saturate,
                fog.profile,
                fog.density,
                fog.debug,
                fog.transfer_function.content_hash()
            ),
            transform: *transform,
            handoff: handoff.map(f32::to_bits),
        };
        if state.key.as_ref() == Some(&key) {
            // Back to what is drawn: a build for anything else is not wanted.
            state.building = None;
            continue;
        }
        if state.building.is_none() {
            // A bad transfer function fails where a failed build does.
            let transfer = scaled_transfer(state, &fog);
            let world_from_terrain = to_double_affine(&transform);
            let origin = mapped.hierarchy.origin();
            let mesh = lod.mesh().clone();
            let profile = fog.profile.clone();
            let eye = world_from_terrain.inverse().transform_point3(camera.eye) - origin;
            let order = if fog.mode == OpticalMode::Sorted {
                CellOrder::BackToFront
            } else {
                CellOrder::Unordered
            };
            // Between two refinements the eye moves by up to the terrain's
            // update distance: keep that much more.
            let beyond = handoff.map(|start| {
                let moved = f64::from(terrain.update_distance * terrain.spacing)
                    * transform.scale().max_element() as f64;
                (camera.eye, f64::from(start) + moved)
            });
            let build = HeavyBuild::spawn(move || {
                let started = Instant::now();
                let transfer = transfer?;
                let profile = FogProfile::new(profile)?;
                let input = PrismInput {
                    world_from_mesh: world_from_terrain * DAffine3::from_translation(origin),
                    eye,
                    mesh_order: TriangleOrder::FrontToBack,
                    order,
                    profile: &profile,
                    scalar: PrismScalar::Profile,
                    beyond,
                };
                let mut cells = Vec::new();
                let counts = fog_prisms(&mesh, &input, &mut cells)?;
                Ok(BuiltPrisms {
                    cells,
                    counts,
                    transfer,
                    terrain_from_world: world_from_terrain.inverse(),
                    update_ms: started.elapsed().as_secs_f32() * 1e3,
                })
            });
            state.building = Some((key, build));
        }
        let Some((key, built)) = state
            .building
            .as_mut()
            .and_then(|(key, build)| Some((key.clone(), build.poll(*mode)?)))
        else {
            continue;
        };
        state.building = None;
        let BuiltPrisms {
            cells,
            counts,
            transfer,
            terrain_from_world,
            update_ms,
        } = match built {
            Ok(built) => built,
            Err(error) => {
                clear(&mut commands, entity, state, has_batch);
                // Not again until something changes.
                state.key = Some(key);
                GroundFogStatus::fail(status.reborrow(), "ground fog", entity, error);
                continue;
            }
        };
        state.key = Some(key);
        if let GroundFogStatus::Failed(_) = *status {
            *status = GroundFogStatus::Ready;
        }
        // No cells, no wireframe: Bevy's mesh allocator refuses empty meshes.
        if fog.debug.wireframe && !cells.is_empty() {
            let lines = wireframe_mesh(&cells, &terrain_from_world);
            match &state.wireframe {
                Some((_, handle)) => {
                    if let Some(mut mesh) = meshes.get_mut(handle) {
                        *mesh = lines;
                    }
                }
                None => {
                    let handle = meshes.add(lines);
                    let material = materials.add(StandardMaterial {
                        base_color: Color::srgb(0.55, 0.85, 1.0),
                        unlit: true,
                        ..default()
                    });
                    // A child in the terrain's frame: it moves, hides and
                    // despawns with the terrain.
                    let wireframe = commands
                        .spawn((
                            Mesh3d(handle.clone()),
                            MeshMaterial3d(material),
                            Transform::IDENTITY,
                            ChildOf(entity),
                        ))
                        .id();
                    state.wireframe = Some((wireframe, handle));
                }
            }
        } else if let Some((wireframe, _)) = state.wireframe.take() {
            commands.entity(wireframe).try_despawn();
        }
        if cells.is_empty() {
            if has_batch {
                commands.entity(entity).remove::<CellBatch>();
            }
        } else {
            commands.entity(entity).insert(CellBatch {
                // A camera's fog layers take over from where they begin.
                ends_where_fog_layers_begin: true,
                light_response: fog.light_response,
                ..CellBatch::new(
                    Arc::new(Cells::with_bounds(cells)),
                    transfer,
                    fog.drawn_mode(),
                )
            });
        }
        *stats = GroundFogStats {
            prisms: counts.prisms as u32,
            tetrahedra: counts.tetrahedra as u32,
            updates: stats.updates + 1,
            update_ms,
            ..*stats
        };
        *frame_ms.get_or_insert(0.0) += f64::from(update_ms);
    }
    if let Some(ms) = frame_ms {
        diagnostics.add_measurement(&GroundFogPlugin::UPDATE_MS, || ms);
    }
}

/// Measures the fogs' totals; nothing in a world without a fog.
pub(crate) fn measure_fogs(
    fogs: Query<(&GroundFogStats, Has<CellBatch>), With<GroundFog>>,
    mut diagnostics: Diagnostics,
) {
    if fogs.is_empty() {
        return;
    }
    let (mut drawn, mut prisms, mut tetrahedra) = (0.0, 0.0, 0.0);
    for (stats, has_batch) in &fogs {
        if has_batch {
            drawn += 1.0;
            prisms += f64::from(stats.prisms);
            tetrahedra += f64::from(stats.tetrahedra);
        }
    }
    diagnostics.add_measurement(&GroundFogPlugin::FOGS, || drawn);
    diagnostics.add_measurement(&GroundFogPlugin::PRISMS, || prisms);
    diagnostics.add_measurement(&GroundFogPlugin::TETRAHEDRA, || tetrahedra);
}
