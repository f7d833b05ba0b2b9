//! The [`Volume`] component and [`VolumePlugin`].
//!
//! A volume is a scalar field in its entity's local frame, a transfer
//! function and an optical mode. Its [`CellBatch`](nebel_render::CellBatch)
//! is kept current by the
//! systems of [`crate::batching`]: a grid volume at full resolution (Kuhn's
//! six tetrahedra per voxel; bricks whose scalar range is
//! transparent under the transfer function dropped, Röttger and Ertl, "Fast
//! Volumetric Display of Natural Gaseous Phenomena", 2003, §4.1; for
//! [`OpticalMode::Sorted`] bricks outside the view frustum dropped and the
//! cells in exact back-to-front order for the eye), with [`VolumeLod`]
//! through the octree C-LOD, with [`VolumeLighting`] lit as a cloud; a sorted
//! cell volume (a search light switched to `Sorted`, cells from a scene file)
//! in MPVO order for the eye (Williams 1992, exact for convex conforming
//! meshes); an emissive or MIP one as given.
//!
//! Work happens only on change: the view-independent part (bricks, octree,
//! light field, adjacency) when the field, the mode or the LOD and lighting
//! settings change (on the task pool, see
//! [`nebel_render::HeavyBuilds`]), the batch when the view
//! changes what it would be. Emissive and MIP grids draw unordered and
//! unculled, so a moving camera costs them nothing. A hidden volume (its
//! [`InheritedVisibility`] false) has no batch. [`VolumeStatus`] tells
//! whether a volume is drawn, pending or failed and why.

use std::sync::Arc;

use bevy::camera::CameraUpdateSystems;
use bevy::camera::visibility::VisibilitySystems;
use bevy::diagnostic::{DiagnosticPath, Diagnostics};
use bevy::prelude::*;
use bevy::transform::TransformSystems;
use nebel_core::cell::Tetrahedron;
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_render::{HeavyBuilds, LodCamera, NebelSystems, cpu_timed, register_diagnostics};

use crate::batching::{
    VolumeBatching, build_batchers, measure_volumes, report_status, update_batches,
};
use crate::grid::VolumeGrid;
use crate::status::VolumeStatus;
use crate::{VolumeLighting, VolumeLod};

/// Adds [`Volume`], the [`VolumeGrid`] asset and its loader, the campfire
/// and cloud generators, the volume systems and their diagnostics. A world
/// without volumes runs no volume work.
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
    /// Time of the batch updates of a frame that rebuilt one, ms.
    pub const UPDATE_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/volume/update_ms");
    /// Time of each background build of a batcher (padding, light field,
    /// octree or bricks), ms.
    pub const BUILD_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/volume/build_ms");
    /// Time of each cloud grid generation (on the task pool), ms.
    pub const GENERATION_MS: DiagnosticPath =
        DiagnosticPath::const_new("nebel/volume/generation_ms");
    /// Time of each keyframe pair a windy cloud's track built (grid, light
    /// field, octree and the pair's octree, on the task pool), ms.
    pub const KEYFRAME_MS: DiagnosticPath = DiagnosticPath::const_new("nebel/volume/keyframe_ms");
    /// Under [`HeavyBuilds::Budgeted`], the CPU time the budgeted builds
    /// (keyframes and refinement steps) worked in the frame before, ms: at
    /// most the budget plus one unit of a build.
    pub const BUDGETED_BUILD_MS: DiagnosticPath =
        DiagnosticPath::const_new("nebel/volume/budgeted_build_ms");
}

