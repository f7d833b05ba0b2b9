//! What every example does besides building its scene: open a window with a
//! fly camera, or render headless when there is no display.
//!
//! `cargo run --release --example NAME [-- --headless]`: without `--headless`
//! and with a display (`DISPLAY` or `WAYLAND_DISPLAY` set), a window opens
//! and every 3D camera the example spawns gets a [`FlyCamera`]; otherwise the
//! example's frames render to `target/nebel/NAME.png` ([`render_headless`])
//! and the path is printed.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use bevy::prelude::*;
use nebel::NebelPlugins;
use nebel_scene::OutputSettings;

use crate::fly_camera::{FlyCamera, FlyCameraPlugin};
use crate::headless::{HeadlessOptions, render_headless};

/// An example's name, its headless output and its fly camera's speed.
#[derive(Clone, Debug)]
pub struct Example {
    /// The example's name: the window title and `target/nebel/NAME.png`.
    pub name: &'static str,
    /// Window size; image size, frames and frame rate of a headless run.
    pub output: OutputSettings,
    /// Fly camera speed, metres per second.
    pub fly_speed: f32,
}

impl Example {
    /// Runs the example: `add_scene` adds its systems (its scene) to the
    /// app, which already has Bevy's and nebel's plugins.
    pub fn run(self, add_scene: impl FnOnce(&mut App)) -> ExitCode {
        let headless_asked = std::env::args().skip(1).any(|arg| arg == "--headless");
        let has_display = ["DISPLAY", "WAYLAND_DISPLAY"]
            .iter()
            .any(|var| std::env::var_os(var).is_some_and(|v| !v.is_empty()));
        if headless_asked || !has_display {
            return self.run_headless(headless_asked, add_scene);
        }
        let mut app = App::new();
        app.add_plugins((
            DefaultPlugins.set(WindowPlugin {
                primary_window: Some(Window {
                    title: format!("nebel: {}", self.name),
                    resolution: (self.output.width, self.output.height).into(),
                    ..default()
                }),
                ..default()
            }),
            NebelPlugins,
            FlyCameraPlugin,
        ));
        add_scene(&mut app);
        let speed = self.fly_speed;
        app.add_systems(
            Update,
            move |mut commands: Commands, cameras: Query<Entity, Added<Camera3d>>| {
                for camera in &cameras {
                    commands
                        .entity(camera)
                        .insert(FlyCamera { speed, ..default() });
                }
            },
        );
        match app.run() {
            AppExit::Success => ExitCode::SUCCESS,
            AppExit::Error(_) => ExitCode::FAILURE,
        }
    }

    fn run_headless(self, asked: bool, add_scene: impl FnOnce(&mut App)) -> ExitCode {
        let root = Path::new(env!("CARGO_MANIFEST_DIR"))
            .ancestors()
            .nth(2)
            .expect("the tools crate lies two folders below the workspace root");
        let out: PathBuf = root.join("target/nebel").join(format!("{}.png", self.name));
        let why = if asked { "--headless" } else { "no display" };
        eprintln!("{}: {why}: rendering headless", self.name);
        let options = HeadlessOptions {
            progress: true,
            ..HeadlessOptions::default()
        };
        match render_headless(&self.output, options, &out, add_scene) {
            Ok(stats) => {
                println!(
                    "{}: wrote {} ({} frames on {})",
                    self.name,
                    out.display(),
                    stats.frames_rendered,
                    stats.adapter.name
                );
                ExitCode::SUCCESS
            }
            Err(error) => {
                eprintln!("{}: {error}", self.name);
                ExitCode::FAILURE
            }
        }
    }
}
