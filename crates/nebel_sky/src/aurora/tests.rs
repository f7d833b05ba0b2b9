//! The aurora plugin in an app without a GPU: emissive cells that follow the
//! animation, a still map footprint, nothing for dark or hidden auroras, and
//! bad settings as a status.

use std::sync::Arc;
use std::time::Duration;

use bevy::prelude::*;
use bevy::time::TimeUpdateStrategy;
use nebel_core::optics::OpticalMode;
use nebel_render::CellBatch;
use nebel_render::GrayscaleMap;
use nebel_render::headless::{headless_app, spawn_computed_camera};

use super::{Aurora, AuroraFootprint, AuroraPlugin, AuroraStats, AuroraStatus};

/// An app with the aurora plugin, 1/30 s frames, and a camera on the ground
/// looking up at the aurora.
fn app() -> (App, Entity) {
    let mut app = headless_app(None);
    app.add_plugins(AuroraPlugin)
        .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
            1.0 / 30.0,
        )));
    let transform =
        Transform::from_xyz(0.0, 2.0, 0.0).looking_at(Vec3::new(0.0, 150e3, 80e3), Vec3::Y);
    let camera = spawn_computed_camera(app.world_mut(), 1.4, UVec2::new(96, 64), transform);
    (app, camera)
}

/// A small aurora (65 points per side) that is visible.
fn spawn(app: &mut App, aurora: Aurora) -> Entity {
    app.world_mut()
        .spawn((
            Aurora {
                resolution: 65,
                ..aurora
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

fn stats(app: &App, entity: Entity) -> AuroraStats {
    *app.world().get::<AuroraStats>(entity).unwrap()
}

fn status(app: &App, entity: Entity) -> AuroraStatus {
    app.world().get::<AuroraStatus>(entity).unwrap().clone()
}

#[test]
fn an_aurora_draws_emissive_cells_that_follow_its_animation() {
    let (mut app, _) = app();
    let aurora = spawn(&mut app, Aurora::default());
    settle(&mut app);
    assert_eq!(status(&app, aurora), AuroraStatus::Ready);
    let first = batch(&app, aurora).expect("a batch");
    assert_eq!(first.mode, OpticalMode::Emissive);
    assert!(first.is_drawable());
    let counts = stats(&app, aurora);
    assert_eq!(counts.tetrahedra as usize, first.cells.len());
    assert!(
        counts.tetrahedra > 50 && counts.prisms < counts.triangles,
        "{counts:?}"
    );
    // Every cell lies between the bottom and the top, its scalar the
    // altitude over the span.
    for cell in &first.cells.tetrahedra {
        for [_, y, _, s] in cell.vertices {
            assert!((100e3 - 1.0..=300e3 + 1.0).contains(&y), "{y}");
            assert!((s - (y - 100e3) / 200e3).abs() < 1e-4, "{s} at {y}");
        }
    }
    // Animated: each frame a new footprint and new cells.
    app.update();
    let second = batch(&app, aurora).unwrap();
    assert_ne!(first.cells.tetrahedra, second.cells.tetrahedra);
    assert_eq!(stats(&app, aurora).updates, counts.updates + 1);
    // Held still (speed 0) with a still camera: nothing is built again.
    app.world_mut().get_mut::<Aurora>(aurora).unwrap().speed = 0.0;
    settle(&mut app);
    let held = stats(&app, aurora).updates;
    settle(&mut app);
    assert_eq!(stats(&app, aurora).updates, held);
}

#[test]
fn a_map_footprint_draws_still_curtains() {
    let (mut app, camera) = app();
    // One bright band across the footprint.
    let side = 33;
    let values: Vec<f32> = (0..side * side)
        .map(|p| {
            if (14..19).contains(&(p / side)) {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let map = app
        .world_mut()
        .resource_mut::<Assets<GrayscaleMap>>()
        .add(GrayscaleMap {
            dims: UVec2::splat(side as u32),
            values: Arc::new(values),
        });
    let aurora = spawn(
        &mut app,
        Aurora {
            footprint: AuroraFootprint::Map(map),
            ..default()
        },
    );
    settle(&mut app);
    assert_eq!(status(&app, aurora), AuroraStatus::Ready);
    let cells = batch(&app, aurora).expect("a batch").cells;
    // The band's curtains reach the top.
    let highest = cells
        .tetrahedra
        .iter()
        .flat_map(|cell| cell.vertices)
        .map(|v| v[1])
        .fold(0.0, f32::max);
    assert!((highest - 300e3).abs() < 1.0, "{highest}");
    // Still: no new cells while the camera stands, nor when it moves by less
    // than a quarter of the footprint's spacing (9.4 km); new ones beyond.
    let updates = stats(&app, aurora).updates;
    settle(&mut app);
    assert_eq!(stats(&app, aurora).updates, updates);
    let mut transform = app.world_mut().get_mut::<Transform>(camera).unwrap();
    transform.translation.x += 2000.0;
    settle(&mut app);
    assert_eq!(stats(&app, aurora).updates, updates);
    let mut transform = app.world_mut().get_mut::<Transform>(camera).unwrap();
    transform.translation.x += 500.0;
    settle(&mut app);
    assert_eq!(stats(&app, aurora).updates, updates + 1);
}

#[test]
fn dark_hidden_and_invalid_auroras_draw_nothing() {
    let (mut app, _) = app();
    let dark = spawn(
        &mut app,
        Aurora {
            brightness: 0.0,
            ..default()
        },
    );
    let hidden = app
        .world_mut()
        .spawn((
            Aurora {
                resolution: 65,
                ..default()
            },
            InheritedVisibility::HIDDEN,
        ))
        .id();
    let invalid = [
        (
            Aurora {
                resolution: 100,
                ..default()
            },
            "resolution",
        ),
        (
            Aurora {
                brightness: f32::NAN,
                ..default()
            },
            "brightness",
        ),
        (
            Aurora {
                top: 50e3,
                ..default()
            },
            "top",
        ),
        (
            Aurora {
                speed: -1.0,
                ..default()
            },
            "speed",
        ),
        (
            Aurora {
                extent: 0.0,
                ..default()
            },
            "extent",
        ),
    ]
    .map(|(aurora, needle)| {
        let resolution = if aurora.resolution == 100 { 100 } else { 65 };
        let entity = app
            .world_mut()
            .spawn((
                Aurora {
                    resolution,
                    ..aurora
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
        let AuroraStatus::Failed(error) = status(&app, entity) else {
            panic!("{needle}: {:?}", status(&app, entity));
        };
        assert!(error.to_string().contains(needle), "{error}");
    }
    // Brightening the dark one draws it; removing the aurora removes its
    // batch.
    app.world_mut().get_mut::<Aurora>(dark).unwrap().brightness = 1e-5;
    settle(&mut app);
    assert!(batch(&app, dark).is_some());
    app.world_mut().entity_mut(dark).remove::<Aurora>();
    settle(&mut app);
    assert!(batch(&app, dark).is_none());
}