impl Plugin for VolumePlugin {
    fn build(&self, app: &mut App) {
        register_diagnostics(
            app,
            &[
                (Self::VOLUMES, ""),
                (Self::CELLS_DRAWN, ""),
                (Self::CELLS_FULL_RESOLUTION, ""),
                (Self::UPDATE_MS, " ms"),
                (Self::BUILD_MS, " ms"),
                (Self::GENERATION_MS, " ms"),
                (Self::KEYFRAME_MS, " ms"),
                (Self::BUDGETED_BUILD_MS, " ms"),
            ],
        );
        // Weather maps are grayscale map assets.
        nebel_render::GrayscaleMapPlugin::add_once(app);
        app.init_asset::<VolumeGrid>()
            .register_asset_loader(crate::grid_loader::VolumeGridLoader)
            .init_resource::<HeavyBuilds>()
            .register_type::<Volume>()
            .register_type::<ProjectedCells>()
            .register_type::<VolumeStatus>()
            .register_type::<crate::Campfire>()
            .register_type::<crate::CloudVolume>()
            .register_type::<crate::CloudPrimitive>()
            .register_type::<crate::CloudWeatherMap>()
            .register_type::<VolumeLod>()
            .register_type::<VolumeLighting>()
            .register_type::<LodCamera>()
            .register_type::<HeavyBuilds>()
            .add_systems(First, open_build_budget)
            .add_systems(
                Update,
                (
                    cpu_timed(crate::campfire::animate_campfires),
                    (
                        cpu_timed(crate::cloud_primitive::gather_cloud_primitives),
                        cpu_timed(crate::cloud_weather_map::apply_weather_maps),
                        cpu_timed(crate::cloud::generate_clouds),
                    )
                        .chain(),
                )
                    .in_set(NebelSystems),
            )
            // The batches follow this frame's camera: after its transform,
            // projection and the volumes' visibility are up to date.
            .add_systems(
                PostUpdate,
                (
                    cpu_timed(build_batchers),
                    cpu_timed(update_batches),
                    cpu_timed(report_status),
                    cpu_timed(measure_volumes),
                )
                    .chain()
                    .in_set(NebelSystems)
                    .after(TransformSystems::Propagate)
                    .after(CameraUpdateSystems)
                    .after(VisibilitySystems::VisibilityPropagate),
            );
    }
}

/// Opens the frame's budget for the budgeted builds and, under
/// [`HeavyBuilds::Budgeted`], measures what they did in the frame before
/// ([`VolumePlugin::BUDGETED_BUILD_MS`], every frame: zero while none runs).
fn open_build_budget(mode: Res<HeavyBuilds>, mut diagnostics: Diagnostics) {
    let worked = mode.open_frame();
    if let HeavyBuilds::Budgeted(_) = *mode {
        diagnostics.add_measurement(&VolumePlugin::BUDGETED_BUILD_MS, || {
            worked.as_secs_f64() * 1e3
        });
    }
}

