//! The cloud-layer plugin in an app without a GPU: sorted cells lit from
//! above, re-sorted as the eye moves, relit as the sun moves, two map
//! surfaces, nothing for dark or hidden layers, and bad settings as a
//! status.

use std::sync::Arc;

use bevy::prelude::*;
use nebel_core::optics::OpticalMode;
use nebel_render::GrayscaleMap;
use nebel_render::headless::{headless_app, spawn_computed_camera};
use nebel_render::{CellBatch, HeavyBuilds};

use super::{CloudLayer, CloudLayerPlugin, CloudLayerSource, CloudLayerStats, CloudLayerStatus};

/// An app with the cloud-layer plugin, a sun 60° up, and a camera below the
/// clouds looking up at them.
fn app() -> (App, Entity, Entity) {
    let mut app = headless_app(None);
    app.add_plugins(CloudLayerPlugin);
    let transform =
        Transform::from_xyz(0.0, 300.0, 4000.0).looking_at(Vec3::new(0.0, 1500.0, 0.0), Vec3::Y);
    let camera = spawn_computed_camera(app.world_mut(), 1.2, UVec2::new(96, 64), transform);
    let sun = app
        .world_mut()
        .spawn((
            DirectionalLight::default(),
            Transform::default().looking_to(Vec3::new(0.5, -3f32.sqrt(), 0.0), Vec3::Y),
        ))
        .id();
    (app, camera, sun)
}

fn spawn(app: &mut App, layer: CloudLayer) -> Entity {
    app.world_mut()
        .spawn((
            CloudLayer {
                resolution: 65,
                extent: 10e3,
                ..layer
            },
            InheritedVisibility::VISIBLE,
        ))
        .id()
}

fn settle(app: &mut App) {
    for _ in 0..3 {
        app.update();
    }
}

fn batch(app: &App, entity: Entity) -> Option<CellBatch> {
    app.world().get::<CellBatch>(entity).cloned()
}

fn stats(app: &App, entity: Entity) -> CloudLayerStats {
    *app.world().get::<CloudLayerStats>(entity).unwrap()
}

fn status(app: &App, entity: Entity) -> CloudLayerStatus {
    app.world().get::<CloudLayerStatus>(entity).unwrap().clone()
}

/// The mean light of the cells' vertices in the lower and upper half of
/// the layer's altitudes.
fn light_below_and_above(batch: &CellBatch, middle: f32) -> (f32, f32) {
    let (mut below, mut above) = ((0.0, 0), (0.0, 0));
    for cell in &batch.cells.tetrahedra {
        for [_, y, _, s] in cell.vertices {
            let side = if y < middle { &mut below } else { &mut above };
            side.0 += s;
            side.1 += 1;
        }
    }
    (below.0 / below.1 as f32, above.0 / above.1 as f32)
}

#[test]
fn a_cloud_layer_draws_sorted_cells_lit_from_above_that_follow_eye_and_sun() {
    let (mut app, camera, sun) = app();
    let layer = spawn(&mut app, CloudLayer::default());
    settle(&mut app);
    assert_eq!(status(&app, layer), CloudLayerStatus::Ready);
    let first = batch(&app, layer).expect("a batch");
    assert_eq!(first.mode, OpticalMode::Sorted);
    let counts = stats(&app, layer);
    assert_eq!(counts.tetrahedra as usize, first.cells.len());
    assert!(counts.tetrahedra > 100, "{counts:?}");
    // Between the base's sag and the tops: 1500 m − 0.2 · 700 m to
    // 1500 m + 0.8 · 700 m.
    for cell in &first.cells.tetrahedra {
        for [_, y, _, s] in cell.vertices {
            assert!((1360.0 - 1.0..=2060.0 + 1.0).contains(&y), "{y}");
            assert!((0.3..=1.0).contains(&s), "{s}");
        }
    }
    // Bright tops, darker bases.
    let (below, above) = light_below_and_above(&first, 1500.0);
    assert!(above > below + 0.05, "{below} below, {above} above");
    // Still: nothing again, nor after a move under a quarter of the layer's
    // spacing (156 m) and a turn under 3°; beyond them: sorted again.
    settle(&mut app);
    assert_eq!(stats(&app, layer).updates, counts.updates);
    let mut transform = app.world_mut().get_mut::<Transform>(camera).unwrap();
    transform.translation.x += 30.0;
    transform.rotate_y(2f32.to_radians());
    settle(&mut app);
    assert_eq!(stats(&app, layer).updates, counts.updates);
    app.world_mut()
        .get_mut::<Transform>(camera)
        .unwrap()
        .translation
        .x += 20.0;
    settle(&mut app);
    assert_eq!(stats(&app, layer).updates, counts.updates + 1);
    app.world_mut()
        .get_mut::<Transform>(camera)
        .unwrap()
        .rotate_y(4f32.to_radians());
    settle(&mut app);
    assert_eq!(stats(&app, layer).updates, counts.updates + 2);
    // A low sun: the light falls.
    *app.world_mut().get_mut::<Transform>(sun).unwrap() =
        Transform::default().looking_to(Vec3::new(1.0, -0.2, 0.0), Vec3::Y);
    settle(&mut app);
    let low = batch(&app, layer).unwrap();
    let (low_below, _) = light_below_and_above(&low, 1500.0);
    assert!(low_below < below, "{low_below} vs {below}");
}

