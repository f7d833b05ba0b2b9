//! The terrain's per-frame systems: refine the quadtree for the camera when
//! the view changed enough, copy the result into the entity's Bevy mesh, and
//! measure (the quadtree itself is built in [`crate::build`]).
//!
//! # When the mesh is rebuilt
//!
//! The mesh is refined for the eye of the camera that drives the level of
//! detail ([`nebel_render::LodCamera`], or the active 3D camera of lowest
//! order), in the terrain's local frame, in [`PostUpdate`] after transform
//! propagation and the camera's projection update, so it matches the frame
//! being drawn, by [`nebel_lod::quadtree::TerrainRefiner`] (no Bevy): it
//! refines again only when the terrain changed (accuracy or pixel error — the
//! accuracy a pixel error gives changes with the camera's projection and
//! viewport —, morphing, material,
//! debug view, a new quadtree) or the view changed enough (the eye moved more
//! than `δ = update_distance · spacing`, the camera turned by more than
//! `view_margin_degrees`, the projection or the terrain's transform
//! changed), and culls with a frustum widened by both so the mesh stays valid
//! in between; its docs give the bound this keeps. A still camera costs
//! nothing.
//!
//! The refinement and the Bevy mesh it gives run on the
//! [`AsyncComputeTaskPool`](bevy::tasks::AsyncComputeTaskPool), one per
//! terrain at a time; the frame keeps drawing the last mesh and takes the new
//! one in the first frame after it is done (the same frame under
//! [`HeavyBuilds::Blocking`]). A mesh is then drawn for views up to δ plus
//! what the view changes during two refinements away from the one it was
//! refined for, so the culling frustum is widened by twice what the view
//! moved and turned during the last refinement
//! ([`RefinerSettings::latency`](nebel_lod::quadtree::RefinerSettings)): no
//! gap opens at the edges of the view along a steady flight. The unit test of a flight toward a 129² terrain (`c` = 40,
//! 8.5 m per rebuild) measures surface steps of at most 0.5 m with morphing
//! against 18 m without.
//!
//! # Failures
//!
//! Unusable input (a height map that failed to load, too small or too
//! large, NaN or infinite heights, a bad spacing, vertical scale, `c`,
//! pixel error or `C`, a pixel error through an orthographic camera) sets [`TerrainStatus::Failed`] with the reason
//! ([`TerrainBuildError`](crate::TerrainBuildError)), logs it once per entity
//! as an error and leaves the entity without a mesh; nothing panics.
//! Changing the terrain or its height asset tries again.
//!
//! # Diagnostics
//!
//! The `nebel/terrain/*` diagnostics of [`TerrainPlugin`]:
//! `terrains`, `triangles` and `vertices` (of the level of detail, all
//! terrains), `updates` (mesh rebuilds so far), `update_ms` (each frame that
//! rebuilt a mesh: refinement, morphing, triangle output and the copy into
//! the Bevy mesh), `refine_ms` (the part of it `TerrainHierarchy::update`
//! took), `build_ms` (each quadtree build), `points` (grid points of all
//! quadtrees) and `bytes_per_point`. Per terrain the same figures are in
//! [`TerrainLodStats`]. A world without a terrain measures none of them.

use std::sync::Arc;
use std::time::Instant;

use bevy::camera::visibility::NoAutoAabb;
use bevy::diagnostic::Diagnostics;
use bevy::ecs::system::SystemParam;
use bevy::prelude::*;
use nebel_lod::TerrainError;
use nebel_lod::quadtree::{
    LodSettings, LodStats, RefinerSettings, TerrainHierarchy, TerrainMap, TerrainRefiner,
    TerrainView, TriangleOrder, accuracy_for_pixel_error,
};
use nebel_render::camera::{to_double, to_double_affine};
use nebel_render::{
    EffectiveQuality, HeavyBuild, HeavyBuilds, LodCameras, LodView, free_in_background,
};

use crate::build::{TerrainLod, bounds};
use crate::map::TerrainMapLod;
use crate::shading::{Colouring, Palette, default_material, empty_mesh, write_mesh};
use crate::terrain::{Terrain, TerrainLodStats, TerrainMaterial, TerrainPlugin, TerrainStatus};

/// The meshes and materials the terrain systems write.
#[derive(SystemParam)]
pub(crate) struct TerrainAssets<'w, 's> {
    meshes: ResMut<'w, Assets<Mesh>>,
    materials: ResMut<'w, Assets<StandardMaterial>>,
    default_material: Local<'s, Option<Handle<StandardMaterial>>>,
}

impl TerrainAssets<'_, '_> {
    /// The `StandardMaterial` the terrain inserts for `material`: the
    /// default one (made on first use) or the user's; `None` for the
    /// entity's own.
    fn material(&mut self, material: &TerrainMaterial) -> Option<Handle<StandardMaterial>> {
        match material {
            TerrainMaterial::HeightAndSlope => {
                let materials = &mut self.materials;
                Some(
                    self.default_material
                        .get_or_insert_with(|| materials.add(default_material()))
                        .clone(),
                )
            }
            TerrainMaterial::Standard(handle) => Some(handle.clone()),
            TerrainMaterial::Own => None,
        }
    }
}