/// Where a volume's scalar comes from.
#[derive(Clone, Debug, Reflect)]
#[reflect(Clone, Default)]
pub enum VolumeField {
    /// A density grid asset in the volume's local space (its own origin and
    /// spacing), trilinear between points, drawn as six tetrahedra per
    /// voxel (Kuhn's, linear in each).
    Grid(Handle<VolumeGrid>),
    /// Tetrahedra in the volume's local space: a conforming mesh, put in
    /// visibility order when the volume is sorted, drawn as given otherwise.
    Cells(#[reflect(ignore)] Arc<Vec<Tetrahedron>>),
}

impl Default for VolumeField {
    /// No cells: nothing to draw (a generator fills it).
    fn default() -> Self {
        Self::Cells(Arc::default())
    }
}

/// A volume of participating medium drawn by cell projection (see the
/// module docs).
#[derive(Component, Clone, Debug, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(Transform, Visibility, VolumeStatus, VolumeBatching)]
pub struct Volume {
    /// The scalar field. Default: no cells.
    pub field: VolumeField,
    /// κ and ρ over the scalar. Default: the `Cloud` preset.
    #[reflect(ignore, default = "cloud_transfer_function")]
    pub transfer_function: Arc<TransferFunction>,
    /// How segments combine. Default [`OpticalMode::Sorted`].
    pub mode: OpticalMode,
    /// How a sorted volume scatters the point and spot lights opted in with
    /// Bevy's `VolumetricLight` (`nebel_render::local_lights`): the phase's
    /// asymmetry and a factor on its colour. Default: isotropic, factor 1.
    pub light_response: LightResponse,
}

/// Draws a grid [`Volume`] at full resolution as its tetrahedra projected
/// in exact visibility order (Röttger 2004 §8), as the paper does, instead
/// of ray casting them. Both are exact for the grid's tetrahedra; ray
/// casting needs no order rebuilt when the eye moves and stops each pixel
/// once it is opaque. No effect with [`VolumeLod`] or on
/// a volume of cells.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Eq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct ProjectedCells;

fn cloud_transfer_function() -> Arc<TransferFunction> {
    Arc::new(TransferFunction::preset(TransferPreset::Cloud))
}

impl Default for Volume {
    fn default() -> Self {
        Self {
            field: VolumeField::default(),
            transfer_function: cloud_transfer_function(),
            mode: OpticalMode::Sorted,
            light_response: LightResponse::default(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::LodCriterion;
    use crate::test_support::volume_grid;
    use bevy::diagnostic::DiagnosticsStore;
    use bevy::math::DVec3;
    use nebel_core::field::DensityGrid;
    use nebel_core::field::effects::campfire_density;
    use nebel_render::CellBatch;
    use nebel_render::headless::{headless_app, spawn_computed_camera};

    fn app_with_volume(mode: OpticalMode) -> (App, Entity, Entity) {
        let mut app = headless_app(None);
        app.add_plugins(VolumePlugin);
        let transform = Transform::from_xyz(5.0, 2.0, 7.0).looking_at(Vec3::ONE, Vec3::Y);
        let camera = spawn_computed_camera(app.world_mut(), 1.0, UVec2::splat(64), transform);
        let grid = DensityGrid::new([3, 3, 3], DVec3::ONE, DVec3::ZERO, vec![1.0; 27]).unwrap();
        let field = grid_field(&mut app, grid);
        let volume = app
            .world_mut()
            .spawn((
                Volume {
                    field,
                    transfer_function: cloud_transfer_function(),
                    mode,
                    ..default()
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

    fn grid_field(app: &mut App, grid: DensityGrid) -> VolumeField {
        VolumeField::Grid(
            app.world_mut()
                .resource_mut::<Assets<VolumeGrid>>()
                .add(VolumeGrid::from(grid)),
        )
    }

    /// Gives `volume` a 17³ noise grid drawn through the octree by the
    /// distance criterion at `accuracy`.
    fn give_noise_lod(app: &mut App, volume: Entity, accuracy: f64) {
        give_noise_lod_by(app, volume, LodCriterion::distance(accuracy));
    }

    /// Gives `volume` a 17³ noise grid drawn through the octree by
    /// `criterion`.
    fn give_noise_lod_by(app: &mut App, volume: Entity, criterion: LodCriterion) {
        let noise = nebel_core::field::ProceduralNoise {
            octaves: 3,
            ..default()
        };
        let grid = DensityGrid::procedural([17, 17, 17], DVec3::splat(0.125), DVec3::ZERO, &noise)
            .unwrap();
        let field = grid_field(app, grid);
        app.world_mut().get_mut::<Volume>(volume).unwrap().field = field;
        app.world_mut().entity_mut(volume).insert(VolumeLod {
            criterion,
            min_accuracy: 2.0,
        });
    }

    /// Gives `volume` a 9³ noise grid lit by `lighting` with a shadow of
    /// extinction 2, drawn through the octree (its own `VolumeLod`, or the
    /// default).
    fn give_lit_noise(app: &mut App, volume: Entity, lighting: VolumeLighting) {
        let noise = nebel_core::field::ProceduralNoise {
            octaves: 3,
            ..default()
        };
        let grid =
            DensityGrid::procedural([9, 9, 9], DVec3::splat(0.25), DVec3::ZERO, &noise).unwrap();
        let field = grid_field(app, grid);
        app.world_mut().get_mut::<Volume>(volume).unwrap().field = field;
        let mut entity = app.world_mut().entity_mut(volume);
        entity.insert(VolumeLighting {
            shadow_extinction: 2.0,
            ..lighting
        });
        if !entity.contains::<VolumeLod>() {
            entity.insert(VolumeLod::default());
        }
    }

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
    fn last_changed(app: &App, volume: Entity) -> Option<u32> {
        app.world()
            .entity(volume)
            .get_ref::<CellBatch>()
            .map(|batch| batch.last_changed().get())
    }

    fn status(app: &App, volume: Entity) -> VolumeStatus {
        app.world().get::<VolumeStatus>(volume).unwrap().clone()
    }

    #[test]
    fn a_camera_without_a_projection_yet_builds_no_batch() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Sorted);
        app.world_mut().entity_mut(volume).remove::<CellBatch>();
        app.world_mut().get_mut::<Camera>(camera).unwrap().computed = default();
        app.update();
        assert!(app.world().get::<CellBatch>(volume).is_none());
    }

    #[test]
    fn a_light_response_reaches_the_batch_once_even_when_bad() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        let response = LightResponse {
            asymmetry: 0.4,
            strength: 3.0,
        };
        app.world_mut()
            .get_mut::<Volume>(volume)
            .unwrap()
            .light_response = response;
        app.update();
        let batch = app.world().get::<CellBatch>(volume).expect("a batch");
        assert_eq!(batch.light_response, response);
        // NaN draws as 0 (`LightResponse::checked`) and, compared as drawn,
        // does not rebuild the batch every frame.
        app.world_mut()
            .get_mut::<Volume>(volume)
            .unwrap()
            .light_response
            .strength = f32::NAN;
        app.update();
        let first = last_changed(&app, volume);
        app.update();
        app.update();
        assert_eq!(
            last_changed(&app, volume),
            first,
            "a NaN rebuilds every frame"
        );
    }

    #[test]
    fn a_grid_becomes_six_cells_per_voxel_and_is_rebuilt_only_on_change() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Sorted);
        assert_eq!(status(&app, volume), VolumeStatus::Ready);
        let batch = app.world().get::<CellBatch>(volume).expect("a batch");
        assert_eq!(batch.cells.len(), 6 * 8);
        // Ray cast (the default): the whole grid, whatever the eye.
        assert!(batch.cells.grid.is_some() && batch.cells.tetrahedra.is_empty());
        let cast = last_changed(&app, volume);
        let start = *app.world().get::<Transform>(camera).unwrap();
        *app.world_mut().get_mut::<Transform>(camera).unwrap() =
            Transform::from_xyz(1.0, 1.0, -6.0).looking_at(Vec3::ONE, Vec3::Y);
        app.update();
        turn_camera(&mut app, camera);
        assert_eq!(
            last_changed(&app, volume),
            cast,
            "a ray-cast grid ignores the eye"
        );
        *app.world_mut().get_mut::<Transform>(camera).unwrap() = start;

        // As projected cells: six per voxel, in the eye's order.
        app.world_mut().entity_mut(volume).insert(ProjectedCells);
        app.update();
        app.update();
        let batch = app.world().get::<CellBatch>(volume).expect("a batch");
        assert_eq!(batch.cells.tetrahedra.len(), 6 * 8);
        assert!(batch.cells.grid.is_none());
        let first = last_changed(&app, volume).unwrap();

        app.update();
        assert_eq!(
            last_changed(&app, volume),
            Some(first),
            "nothing moved: no rebuild"
        );

        // A sorted grid follows the eye where its visibility order changes.
        *app.world_mut().get_mut::<Transform>(camera).unwrap() =
            Transform::from_xyz(1.0, 1.0, -6.0).looking_at(Vec3::ONE, Vec3::Y);
        app.update();
        app.update();
        assert!(
            last_changed(&app, volume).unwrap() > first,
            "a sorted volume follows the eye"
        );

        let moved = last_changed(&app, volume);
        turn_camera(&mut app, camera);
        assert!(
            last_changed(&app, volume) > moved,
            "the frustum changes when the camera turns in place"
        );

        let moved = last_changed(&app, volume);
        app.world_mut()
            .get_mut::<Volume>(volume)
            .unwrap()
            .transfer_function = Arc::new(TransferFunction::preset(TransferPreset::Smoke));
        app.update();
        assert!(
            last_changed(&app, volume) > moved,
            "a changed volume is rebuilt"
        );
        let measured = |path| {
            app.world()
                .resource::<DiagnosticsStore>()
                .get_measurement(&path)
                .map(|m| m.value)
        };
        assert_eq!(measured(VolumePlugin::VOLUMES), Some(1.0));
        assert_eq!(measured(VolumePlugin::CELLS_DRAWN), Some(48.0));
        assert_eq!(measured(VolumePlugin::CELLS_FULL_RESOLUTION), Some(48.0));
    }

    #[test]
    fn an_emissive_volume_ignores_the_camera_and_a_hidden_one_has_no_batch() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Emissive);
        let first = last_changed(&app, volume).expect("a batch");
        move_camera(&mut app, camera);
        assert_eq!(last_changed(&app, volume), Some(first));

        app.world_mut()
            .entity_mut(volume)
            .insert(InheritedVisibility::HIDDEN);
        app.update();
        assert!(app.world().get::<CellBatch>(volume).is_none());
        app.world_mut()
            .entity_mut(volume)
            .insert(InheritedVisibility::VISIBLE);
        app.update();
        assert!(
            app.world().get::<CellBatch>(volume).is_some(),
            "shown again"
        );
    }

