//! The [`Volume`] component and the system that keeps its [`CellBatch`]
//! current.
//!
//! A grid volume becomes the full-resolution batch of
//! [`nebel_lod::full_resolution_batch`]: five tetrahedra per voxel, bricks
//! whose scalar range is transparent under the transfer function dropped
//! (000 §4.1), and for [`OpticalMode::Sorted`] bricks outside the view
//! frustum dropped and the cells in exact back-to-front order for the eye
//! (001 §8.1). A sorted cell volume (a search light switched to `Sorted`, cells
//! from a scene file) is put in MPVO order for the eye (Williams 1992, exact
//! for convex conforming meshes; [`nebel_lod::visibility`]); an emissive or
//! MIP one is drawn as given.
//!
//! The batch system runs in `PostUpdate`, after transform propagation, the
//! camera's projection update and visibility propagation, so a batch is built
//! for the eye of the frame it is drawn in (a batch one frame behind a moving
//! camera is ordered and refined for the wrong eye). The systems that change
//! volumes (campfire, clouds) run in `Update`.
//!
//! Work happens only on change: a batch is rebuilt when the volume or its
//! transform changed, and, for sorted volumes, when the camera moved or
//! turned (the order depends on the eye, the culling on the whole view). Emissive and MIP volumes
//! draw unordered and unculled, so a moving camera costs them nothing.
//! With [`VolumeLod`] a grid volume's batch comes from the octree C-LOD
//! instead (see [`crate::VolumeLod`]), rebuilt whenever the eye moves.
//!
//! A hidden volume (its [`InheritedVisibility`] false) has no batch. The
//! `volume` group of [`EffectCounters`] reports volumes, cells drawn, cells
//! at full resolution and the last rebuild's time.

use std::sync::{Arc, LazyLock};
use std::time::Instant;

use bevy::camera::visibility::VisibilitySystems;
use bevy::camera::{Camera3d, CameraUpdateSystems};
use bevy::math::{DAffine3, DMat4, DVec3};
use bevy::prelude::*;
use bevy::transform::TransformSystems;
use nebel_core::cell::Tetrahedron;
use nebel_core::field::DensityGrid;
use nebel_core::field::{PadFill, light_field};
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{ControlPoint, TransferFunction};
use nebel_lod::octree::{CellScalars, RefinementSettings, VolumeHierarchy, lod_batch_with, refine};
use nebel_lod::{
    BrickTable, CellAdjacency, CellBatch as LodCellBatch, CellOrder, Frustum, full_resolution_batch,
};

use crate::lighting::sun_in_local_frame;
use crate::{VolumeLighting, VolumeLod};
use bevy::diagnostic::{Diagnostic, DiagnosticPath, Diagnostics, RegisterDiagnostic};
use nebel_render::{CellBatch, NebelSystems};

/// Voxels per brick edge for the zero-opacity and frustum tests.
const BRICK_SIZE: usize = 4;

/// Adds the [`Volume`] component's systems.
#[derive(Default)]
pub struct VolumePlugin;

impl VolumePlugin {
    /// Volumes in the world.
    pub const VOLUMES: DiagnosticPath = DiagnosticPath::const_new("nebel/volume/volumes");
    /// Cells of all volume batches.
    pub const CELLS_DRAWN: DiagnosticPath = DiagnosticPath::const_new("nebel/volume/cells_drawn");
    /// Cells all volumes would have at full resolution.
    pub const CELLS_FULL_RESOLUTION: DiagnosticPath =
        DiagnosticPath::const_new("nebel/volume/cells_full_resolution");
    /// Time of the batch rebuilds of a frame that rebuilt one, ms.
    pub const UPDATE_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/volume/update_ms");
}