/// The refinement settings of `terrain` seen by `camera` through a
/// quadtree of minimum resolution `min_resolution`, carrying a map or not,
/// its accuracy (given, or derived from its pixel error for the camera's
/// projection and viewport) scaled by the quality's factor.
fn refiner_settings(
    terrain: &Terrain,
    map: Option<&TerrainMapLod>,
    accuracy_scale: f64,
    camera: &LodView,
    min_resolution: f32,
    latency: (f64, f64),
) -> Result<RefinerSettings, TerrainError> {
    let accuracy = match terrain.pixel_error {
        Some(pixel_error) => accuracy_for_pixel_error(
            f64::from(pixel_error),
            to_double(camera.clip_from_view),
            camera.viewport.to_array(),
            min_resolution,
        )?,
        None => f64::from(terrain.accuracy),
    };
    Ok(RefinerSettings {
        lod: LodSettings {
            accuracy: (accuracy * accuracy_scale) as f32,
            morph: terrain.morph,
            normals: true,
            // The map's cells need each vertex's grid point.
            grid_points: terrain.debug.lod_colours || map.is_some(),
            // Opaque: nearest first lets the depth test reject more.
            order: TriangleOrder::FrontToBack,
        },
        update_distance: f64::from(
            map.and_then(|map| map.max_update_distance)
                .map_or(terrain.update_distance, |most| {
                    terrain.update_distance.min(most)
                })
                * terrain.spacing,
        ),
        view_margin: f64::from(terrain.view_margin_degrees).to_radians(),
        latency,
    })
}

/// A refinement done on a worker: the refiner with its new mesh, the Bevy
/// mesh written from it (`None`: nothing in view) and its timings.
pub(crate) struct Refined {
    refiner: TerrainRefiner,
    /// The quadtree refined (the terrain's own or its mapped one).
    hierarchy: Arc<TerrainHierarchy>,
    /// The view refined for.
    view: TerrainView,
    result: Result<(LodStats, Option<Mesh>), TerrainError>,
    refine_ms: f32,
    update_ms: f32,
}

/// What a refinement needs, moved to the worker that runs it.
struct Refinement {
    refiner: TerrainRefiner,
    hierarchy: Arc<TerrainHierarchy>,
    map: Option<Arc<TerrainMap>>,
    view: TerrainView,
    settings: RefinerSettings,
    /// The heights' rectangle, for the UVs.
    extent: Vec2,
    /// The default material's palette is used (no material of the user's).
    palette: bool,
    debug: crate::TerrainDebug,
}

impl Refinement {
    /// Refines and writes the Bevy mesh (see the module docs).
    fn run(mut self) -> Refined {
        let started = Instant::now();
        let refined = self.refiner.update(
            &self.hierarchy,
            self.map.as_deref(),
            &self.view,
            &self.settings,
            true,
        );
        let refine_ms = started.elapsed().as_secs_f32() * 1e3;
        let result = refined.map(|stats| {
            let stats = stats.expect("a forced refinement");
            let lod = self.refiner.mesh();
            let mesh = (!lod.indices.is_empty()).then(|| {
                let palette = Palette::default();
                let colouring = Colouring {
                    palette: self
                        .palette
                        .then_some((&palette, self.hierarchy.height_range())),
                    debug: self.debug,
                    levels: self.hierarchy.levels(),
                };
                let mut mesh = empty_mesh();
                write_mesh(
                    &mut mesh,
                    lod,
                    self.hierarchy.origin().as_vec3(),
                    self.extent,
                    &colouring,
                );
                mesh
            });
            (stats, mesh)
        });
        Refined {
            refiner: self.refiner,
            hierarchy: self.hierarchy,
            view: self.view,
            result,
            refine_ms,
            update_ms: started.elapsed().as_secs_f32() * 1e3,
        }
    }
}

