//! Aurora: a night over snowy mountains (a procedural terrain of 513 × 513
//! points 20 m apart through the quadtree C-LOD, [`Terrain`]), stars, and an
//! aurora to the north ([`Aurora`]): four seeded arcs with folds and rays
//! over a 600 km square 350 km away, rising from 100 km up to 300 km where strongest,
//! drawn as emissive prisms between two surfaces (Röttger 2004 §10.4),
//! coloured by altitude (oxygen's green 557.7 nm line low, its red 630.0 nm
//! line high), swaying, folding and pulsing over time.
//!
//! `cargo run --release --example aurora` opens a window with a fly camera
//! (WASD, Q/E down and up, Shift, right mouse button to look); `Space`
//! holds and releases the animation. With no display, or with
//! `-- --headless`, it renders to `target/nebel/aurora.png`. The same scene
//! is `assets/scenes/aurora.ron` for `nebel render`.

use std::process::ExitCode;

use bevy::camera::Hdr;
use bevy::prelude::*;
use nebel::prelude::*;
use nebel_tools::example_runner::Example;
use nebel_tools::nebel_scene::{OutputSettings, StarsDescription};
use nebel_tools::stars::spawn_stars;

fn main() -> ExitCode {
    let output = OutputSettings {
        width: 640,
        height: 360,
        frames: 3,
        frame_rate: 30.0,
    };
    let height = output.height;
    Example {
        name: "aurora",
        output,
        fly_speed: 300.0,
    }
    .run(move |app| {
        app.insert_resource(GlobalAmbientLight {
            color: Color::srgb(0.4, 0.5, 0.8),
            brightness: 40.0,
            ..default()
        })
        .add_systems(
            Startup,
            move |mut commands: Commands,
                  mut meshes: ResMut<Assets<Mesh>>,
                  mut materials: ResMut<Assets<StandardMaterial>>| {
                spawn_night(&mut commands);
                // Stars about 1.5 pixels across.
                let fov = 75f32.to_radians();
                spawn_stars(
                    &mut commands,
                    &mut meshes,
                    &mut materials,
                    &StarsDescription::default(),
                    1.5 * fov / height as f32,
                    CAMERA,
                );
            },
        )
        .add_systems(Update, hold_animation);
    })
}

/// Where the camera starts: on a ridge, 1.1 km up.
const CAMERA: Vec3 = Vec3::new(0.0, 1100.0, 2500.0);

/// `Space` holds the curtains still and lets them move again.
fn hold_animation(keys: Option<Res<ButtonInput<KeyCode>>>, mut auroras: Query<&mut Aurora>) {
    let Some(keys) = keys else {
        return;
    };
    if keys.just_pressed(KeyCode::Space) {
        for mut aurora in &mut auroras {
            aurora.speed = if aurora.speed > 0.0 { 0.0 } else { 1.0 };
        }
    }
}

fn spawn_night(commands: &mut Commands) {
    commands.spawn((
        Camera3d::default(),
        Camera {
            clear_color: ClearColorConfig::Custom(Color::srgb(0.004, 0.008, 0.03)),
            ..default()
        },
        Hdr,
        Projection::Perspective(PerspectiveProjection {
            fov: 75f32.to_radians(),
            near: 1.0,
            ..default()
        }),
        Transform::from_translation(CAMERA)
            .looking_at(Vec3::new(0.0, 70_000.0, -300_000.0), Vec3::Y),
        // The terrain's level of detail follows this camera.
        LodCamera,
    ));
    // Moonlight.
    commands.spawn((
        DirectionalLight {
            color: Color::srgb(0.55, 0.65, 1.0),
            illuminance: 400.0,
            ..default()
        },
        Transform::default().looking_to(Vec3::new(0.4, -0.5, 0.8), Vec3::Y),
    ));
    commands.spawn(Terrain {
        source: TerrainSource::Procedural {
            size: 513,
            noise: TerrainNoise {
                seed: 11,
                octaves: 8,
                wavelength: 3000.0,
                exponent: 1.6,
                ..default()
            },
        },
        spacing: 20.0,
        vertical_scale: 900.0,
        accuracy: 200.0,
        min_accuracy: 2.0,
        ..default()
    });
    // The curtains' footprint is centred 350 km to the north; they stand
    // from 100 km up.
    commands.spawn((
        Aurora {
            footprint: AuroraFootprint::Curtains(AuroraCurtains {
                seed: 3,
                count: 4,
                width: 0.006,
                ..default()
            }),
            ..default()
        },
        Transform::from_xyz(0.0, 0.0, -350_000.0),
    ));
}
