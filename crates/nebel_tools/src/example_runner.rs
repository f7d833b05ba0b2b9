//! What every example does: load its scene file, open a window with a fly
//! camera, or render headless when there is no display.
//!
//! `cargo run --release --example NAME [-- --headless]`: without `--headless`
//! and with a display (`DISPLAY` or `WAYLAND_DISPLAY` set), a window opens;
//! otherwise the scene renders to `target/nebel/NAME.png` and the path is
//! printed.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use bevy::prelude::*;
use nebel_scene::SceneDescription;

use crate::fly_camera::{FlyCamera, FlyCameraPlugin};
use crate::headless::render_headless;
use crate::scene_setup::{SceneCamera, SceneSetupPlugin};
use nebel::NebelPlugins;

/// Runs the example `name` with the scene file `assets/scenes/NAME.ron`.
pub fn run_example(name: &str) -> ExitCode {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let scene_path = root.join("assets/scenes").join(format!("{name}.ron"));
    let setup = match SceneDescription::load(&scene_path)
        .and_then(|scene| SceneSetupPlugin::new(scene, &scene_path))
    {
        Ok(setup) => setup,
        Err(error) => {
            eprintln!("{name}: {error}");
            return ExitCode::FAILURE;
        }
    };
    let headless_asked = std::env::args().skip(1).any(|arg| arg == "--headless");
    let has_display = ["DISPLAY", "WAYLAND_DISPLAY"]
        .iter()
        .any(|var| std::env::var_os(var).is_some_and(|v| !v.is_empty()));
    if headless_asked || !has_display {
        let out: PathBuf = root.join("target/nebel").join(format!("{name}.png"));
        let why = if headless_asked {
            "--headless"
        } else {
            "no display"
        };
        eprintln!("{name}: {why}: rendering {} headless", scene_path.display());
        return match render_headless(setup, &out, true) {
            Ok(stats) => {
                println!(
                    "{name}: wrote {} ({} frames on {})",
                    out.display(),
                    stats.frames_rendered,
                    stats.adapter.name
                );
                ExitCode::SUCCESS
            }
            Err(error) => {
                eprintln!("{name}: {error}");
                ExitCode::FAILURE
            }
        };
    }
    App::new()
        .add_plugins((
            DefaultPlugins.set(WindowPlugin {
                primary_window: Some(Window {
                    title: format!("nebel: {name}"),
                    resolution: (setup.scene.output.width, setup.scene.output.height).into(),
                    ..default()
                }),
                ..default()
            }),
            NebelPlugins,
            setup,
            FlyCameraPlugin,
        ))
        .add_systems(PostStartup, attach_fly_camera)
        .run();
    ExitCode::SUCCESS
}

/// Gives the scene camera a fly camera whose speed suits the scene: a
/// twentieth of the distance to the point the scene looks at per second (at
/// least the default 10 m/s), so a kilometre-sized terrain is crossed in
/// seconds and a campfire is not.
fn attach_fly_camera(
    mut commands: Commands,
    scene: Res<crate::scene_setup::LoadedScene>,
    cameras: Query<Entity, With<SceneCamera>>,
) {
    let pose = scene.camera_pose_at(0.0);
    let distance = Vec3::from(pose.position).distance(Vec3::from(pose.look_at));
    let defaults = FlyCamera::default();
    for camera in &cameras {
        commands.entity(camera).insert(FlyCamera {
            speed: defaults.speed.max(distance / 20.0),
            ..defaults
        });
    }
}