/// Refines every visible terrain with a quadtree for the LOD camera when
/// the view changed enough, on a worker, and writes its mesh when the
/// refinement is done (see the module docs).
pub(crate) fn update_terrain_meshes(
    mut commands: Commands,
    cameras: LodCameras,
    mut terrains: Query<(
        Entity,
        Ref<Terrain>,
        &GlobalTransform,
        &InheritedVisibility,
        &mut TerrainStatus,
        &mut TerrainLodStats,
        &mut TerrainLod,
        Option<Ref<TerrainMapLod>>,
    )>,
    mut assets: TerrainAssets,
    quality: Option<Res<EffectiveQuality>>,
    mode: Res<HeavyBuilds>,
    mut diagnostics: Diagnostics,
) {
    let Some(camera) = cameras.view() else {
        return;
    };
    let (accuracy_scale, quality_changed) = quality.as_ref().map_or((1.0, false), |quality| {
        (quality.terrain_accuracy_scale(), quality.is_changed())
    });
    let (mut frame_update_ms, mut frame_refine_ms) = (None, None);
    for (entity, terrain, transform, visibility, mut status, mut stats, mut state, map) in
        &mut terrains
    {
        let state = &mut *state;
        let Some(own) = state.hierarchy.clone() else {
            continue;
        };
        if terrain.is_changed() && state.mesh.is_some() {
            match assets.material(&terrain.material) {
                Some(material) => {
                    commands
                        .entity(entity)
                        .insert(MeshMaterial3d(material.clone()));
                    state.material_inserted = Some(material);
                }
                None => state.remove_material(&mut commands, entity),
            }
        }
        // Hidden: nothing is refined, and a map that changed meanwhile is
        // still new when the terrain shows again.
        if !visibility.get() {
            continue;
        }
        // A map derived from this quadtree replaces it (see crate::map).
        let mapped = map.as_ref().and_then(|map| {
            map.quadtree
                .as_ref()
                .filter(|mapped| Arc::ptr_eq(&mapped.base, &own))
        });
        let hierarchy = mapped.map_or_else(|| own.clone(), |mapped| mapped.hierarchy.clone());
        let map_changed = match (mapped, &state.mapped) {
            (Some(mapped), Some(used)) => !Arc::ptr_eq(&mapped.hierarchy, used),
            (None, None) => false,
            _ => true,
        };
        if map_changed {
            state.mapped = mapped.map(|mapped| mapped.hierarchy.clone());
        }
        state.stale |= terrain.is_changed()
            || quality_changed
            || map_changed
            || map.as_ref().is_some_and(Ref::is_changed);
        let view = camera.seen_from(to_double_affine(transform));
        let settings = match refiner_settings(
            &terrain,
            mapped.and(map.as_deref()),
            accuracy_scale,
            &camera,
            hierarchy.min_resolution(),
            state.latency,
        ) {
            Ok(settings) => settings,
            Err(error) => {
                state.refining = None;
                failed(&mut commands, entity, &mut status, state, error);
                continue;
            }
        };
        if state.refining.is_none() && (state.stale || !state.refiner.is_current(&view, &settings))
        {
            state.stale = false;
            let refinement = Refinement {
                refiner: state.refiner.clone(),
                hierarchy: hierarchy.clone(),
                map: mapped.map(|mapped| mapped.map.clone()),
                view,
                settings,
                extent: state.extent,
                palette: terrain.material == TerrainMaterial::HeightAndSlope,
                debug: terrain.debug,
            };
            state.refining = Some(HeavyBuild::spawn(move || refinement.run()));
        }
        let Some(refined) = state.refining.as_mut().and_then(|build| build.poll(*mode)) else {
            continue;
        };
        state.refining = None;
        if !Arc::ptr_eq(&refined.hierarchy, &hierarchy) {
            // Refined for a quadtree replaced meanwhile.
            state.stale = true;
            continue;
        }
        state.refiner = refined.refiner;
        // The next mesh is drawn from its landing until the one after it
        // lands: about twice what the view changed during this refinement.
        let (moved, turned) = view.change_since(&refined.view);
        state.latency = (2.0 * moved, 2.0 * turned);
        let (lod_stats, mesh) = match refined.result {
            Ok(done) => done,
            Err(error) => {
                failed(&mut commands, entity, &mut status, state, error);
                continue;
            }
        };
        *status = TerrainStatus::Ready;
        match (mesh, &state.mesh) {
            // Nothing of the terrain in view: no mesh at all rather than an
            // empty one (Bevy's mesh allocator refuses empty meshes); a new
            // one is made when the terrain comes back into view.
            (None, _) => state.remove_mesh(&mut commands, entity),
            (Some(mesh), Some(handle)) => {
                if let Some(mut drawn) = assets.meshes.get_mut(handle) {
                    free_in_background(std::mem::replace(&mut *drawn, mesh));
                }
            }
            (Some(mesh), None) => {
                let handle = assets.meshes.add(mesh);
                let mut entity = commands.entity(entity);
                entity.insert((Mesh3d(handle.clone()), bounds(&hierarchy), NoAutoAabb));
                if let Some(material) = assets.material(&terrain.material) {
                    entity.insert(MeshMaterial3d(material.clone()));
                    state.material_inserted = Some(material);
                }
                state.mesh = Some(handle);
            }
        }
        *stats = TerrainLodStats {
            updates: stats.updates + 1,
            update_ms: refined.update_ms,
            refine_ms: refined.refine_ms,
            triangles: lod_stats.triangles as u32,
            vertices: lod_stats.vertices as u32,
            deepest_level: lod_stats.deepest_level,
            culled_nodes: lod_stats.culled as u32,
            ..*stats
        };
        *frame_update_ms.get_or_insert(0.0) += f64::from(refined.update_ms);
        *frame_refine_ms.get_or_insert(0.0) += f64::from(refined.refine_ms);
    }
    if let Some(ms) = frame_update_ms {
        diagnostics.add_measurement(&TerrainPlugin::UPDATE_MS, || ms);
    }
    if let Some(ms) = frame_refine_ms {
        diagnostics.add_measurement(&TerrainPlugin::REFINE_MS, || ms);
    }
}

/// A refinement failed: the status with the reason, logged once, and no
/// mesh. The quadtree stays; a new setting or view may fix it.
fn failed(
    commands: &mut Commands,
    entity: Entity,
    status: &mut TerrainStatus,
    state: &mut TerrainLod,
    error: TerrainError,
) {
    let error = crate::TerrainBuildError::from(error);
    TerrainStatus::fail(&mut *status, "terrain", entity, error);
    // Refined again when the view or a setting changes.
    state.refiner = TerrainRefiner::new();
    state.remove_mesh(commands, entity);
}

