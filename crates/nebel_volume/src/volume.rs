//! The [`Volume`] component and the system that keeps its [`CellBatch`]
//! current.
//!
//! A grid volume becomes the full-resolution batch of
//! [`nebel_lod::full_resolution_batch`]: five tetrahedra per voxel, bricks
//! whose scalar range is transparent under the transfer function dropped
//! (000 §4.1), and for [`OpticalMode::Sorted`] bricks outside the view
//! frustum dropped and the cells in exact back-to-front order for the eye
//! (001 §8.1). A cell volume is drawn as given.
//!
//! Work happens only on change: a batch is rebuilt when the volume or its
//! transform changed, and, for sorted grid volumes, when the camera moved
//! (the order and the culling depend on the eye). Emissive and MIP volumes
//! draw unordered and unculled, so a moving camera costs them nothing.
//! The `volume` group of [`EffectCounters`] reports volumes, cells drawn,
//! cells at full resolution and the last rebuild's time.

use std::sync::Arc;
use std::time::Instant;

use bevy::camera::Camera3d;
use bevy::math::{DAffine3, DMat4, DVec3};
use bevy::prelude::*;
use nebel_core::cell::Tetrahedron;
use nebel_core::field::DensityGrid;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::TransferFunction;
use nebel_lod::{BrickTable, CellBatch as LodCellBatch, CellOrder, Frustum, full_resolution_batch};
use nebel_render::{CellBatch, EffectCounters, NebelSystems};

/// Voxels per brick edge for the zero-opacity and frustum tests.
const BRICK_SIZE: usize = 4;

/// Adds the [`Volume`] component's systems.
#[derive(Default)]
pub struct VolumePlugin;

impl Plugin for VolumePlugin {
    fn build(&self, app: &mut App) {
        app.register_type::<crate::Campfire>().add_systems(
            Update,
            (crate::campfire::animate_campfires, update_volume_batches)
                .chain()
                .in_set(NebelSystems),
        );
    }
}

/// Where a volume's scalar comes from.
#[derive(Clone, Debug)]
pub enum VolumeField {
    /// A density grid in the volume's local space (its own origin and
    /// spacing), trilinear between points, drawn as five tetrahedra per voxel.
    Grid(Arc<DensityGrid>),
    /// Tetrahedra in the volume's local space, drawn as given.
    Cells(Arc<Vec<Tetrahedron>>),
}

/// A volume of participating medium drawn by cell projection.
#[derive(Component, Clone, Debug)]
#[require(Transform, Visibility)]
pub struct Volume {
    /// The scalar field.
    pub field: VolumeField,
    /// κ and ρ over the scalar.
    pub transfer_function: Arc<TransferFunction>,
    /// How segments combine. Default [`OpticalMode::Sorted`].
    pub mode: OpticalMode,
}

impl Default for Volume {
    fn default() -> Self {
        Self {
            field: VolumeField::Cells(Arc::default()),
            transfer_function: Arc::new(TransferFunction::preset(
                nebel_core::transfer::TransferPreset::Cloud,
            )),
            mode: OpticalMode::Sorted,
        }
    }
}

/// What a volume's batch was built from, to skip rebuilds when nothing changed.
#[derive(Component, Clone, Debug)]
struct VolumeBatchSource {
    eye: DVec3,
    bricks: Option<Arc<BrickTable>>,
    generation: u64,
}

fn to_double(matrix: Mat4) -> DMat4 {
    DMat4::from_cols_array(&matrix.to_cols_array().map(f64::from))
}

#[allow(clippy::type_complexity)]
fn update_volume_batches(
    mut commands: Commands,
    cameras: Query<(&Camera, &GlobalTransform), With<Camera3d>>,
    mut volumes: Query<(
        Entity,
        Ref<Volume>,
        Ref<GlobalTransform>,
        &ViewVisibility,
        Option<&mut VolumeBatchSource>,
    )>,
    mut counters: ResMut<EffectCounters>,
) {
    if volumes.is_empty() {
        return;
    }
    let Some((camera, camera_transform)) = cameras.iter().find(|(camera, _)| camera.is_active)
    else {
        return;
    };
    let eye = camera_transform.translation().as_dvec3();
    let clip_from_world =
        to_double(camera.clip_from_view() * camera_transform.to_matrix().inverse());
    // A degenerate projection culls nothing rather than everything.
    let frustum = Frustum::from_view_projection(clip_from_world).ok();

    let started = Instant::now();
    let mut rebuilt = false;
    let (mut cells_drawn, mut cells_full) = (0_u64, 0_u64);
    for (entity, volume, transform, _visibility, source) in &mut volumes {
        let ordered = volume.mode == OpticalMode::Sorted;
        let grid_full_cells = match &volume.field {
            VolumeField::Grid(grid) => {
                let [nx, ny, nz] = grid.dims();
                5 * (nx - 1) * (ny - 1) * (nz - 1)
            }
            VolumeField::Cells(cells) => cells.len(),
        };
        cells_full += grid_full_cells as u64;
        let changed = volume.is_changed() || transform.is_changed();
        let eye_moved = source.as_ref().is_some_and(|s| s.eye != eye);
        let grid_sorted = ordered && matches!(volume.field, VolumeField::Grid(_));
        if source.is_some() && !changed && !(grid_sorted && eye_moved) {
            continue;
        }
        rebuilt = true;
        let generation = source.as_ref().map_or(0, |s| s.generation + 1);
        let world_from_local = transform.affine();
        let world_from_local = DAffine3::from_mat4(to_double(Mat4::from(world_from_local)));
        let (lod_batch, bricks) = match &volume.field {
            VolumeField::Grid(grid) => {
                let bricks = match source.as_ref().and_then(|s| s.bricks.clone()) {
                    Some(bricks) if !volume.is_changed() => bricks,
                    _ => Arc::new(BrickTable::new(grid, BRICK_SIZE)),
                };
                let order = if ordered {
                    CellOrder::BackToFront
                } else {
                    CellOrder::Unordered
                };
                let frustum = frustum.as_ref().filter(|_| ordered);
                let batch = full_resolution_batch(
                    grid,
                    &bricks,
                    world_from_local,
                    eye,
                    frustum,
                    &volume.transfer_function,
                    order,
                );
                match batch {
                    Ok(batch) => (batch, Some(bricks)),
                    Err(error) => {
                        warn_once!("nebel: volume {entity} not drawn: {error}");
                        continue;
                    }
                }
            }
            VolumeField::Cells(cells) => {
                let world: Vec<Tetrahedron> = cells
                    .iter()
                    .map(|tet| Tetrahedron {
                        positions: tet.positions.map(|p| world_from_local.transform_point3(p)),
                        scalars: tet.scalars,
                    })
                    .collect();
                (LodCellBatch::from_tetrahedra(&world), None)
            }
        };
        let LodCellBatch { cells, .. } = lod_batch;
        cells_drawn += cells.len() as u64;
        commands.entity(entity).insert((
            CellBatch::new(
                cells,
                volume.transfer_function.clone(),
                volume.mode,
                generation,
            ),
            VolumeBatchSource {
                eye,
                bricks,
                generation,
            },
        ));
    }
    if rebuilt {
        counters.set("volume", "update_ms", started.elapsed().as_secs_f64() * 1e3);
        counters.set("volume", "cells_drawn", cells_drawn as f64);
    }
    counters.set("volume", "volumes", volumes.iter().len() as f64);
    counters.set("volume", "cells_full_resolution", cells_full as f64);
}