#[test]
fn two_map_surfaces_give_clouds_where_the_top_lies_above_the_bottom() {
    let (mut app, _, _) = app();
    let side = 17;
    let map = |values: Vec<f32>| GrayscaleMap {
        dims: UVec2::splat(side as u32),
        values: Arc::new(values),
    };
    // The top at 0.5 everywhere, the bottom at 0.25 on the left half and 1
    // (above the top: no cloud) on the right.
    let bottom: Vec<f32> = (0..side * side)
        .map(|p| if p % side < side / 2 { 0.25 } else { 1.0 })
        .collect();
    let mut maps = app.world_mut().resource_mut::<Assets<GrayscaleMap>>();
    let (bottom, top) = (maps.add(map(bottom)), maps.add(map(vec![0.5; side * side])));
    let layer = spawn(
        &mut app,
        CloudLayer {
            source: CloudLayerSource::Maps {
                bottom,
                top,
                scale: 400.0,
            },
            ..default()
        },
    );
    settle(&mut app);
    assert_eq!(status(&app, layer), CloudLayerStatus::Ready);
    let cells = batch(&app, layer).expect("a batch").cells;
    for cell in &cells.tetrahedra {
        for [x, y, _, _] in cell.vertices {
            // The left half (x < 0 on the 10 km square), from 1600 m up to
            // the top at 1700 m; where the surfaces cross, a column's corner
            // of no thickness lies on the bottom, up to 1900 m.
            assert!(x < 1.0, "a cloud at x = {x}");
            assert!((1600.0 - 1.0..=1900.0 + 1.0).contains(&y), "{y}");
        }
    }
    // Far from the crossing, the clouds lie between the two surfaces.
    for cell in &cells.tetrahedra {
        if cell.vertices.iter().all(|v| v[0] < -1000.0) {
            for [_, y, _, _] in cell.vertices {
                assert!((1600.0 - 1.0..=1700.0 + 1.0).contains(&y), "{y}");
            }
        }
    }
}

#[test]
fn dark_hidden_and_invalid_cloud_layers_draw_nothing() {
    let (mut app, _, _) = app();
    let dark = spawn(
        &mut app,
        CloudLayer {
            density: 0.0,
            ..default()
        },
    );
    let hidden = app
        .world_mut()
        .spawn((
            CloudLayer {
                resolution: 65,
                ..default()
            },
            InheritedVisibility::HIDDEN,
        ))
        .id();
    let invalid = [
        (
            CloudLayer {
                resolution: 64,
                ..default()
            },
            "resolution",
        ),
        (
            CloudLayer {
                ambient: 2.0,
                ..default()
            },
            "ambient",
        ),
        (
            CloudLayer {
                shadow_extinction: f32::NAN,
                ..default()
            },
            "shadow_extinction",
        ),
        (
            CloudLayer {
                sag: -0.5,
                ..default()
            },
            "sag",
        ),
        (
            CloudLayer {
                scattering_octaves: 0,
                ..default()
            },
            "scattering_octaves",
        ),
    ]
    .map(|(layer, needle)| {
        let resolution = if layer.resolution == 64 { 64 } else { 65 };
        let entity = app
            .world_mut()
            .spawn((
                CloudLayer {
                    resolution,
                    ..layer
                },
                InheritedVisibility::VISIBLE,
            ))
            .id();
        (entity, needle)
    });
    settle(&mut app);
    for entity in [dark, hidden] {
        assert!(batch(&app, entity).is_none());
        assert_eq!(stats(&app, entity).updates, 0);
    }
    for (entity, needle) in invalid {
        assert!(batch(&app, entity).is_none());
        let CloudLayerStatus::Failed(error) = status(&app, entity) else {
            panic!("{needle}: {:?}", status(&app, entity));
        };
        assert!(error.to_string().contains(needle), "{error}");
    }
}

#[test]
fn in_the_background_the_last_cells_draw_until_the_new_ones_land_as_same_frame_ones_would() {
    let (mut blocking, blocking_camera, _) = app();
    let (mut background, background_camera, _) = app();
    background.insert_resource(HeavyBuilds::Background);
    let layers = [&mut blocking, &mut background].map(|app| spawn(app, CloudLayer::default()));
    // Bounded waits for the background's builds: a guard against a hang.
    let land = |app: &mut App, layer: Entity, after: u64| {
        for _ in 0..10_000 {
            app.update();
            if stats(app, layer).updates > after {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        panic!("no build landed");
    };
    settle(&mut blocking);
    land(&mut background, layers[1], 0);
    for (app, camera) in [
        (&mut blocking, blocking_camera),
        (&mut background, background_camera),
    ] {
        app.world_mut()
            .get_mut::<Transform>(camera)
            .unwrap()
            .translation
            .x += 300.0;
    }
    let drawn = batch(&background, layers[1]).expect("a batch");
    let updates = stats(&background, layers[1]).updates;
    background.update();
    // The frame that starts a build draws what it had, unless the build
    // already landed.
    if stats(&background, layers[1]).updates == updates {
        assert_eq!(batch(&background, layers[1]).unwrap().cells, drawn.cells);
    }
    land(&mut background, layers[1], updates);
    settle(&mut blocking);
    let (same_frame, landed) = (
        batch(&blocking, layers[0]).unwrap(),
        batch(&background, layers[1]).unwrap(),
    );
    assert_ne!(landed.cells, drawn.cells, "refined for the new eye");
    assert_eq!(landed.cells, same_frame.cells);
}