impl Plugin for VolumePlugin {
    fn build(&self, app: &mut App) {
        for (path, suffix) in [
            (Self::VOLUMES, ""),
            (Self::CELLS_DRAWN, ""),
            (Self::CELLS_FULL_RESOLUTION, ""),
            (Self::UPDATE_MS, " ms"),
        ] {
            app.register_diagnostic(Diagnostic::new(path).with_suffix(suffix));
        }
        app.register_type::<crate::Campfire>()
            .register_type::<crate::CloudVolume>()
            .register_type::<crate::VolumeLod>()
            .register_type::<crate::VolumeLighting>()
            .add_systems(
                Update,
                (
                    crate::campfire::animate_campfires,
                    crate::cloud::generate_clouds,
                )
                    .in_set(NebelSystems),
            )
            // The batches follow this frame's camera: after its transform,
            // projection and the volumes' visibility are up to date.
            .add_systems(
                PostUpdate,
                update_volume_batches
                    .in_set(NebelSystems)
                    .after(TransformSystems::Propagate)
                    .after(CameraUpdateSystems)
                    .after(VisibilitySystems::VisibilityPropagate),
            );
    }
}

/// Where a volume's scalar comes from.
#[derive(Clone, Debug)]
pub enum VolumeField {
    /// A density grid in the volume's local space (its own origin and
    /// spacing), trilinear between points, drawn as five tetrahedra per voxel.
    Grid(Arc<DensityGrid>),
    /// Tetrahedra in the volume's local space: a conforming mesh, put in
    /// visibility order when the volume is sorted, drawn as given otherwise.
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
    /// The view-projection the frustum was culled with.
    clip_from_world: DMat4,
    hierarchy: Option<Arc<VolumeHierarchy>>,
    /// The direction toward the sun, volume frame, the light field was
    /// computed for (lit volumes only).
    sun: Option<Vec3>,
    bricks: Option<Arc<BrickTable>>,
    adjacency: Option<Arc<CellAdjacency>>,
}

fn to_double(matrix: Mat4) -> DMat4 {
    DMat4::from_cols_array(&matrix.to_cols_array().map(f64::from))
}

/// The octree of `grid`, padded with zero density to `2^n + 1` points per
/// side, with the light field for `lighting` when the volume is lit.
fn build_hierarchy(
    grid: &DensityGrid,
    lod: &VolumeLod,
    lighting: Option<(&VolumeLighting, Vec3)>,
) -> Result<VolumeHierarchy, String> {
    let padded = grid
        .padded_to_power_of_two_plus_one(PadFill::Value(0.0))
        .map_err(|error| error.to_string())?;
    match lighting {
        Some((lighting, sun)) => {
            let light = light_field(&padded, &lighting.light_field_settings(sun))
                .map_err(|error| error.to_string())?;
            VolumeHierarchy::with_light(&padded, &light, lod.min_accuracy)
        }
        None => VolumeHierarchy::new(&padded, lod.min_accuracy),
    }
    .map_err(|error| error.to_string())
}

/// The zero-opacity test of a volume whose density is the opacity itself
/// (`ρ = f`, the lit model of paper 000 §5.1): only density 0 is empty.
static DENSITY_AS_OPACITY: LazyLock<TransferFunction> = LazyLock::new(|| {
    let point = |s: f32| ControlPoint {
        s,
        kappa: [0.0; 3],
        rho: s,
    };
    TransferFunction::new([point(0.0), point(1.0)]).expect("two ordered control points")
});

