//! Valley fog: a procedural terrain of 513 × 513 points 10 m apart with
//! 700 m of relief, drawn through the quadtree C-LOD with geomorphing
//! ([`Terrain`]), under a low sun, with ground fog ([`GroundFog`]) lying in
//! its valleys: prisms on the terrain's own triangles, morphed with it,
//! drawn back to front by cell projection (Röttger and Ertl 2003 §6), and
//! beyond 3 km as fog layers ([`FogLayers`], Röttger 2004 §5.3): the same
//! fog as a function of altitude, in one full-screen pass. Above the hills a
//! thin cumulus layer ([`CloudVolume`]) drifts in a 10 m/s wind, drawn from
//! keyframes 4 s apart blended on the GPU, lit by the sun with shadows.
//!
//! `cargo run --release --example valley_fog` opens a window with a fly
//! camera (WASD, Q/E down and up, Shift, right mouse button to look): fly
//! down into the fog. `F` cycles the fog's thickness between the valleys
//! filled to 110 m, noise patches and the painted map
//! `assets/fog/valley_fog_map.png`; `G` shows the prisms' edges. With no
//! display, or with `-- --headless`, it renders to
//! `target/nebel/valley_fog.png`.

use std::process::ExitCode;
use std::sync::Arc;

use bevy::camera::Hdr;
use bevy::math::DVec3;
use bevy::prelude::*;
use nebel::nebel_core::field::CloudNoise;
use nebel::nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel::prelude::*;
use nebel_tools::example_runner::Example;
use nebel_tools::nebel_scene::OutputSettings;

fn main() -> ExitCode {
    Example {
        name: "valley_fog",
        output: OutputSettings {
            width: 640,
            height: 360,
            frames: 4,
            frame_rate: 60.0,
        },
        fly_speed: 150.0,
    }
    .run(|app| {
        app.insert_resource(GlobalAmbientLight {
            color: Color::srgb(0.6, 0.7, 0.9),
            brightness: 1500.0,
            ..default()
        })
        .add_systems(Startup, spawn_valley)
        .add_systems(Update, switch_fog);
    })
}

/// The valleys filled up to 110 m, the shore ragged by ±15 m.
fn valley_fill() -> FogThickness {
    FogThickness::Valley(ValleyFog {
        altitude: 110.0,
        edge: 15.0,
        ..default()
    })
}

/// `F`: valley fill → noise patches → painted map; `G`: the prisms' edges.
fn switch_fog(
    keys: Option<Res<ButtonInput<KeyCode>>>,
    assets: Res<AssetServer>,
    mut fogs: Query<&mut GroundFog>,
) {
    let Some(keys) = keys else {
        return;
    };
    for mut fog in &mut fogs {
        if keys.just_pressed(KeyCode::KeyF) {
            fog.thickness = match fog.thickness {
                FogThickness::Valley(_) => FogThickness::Noise(FogNoise {
                    thickness: 50.0,
                    coverage: 0.4,
                    ..default()
                }),
                FogThickness::Noise(_) => FogThickness::Map {
                    map: assets.load("fog/valley_fog_map.png"),
                    scale: 80.0,
                },
                FogThickness::Map { .. } => valley_fill(),
            };
        }
        if keys.just_pressed(KeyCode::KeyG) {
            fog.debug.wireframe = !fog.debug.wireframe;
        }
    }
}

fn spawn_valley(mut commands: Commands) {
    commands.spawn((
        Camera3d::default(),
        Camera {
            clear_color: ClearColorConfig::Custom(Color::srgb(0.55, 0.65, 0.8)),
            ..default()
        },
        Hdr,
        Projection::Perspective(PerspectiveProjection {
            fov: 55f32.to_radians(),
            near: 1.0,
            ..default()
        }),
        Transform::from_xyz(2400.0, 950.0, 2400.0)
            .looking_at(Vec3::new(-300.0, 0.0, -300.0), Vec3::Y),
        // The level of detail follows this camera.
        LodCamera,
        // Beyond 3 km the fog is drawn as layers of altitude (one pass),
        // nearer as the prisms of the ground fog.
        FogLayers {
            layers: vec![HeightFogLayer::Linear(vec![[0.0, 0.015], [110.0, 0.0]])],
            color: Color::linear_rgb(0.77, 0.8, 0.86),
            start_distance: 3000.0,
            max_distance: 8000.0,
            ..default()
        },
    ));
    commands.spawn((
        DirectionalLight {
            color: Color::srgb(1.0, 0.9, 0.75),
            illuminance: 9000.0,
            ..default()
        },
        Transform::default().looking_to(Vec3::new(-0.3, -0.45, -1.0), Vec3::Y),
    ));
    // 513 × 513 points of fBm noise (8 octaves from 2.2 km), the exponent
    // 2.2 widening the valley floors; c = 300 keeps a left-out detail under
    // about two pixels.
    commands.spawn((
        Terrain {
            source: TerrainSource::Procedural {
                size: 513,
                noise: TerrainNoise {
                    seed: 4,
                    octaves: 8,
                    wavelength: 2200.0,
                    exponent: 2.2,
                    ..default()
                },
            },
            spacing: 10.0,
            vertical_scale: 700.0,
            accuracy: 300.0,
            min_accuracy: 2.0,
            ..default()
        },
        // Fog in the valleys: 0.015/m at the ground, clear at its top.
        GroundFog {
            thickness: valley_fill(),
            density: 0.015,
            ..default()
        },
    ));
    // Drifting clouds over the hills: 129 × 17 × 129 points over 8 km,
    // 900 to 1,400 m up, a 10 m/s wind (finer octaves faster).
    commands.spawn((
        CloudVolume {
            dims: UVec3::new(129, 17, 129),
            min: Vec3::new(-4000.0, 900.0, -4000.0),
            max: Vec3::new(4000.0, 1400.0, 4000.0),
            noise: CloudNoise {
                seed: 3,
                coverage: 0.3,
                octaves: 5,
                wavelength: 1600.0,
                wind: DVec3::new(10.0, 0.0, 3.0),
                ..default()
            },
            keyframe_interval: 4.0,
            ..default()
        },
        // Thin: the light preset's opacity at 3 % per metre of density.
        Volume {
            transfer_function: Arc::new(
                TransferFunction::preset(TransferPreset::CloudLight)
                    .scale_density(0.03)
                    .expect("a finite scale"),
            ),
            ..CloudVolume::lit_volume()
        },
        VolumeLighting {
            shadow_extinction: 0.008,
            ..default()
        },
    ));
}
