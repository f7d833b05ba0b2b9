//! Campfire: a night scene with an animated emissive fire, a flickering
//! point light and smoke rising above it, built with nebel's components.
//!
//! - [`Campfire`] regenerates its 16³ fire grid every frame and draws it
//!   emissive (no sorting needed);
//! - the smoke is a [`Volume`] with a [`VolumeGrid`] asset built from values
//!   (fractal noise faded to an ellipsoid), sorted back to front;
//! - [`FlickeringLight`] makes the point light flicker like firelight, and
//!   Bevy's [`VolumetricLight`] lets the smoke scatter it.
//!
//! `cargo run --release --example campfire` opens a window with a fly camera
//! (WASD, Q/E, Shift, right mouse button to look); with no display, or with
//! `-- --headless`, it renders to `target/nebel/campfire.png`.

use std::process::ExitCode;
use std::sync::Arc;

use bevy::camera::Hdr;
use bevy::light::VolumetricLight;
use bevy::math::DVec3;
use bevy::prelude::*;
use nebel::nebel_core::field::{DensityGrid, ProceduralNoise};
use nebel::nebel_core::local_light::LightResponse;
use nebel::nebel_core::optics::OpticalMode;
use nebel::nebel_core::transfer::{ControlPoint, TransferFunction, TransferPreset};
use nebel::prelude::*;
use nebel_tools::example_runner::Example;
use nebel_tools::nebel_scene::OutputSettings;

fn main() -> ExitCode {
    Example {
        name: "campfire",
        output: OutputSettings {
            width: 640,
            height: 400,
            frames: 12,
            frame_rate: 24.0,
        },
        fly_speed: 2.0,
    }
    .run(|app| {
        app.insert_resource(GlobalAmbientLight {
            color: Color::srgb(0.4, 0.5, 1.0),
            brightness: 20.0,
            ..default()
        })
        .add_systems(Startup, (spawn_camera_and_ground, spawn_fire, spawn_smoke));
    })
}

fn spawn_camera_and_ground(
    mut commands: Commands,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    commands.spawn((
        Camera3d::default(),
        Camera {
            clear_color: ClearColorConfig::Custom(Color::srgb(0.01, 0.012, 0.03)),
            ..default()
        },
        // nebel's volumes accumulate in float: render in HDR.
        Hdr,
        Projection::Perspective(PerspectiveProjection {
            fov: 50f32.to_radians(),
            ..default()
        }),
        Transform::from_xyz(-2.6, 1.2, 3.4).looking_at(Vec3::new(0.0, 0.8, 0.0), Vec3::Y),
    ));
    // Moonlight.
    commands.spawn((
        DirectionalLight {
            color: Color::srgb(0.5, 0.6, 1.0),
            illuminance: 30.0,
            ..default()
        },
        Transform::default().looking_to(Vec3::new(0.3, -1.0, 0.2), Vec3::Y),
    ));
    let mut solid = |mesh: Mesh, colour: Color, at: Vec3| {
        (
            Mesh3d(meshes.add(mesh)),
            MeshMaterial3d(materials.add(StandardMaterial {
                base_color: colour,
                perceptual_roughness: 0.9,
                ..default()
            })),
            Transform::from_translation(at),
        )
    };
    commands.spawn(solid(
        Plane3d::new(Vec3::Y, Vec2::splat(15.0)).into(),
        Color::srgb(0.18, 0.16, 0.12),
        Vec3::ZERO,
    ));
    for (size, colour) in [
        (Vec3::new(0.9, 0.14, 0.16), Color::srgb(0.25, 0.15, 0.08)),
        (Vec3::new(0.16, 0.14, 0.9), Color::srgb(0.22, 0.13, 0.07)),
    ] {
        commands.spawn(solid(
            Cuboid::from_size(size).into(),
            colour,
            Vec3::new(0.0, 0.08, 0.0),
        ));
    }
    commands.spawn(solid(
        Sphere::new(0.45).mesh().uv(48, 24),
        Color::srgb(0.35, 0.33, 0.3),
        Vec3::new(-1.6, 0.25, -1.2),
    ));
}

fn spawn_fire(mut commands: Commands) {
    // The flame box is [−0.5, 0.5] × [0, 1.5] × [−0.5, 0.5] of the entity:
    // lift it onto the logs. The fire preset three times as dense.
    let fire = TransferFunction::preset(TransferPreset::Fire)
        .scale_density(3.0)
        .expect("a finite factor");
    commands.spawn((
        Campfire {
            seed: 3,
            ..default()
        },
        Volume {
            transfer_function: Arc::new(fire),
            mode: OpticalMode::Emissive,
            ..default()
        },
        Transform::from_xyz(0.0, 0.05, 0.0),
    ));
    // Firelight: 60 000 lm, flickering by ±30 %, scattered by the smoke.
    commands.spawn((
        PointLight {
            color: Color::srgb(1.0, 0.55, 0.2),
            range: 12.0,
            shadow_maps_enabled: true,
            ..default()
        },
        FlickeringLight {
            base_intensity: 60_000.0,
            amplitude: 0.3,
        },
        VolumetricLight,
        Transform::from_xyz(0.0, 0.5, 0.0),
    ));
}

fn spawn_smoke(mut commands: Commands, mut grids: ResMut<Assets<VolumeGrid>>) {
    // 9 × 17 × 9 points of fractal noise over a 1.4 × 2.4 × 1.4 m box, kept
    // above a threshold and faded to zero towards an ellipsoid's surface.
    let dims = [9, 17, 9];
    let size = DVec3::new(1.4, 2.4, 1.4);
    let spacing = size / DVec3::new(8.0, 16.0, 8.0);
    let noise = ProceduralNoise {
        seed: 21,
        octaves: 3,
        frequency: 1.2,
        ..default()
    };
    let noise = DensityGrid::procedural(dims, spacing, DVec3::ZERO, &noise).expect("valid noise");
    let values = noise
        .values()
        .iter()
        .enumerate()
        .map(|(index, n)| {
            let point = DVec3::new(
                (index % 9) as f64,
                ((index / 9) % 17) as f64,
                (index / (9 * 17)) as f64,
            ) * spacing;
            let r = (point / size * 2.0 - 1.0).length_squared();
            ((n - 0.2) / 0.8).clamp(0.0, 1.0) * (1.0 - r as f32).max(0.0)
        })
        .collect();
    let smoke = DensityGrid::new(dims, spacing, DVec3::ZERO, values).expect("valid grid");
    // The smoke preset's colours at a fifth (its look at night), scattering
    // the fire's light fifteen times as strongly.
    let night_smoke = TransferFunction::new(
        TransferFunction::preset(TransferPreset::Smoke)
            .points()
            .iter()
            .map(|point| ControlPoint {
                kappa: point.kappa.map(|k| k / 5.0),
                rho: point.rho * 2.5,
                ..*point
            })
            .collect::<Vec<_>>(),
    )
    .expect("valid control points");
    commands.spawn((
        Volume {
            field: VolumeField::Grid(grids.add(VolumeGrid::from(smoke))),
            transfer_function: Arc::new(night_smoke),
            mode: OpticalMode::Sorted,
            light_response: LightResponse {
                asymmetry: 0.3,
                strength: 15.0,
            },
        },
        Transform::from_xyz(-0.7, 1.2, -0.7),
    ));
}