#[allow(clippy::type_complexity)]
fn update_volume_batches(
    mut commands: Commands,
    cameras: Query<(&Camera, &GlobalTransform), With<Camera3d>>,
    suns: Query<&GlobalTransform, With<DirectionalLight>>,
    mut volumes: Query<(
        Entity,
        Ref<Volume>,
        Ref<GlobalTransform>,
        Option<Ref<VolumeLod>>,
        Option<Ref<VolumeLighting>>,
        &InheritedVisibility,
        Option<&CellBatch>,
        Option<&mut VolumeBatchSource>,
    )>,
    mut diagnostics: Diagnostics,
) {
    if volumes.is_empty() {
        return;
    }
    let Some((camera, camera_transform)) = cameras.iter().find(|(camera, _)| camera.is_active)
    else {
        return;
    };
    if camera.physical_target_size().is_none() {
        // The projection is computed in the camera's first PostUpdate; a
        // batch culled with the placeholder would never be rebuilt.
        return;
    }
    let eye = camera_transform.translation().as_dvec3();
    let clip_from_world =
        to_double(camera.clip_from_view() * camera_transform.to_matrix().inverse());
    // A degenerate projection culls nothing rather than everything.
    let frustum = Frustum::from_view_projection(clip_from_world).ok();
    let sun_world = suns.iter().next().map(|sun| sun.back().as_vec3());

    let started = Instant::now();
    let mut rebuilt = false;
    let (mut cells_drawn, mut cells_full) = (0_u64, 0_u64);
    for (entity, volume, transform, lod, lighting, visibility, drawn, source) in &mut volumes {
        if !visibility.get() {
            // Hidden: nothing to build, upload or draw.
            if source.is_some() {
                commands
                    .entity(entity)
                    .remove::<(CellBatch, VolumeBatchSource)>();
            }
            continue;
        }
        let ordered = volume.mode == OpticalMode::Sorted;
        let grid_full_cells = match &volume.field {
            VolumeField::Grid(grid) => {
                let [nx, ny, nz] = grid.dims();
                5 * (nx - 1) * (ny - 1) * (nz - 1)
            }
            VolumeField::Cells(cells) => cells.len(),
        };
        cells_full += grid_full_cells as u64;
        let lod_changed = lod.as_ref().is_some_and(|lod| lod.is_changed())
            || lighting
                .as_ref()
                .is_some_and(|lighting| lighting.is_changed());
        // A lit volume's light field depends on the sun in its own frame.
        let sun = lighting
            .as_ref()
            .map(|_| sun_in_local_frame(sun_world, &transform.affine()));
        let sun_moved = source.as_ref().is_some_and(|s| s.sun != sun);
        let changed = volume.is_changed() || transform.is_changed() || lod_changed || sun_moved;
        // The order, the culling and the level of detail depend on the eye.
        let view_dependent = ordered || lod.is_some();
        // A camera turning in place changes the frustum but not the eye.
        let view_moved = source
            .as_ref()
            .is_some_and(|s| s.eye != eye || s.clip_from_world != clip_from_world);
        if source.is_some() && !changed && !(view_dependent && view_moved) {
            cells_drawn += drawn.map_or(0, |batch| batch.cells.len() as u64);
            continue;
        }
        rebuilt = true;
        let world_from_local = transform.affine();
        let world_from_local = DAffine3::from_mat4(to_double(Mat4::from(world_from_local)));
        let (lod_batch, bricks, adjacency, hierarchy) = match &volume.field {
            VolumeField::Grid(grid) if let Some(lod) = lod.as_deref() => {
                let cached = source.as_ref().and_then(|s| s.hierarchy.clone());
                let lit = lighting.as_deref().zip(sun);
                let hierarchy = match cached {
                    Some(hierarchy) if !volume.is_changed() && !lod_changed && !sun_moved => {
                        hierarchy
                    }
                    _ => match build_hierarchy(grid, lod, lit) {
                        Ok(hierarchy) => Arc::new(hierarchy),
                        Err(error) => {
                            warn_once!("nebel: volume {entity} not drawn: {error}");
                            continue;
                        }
                    },
                };
                let settings = RefinementSettings {
                    accuracy: lod.accuracy,
                };
                let scalars = lit.map_or(CellScalars::Density, |(lighting, _)| {
                    lighting.model.cell_scalars()
                });
                // The zero-opacity test is on the field that sets the opacity.
                let opacity = match scalars {
                    CellScalars::LightModulatedByDensity => &*DENSITY_AS_OPACITY,
                    _ => &*volume.transfer_function,
                };
                let batch = refine(
                    &hierarchy,
                    world_from_local,
                    eye,
                    frustum.as_ref(),
                    opacity,
                    &settings,
                )
                .and_then(|refinement| {
                    lod_batch_with(&hierarchy, &refinement, world_from_local, eye, scalars)
                });
                match batch {
                    Ok(batch) => (batch, None, None, Some(hierarchy)),
                    Err(error) => {
                        warn_once!("nebel: volume {entity} not drawn: {error}");
                        continue;
                    }
                }
            }
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
                    Ok(batch) => (batch, Some(bricks), None, None),
                    Err(error) => {
                        warn_once!("nebel: volume {entity} not drawn: {error}");
                        continue;
                    }
                }
            }
            VolumeField::Cells(cells) => {
                let to_world = |tet: &Tetrahedron| Tetrahedron {
                    positions: tet.positions.map(|p| world_from_local.transform_point3(p)),
                    scalars: tet.scalars,
                };
                if ordered {
                    let adjacency = match source.as_ref().and_then(|s| s.adjacency.clone()) {
                        Some(adjacency) if !volume.is_changed() => adjacency,
                        _ => Arc::new(CellAdjacency::new(cells)),
                    };
                    let eye_local = world_from_local.inverse().transform_point3(eye);
                    let world: Vec<Tetrahedron> = adjacency
                        .back_to_front(cells, eye_local)
                        .into_iter()
                        .map(|index| to_world(&cells[index]))
                        .collect();
                    (
                        LodCellBatch::from_tetrahedra(&world),
                        None,
                        Some(adjacency),
                        None,
                    )
                } else {
                    let world: Vec<Tetrahedron> = cells.iter().map(to_world).collect();
                    (LodCellBatch::from_tetrahedra(&world), None, None, None)
                }
            }
        };
        let LodCellBatch {
            cells, modulators, ..
        } = lod_batch;
        cells_drawn += cells.len() as u64;
        let mut batch = CellBatch::new(cells, volume.transfer_function.clone(), volume.mode)
            .with_modulators(modulators);
        batch.scattering = lighting
            .as_deref()
            .and_then(|lighting| lighting.cell_scattering(sun_world.unwrap_or(Vec3::Y)));
        commands.entity(entity).insert((
            batch,
            VolumeBatchSource {
                eye,
                clip_from_world,
                hierarchy,
                sun,
                bricks,
                adjacency,
            },
        ));
    }
    if rebuilt {
        let ms = started.elapsed().as_secs_f64() * 1e3;
        diagnostics.add_measurement(&VolumePlugin::UPDATE_MS, || ms);
    }
    let count = volumes.iter().len() as f64;
    diagnostics.add_measurement(&VolumePlugin::CELLS_DRAWN, || cells_drawn as f64);
    diagnostics.add_measurement(&VolumePlugin::VOLUMES, || count);
    diagnostics.add_measurement(&VolumePlugin::CELLS_FULL_RESOLUTION, || cells_full as f64);
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::camera::{ComputedCameraValues, RenderTargetInfo};
    use bevy::math::DVec3;
    use bevy::transform::TransformPlugin;
    use nebel_core::transfer::TransferPreset;

    fn app_with_volume(mode: OpticalMode) -> (App, Entity, Entity) {
        let mut app = App::new();
        app.add_plugins((MinimalPlugins, TransformPlugin, VolumePlugin));
        // What Bevy's camera systems compute for a 64×64 target.
        let camera = Camera {
            computed: ComputedCameraValues {
                clip_from_view: Mat4::perspective_infinite_reverse_rh(1.0, 1.0, 0.1),
                target_info: Some(RenderTargetInfo {
                    physical_size: UVec2::splat(64),
                    scale_factor: 1.0,
                }),
                ..default()
            },
            ..default()
        };
        let camera = app
            .world_mut()
            .spawn((
                Camera3d::default(),
                camera,
                Transform::from_xyz(5.0, 2.0, 7.0).looking_at(Vec3::ONE, Vec3::Y),
            ))
            .id();
        let grid = DensityGrid::new([3, 3, 3], DVec3::ONE, DVec3::ZERO, vec![1.0; 27]).unwrap();
        let volume = app
            .world_mut()
            .spawn((
                Volume {
                    field: VolumeField::Grid(Arc::new(grid)),
                    transfer_function: Arc::new(TransferFunction::preset(TransferPreset::Cloud)),
                    mode,
                },
                // What Bevy's visibility propagation computes for a shown entity.
                InheritedVisibility::VISIBLE,
            ))
            .id();
        // Transforms propagate in PostUpdate: the batch settles in the second frame.
        app.update();
        app.update();
        (app, camera, volume)
    }

    /// Moves the camera a metre and runs until the move has propagated.
    fn move_camera(app: &mut App, camera: Entity) {
        let mut transform = app.world_mut().get_mut::<Transform>(camera).unwrap();
        transform.translation.x += 1.0;
        app.update();
        app.update();
    }

    /// Turns the camera in place and runs until the turn has propagated.
    fn turn_camera(app: &mut App, camera: Entity) {
        let mut transform = app.world_mut().get_mut::<Transform>(camera).unwrap();
        transform.rotate_y(0.05);
        app.update();
        app.update();
    }

    /// The change tick of the batch's last change.
    fn generation(app: &App, volume: Entity) -> Option<u32> {
        app.world()
            .entity(volume)
            .get_ref::<CellBatch>()
            .map(|batch| batch.last_changed().get())
    }

    #[test]
    fn a_camera_without_a_projection_yet_builds_nothing() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Sorted);
        app.world_mut().entity_mut(volume).remove::<CellBatch>();
        app.world_mut().get_mut::<Camera>(camera).unwrap().computed = default();
        app.world_mut().get_mut::<Volume>(volume).unwrap().mode = OpticalMode::Sorted;
        app.update();
        assert!(app.world().get::<CellBatch>(volume).is_none());
    }

    #[test]
    fn a_grid_becomes_five_cells_per_voxel_and_is_rebuilt_only_on_change() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Sorted);
        let batch = app.world().get::<CellBatch>(volume).expect("a batch");
        assert_eq!(batch.cells.len(), 5 * 8);
        let first = generation(&app, volume).unwrap();

        app.update();
        assert_eq!(
            generation(&app, volume),
            Some(first),
            "nothing moved: no rebuild"
        );

        move_camera(&mut app, camera);
        assert!(
            generation(&app, volume).unwrap() > first,
            "a sorted volume follows the eye"
        );

        let moved = generation(&app, volume);
        turn_camera(&mut app, camera);
        assert!(
            generation(&app, volume) > moved,
            "the frustum changes when the camera turns in place"
        );

        let moved = generation(&app, volume);
        app.world_mut().get_mut::<Volume>(volume).unwrap().mode = OpticalMode::Sorted;
        app.update();
        assert!(
            generation(&app, volume) > moved,
            "a changed volume is rebuilt"
        );
    }

    #[test]
    fn an_emissive_volume_ignores_the_camera_and_a_hidden_one_has_no_batch() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Emissive);
        let first = generation(&app, volume).expect("a batch");
        move_camera(&mut app, camera);
        assert_eq!(generation(&app, volume), Some(first));

        app.world_mut()
            .entity_mut(volume)
            .insert(InheritedVisibility::HIDDEN);
        app.update();
        assert!(app.world().get::<CellBatch>(volume).is_none());
    }

    #[test]
    fn a_lod_volume_draws_fewer_cells_from_afar_and_follows_the_eye() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Emissive);
        let noise = nebel_core::field::ProceduralNoise {
            octaves: 3,
            ..default()
        };
        let grid = DensityGrid::procedural([17, 17, 17], DVec3::splat(0.125), DVec3::ZERO, &noise)
            .unwrap();
        app.world_mut().get_mut::<Volume>(volume).unwrap().field =
            VolumeField::Grid(Arc::new(grid));
        app.world_mut().entity_mut(volume).insert(VolumeLod {
            accuracy: 0.0,
            min_accuracy: 2.0,
        });
        app.update();
        let coarse = app.world().get::<CellBatch>(volume).unwrap().cells.len();
        assert!(coarse > 0 && coarse < 5 * 16 * 16 * 16, "{coarse} cells");

        // An emissive volume at full resolution ignores the eye; with LOD it follows it.
        let before = generation(&app, volume);
        move_camera(&mut app, camera);
        assert!(generation(&app, volume) > before);

        app.world_mut()
            .get_mut::<VolumeLod>(volume)
            .unwrap()
            .accuracy = f64::INFINITY;
        app.update();
        let fine = app.world().get::<CellBatch>(volume).unwrap().cells.len();
        assert!(
            fine > coarse,
            "{fine} cells at c = ∞ against {coarse} at c = 0"
        );
    }

    #[test]
    fn a_lit_volume_carries_its_density_as_modulator_and_follows_the_sun() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        let noise = nebel_core::field::ProceduralNoise {
            octaves: 3,
            ..default()
        };
        let grid =
            DensityGrid::procedural([9, 9, 9], DVec3::splat(0.25), DVec3::ZERO, &noise).unwrap();
        app.world_mut().get_mut::<Volume>(volume).unwrap().field =
            VolumeField::Grid(Arc::new(grid));
        app.world_mut().entity_mut(volume).insert(VolumeLighting {
            shadow_extinction: 2.0,
            ..default()
        });
        app.update();
        let batch = app.world().get::<CellBatch>(volume).unwrap().clone();
        let modulators = batch.modulators.clone().expect("a lit batch is modulated");
        assert_eq!(modulators.len(), batch.cells.len());
        // Isotropic model: the scalar is γ ≥ ambient, the modulator the density.
        assert!(
            batch
                .cells
                .iter()
                .flat_map(|c| c.vertices)
                .all(|v| v[3] >= 0.3 - 1.0 / 255.0)
        );
        let lit_first = generation(&app, volume).unwrap();
        app.update();
        assert_eq!(generation(&app, volume), Some(lit_first), "nothing moved");

        // A sun appears (straight up before): the light field is recomputed.
        app.world_mut().spawn((
            DirectionalLight::default(),
            Transform::default().looking_to(Vec3::new(1.0, -0.2, 0.0), Vec3::Y),
        ));
        app.update();
        app.update();
        let relit = app.world().get::<CellBatch>(volume).unwrap();
        assert!(generation(&app, volume).unwrap() > lit_first);
        assert_ne!(relit.cells, batch.cells, "the light changed with the sun");

        app.world_mut()
            .entity_mut(volume)
            .get_mut::<VolumeLighting>()
            .unwrap()
            .model = crate::CloudLightModel::NonPhysical;
        app.update();
        let swapped = app.world().get::<CellBatch>(volume).unwrap();
        assert!(swapped.modulators.is_some());
        assert!(swapped.scattering.is_none());

        // Single scattering: γ is the transmittance (≤ 1, no ambient floor),
        // and the batch carries the sun for the per-pixel phase.
        app.world_mut()
            .entity_mut(volume)
            .get_mut::<VolumeLighting>()
            .unwrap()
            .model = crate::CloudLightModel::Scattering { asymmetry: 0.7 };
        app.update();
        let scattered = app.world().get::<CellBatch>(volume).unwrap();
        let scattering = scattered.scattering.expect("a scattering batch");
        assert_eq!(scattering.asymmetry, 0.7);
        let sun = Transform::default()
            .looking_to(Vec3::new(1.0, -0.2, 0.0), Vec3::Y)
            .back()
            .as_vec3();
        assert!(scattering.sun_direction.distance(sun) < 1e-6);
        assert!(
            scattered
                .cells
                .iter()
                .flat_map(|c| c.vertices)
                .any(|v| v[3] < 0.3),
            "the transmittance has no ambient floor"
        );
    }

    #[test]
    fn a_batch_follows_the_camera_in_the_same_frame() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Sorted);
        let before = generation(&app, volume);
        let mut transform = app.world_mut().get_mut::<Transform>(camera).unwrap();
        transform.translation.x += 1.0;
        let moved_to = transform.translation.as_dvec3();
        // One frame: the batch is rebuilt for the eye that frame is drawn from.
        app.update();
        assert!(generation(&app, volume) > before);
        let source = app.world().get::<VolumeBatchSource>(volume).unwrap();
        assert_eq!(source.eye, moved_to);
    }

    #[test]
    fn a_transparent_grid_draws_nothing() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        let empty = DensityGrid::new([2, 2, 2], DVec3::ONE, DVec3::ZERO, vec![0.0; 8]).unwrap();
        app.world_mut().get_mut::<Volume>(volume).unwrap().field =
            VolumeField::Grid(Arc::new(empty));
        app.update();
        let batch = app.world().get::<CellBatch>(volume).unwrap();
        assert!(batch.cells.is_empty() && !batch.is_drawable());
    }
}
