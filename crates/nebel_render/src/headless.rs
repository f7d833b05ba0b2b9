//! An app that drives nebel's level of detail without rendering, for tests
//! and servers: [`headless_app`], and cameras as Bevy's camera systems would
//! leave them ([`computed_camera`], [`spawn_computed_camera`]), which
//! [`LodCameras`](crate::LodCameras) picks like any active camera.

use std::path::Path;

use bevy::camera::{ComputedCameraValues, RenderTargetInfo};
use bevy::prelude::*;

use crate::HeavyBuilds;

/// An app with Bevy's minimal plugins, transforms and an asset server that
/// does not watch for changes (over `asset_folder`, or Bevy's default
/// folder), whose builds land in the frame that starts them
/// ([`HeavyBuilds::Blocking`]). Add the effects' plugins to it.
pub fn headless_app(asset_folder: Option<&Path>) -> App {
    let mut assets = AssetPlugin {
        watch_for_changes_override: Some(false),
        ..default()
    };
    if let Some(folder) = asset_folder {
        assets.file_path = folder.to_string_lossy().into_owned();
    }
    let mut app = App::new();
    app.add_plugins((MinimalPlugins, TransformPlugin, assets))
        .insert_resource(HeavyBuilds::Blocking);
    app
}

/// A camera as Bevy's camera systems leave it for a render target of
/// `physical_size` pixels: `clip_from_view` and the target already
/// computed.
pub fn computed_camera(clip_from_view: Mat4, physical_size: UVec2) -> Camera {
    Camera {
        computed: ComputedCameraValues {
            clip_from_view,
            target_info: Some(RenderTargetInfo {
                physical_size,
                scale_factor: 1.0,
            }),
            ..default()
        },
        ..default()
    }
}

/// Spawns a 3D camera placed by `transform` with the perspective projection
/// of `fov` (vertical, radians) computed for a target of `size` pixels,
/// near plane at 0.1 ([`computed_camera`]).
pub fn spawn_computed_camera(
    world: &mut World,
    fov: f32,
    size: UVec2,
    transform: Transform,
) -> Entity {
    let aspect = size.x as f32 / size.y.max(1) as f32;
    let projection = Mat4::perspective_infinite_reverse_rh(fov, aspect, 0.1);
    world
        .spawn((
            Camera3d::default(),
            computed_camera(projection, size),
            transform,
        ))
        .id()
}