    #[test]
    fn a_lod_volume_draws_fewer_cells_from_afar_and_follows_the_eye() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Emissive);
        give_noise_lod(&mut app, volume, 0.0);
        app.update();
        let coarse = app.world().get::<CellBatch>(volume).unwrap().cells.len();
        assert!(coarse > 0 && coarse < 6 * 16 * 16 * 16, "{coarse} cells");

        // An emissive volume at full resolution ignores the eye; with LOD it follows it.
        let before = last_changed(&app, volume);
        move_camera(&mut app, camera);
        assert!(last_changed(&app, volume) > before);

        app.world_mut()
            .get_mut::<VolumeLod>(volume)
            .unwrap()
            .criterion = LodCriterion::distance(f64::INFINITY);
        app.update();
        let fine = app.world().get::<CellBatch>(volume).unwrap().cells.len();
        assert!(
            fine > coarse,
            "{fine} cells at c = ∞ against {coarse} at c = 0"
        );
    }

    #[test]
    fn the_quality_preset_scales_the_octree_accuracy() {
        use nebel_render::{NebelQuality, NebelQualityPlugin, QualityPreset};
        // The distance criterion's c, and the screen error's tolerance, which
        // also needs the LOD camera's projection to get through.
        for criterion in [
            LodCriterion::distance(40.0),
            LodCriterion::screen_error(0.002),
        ] {
            let (mut app, _, volume) = app_with_volume(OpticalMode::Emissive);
            app.add_plugins(NebelQualityPlugin);
            give_noise_lod_by(&mut app, volume, criterion);
            let cells = |app: &mut App, preset| {
                app.world_mut().resource_mut::<NebelQuality>().preset = preset;
                app.update();
                app.update();
                assert_eq!(status(app, volume), VolumeStatus::Ready, "{criterion:?}");
                app.world().get::<CellBatch>(volume).unwrap().cells.len()
            };
            let high = cells(&mut app, QualityPreset::High);
            let medium = cells(&mut app, QualityPreset::Medium);
            let low = cells(&mut app, QualityPreset::Low);
            assert!(
                low < medium && medium < high,
                "{criterion:?}: {low} < {medium} < {high}"
            );
            assert_eq!(cells(&mut app, QualityPreset::High), high);
        }
    }

    #[test]
    fn a_lit_volume_carries_its_density_as_modulator_and_follows_the_sun() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        give_lit_noise(&mut app, volume, VolumeLighting::default());
        app.update();
        let batch = app.world().get::<CellBatch>(volume).unwrap().clone();
        assert!(batch.cells.is_modulated(), "a lit batch is modulated");
        assert_eq!(batch.cells.modulators.len(), batch.cells.len());
        // Isotropic model: the scalar is γ ≥ ambient, the modulator the density.
        assert!(
            batch
                .cells
                .tetrahedra
                .iter()
                .flat_map(|c| c.vertices)
                .all(|v| v[3] >= 0.3 - 1.0 / 255.0)
        );
        let lit_first = last_changed(&app, volume).unwrap();
        app.update();
        assert_eq!(last_changed(&app, volume), Some(lit_first), "nothing moved");

        // A sun appears (straight up before): the light field is recomputed.
        app.world_mut().spawn((
            DirectionalLight::default(),
            Transform::default().looking_to(Vec3::new(1.0, -0.2, 0.0), Vec3::Y),
        ));
        app.update();
        app.update();
        let relit = app.world().get::<CellBatch>(volume).unwrap();
        assert!(last_changed(&app, volume).unwrap() > lit_first);
        assert_ne!(relit.cells, batch.cells, "the light changed with the sun");

        app.world_mut()
            .entity_mut(volume)
            .get_mut::<VolumeLighting>()
            .unwrap()
            .model = crate::CloudLightModel::NonPhysical;
        app.update();
        let swapped = app.world().get::<CellBatch>(volume).unwrap();
        assert!(swapped.cells.is_modulated());
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
        assert!(!scattering.shadows);
        assert!(
            scattered
                .cells
                .tetrahedra
                .iter()
                .flat_map(|c| c.vertices)
                .any(|v| v[3] < 0.3),
            "the transmittance has no ambient floor"
        );
        // The sun's shadow maps on: the batch reads Bevy's map of it.
        let mut suns = app.world_mut().query::<&mut DirectionalLight>();
        suns.single_mut(app.world_mut())
            .unwrap()
            .shadow_maps_enabled = true;
        app.update();
        let shadowed = app.world().get::<CellBatch>(volume).unwrap();
        assert!(shadowed.scattering.is_some_and(|s| s.shadows));
    }

    #[test]
    fn a_lit_grid_without_the_octree_is_ray_cast_with_its_light_field() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        give_lit_noise(&mut app, volume, VolumeLighting::default());
        app.world_mut().entity_mut(volume).remove::<VolumeLod>();
        app.update();
        let batch = app.world().get::<CellBatch>(volume).unwrap();
        let grid = batch.cells.grid.as_ref().expect("a ray-cast grid");
        assert!(batch.cells.is_modulated() && batch.cells.modulators.is_empty());
        // Isotropic model: the scalar is γ ≥ ambient, the modulator the
        // density.
        let modulators = grid.modulators().expect("the density as modulator");
        assert_eq!(modulators.dims(), [9, 9, 9]);
        assert!(
            grid.grid()
                .values()
                .iter()
                .all(|&light| light >= 0.3 - 1e-6)
        );
        assert!(grid.clears_modulators());
        // It needs the octree to be drawn as projected cells.
        app.world_mut().entity_mut(volume).insert(ProjectedCells);
        app.update();
        assert!(matches!(
            app.world().get::<VolumeStatus>(volume),
            Some(VolumeStatus::Failed(_))
        ));
    }

    #[test]
    fn a_windy_cloud_is_drawn_from_keyframes_blended_by_the_clock() {
        let (mut app, _, _) = app_with_volume(OpticalMode::Sorted);
        app.insert_resource(bevy::time::TimeUpdateStrategy::ManualDuration(
            std::time::Duration::from_millis(10),
        ));
        let mut noise = nebel_core::field::CloudNoise {
            wavelength: 4.0,
            wind: DVec3::new(2.0, 0.0, 1.0),
            ..default()
        };
        let cloud = app
            .world_mut()
            .spawn((
                crate::CloudVolume {
                    dims: UVec3::new(9, 5, 9),
                    min: Vec3::ZERO,
                    max: Vec3::new(4.0, 2.0, 4.0),
                    noise,
                    keyframe_interval: 1.0,
                    ..default()
                },
                InheritedVisibility::VISIBLE,
            ))
            .id();
        let mut blends = Vec::new();
        let mut changes = Vec::new();
        for _ in 0..250 {
            app.update();
            let batch = app.world().get::<CellBatch>(cloud);
            if let Some(batch) = batch {
                assert!(batch.cells.is_blended() && batch.cells.is_modulated());
                // The blend drawn: the mix of the batch's two ends.
                let mix = app
                    .world()
                    .get::<nebel_render::CellBlend>(cloud)
                    .unwrap()
                    .factor;
                assert!((0.0..=1.0).contains(&mix), "{mix}");
                let [first, last] = batch.cells.blends;
                assert!(first < last, "{:?}", batch.cells.blends);
                blends.push(first + mix * (last - first));
                changes.push(last_changed(&app, cloud).unwrap());
            }
        }
        assert_eq!(status(&app, cloud), VolumeStatus::Ready);
        assert!(blends.len() >= 240, "{}", blends.len());
        // A hundredth of the interval per frame, starting again at each
        // hand-over: each step's batch, made ahead, takes over as the blend
        // reaches it, so the drawn blend never holds or jumps. The cells are
        // uploaded again where (and only where) the octree is refined for
        // the next step of the blend.
        let hand_overs = blends.windows(2).filter(|w| w[1] < w[0]).count();
        assert!(hand_overs >= 2, "{blends:?}");
        assert!(
            blends
                .windows(2)
                .all(|w| w[1] < w[0] || (w[1] - w[0] - 0.01).abs() < 1e-4),
            "{blends:?}"
        );
        let steps = nebel_lod::octree::keyframe::REFINEMENT_STEPS as f32;
        let step = |blend: f32| (blend * steps).floor();
        for (frame, (blend, change)) in blends.windows(2).zip(changes.windows(2)).enumerate() {
            let refined = step(blend[1]) != step(blend[0]);
            assert_eq!(change[1] != change[0], refined, "frame {frame}: {blend:?}");
        }

        // Calm: one grid, no keyframes, no blend.
        noise.wind = DVec3::ZERO;
        app.world_mut()
            .get_mut::<crate::CloudVolume>(cloud)
            .unwrap()
            .noise = noise;
        app.update();
        app.update();
        let batch = app.world().get::<CellBatch>(cloud).unwrap();
        assert!(!batch.cells.is_blended());
        assert!(app.world().get::<nebel_render::CellBlend>(cloud).is_none());
    }

    #[test]
    fn a_moving_sun_lights_a_grid_through_keyframes_until_it_rests() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        app.insert_resource(bevy::time::TimeUpdateStrategy::ManualDuration(
            std::time::Duration::from_millis(100),
        ));
        let lighting = VolumeLighting {
            keyframe_interval: 0.5,
            ..default()
        };
        give_lit_noise(&mut app, volume, lighting);
        let sun = app
            .world_mut()
            .spawn((
                DirectionalLight::default(),
                Transform::default().looking_to(Vec3::new(1.0, -0.5, 0.0), Vec3::Y),
            ))
            .id();
        let blended = |app: &App| {
            let batch = app.world().get::<CellBatch>(volume).unwrap();
            let blend = app.world().get::<nebel_render::CellBlend>(volume);
            (batch.cells.is_blended(), blend.map(|blend| blend.factor))
        };
        app.update();
        app.update();
        assert_eq!(blended(&app), (false, None), "a still sun: one build");
        // A day cycle: 5° per frame about the north-south axis.
        let mut factors = Vec::new();
        for _ in 0..20 {
            app.world_mut()
                .get_mut::<Transform>(sun)
                .unwrap()
                .rotate_x(5f32.to_radians());
            app.update();
            if let (true, Some(factor)) = blended(&app) {
                factors.push(factor);
            }
        }
        assert!(factors.len() >= 15, "{factors:?}");
        assert!(
            factors.windows(2).any(|w| w[1] < w[0]),
            "hand-overs: {factors:?}"
        );
        // The sun rests: after two intervals one build for where it stopped.
        for _ in 0..15 {
            app.update();
        }
        assert_eq!(blended(&app), (false, None));
        assert_eq!(status(&app, volume), VolumeStatus::Ready);
    }

    #[test]
    fn a_batch_follows_the_camera_in_the_same_frame() {
        let (mut app, camera, volume) = app_with_volume(OpticalMode::Sorted);
        app.world_mut()
            .entity_mut(volume)
            .insert(VolumeLod::default());
        app.update();
        let before = last_changed(&app, volume);
        let mut transform = app.world_mut().get_mut::<Transform>(camera).unwrap();
        transform.translation.x += 1.0;
        // One frame: the batch is rebuilt for the eye that frame is drawn from.
        app.update();
        assert!(last_changed(&app, volume) > before);
    }

    #[test]
    fn a_transparent_grid_draws_nothing() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        let empty = DensityGrid::new([2, 2, 2], DVec3::ONE, DVec3::ZERO, vec![0.0; 8]).unwrap();
        let field = grid_field(&mut app, empty);
        app.world_mut().get_mut::<Volume>(volume).unwrap().field = field;
        app.update();
        let batch = app.world().get::<CellBatch>(volume).unwrap();
        assert!(batch.cells.is_empty() && !batch.is_drawable());
    }

    #[test]
    fn a_failure_is_kept_logged_once_and_not_rebuilt_until_the_volume_changes() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        // C ≤ √3 cannot build an octree.
        app.world_mut().entity_mut(volume).insert(VolumeLod {
            criterion: LodCriterion::distance(16.0),
            min_accuracy: 1.0,
        });
        app.update();
        let VolumeStatus::Failed(error) = status(&app, volume) else {
            panic!("expected a failure, got {:?}", status(&app, volume));
        };
        assert!(error.to_string().contains("√3"), "{error}");
        assert!(app.world().get::<CellBatch>(volume).is_none(), "no batch");
        // No rebuild while nothing changes: no build is in flight.
        app.update();
        let batching = app.world().get::<VolumeBatching>(volume).unwrap();
        assert!(batching.is_idle());
        app.world_mut()
            .get_mut::<VolumeLod>(volume)
            .unwrap()
            .min_accuracy = 4.0;
        app.update();
        assert_eq!(status(&app, volume), VolumeStatus::Ready);
        assert!(app.world().get::<CellBatch>(volume).is_some());
    }

    #[test]
    fn a_campfire_appears_under_background_builds_although_its_grid_changes_every_frame() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Emissive);
        app.insert_resource(HeavyBuilds::Background);
        app.world_mut().despawn(volume);
        let fire = app
            .world_mut()
            .spawn((crate::Campfire::default(), InheritedVisibility::VISIBLE))
            .id();
        for _ in 0..2000 {
            app.update();
            if app
                .world()
                .get::<CellBatch>(fire)
                .is_some_and(|batch| !batch.cells.is_empty())
            {
                assert_eq!(status(&app, fire), VolumeStatus::Ready);
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        panic!("the fire never appeared: its builds were dropped");
    }

    #[test]
    fn a_campfire_draws_its_frames_grid_when_blocking_and_the_last_frames_in_the_background() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Emissive);
        app.world_mut().despawn(volume);
        let campfire = crate::Campfire {
            seed: 5,
            dims: [9, 13, 9],
        };
        let fire = app
            .world_mut()
            .spawn((campfire, InheritedVisibility::VISIBLE))
            .id();
        let now = |app: &App| app.world().resource::<Time>().elapsed_secs_f64();
        for _ in 0..3 {
            std::thread::sleep(std::time::Duration::from_millis(2));
            app.update();
            let grid = volume_grid(&app, fire).expect("a grid every frame");
            assert_eq!(
                *grid,
                campfire_density(campfire.dims, now(&app), campfire.seed)
            );
        }
        // In the background each new grid is one started in this frame or
        // an earlier one (a small build may finish before the frame polls
        // it), and they keep coming.
        app.insert_resource(HeavyBuilds::Background);
        let mut times = vec![now(&app)];
        let mut last = volume_grid(&app, fire);
        let mut new_grids = 0;
        for _ in 0..2000 {
            std::thread::sleep(std::time::Duration::from_millis(1));
            app.update();
            times.push(now(&app));
            let grid = volume_grid(&app, fire);
            if grid != last {
                let grid = grid.as_deref().unwrap();
                assert!(
                    times
                        .iter()
                        .any(|at| *grid == campfire_density(campfire.dims, *at, campfire.seed)),
                    "a grid of an earlier frame's time"
                );
                new_grids += 1;
                if new_grids == 4 {
                    return;
                }
            }
            last = grid;
        }
        panic!("only {new_grids} new grids in the background");
    }

    #[test]
    fn a_new_mode_or_scattering_reaches_the_batch_without_a_rebuild_of_the_cells() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Emissive);
        app.world_mut().get_mut::<Volume>(volume).unwrap().mode = OpticalMode::Mip;
        app.update();
        let batch = app.world().get::<CellBatch>(volume).unwrap();
        assert_eq!(batch.mode, OpticalMode::Mip);
    }

    #[test]
    fn an_update_failure_clears_when_its_input_is_restored() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        // A flat volume: its transform cannot be inverted.
        app.world_mut()
            .entity_mut(volume)
            .insert(Transform::from_scale(Vec3::new(1.0, 0.0, 1.0)));
        app.update();
        assert!(matches!(status(&app, volume), VolumeStatus::Failed(_)));
        app.world_mut()
            .entity_mut(volume)
            .insert(Transform::IDENTITY);
        app.update();
        assert_eq!(status(&app, volume), VolumeStatus::Ready);
        assert!(app.world().get::<CellBatch>(volume).is_some());
    }

    #[test]
    fn a_background_build_appears_when_ready() {
        let (mut app, _, volume) = app_with_volume(OpticalMode::Sorted);
        app.insert_resource(HeavyBuilds::Background);
        let noise = nebel_core::field::ProceduralNoise::default();
        let grid =
            DensityGrid::procedural([33, 33, 33], DVec3::splat(0.1), DVec3::ZERO, &noise).unwrap();
        let field = grid_field(&mut app, grid);
        app.world_mut().get_mut::<Volume>(volume).unwrap().field = field;
        app.world_mut()
            .entity_mut(volume)
            .insert(VolumeLighting::default());
        let old = app.world().get::<CellBatch>(volume).unwrap().cells.len();
        for _ in 0..2000 {
            app.update();
            let cells = app.world().get::<CellBatch>(volume).unwrap().cells.len();
            if cells != old {
                assert!(
                    app.world()
                        .get::<CellBatch>(volume)
                        .unwrap()
                        .cells
                        .is_modulated()
                );
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        panic!("the lit 33³ volume never appeared");
    }
}