/// Measures the terrains' totals (see the module docs); nothing in a world
/// without a terrain.
pub(crate) fn measure_terrains(terrains: Query<&TerrainLodStats>, mut diagnostics: Diagnostics) {
    if terrains.is_empty() {
        return;
    }
    let (mut triangles, mut vertices, mut updates, mut points, mut bytes) = (0, 0, 0, 0.0, 0.0);
    for stats in &terrains {
        triangles += u64::from(stats.triangles);
        vertices += u64::from(stats.vertices);
        updates += stats.updates;
        let n = f64::from(stats.points_per_side).powi(2);
        points += n;
        bytes += n * f64::from(stats.bytes_per_point);
    }
    let terrain_count = terrains.iter().len() as f64;
    diagnostics.add_measurement(&TerrainPlugin::TERRAINS, || terrain_count);
    diagnostics.add_measurement(&TerrainPlugin::TRIANGLES, || triangles as f64);
    diagnostics.add_measurement(&TerrainPlugin::VERTICES, || vertices as f64);
    diagnostics.add_measurement(&TerrainPlugin::UPDATES, || updates as f64);
    diagnostics.add_measurement(&TerrainPlugin::POINTS, || points);
    if points > 0.0 {
        diagnostics.add_measurement(&TerrainPlugin::BYTES_PER_POINT, || bytes / points);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::TerrainSource;
    use crate::build::BuildInput;
    use crate::{TerrainDebug, TerrainPlugin};
    use bevy::diagnostic::DiagnosticsStore;
    use bevy::mesh::VertexAttributeValues;
    use nebel_core::field::TerrainNoise;
    use nebel_lod::TerrainMesh;
    use nebel_render::GrayscaleMap;
    use nebel_render::HeavyBuilds;
    use nebel_render::headless::{computed_camera, headless_app, spawn_computed_camera};
    use std::path::PathBuf;

    /// A folder of its own per test for the asset server's files.
    fn asset_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("nebel-terrain-{name}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// An app with the terrain plugin, assets read from `dir`, and a camera
    /// (what Bevy's camera systems compute for a 64 × 64 target) at `eye`
    /// looking at the origin.
    fn app(dir: &std::path::Path, eye: Vec3) -> (App, Entity) {
        app_looking_at(dir, eye, Vec3::ZERO)
    }

    fn app_looking_at(dir: &std::path::Path, eye: Vec3, target: Vec3) -> (App, Entity) {
        // Every build lands in the frame that starts it, so the tests count
        // frames; `a_background_build_appears_when_ready` covers the default.
        let mut app = headless_app(Some(dir));
        app.init_asset::<Mesh>()
            .init_asset::<StandardMaterial>()
            .add_plugins(TerrainPlugin);
        let transform = Transform::from_translation(eye).looking_at(target, Vec3::Y);
        let camera = spawn_computed_camera(app.world_mut(), 1.0, UVec2::splat(64), transform);
        (app, camera)
    }

    fn procedural(size: u32) -> Terrain {
        Terrain {
            source: TerrainSource::Procedural {
                size,
                noise: TerrainNoise {
                    wavelength: 200.0,
                    ..default()
                },
            },
            spacing: 10.0,
            vertical_scale: 100.0,
            ..default()
        }
    }

    fn spawn(app: &mut App, terrain: Terrain, transform: Transform) -> Entity {
        // What Bevy's visibility propagation computes for a shown entity.
        app.world_mut()
            .spawn((terrain, transform, InheritedVisibility::VISIBLE))
            .id()
    }

    fn stats(app: &App, terrain: Entity) -> TerrainLodStats {
        *app.world().get::<TerrainLodStats>(terrain).unwrap()
    }

    fn status(app: &App, terrain: Entity) -> TerrainStatus {
        app.world().get::<TerrainStatus>(terrain).unwrap().clone()
    }

    fn positions(app: &App, terrain: Entity) -> Vec<[f32; 3]> {
        let handle = &app.world().get::<Mesh3d>(terrain).expect("a mesh").0;
        let mesh = app.world().resource::<Assets<Mesh>>().get(handle).unwrap();
        match mesh.attribute(Mesh::ATTRIBUTE_POSITION) {
            Some(VertexAttributeValues::Float32x3(p)) => p.clone(),
            _ => panic!("positions"),
        }
    }

    fn move_camera(app: &mut App, camera: Entity, by: Vec3) {
        app.world_mut()
            .get_mut::<Transform>(camera)
            .unwrap()
            .translation += by;
        app.update();
    }

    /// Runs frames until the terrain leaves `Pending` (asset loads are
    /// asynchronous).
    fn settle(app: &mut App, terrain: Entity) -> TerrainStatus {
        for _ in 0..1000 {
            app.update();
            let status = status(app, terrain);
            if status != TerrainStatus::Pending {
                return status;
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        panic!("the terrain stayed pending");
    }

    #[test]
    fn a_terrain_wholly_out_of_view_has_no_mesh_until_it_comes_back() {
        // Bevy's mesh allocator refuses empty meshes: a terrain the frustum
        // culls entirely must not hand it one.
        let dir = asset_dir("out-of-view");
        let (mut app, camera) = app(&dir, Vec3::new(0.0, 300.0, 600.0));
        let terrain = spawn(&mut app, procedural(65), Transform::default());
        for _ in 0..3 {
            app.update();
        }
        assert!(!positions(&app, terrain).is_empty());
        // Looking straight up, away from the terrain.
        *app.world_mut().get_mut::<Transform>(camera).unwrap() =
            Transform::from_xyz(0.0, 300.0, 600.0).looking_to(Vec3::Y, Vec3::Z);
        for _ in 0..3 {
            app.update();
        }
        assert!(
            app.world().get::<Mesh3d>(terrain).is_none(),
            "an empty mesh"
        );
        assert_eq!(
            app.world()
                .get::<TerrainLodStats>(terrain)
                .unwrap()
                .triangles,
            0
        );
        let empty = app
            .world()
            .resource::<Assets<Mesh>>()
            .iter()
            .filter(|(_, mesh)| mesh.count_vertices() == 0)
            .count();
        assert_eq!(empty, 0, "an empty mesh asset");
        // Looking back down: a mesh again.
        *app.world_mut().get_mut::<Transform>(camera).unwrap() =
            Transform::from_xyz(0.0, 300.0, 600.0).looking_at(Vec3::ZERO, Vec3::Y);
        for _ in 0..3 {
            app.update();
        }
        assert!(!positions(&app, terrain).is_empty());
    }

    #[test]
    fn a_mesh_appears_and_is_rebuilt_only_when_the_view_changed_enough() {
        let (mut app, camera) = app(&asset_dir("rebuild"), Vec3::new(0.0, 200.0, 300.0));
        let coarse = Terrain {
            accuracy: 5.0,
            ..procedural(33)
        };
        let terrain = spawn(&mut app, coarse, Transform::default());
        app.update();
        assert_eq!(status(&app, terrain), TerrainStatus::Ready);
        let first = stats(&app, terrain);
        assert_eq!(first.updates, 1);
        assert_eq!(first.points_per_side, 33);
        assert!(first.triangles > 0 && first.vertices > 0, "{first:?}");
        assert_eq!(positions(&app, terrain).len(), first.vertices as usize);
        let measured = |path| {
            app.world()
                .resource::<DiagnosticsStore>()
                .get_measurement(&path)
                .map(|m| m.value)
        };
        assert_eq!(
            measured(TerrainPlugin::TRIANGLES),
            Some(f64::from(first.triangles))
        );
        assert_eq!(measured(TerrainPlugin::TERRAINS), Some(1.0));
        assert!(measured(TerrainPlugin::UPDATE_MS).unwrap() >= 0.0);
        assert!(measured(TerrainPlugin::BUILD_MS).unwrap() >= 0.0);

        app.update();
        assert_eq!(stats(&app, terrain).updates, 1, "nothing moved");
        // δ = 0.25 · 10 m: 2 m is not enough, 2 + 1 m is.
        move_camera(&mut app, camera, Vec3::new(2.0, 0.0, 0.0));
        assert_eq!(stats(&app, terrain).updates, 1, "moved 2 m < δ");
        move_camera(&mut app, camera, Vec3::new(0.0, 0.0, -2.0));
        assert_eq!(stats(&app, terrain).updates, 2, "moved 2.8 m > δ");

        // Turning: 1° stays within the 3° margin, 4° does not.
        let turn = |app: &mut App, degrees: f32| {
            app.world_mut()
                .get_mut::<Transform>(camera)
                .unwrap()
                .rotate_y(degrees.to_radians());
            app.update();
        };
        turn(&mut app, 1.0);
        assert_eq!(stats(&app, terrain).updates, 2);
        turn(&mut app, 3.0);
        assert_eq!(stats(&app, terrain).updates, 3);

        // A setting: rebuilt; a finer c draws more triangles.
        let before = stats(&app, terrain).triangles;
        app.world_mut()
            .get_mut::<Terrain>(terrain)
            .unwrap()
            .accuracy = 3000.0;
        app.update();
        let after = stats(&app, terrain);
        assert_eq!(after.updates, 4);
        assert!(after.triangles > before, "{} <= {before}", after.triangles);
    }

    #[test]
    fn a_pixel_error_refines_for_the_viewport_and_bad_ones_fail() {
        let (mut app, camera) = app(&asset_dir("pixel-error"), Vec3::new(0.0, 200.0, 300.0));
        let terrain = spawn(
            &mut app,
            Terrain {
                pixel_error: Some(2.0),
                ..procedural(65)
            },
            Transform::default(),
        );
        app.update();
        assert_eq!(status(&app, terrain), TerrainStatus::Ready);
        let small = stats(&app, terrain);
        app.update();
        assert_eq!(
            stats(&app, terrain).updates,
            small.updates,
            "nothing changed"
        );
        // Four times the pixels each way: the same tolerance needs a finer mesh.
        app.world_mut().entity_mut(camera).insert(computed_camera(
            Mat4::perspective_infinite_reverse_rh(1.0, 1.0, 0.1),
            UVec2::splat(256),
        ));
        app.update();
        let large = stats(&app, terrain);
        assert_eq!(large.updates, small.updates + 1, "a new viewport");
        assert!(large.triangles > small.triangles, "{large:?} vs {small:?}");
        for bad in [0.0, f32::NAN, -1.0] {
            app.world_mut()
                .get_mut::<Terrain>(terrain)
                .unwrap()
                .pixel_error = Some(bad);
            app.update();
            assert!(
                matches!(status(&app, terrain), TerrainStatus::Failed(_)),
                "pixel error {bad}"
            );
            assert!(app.world().get::<Mesh3d>(terrain).is_none());
        }
    }

    #[test]
    fn the_mesh_is_the_lod_of_the_eye_in_the_terrains_frame_100_km_out() {
        let far = Vec3::new(100_000.0, 50.0, -100_000.0);
        let eye = Vec3::new(40.0, 1500.0, 60.0);
        let (mut app, _) = app_looking_at(&asset_dir("frame"), far + eye, far);
        let terrain = spawn(&mut app, procedural(65), Transform::from_translation(far));
        app.update();
        let stats = stats(&app, terrain);
        assert_eq!(stats.culled_nodes, 0, "the whole terrain is in view");
        let mesh = positions(&app, terrain);

        let hierarchy = crate::build::build_quadtree(BuildInput::of(&procedural(65)))
            .unwrap()
            .hierarchy;
        let mut expected = TerrainMesh::new();
        let eye = eye.as_dvec3();
        let settings = LodSettings {
            order: TriangleOrder::FrontToBack,
            ..default()
        };
        hierarchy
            .update(eye, None, &settings, &mut expected)
            .unwrap();
        assert_eq!(mesh.len(), expected.positions.len());
        let origin = hierarchy.origin().as_vec3();
        assert_eq!(
            origin,
            Vec3::new(-320.0, 0.0, -320.0),
            "centred on the entity"
        );
        for (got, want) in mesh.iter().zip(&expected.positions) {
            let want = Vec3::from(*want) + origin;
            assert!(
                Vec3::from(*got).distance(want) < 1e-3,
                "{got:?} != {want:?}"
            );
        }
    }

    fn indices(app: &App, terrain: Entity) -> Vec<u32> {
        let handle = &app.world().get::<Mesh3d>(terrain).expect("a mesh").0;
        let mesh = app.world().resource::<Assets<Mesh>>().get(handle).unwrap();
        mesh.indices().unwrap().iter().map(|i| i as u32).collect()
    }

    /// The height of the drawn surface at every grid point (spacing 10)
    /// the mesh covers, by barycentric interpolation in its triangles.
    fn surface(app: &App, terrain: Entity) -> std::collections::HashMap<[i32; 2], f32> {
        let positions = positions(app, terrain);
        let mut heights = std::collections::HashMap::new();
        for triangle in indices(app, terrain).chunks_exact(3) {
            let [a, b, c] = [0, 1, 2].map(|k| Vec3::from(positions[triangle[k] as usize]));
            let lo = a.min(b).min(c) / 10.0;
            let hi = a.max(b).max(c) / 10.0;
            for i in lo.x.round() as i32..=hi.x.round() as i32 {
                for j in lo.z.round() as i32..=hi.z.round() as i32 {
                    let p = Vec2::new(i as f32, j as f32) * 10.0;
                    let (a2, b2, c2) = (a.xz(), b.xz(), c.xz());
                    let area = (b2 - a2).perp_dot(c2 - a2);
                    let wa = (b2 - p).perp_dot(c2 - p) / area;
                    let wb = (c2 - p).perp_dot(a2 - p) / area;
                    let wc = 1.0 - wa - wb;
                    if wa >= -1e-4 && wb >= -1e-4 && wc >= -1e-4 {
                        heights.insert([i, j], wa * a.y + wb * b.y + wc * c.y);
                    }
                }
            }
        }
        heights
    }

    /// The largest change of the drawn surface at a grid point between
    /// consecutive meshes along a flight toward the terrain.
    fn largest_step(morph: bool) -> f32 {
        let (mut app, camera) = app(&asset_dir("morph"), Vec3::new(-900.0, 400.0, 0.0));
        let terrain = spawn(
            &mut app,
            Terrain {
                morph,
                accuracy: 40.0,
                view_margin_degrees: 45.0,
                ..procedural(129)
            },
            Transform::default(),
        );
        app.update();
        let mut last = surface(&app, terrain);
        let mut largest = 0.0f32;
        for _ in 0..60 {
            move_camera(&mut app, camera, Vec3::new(8.0, -3.0, 0.0));
            let now = surface(&app, terrain);
            for (point, h) in &now {
                if let Some(before) = last.get(point) {
                    largest = largest.max((h - before).abs());
                }
            }
            last = now;
        }
        assert_eq!(stats(&app, terrain).updates, 61);
        largest
    }

    #[test]
    fn morphing_keeps_the_drawn_heights_continuous_along_a_flight() {
        let morphed = largest_step(true);
        let popping = largest_step(false);
        eprintln!("largest step {morphed} m with morphing, {popping} m without");
        assert!(
            morphed * 4.0 < popping,
            "largest step {morphed} m with morphing, {popping} m without"
        );
    }

    fn heights_asset(app: &mut App, dims: UVec2, values: Vec<f32>) -> Handle<GrayscaleMap> {
        app.world_mut()
            .resource_mut::<Assets<GrayscaleMap>>()
            .add(GrayscaleMap {
                dims,
                values: Arc::new(values),
            })
    }

    fn from_asset(handle: Handle<GrayscaleMap>) -> Terrain {
        Terrain {
            source: TerrainSource::Heights(handle),
            ..procedural(2)
        }
    }

    fn assert_failed(app: &App, terrain: Entity, needles: &[&str]) {
        let TerrainStatus::Failed(error) = status(app, terrain) else {
            panic!("expected a failure, got {:?}", status(app, terrain));
        };
        let reason = error.to_string();
        for needle in needles {
            assert!(reason.contains(needle), "{reason:?} lacks {needle:?}");
        }
        assert!(app.world().get::<Mesh3d>(terrain).is_none(), "no mesh");
        assert_eq!(stats(app, terrain).updates, 0);
    }

    #[test]
    fn bad_heights_fail_with_the_reason_and_no_mesh_and_recover_when_fixed() {
        let (mut app, _) = app(&asset_dir("bad"), Vec3::new(0.0, 100.0, 100.0));
        let mut values = vec![0.5; 25];
        values[1 + 5 * 2] = f32::NAN;
        let nan = heights_asset(&mut app, UVec2::new(5, 5), values);
        let terrain = spawn(&mut app, from_asset(nan.clone()), Transform::default());
        for _ in 0..3 {
            app.update();
        }
        assert_failed(&app, terrain, &["grid point (1, 2)", "NaN", "finite"]);

        // Fixing the asset in place rebuilds the terrain.
        app.world_mut()
            .resource_mut::<Assets<GrayscaleMap>>()
            .get_mut(&nan)
            .map(|mut heights| Arc::make_mut(&mut heights.values)[11] = 0.25)
            .unwrap();
        app.update();
        assert_eq!(status(&app, terrain), TerrainStatus::Ready);
        assert!(app.world().get::<Mesh3d>(terrain).is_some());

        let thin = heights_asset(&mut app, UVec2::new(1, 5), vec![0.0; 5]);
        let terrain = spawn(&mut app, from_asset(thin), Transform::default());
        app.update();
        assert_failed(&app, terrain, &["1 × 5 points", "at least 2 × 2"]);

        let short = heights_asset(&mut app, UVec2::new(3, 3), vec![0.0; 8]);
        let terrain = spawn(&mut app, from_asset(short), Transform::default());
        app.update();
        assert_failed(&app, terrain, &["3 × 3 points but holds 8 values"]);

        let terrain = spawn(
            &mut app,
            Terrain {
                min_accuracy: 1.0,
                ..procedural(9)
            },
            Transform::default(),
        );
        app.update();
        assert_failed(&app, terrain, &["min_resolution C = 1"]);
        let terrain = spawn(
            &mut app,
            Terrain {
                spacing: -1.0,
                ..procedural(9)
            },
            Transform::default(),
        );
        app.update();
        assert_failed(&app, terrain, &["spacing = -1"]);
    }

    #[test]
    fn height_maps_load_through_the_asset_server_or_fail_with_the_file_named() {
        let dir = asset_dir("load");
        let values: Vec<u16> = (0..15).map(|v| v * 4000).collect();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(5, 3, values)
            .unwrap()
            .save(dir.join("hills.png"))
            .unwrap();
        image::RgbImage::from_raw(2, 2, vec![9; 12])
            .unwrap()
            .save(dir.join("photo.png"))
            .unwrap();
        let (mut app, _) = app(&dir, Vec3::new(0.0, 100.0, 100.0));
        let load = |app: &mut App, path: &str| {
            let handle = app
                .world()
                .resource::<AssetServer>()
                .load::<GrayscaleMap>(path.to_owned());
            spawn(app, from_asset(handle), Transform::default())
        };

        let hills = load(&mut app, "hills.png");
        assert_eq!(settle(&mut app, hills), TerrainStatus::Ready);
        // 5 × 3 points, padded to 5 × 5 at the high z end.
        assert_eq!(stats(&app, hills).points_per_side, 5);
        assert!(!positions(&app, hills).is_empty());

        let missing = load(&mut app, "missing.png");
        settle(&mut app, missing);
        assert_failed(&app, missing, &["cannot load the height map missing.png"]);

        let photo = load(&mut app, "photo.png");
        settle(&mut app, photo);
        assert_failed(&app, photo, &["photo.png", "grayscale"]);

        // The failures are stable: no retry, the status stays.
        for _ in 0..3 {
            app.update();
        }
        assert_failed(&app, missing, &["missing.png"]);
    }

    #[test]
    fn debug_views_and_a_custom_material() {
        let (mut app, _) = app(&asset_dir("debug"), Vec3::new(0.0, 200.0, 300.0));
        let material = app
            .world_mut()
            .resource_mut::<Assets<StandardMaterial>>()
            .add(StandardMaterial::default());
        let terrain = spawn(
            &mut app,
            Terrain {
                material: TerrainMaterial::Standard(material.clone()),
                accuracy: 5.0,
                ..procedural(33)
            },
            Transform::default(),
        );
        app.update();
        let mesh_of = |app: &App| {
            let handle = &app.world().get::<Mesh3d>(terrain).unwrap().0;
            app.world()
                .resource::<Assets<Mesh>>()
                .get(handle)
                .unwrap()
                .clone()
        };
        assert_eq!(
            app.world()
                .get::<MeshMaterial3d<StandardMaterial>>(terrain)
                .unwrap()
                .0,
            material
        );
        assert!(mesh_of(&app).attribute(Mesh::ATTRIBUTE_COLOR).is_none());
        let vertices = stats(&app, terrain).vertices as usize;

        app.world_mut().get_mut::<Terrain>(terrain).unwrap().debug = TerrainDebug {
            lod_colours: true,
            edges: false,
        };
        app.update();
        let Some(VertexAttributeValues::Float32x4(colours)) =
            mesh_of(&app).attribute(Mesh::ATTRIBUTE_COLOR).cloned()
        else {
            panic!("level colours");
        };
        let distinct: std::collections::HashSet<_> =
            colours.iter().map(|c| c.map(f32::to_bits)).collect();
        assert!(distinct.len() >= 2, "several levels: {}", distinct.len());

        app.world_mut()
            .get_mut::<Terrain>(terrain)
            .unwrap()
            .debug
            .edges = true;
        app.update();
        let triangles = stats(&app, terrain).triangles as usize;
        assert_eq!(mesh_of(&app).count_vertices(), 6 * triangles);
        assert!(vertices < 6 * triangles);
    }

    #[test]
    fn an_own_material_is_left_to_the_entity_and_the_mesh_has_uvs_over_the_terrain() {
        let (mut app, _) = app(&asset_dir("own"), Vec3::new(0.0, 200.0, 300.0));
        // 30 points a side, padded to the quadtree's 33.
        let terrain = spawn(
            &mut app,
            Terrain {
                accuracy: 5.0,
                ..procedural(30)
            },
            Transform::default(),
        );
        app.update();
        let standard = |app: &App| {
            app.world()
                .get::<MeshMaterial3d<StandardMaterial>>(terrain)
                .map(|material| material.0.clone())
        };
        assert!(standard(&app).is_some(), "the default material");

        // Own: the terrain's material goes, the user's stays through
        // refinements.
        app.world_mut()
            .get_mut::<Terrain>(terrain)
            .unwrap()
            .material = TerrainMaterial::Own;
        app.update();
        assert!(standard(&app).is_none());
        let users = app
            .world_mut()
            .resource_mut::<Assets<StandardMaterial>>()
            .add(StandardMaterial::default());
        app.world_mut()
            .entity_mut(terrain)
            .insert(MeshMaterial3d(users.clone()));
        app.world_mut()
            .get_mut::<Terrain>(terrain)
            .unwrap()
            .accuracy = 8.0;
        app.update();
        assert_eq!(standard(&app), Some(users.clone()));

        // Back to the default, then Own with the user's material put in the
        // same frame: the terrain removes only the material it inserted.
        app.world_mut()
            .get_mut::<Terrain>(terrain)
            .unwrap()
            .material = TerrainMaterial::HeightAndSlope;
        app.update();
        assert_ne!(standard(&app), Some(users.clone()));
        app.world_mut()
            .get_mut::<Terrain>(terrain)
            .unwrap()
            .material = TerrainMaterial::Own;
        app.world_mut()
            .entity_mut(terrain)
            .insert(MeshMaterial3d(users.clone()));
        app.update();
        assert_eq!(standard(&app), Some(users));

        let handle = app.world().get::<Mesh3d>(terrain).unwrap().0.clone();
        let mesh = app.world().resource::<Assets<Mesh>>().get(&handle).unwrap();
        assert!(mesh.attribute(Mesh::ATTRIBUTE_COLOR).is_none());
        let (
            Some(VertexAttributeValues::Float32x3(positions)),
            Some(VertexAttributeValues::Float32x2(uvs)),
        ) = (
            mesh.attribute(Mesh::ATTRIBUTE_POSITION),
            mesh.attribute(Mesh::ATTRIBUTE_UV_0),
        )
        else {
            panic!("positions and uvs");
        };
        // Each vertex's x and z over the height map's side (29 spacings),
        // from its first corner: 0 to 1 over the map, up to 32/29 over the
        // padding.
        let side = 29.0 * procedural(30).spacing;
        let lod = app.world().get::<TerrainLod>(terrain).unwrap();
        assert_eq!(lod.hierarchy.as_ref().unwrap().size(), 33);
        let corner = lod.hierarchy.as_ref().unwrap().origin().as_vec3();
        for (p, uv) in positions.iter().zip(uvs) {
            assert!(
                (uv[0] - (p[0] - corner.x) / side).abs() < 1e-5,
                "{p:?} {uv:?}"
            );
            assert!(
                (uv[1] - (p[2] - corner.z) / side).abs() < 1e-5,
                "{p:?} {uv:?}"
            );
            assert!(uv.iter().all(|c| (-1e-6..=32.0 / 29.0 + 1e-6).contains(c)));
        }
    }

    #[test]
    fn a_world_without_terrain_measures_nothing() {
        let (mut app, _) = app(&asset_dir("none"), Vec3::ONE);
        for _ in 0..3 {
            app.update();
        }
        let store = app.world().resource::<DiagnosticsStore>();
        let terrain: Vec<_> = store
            .iter()
            .filter(|d| d.path().as_str().starts_with("nebel/terrain/"))
            .collect();
        assert!(!terrain.is_empty(), "the plugin registers its diagnostics");
        assert!(terrain.iter().all(|d| d.measurement().is_none()));
    }

    #[test]
    fn a_background_build_appears_when_ready_and_the_old_terrain_stays_meanwhile() {
        let (mut app, _) = app(&asset_dir("background"), Vec3::new(0.0, 300.0, 300.0));
        app.insert_resource(HeavyBuilds::Background);
        let terrain = spawn(&mut app, procedural(65), Transform::default());
        let settle = |app: &mut App, until: &dyn Fn(&App) -> bool| {
            for _ in 0..2000 {
                app.update();
                if until(app) {
                    return;
                }
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
            panic!("the build never finished");
        };
        assert_eq!(status(&app, terrain), TerrainStatus::Pending);
        settle(&mut app, &|app| {
            app.world().get::<Mesh3d>(terrain).is_some()
        });
        assert_eq!(status(&app, terrain), TerrainStatus::Ready);
        assert_eq!(stats(&app, terrain).points_per_side, 65);

        // A larger terrain: the 65² mesh stays until the 257² quadtree is done.
        app.world_mut().get_mut::<Terrain>(terrain).unwrap().source = procedural(257).source;
        app.update();
        assert!(app.world().get::<Mesh3d>(terrain).is_some(), "still drawn");
        settle(&mut app, &|app| stats(app, terrain).points_per_side == 257);
        assert_eq!(status(&app, terrain), TerrainStatus::Ready);
    }

    #[test]
    fn refinements_run_off_the_frame_and_land_as_a_same_frame_one_would() {
        let far = Vec3::new(0.0, 300.0, 300.0);
        let near = Vec3::new(40.0, 120.0, 120.0);
        let (mut app, camera) = app(&asset_dir("refine-background"), far);
        app.insert_resource(HeavyBuilds::Background);
        let terrain = spawn(&mut app, procedural(129), Transform::default());
        let mesh_of = |app: &App| {
            let handle = &app.world().get::<Mesh3d>(terrain).expect("a mesh").0;
            app.world()
                .resource::<Assets<Mesh>>()
                .get(handle)
                .unwrap()
                .clone()
        };
        let mut settled = false;
        for _ in 0..2000 {
            app.update();
            if app.world().get::<Mesh3d>(terrain).is_some() {
                settled = true;
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        assert!(settled, "no mesh");
        let first = positions(&app, terrain);
        let updates = stats(&app, terrain).updates;
        // A move and a debug view in one frame: while the refinement runs the
        // old mesh is drawn, then the new one lands with the debug colours
        // (a setting that changed while a refinement ran is not lost).
        app.world_mut()
            .get_mut::<Transform>(camera)
            .unwrap()
            .translation = near;
        app.world_mut().get_mut::<Terrain>(terrain).unwrap().debug = TerrainDebug {
            lod_colours: true,
            ..default()
        };
        let mut landed = None;
        for _ in 0..2000 {
            app.update();
            if stats(&app, terrain).updates > updates {
                landed = Some(mesh_of(&app));
                break;
            }
            assert!(
                positions(&app, terrain) == first,
                "not the old mesh meanwhile"
            );
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        let landed = landed.expect("the refinement never landed");

        // The same terrain refined in the frame, for the same eye.
        let (mut blocking, same_camera) =
            app_looking_at(&asset_dir("refine-blocking"), far, Vec3::ZERO);
        blocking
            .world_mut()
            .get_mut::<Transform>(same_camera)
            .unwrap()
            .translation = near;
        let same = spawn(
            &mut blocking,
            Terrain {
                debug: TerrainDebug {
                    lod_colours: true,
                    ..default()
                },
                ..procedural(129)
            },
            Transform::default(),
        );
        blocking.update();
        let expected = positions(&blocking, same);
        assert!(
            landed
                .attribute(Mesh::ATTRIBUTE_POSITION)
                .unwrap()
                .as_float3()
                == Some(expected.as_slice()),
            "not the mesh of a same-frame refinement"
        );
        let colours = |mesh: &Mesh| match mesh.attribute(Mesh::ATTRIBUTE_COLOR) {
            Some(VertexAttributeValues::Float32x4(c)) => c.clone(),
            _ => panic!("colours"),
        };
        let blocking_mesh = {
            let handle = &blocking.world().get::<Mesh3d>(same).expect("a mesh").0;
            blocking
                .world()
                .resource::<Assets<Mesh>>()
                .get(handle)
                .unwrap()
                .clone()
        };
        assert!(
            colours(&landed) == colours(&blocking_mesh),
            "the debug colours set during the refinement were lost"
        );
        assert_ne!(expected.len(), first.len(), "the move refined anew");
    }
}
