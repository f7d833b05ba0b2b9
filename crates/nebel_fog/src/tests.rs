//! The ground fog plugin in an app without a GPU: maps, batches, status,
//! zero cost without fog, and bad input.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use bevy::asset::AssetPlugin;
use bevy::diagnostic::DiagnosticsStore;
use bevy::prelude::*;
use nebel_core::field::{FogNoise, TerrainNoise, ValleyFog};
use nebel_core::optics::OpticalMode;
use nebel_render::headless::{headless_app, spawn_computed_camera};
use nebel_render::{CellBatch, CellFogSunlight, GrayscaleMap};
use nebel_terrain::{
    Terrain, TerrainLod, TerrainLodStats, TerrainMapLod, TerrainPlugin, TerrainSource,
};

use crate::{
    FogThickness, GroundFog, GroundFogDebug, GroundFogPlugin, GroundFogStats, GroundFogStatus,
};

/// A folder of its own per test for the asset server's files.
fn asset_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("nebel-fog-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// An app with the terrain and fog plugins, builds in the frame, and a
/// camera at `eye` looking at the origin (what Bevy computes for a 64 × 64
/// target).
fn app(dir: &Path, eye: Vec3) -> (App, Entity) {
    let mut app = headless_app(Some(dir));
    app.init_asset::<Mesh>()
        .init_asset::<StandardMaterial>()
        .add_plugins((TerrainPlugin, GroundFogPlugin));
    let transform = Transform::from_translation(eye).looking_at(Vec3::ZERO, Vec3::Y);
    let camera = spawn_computed_camera(app.world_mut(), 1.0, UVec2::splat(64), transform);
    (app, camera)
}

/// A 65 × 65 terrain 10 m apart with 100 m of relief.
fn terrain() -> Terrain {
    Terrain {
        source: TerrainSource::Procedural {
            size: 65,
            noise: TerrainNoise {
                wavelength: 300.0,
                exponent: 1.5,
                ..default()
            },
        },
        spacing: 10.0,
        vertical_scale: 100.0,
        ..default()
    }
}

fn valley(altitude: f32) -> GroundFog {
    GroundFog {
        thickness: FogThickness::Valley(ValleyFog {
            altitude,
            ..default()
        }),
        ..default()
    }
}

/// Spawns a visible terrain with `fog`.
fn spawn_fog(app: &mut App, fog: GroundFog) -> Entity {
    app.world_mut()
        .spawn((terrain(), fog, InheritedVisibility::VISIBLE))
        .id()
}

/// Whether the terrain of `entity` carries a fog layer.
fn has_map(app: &App, entity: Entity) -> bool {
    app.world()
        .get::<TerrainMapLod>(entity)
        .is_some_and(|map| map.quadtree.is_some())
}

/// Moves the camera by `metres` along x.
fn nudge(app: &mut App, camera: Entity, metres: f32) {
    let mut transform = app.world_mut().get_mut::<Transform>(camera).unwrap();
    transform.translation.x += metres;
}

fn settle(app: &mut App) {
    for _ in 0..3 {
        app.update();
    }
}

fn status(app: &App, entity: Entity) -> GroundFogStatus {
    app.world().get::<GroundFogStatus>(entity).unwrap().clone()
}

fn stats(app: &App, entity: Entity) -> GroundFogStats {
    *app.world().get::<GroundFogStats>(entity).unwrap()
}

fn batch(app: &App, entity: Entity) -> Option<&CellBatch> {
    app.world().get::<CellBatch>(entity)
}

fn measured(app: &App, path: &bevy::diagnostic::DiagnosticPath) -> Option<f64> {
    app.world()
        .resource::<DiagnosticsStore>()
        .get(path)
        .and_then(|d| d.measurement())
        .map(|m| m.value)
}

fn assert_failed(app: &App, entity: Entity, needles: &[&str]) {
    let GroundFogStatus::Failed(error) = status(app, entity) else {
        panic!("expected a failure, got {:?}", status(app, entity));
    };
    let reason = error.to_string();
    for needle in needles {
        assert!(reason.contains(needle), "{reason:?} lacks {needle:?}");
    }
    assert!(batch(app, entity).is_none(), "no cells");
}

/// The farthest the terrain under `fog` may wait for the eye, in spacings,
/// as the fog's map asks (`None`: the terrain's own).
fn map_update_distance(app: &App, fog: Entity) -> Option<f32> {
    app.world()
        .get::<TerrainMapLod>(fog)
        .unwrap()
        .max_update_distance
}

#[test]
fn fog_on_a_terrain_becomes_sorted_prisms_that_follow_the_eye() {
    let (mut app, camera) = app(&asset_dir("prisms"), Vec3::new(-400.0, 250.0, -300.0));
    let fog = spawn_fog(&mut app, valley(40.0));
    settle(&mut app);
    assert_eq!(status(&app, fog), GroundFogStatus::Ready);
    let counts = stats(&app, fog);
    let cells = batch(&app, fog).expect("a batch").cells.len();
    assert!(counts.prisms > 50, "{counts:?}");
    assert_eq!(counts.tetrahedra as usize, cells);
    assert!(
        counts.max_thickness > 10.0 && counts.max_thickness < 60.0,
        "{counts:?}"
    );
    assert_eq!(batch(&app, fog).unwrap().mode, OpticalMode::Sorted);
    // The terrain carries the fog's map and refines after half a spacing.
    let map = app.world().get::<TerrainMapLod>(fog).unwrap();
    assert!(map.quadtree.is_some() && map.max_update_distance == Some(0.5));
    let lod = app.world().get::<TerrainLod>(fog).unwrap();
    assert_eq!(lod.mesh().map.len(), lod.mesh().positions.len());
    assert_eq!(
        measured(&app, &GroundFogPlugin::TETRAHEDRA),
        Some(cells as f64)
    );
    assert!(measured(&app, &GroundFogPlugin::UPDATE_MS).is_some());
    // A still camera costs nothing, nor does a move of 1 cm; one beyond the
    // terrain's update distance (a quarter spacing, 2.5 m, within the fog's
    // half) refines the terrain and rebuilds the prisms for the new eye.
    let (terrain_updates, fog_updates) = (
        app.world().get::<TerrainLodStats>(fog).unwrap().updates,
        counts.updates,
    );
    app.update();
    nudge(&mut app, camera, 0.01);
    app.update();
    assert_eq!(stats(&app, fog).updates, fog_updates);
    nudge(&mut app, camera, 2.5);
    app.update();
    assert_eq!(
        app.world().get::<TerrainLodStats>(fog).unwrap().updates,
        terrain_updates + 1
    );
    assert_eq!(stats(&app, fog).updates, fog_updates + 1);
    // A terrain that would wait for 2 spacings waits for half of one under a
    // sorted fog: 6 m is enough.
    app.world_mut()
        .get_mut::<Terrain>(fog)
        .unwrap()
        .update_distance = 2.0;
    settle(&mut app);
    let (terrain_updates, fog_updates) = (
        app.world().get::<TerrainLodStats>(fog).unwrap().updates,
        stats(&app, fog).updates,
    );
    nudge(&mut app, camera, 4.0);
    app.update();
    assert_eq!(stats(&app, fog).updates, fog_updates);
    nudge(&mut app, camera, 2.0);
    app.update();
    assert_eq!(
        app.world().get::<TerrainLodStats>(fog).unwrap().updates,
        terrain_updates + 1
    );
    assert_eq!(stats(&app, fog).updates, fog_updates + 1);
    // Unsorted modes: the terrain's own update distance again.
    app.world_mut().get_mut::<GroundFog>(fog).unwrap().mode = OpticalMode::Emissive;
    settle(&mut app);
    assert_eq!(batch(&app, fog).unwrap().mode, OpticalMode::Emissive);
    assert_eq!(map_update_distance(&app, fog), None);
    let updates = stats(&app, fog).updates;
    nudge(&mut app, camera, 4.0);
    app.update();
    assert_eq!(stats(&app, fog).updates, updates);
    // Saturating emission: the sorted model's segments, still unsorted.
    app.world_mut().get_mut::<GroundFog>(fog).unwrap().saturate = true;
    settle(&mut app);
    assert_eq!(batch(&app, fog).unwrap().mode, OpticalMode::Sorted);
    assert_eq!(map_update_distance(&app, fog), None);
}

#[test]
fn no_fog_means_no_cells_and_no_batch() {
    let (mut app, _) = app(&asset_dir("none"), Vec3::new(-400.0, 250.0, -300.0));
    // A terrain alone: no fog diagnostics.
    let plain = app
        .world_mut()
        .spawn((terrain(), InheritedVisibility::VISIBLE))
        .id();
    settle(&mut app);
    assert!(batch(&app, plain).is_none());
    assert_eq!(measured(&app, &GroundFogPlugin::FOGS), None);
    // Valleys filled to below the lowest point: no thickness anywhere, no
    // map for the terrain, no batch.
    let dry = spawn_fog(&mut app, valley(-50.0));
    settle(&mut app);
    assert_eq!(status(&app, dry), GroundFogStatus::Ready);
    assert!(batch(&app, dry).is_none());
    assert!(!has_map(&app, dry));
    assert_eq!(stats(&app, dry).max_thickness, 0.0);
    assert_eq!(measured(&app, &GroundFogPlugin::FOGS), Some(0.0));
    // No density, or hidden: the batch goes.
    let fog = spawn_fog(&mut app, valley(40.0));
    settle(&mut app);
    assert!(batch(&app, fog).is_some());
    app.world_mut().get_mut::<GroundFog>(fog).unwrap().density = 0.0;
    settle(&mut app);
    assert!(batch(&app, fog).is_none());
    // The terrain refines alone meanwhile.
    assert!(!has_map(&app, fog));
    app.world_mut().get_mut::<GroundFog>(fog).unwrap().density = 0.03;
    settle(&mut app);
    assert!(batch(&app, fog).is_some());
    *app.world_mut().get_mut::<InheritedVisibility>(fog).unwrap() = InheritedVisibility::HIDDEN;
    settle(&mut app);
    assert!(batch(&app, fog).is_none());
}

#[test]
fn bad_input_fails_with_the_reason_and_never_panics() {
    let dir = asset_dir("bad");
    let (mut app, _) = app(&dir, Vec3::new(-400.0, 250.0, -300.0));
    // A fog without a terrain.
    let alone = app.world_mut().spawn(valley(40.0)).id();
    settle(&mut app);
    assert_failed(&app, alone, &["needs a Terrain"]);
    // Settings out of range.
    let weight = spawn_fog(
        &mut app,
        GroundFog {
            roughness_weight: f32::NAN,
            ..valley(40.0)
        },
    );
    let coverage = spawn_fog(
        &mut app,
        GroundFog {
            thickness: FogThickness::Noise(FogNoise {
                coverage: 2.0,
                ..default()
            }),
            ..default()
        },
    );
    let profile = spawn_fog(
        &mut app,
        GroundFog {
            profile: vec![[0.0, 1.0], [0.5, 0.5]],
            ..valley(40.0)
        },
    );
    // A map of NaN, a missing map file.
    let nan = app
        .world_mut()
        .resource_mut::<Assets<GrayscaleMap>>()
        .add(GrayscaleMap {
            dims: UVec2::new(2, 2),
            values: Arc::new(vec![0.5, f32::NAN, 0.5, 0.5]),
        });
    let nan_map = spawn_fog(
        &mut app,
        GroundFog {
            thickness: FogThickness::Map {
                map: nan,
                scale: 30.0,
            },
            ..default()
        },
    );
    let missing = app
        .world()
        .resource::<AssetServer>()
        .load("no_such_fog.png");
    let missing_map = spawn_fog(
        &mut app,
        GroundFog {
            thickness: FogThickness::Map {
                map: missing,
                scale: 30.0,
            },
            ..default()
        },
    );
    for _ in 0..200 {
        app.update();
        if matches!(status(&app, missing_map), GroundFogStatus::Failed(_)) {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    assert_failed(&app, weight, &["roughness_weight", "NaN"]);
    assert_failed(&app, coverage, &["coverage"]);
    assert_failed(&app, profile, &["fog profile"]);
    assert_failed(&app, nan_map, &["NaN", "finite"]);
    assert_failed(&app, missing_map, &["no_such_fog.png"]);
    // Fixing a setting draws the fog.
    app.world_mut()
        .get_mut::<GroundFog>(weight)
        .unwrap()
        .roughness_weight = 1.0;
    settle(&mut app);
    assert_eq!(status(&app, weight), GroundFogStatus::Ready);
    assert!(batch(&app, weight).is_some());
}

#[test]
fn a_fog_map_covers_the_terrain_and_scales_to_metres() {
    let (mut app, _) = app(&asset_dir("map"), Vec3::new(-400.0, 250.0, -300.0));
    // A 3 × 2 map: one white pixel, the rest black.
    let map = app
        .world_mut()
        .resource_mut::<Assets<GrayscaleMap>>()
        .add(GrayscaleMap {
            dims: UVec2::new(3, 2),
            values: Arc::new(vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
        });
    let fog = spawn_fog(
        &mut app,
        GroundFog {
            thickness: FogThickness::Map { map, scale: 25.0 },
            ..default()
        },
    );
    settle(&mut app);
    assert_eq!(status(&app, fog), GroundFogStatus::Ready);
    assert_eq!(stats(&app, fog).max_thickness, 25.0);
    let map = app.world().get::<TerrainMapLod>(fog).unwrap();
    let values = map.quadtree.as_ref().unwrap().map.values();
    // The white pixel is the terrain's corner at high x, low z.
    assert_eq!(values[64], 25.0);
    assert_eq!(values[0], 0.0);
    assert_eq!(values[64 + 65 * 64], 0.0);
    assert!(batch(&app, fog).is_some());
}

#[test]
fn the_wireframe_is_a_child_and_removing_the_fog_removes_what_it_made() {
    let (mut app, _) = app(&asset_dir("remove"), Vec3::new(-400.0, 250.0, -300.0));
    let fog = spawn_fog(
        &mut app,
        GroundFog {
            debug: GroundFogDebug { wireframe: true },
            ..valley(40.0)
        },
    );
    settle(&mut app);
    assert!(batch(&app, fog).is_some());
    let children: Vec<Entity> = app
        .world()
        .get::<Children>(fog)
        .expect("the wireframe is a child")
        .iter()
        .collect();
    assert_eq!(children.len(), 1);
    assert!(app.world().get::<Mesh3d>(children[0]).is_some());
    // Removing the fog takes its batch, the terrain's map and the
    // wireframe; the terrain stays.
    app.world_mut().entity_mut(fog).remove::<GroundFog>();
    settle(&mut app);
    assert!(batch(&app, fog).is_none());
    assert!(app.world().get::<TerrainMapLod>(fog).is_none());
    assert!(app.world().get_entity(children[0]).is_err());
    assert!(app.world().get::<Terrain>(fog).is_some());
    // Despawning a fogged terrain takes its wireframe with it.
    let fog = spawn_fog(
        &mut app,
        GroundFog {
            debug: GroundFogDebug { wireframe: true },
            ..valley(40.0)
        },
    );
    settle(&mut app);
    let wireframe = app.world().get::<Children>(fog).unwrap()[0];
    app.world_mut().entity_mut(fog).despawn();
    settle(&mut app);
    assert!(app.world().get_entity(wireframe).is_err());
}

#[test]
fn a_density_out_of_range_fails_and_recovers() {
    let (mut app, _) = app(&asset_dir("density"), Vec3::new(-400.0, 250.0, -300.0));
    for density in [f32::NAN, -0.5] {
        let fog = spawn_fog(
            &mut app,
            GroundFog {
                density,
                ..valley(40.0)
            },
        );
        settle(&mut app);
        assert_failed(&app, fog, &["density", "finite and ≥ 0"]);
        assert!(!has_map(&app, fog));
        app.world_mut().get_mut::<GroundFog>(fog).unwrap().density = 0.02;
        settle(&mut app);
        assert_eq!(status(&app, fog), GroundFogStatus::Ready);
        assert!(batch(&app, fog).is_some());
    }
}

/// The fog layers of a camera in an app without a GPU: their status and
/// what they hand the render world.
fn fog_layers_status(fog: crate::FogLayers) -> (crate::FogLayersStatus, bool) {
    let mut app = App::new();
    app.add_plugins((MinimalPlugins, AssetPlugin::default()))
        .add_plugins(crate::FogLayersPlugin);
    let camera = app.world_mut().spawn((Camera3d::default(), fog)).id();
    app.update();
    let world = app.world();
    (
        world.get::<crate::FogLayersStatus>(camera).unwrap().clone(),
        world
            .get::<crate::fog_layers::PreparedFogLayers>(camera)
            .unwrap()
            .0
            .is_some(),
    )
}

#[test]
fn fog_layers_are_checked_and_cost_nothing_without_density() {
    use crate::{FogLayers, FogLayersStatus, HeightFogLayer};
    assert_eq!(
        fog_layers_status(FogLayers::default()),
        (FogLayersStatus::Ready, true)
    );
    // No layers, or layers of zero density: nothing for the render world.
    for layers in [
        vec![],
        vec![
            HeightFogLayer::Constant {
                bottom: 0.0,
                top: 10.0,
                density: 0.0,
            },
            HeightFogLayer::Linear(vec![[0.0, 0.0], [5.0, 0.0]]),
        ],
    ] {
        let fog = FogLayers {
            layers,
            ..default()
        };
        assert_eq!(fog_layers_status(fog), (FogLayersStatus::Ready, false));
    }
    // Bad input: a failed status that names the setting, nothing drawn.
    let exponential = |density: f64, falloff: f64| HeightFogLayer::Exponential {
        base: 0.0,
        density,
        falloff,
    };
    for (fog, needle) in [
        (
            FogLayers {
                layers: vec![exponential(-0.01, 0.01)],
                ..default()
            },
            "density",
        ),
        (
            FogLayers {
                layers: vec![exponential(f64::NAN, 0.01)],
                ..default()
            },
            "density",
        ),
        (
            FogLayers {
                layers: vec![exponential(0.01, -1.0)],
                ..default()
            },
            "falloff",
        ),
        (
            FogLayers {
                layers: vec![HeightFogLayer::Constant {
                    bottom: 3.0,
                    top: 3.0,
                    density: 0.1,
                }],
                ..default()
            },
            "bottom below top",
        ),
        (
            FogLayers {
                layers: vec![exponential(0.01, 0.01); 9],
                ..default()
            },
            "at most 8",
        ),
        (
            FogLayers {
                layers: vec![HeightFogLayer::Linear(
                    (0..33).map(|i| [f64::from(i), 0.01]).collect(),
                )],
                ..default()
            },
            "at most 32",
        ),
        (
            FogLayers {
                start_distance: 10.0,
                max_distance: 10.0,
                ..default()
            },
            "max_distance",
        ),
        (
            FogLayers {
                color: Color::linear_rgb(f32::NAN, 0.0, 0.0),
                ..default()
            },
            "color",
        ),
    ] {
        let (status, prepared) = fog_layers_status(fog);
        let FogLayersStatus::Failed(error) = status else {
            panic!("{needle}: {status:?}");
        };
        assert!(error.to_string().contains(needle), "{error}");
        assert!(!prepared, "{needle}");
    }
}

#[test]
fn the_quality_preset_sets_the_fog_method_and_the_terrain_accuracy() {
    use nebel_render::{NebelQuality, NebelQualityPlugin, QualityPreset};
    let (mut app, _camera) = app(&asset_dir("quality"), Vec3::new(-400.0, 250.0, -300.0));
    app.add_plugins(NebelQualityPlugin);
    let fog = spawn_fog(&mut app, valley(40.0));
    settle(&mut app);
    let triangles = |app: &App| app.world().get::<TerrainLodStats>(fog).unwrap().triangles;
    let high = (triangles(&app), batch(&app, fog).map(|b| b.cells.len()));
    assert!(high.1.is_some_and(|cells| cells > 0) && has_map(&app, fog));
    // Low: the fog's prisms give way to the fog layers, the terrain
    // refines at half its accuracy and without the fog's map.
    app.world_mut().resource_mut::<NebelQuality>().preset = QualityPreset::Low;
    settle(&mut app);
    assert!(batch(&app, fog).is_none() && !has_map(&app, fog));
    assert_eq!(stats(&app, fog).tetrahedra, 0);
    assert!(
        triangles(&app) < high.0,
        "{} vs {}",
        triangles(&app),
        high.0
    );
    // Medium: the prisms again, on a coarser terrain than High's.
    app.world_mut().resource_mut::<NebelQuality>().preset = QualityPreset::Medium;
    settle(&mut app);
    let medium = (triangles(&app), batch(&app, fog).map(|b| b.cells.len()));
    assert!(medium.1.is_some_and(|cells| cells > 0) && has_map(&app, fog));
    assert!(medium.0 < high.0, "{} vs {}", medium.0, high.0);
    // And back to High: what it was.
    app.world_mut().resource_mut::<NebelQuality>().preset = QualityPreset::High;
    settle(&mut app);
    assert_eq!(
        (triangles(&app), batch(&app, fog).map(|b| b.cells.len())),
        high
    );
}

#[test]
fn a_sun_colour_and_a_sun_light_the_fog_on_a_map_that_follows_the_sun() {
    let (mut app, _) = app(&asset_dir("sunlight"), Vec3::new(-400.0, 250.0, -300.0));
    let sunlight = |app: &App, fog: Entity| app.world().get::<CellFogSunlight>(fog).cloned();
    // A sun colour without a sun, and a sun without a sun colour: no map.
    let fog = spawn_fog(
        &mut app,
        GroundFog {
            sun_color: Color::linear_rgb(1.0, 0.8, 0.6),
            ..valley(40.0)
        },
    );
    settle(&mut app);
    assert!(batch(&app, fog).is_some());
    assert!(sunlight(&app, fog).is_none());
    let sun = app
        .world_mut()
        .spawn((
            DirectionalLight::default(),
            Transform::from_xyz(0.0, 0.0, 0.0).looking_to(Vec3::new(0.6, -0.3, 0.74), Vec3::Y),
        ))
        .id();
    settle(&mut app);
    let lit = sunlight(&app, fog).expect("lit by the sun");
    let toward = -Vec3::new(0.6, -0.3, 0.74).normalize();
    assert!(lit.direction.distance(toward) < 1e-5);
    assert_eq!(lit.colour, Vec3::new(1.0, 0.8, 0.6));
    // The map is the terrain's: its shadow heights lie on or above its
    // ground, above it somewhere (100 m of relief under a sun 17° up).
    let (shadow, ground) = (lit.map.shadow.heights.heights(), lit.map.ground.heights());
    assert!(shadow.iter().zip(ground).all(|(s, g)| s >= g));
    assert!(shadow.iter().zip(ground).any(|(s, g)| s > &(g + 1.0)));
    assert!(lit.map.thickness.heights().iter().any(|h| *h > 0.0));
    assert!(measured(&app, &GroundFogPlugin::SUN_MAP_MS).is_some());
    // A turn below the step keeps the map (and the component, but for its
    // direction); one beyond it makes a new map.
    let turn = |app: &mut App, angle: f32| {
        let mut transform = app.world_mut().get_mut::<Transform>(sun).unwrap();
        transform.rotate_y(angle);
    };
    turn(&mut app, 0.002);
    settle(&mut app);
    let nudged = sunlight(&app, fog).unwrap();
    assert!(Arc::ptr_eq(&nudged.map, &lit.map));
    assert!(nudged.direction != lit.direction);
    turn(&mut app, 0.05);
    settle(&mut app);
    let turned = sunlight(&app, fog).unwrap();
    assert!(!Arc::ptr_eq(&turned.map, &lit.map));
    assert!(turned.map.shadow.sun.distance(turned.direction.as_dvec3()) < 1e-6);
    // The sun's shadow maps on: the meshes hide it too, on the same map.
    assert!(!turned.shadows);
    app.world_mut()
        .get_mut::<DirectionalLight>(sun)
        .unwrap()
        .shadow_maps_enabled = true;
    settle(&mut app);
    let shadowed = sunlight(&app, fog).unwrap();
    assert!(shadowed.shadows);
    assert!(Arc::ptr_eq(&shadowed.map, &turned.map));
    // An unsorted fog, a black sun colour, a sun below the horizon: unlit.
    for change in [
        GroundFog {
            mode: OpticalMode::Emissive,
            sun_color: Color::WHITE,
            ..valley(40.0)
        },
        GroundFog {
            sun_color: Color::BLACK,
            ..valley(40.0)
        },
    ] {
        *app.world_mut().get_mut::<GroundFog>(fog).unwrap() = change;
        settle(&mut app);
        assert!(batch(&app, fog).is_some());
        assert!(sunlight(&app, fog).is_none());
    }
    app.world_mut().get_mut::<GroundFog>(fog).unwrap().sun_color = Color::WHITE;
    settle(&mut app);
    let white = sunlight(&app, fog).expect("lit again");
    // Another colour keeps the map; another density makes a new one.
    app.world_mut().get_mut::<GroundFog>(fog).unwrap().sun_color = Color::linear_rgb(0.5, 0.5, 0.5);
    settle(&mut app);
    assert!(Arc::ptr_eq(&sunlight(&app, fog).unwrap().map, &white.map));
    app.world_mut().get_mut::<GroundFog>(fog).unwrap().density = 0.05;
    settle(&mut app);
    assert!(!Arc::ptr_eq(&sunlight(&app, fog).unwrap().map, &white.map));
    *app.world_mut().get_mut::<Transform>(sun).unwrap() =
        Transform::default().looking_to(Vec3::new(0.3, 0.5, 0.2), Vec3::Y);
    settle(&mut app);
    assert!(
        sunlight(&app, fog).is_none(),
        "the sun is below the horizon"
    );
    // Removing the fog takes the sunlight with its batch.
    *app.world_mut().get_mut::<Transform>(sun).unwrap() =
        Transform::default().looking_to(Vec3::new(0.3, -0.5, 0.2), Vec3::Y);
    settle(&mut app);
    assert!(sunlight(&app, fog).is_some());
    app.world_mut().entity_mut(fog).remove::<GroundFog>();
    settle(&mut app);
    assert!(sunlight(&app, fog).is_none());
}

#[test]
fn a_sun_that_turns_every_frame_still_gets_new_maps_in_the_background() {
    use nebel_render::HeavyBuilds;
    use std::time::Duration;
    let (mut app, _) = app(&asset_dir("sun-turning"), Vec3::new(-400.0, 250.0, -300.0));
    let fog = spawn_fog(
        &mut app,
        GroundFog {
            sun_color: Color::WHITE,
            ..valley(40.0)
        },
    );
    let sun = app
        .world_mut()
        .spawn((DirectionalLight::default(), Transform::default()))
        .id();
    let toward = |frame: u32| {
        Quat::from_rotation_y(0.02 * frame as f32) * Vec3::new(0.8, 0.4, 0.0).normalize()
    };
    settle(&mut app);
    app.insert_resource(HeavyBuilds::Background);
    // The sun turns by 0.02 rad, four steps, every frame: each build is
    // stale when it lands, and the next starts then.
    let mut suns = Vec::new();
    for frame in 0..80 {
        *app.world_mut().get_mut::<Transform>(sun).unwrap() =
            Transform::default().looking_to(-toward(frame), Vec3::Y);
        app.update();
        std::thread::sleep(Duration::from_millis(5));
        if let Some(lit) = app.world().get::<CellFogSunlight>(fog) {
            let map_sun = lit.map.shadow.sun.as_vec3();
            if suns.last() != Some(&map_sun) {
                suns.push(map_sun);
            }
        }
    }
    assert!(suns.len() >= 4, "maps for {} suns", suns.len());
    // The newest map is for a sun of the last few frames.
    let newest = *suns.last().unwrap();
    assert!(
        (60..80).any(|frame| newest.angle_between(toward(frame)) < 1e-4),
        "{newest}"
    );
}

/// The terrain's shadow heights over sunlit fog layers: none without a sun
/// colour, a sun or a terrain; the terrain's own map for the sun in its
/// frame, kept while the sun turns less than a step and built again when it
/// turns more.
#[test]
fn sunlit_fog_layers_get_the_terrains_shadow_heights() {
    use crate::fog_layers::FogLayersTerrainShadow;
    use crate::{FogLayers, FogLayersPlugin};
    use nebel_core::field::TerrainShadow;
    let (mut app, camera) = app(
        &asset_dir("layers-shadow"),
        Vec3::new(-400.0, 250.0, -300.0),
    );
    app.add_plugins(FogLayersPlugin);
    let shadow = |app: &App| app.world().resource::<FogLayersTerrainShadow>().0.clone();
    let terrain = app
        .world_mut()
        .spawn((
            terrain(),
            Transform::from_xyz(30.0, -5.0, 12.0),
            InheritedVisibility::VISIBLE,
        ))
        .id();
    app.world_mut().entity_mut(camera).insert(FogLayers {
        sun_color: Color::linear_rgb(1.0, 0.8, 0.6),
        ..default()
    });
    settle(&mut app);
    assert!(shadow(&app).is_none(), "no sun, no map");
    let toward = Vec3::new(0.6, -0.3, 0.74);
    let sun = app
        .world_mut()
        .spawn((
            DirectionalLight::default(),
            Transform::default().looking_to(toward, Vec3::Y),
        ))
        .id();
    settle(&mut app);
    let placed = shadow(&app).expect("a map for the sunlit fog");
    let quadtree = app
        .world()
        .get::<TerrainLod>(terrain)
        .unwrap()
        .quadtree()
        .unwrap()
        .clone();
    let sun_direction = app
        .world()
        .get::<GlobalTransform>(sun)
        .unwrap()
        .back()
        .as_dvec3();
    let expected = TerrainShadow::of_field(quadtree.field(), sun_direction).unwrap();
    assert_eq!(*placed.shadow, expected);
    assert_eq!(
        placed.map_from_world.translation,
        -bevy::math::DVec3::new(30.0, -5.0, 12.0)
    );
    assert!(measured(&app, &FogLayersPlugin::TERRAIN_SHADOW_MS).is_some());
    // Less than a step keeps the map, more builds a new one.
    let turn = |app: &mut App, angle: f32| {
        let mut transform = app.world_mut().get_mut::<Transform>(sun).unwrap();
        transform.rotate_y(angle);
    };
    turn(&mut app, 0.002);
    settle(&mut app);
    assert!(Arc::ptr_eq(&shadow(&app).unwrap().shadow, &placed.shadow));
    turn(&mut app, 0.05);
    settle(&mut app);
    let turned = shadow(&app).unwrap();
    assert!(!Arc::ptr_eq(&turned.shadow, &placed.shadow));
    assert!(turned.shadow.sun.angle_between(placed.shadow.sun) > 0.04);
    // Fog without sunlight needs no map.
    app.world_mut()
        .entity_mut(camera)
        .insert(FogLayers::default());
    settle(&mut app);
    assert!(shadow(&app).is_none());
}
