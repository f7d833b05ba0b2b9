//! A fly camera for the example scenes: WASD to move, Q/E down/up, Shift to go
//! fast, hold the right mouse button and move the mouse to look around.
//!
//! Adding [`FlyCamera`] to the scene camera takes it off its keyframe path.

use bevy::input::mouse::AccumulatedMouseMotion;
use bevy::prelude::*;

use crate::scene_setup::SceneCamera;

/// Makes a camera fly under keyboard and mouse control.
#[derive(Component, Clone, Copy, Debug, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct FlyCamera {
    /// Speed in metres per second. Default: 10.
    pub speed: f32,
    /// Speed factor while Shift is held. Default: 5.
    pub fast_factor: f32,
    /// Radians of turn per pixel of mouse motion. Default: 0.003.
    pub sensitivity: f32,
}

impl Default for FlyCamera {
    fn default() -> Self {
        Self {
            speed: 10.0,
            fast_factor: 5.0,
            sensitivity: 0.003,
        }
    }
}

/// Moves every [`FlyCamera`] from the keyboard and mouse.
#[derive(Default)]
pub struct FlyCameraPlugin;

impl Plugin for FlyCameraPlugin {
    fn build(&self, app: &mut App) {
        app.register_type::<FlyCamera>().add_systems(Update, fly);
    }
}

fn fly(
    time: Res<Time>,
    keys: Res<ButtonInput<KeyCode>>,
    buttons: Res<ButtonInput<MouseButton>>,
    motion: Res<AccumulatedMouseMotion>,
    mut cameras: Query<(&FlyCamera, &mut Transform, Option<&mut SceneCamera>)>,
) {
    for (fly, mut transform, scene_camera) in &mut cameras {
        if let Some(mut scene_camera) = scene_camera {
            scene_camera.follows_path = false;
        }
        if buttons.pressed(MouseButton::Right) && motion.delta != Vec2::ZERO {
            let (mut yaw, mut pitch, _) = transform.rotation.to_euler(EulerRot::YXZ);
            yaw -= motion.delta.x * fly.sensitivity;
            pitch = (pitch - motion.delta.y * fly.sensitivity).clamp(-1.54, 1.54);
            transform.rotation = Quat::from_euler(EulerRot::YXZ, yaw, pitch, 0.0);
        }
        let axis = |positive: KeyCode, negative: KeyCode| {
            f32::from(u8::from(keys.pressed(positive)))
                - f32::from(u8::from(keys.pressed(negative)))
        };
        let local = Vec3::new(
            axis(KeyCode::KeyD, KeyCode::KeyA),
            axis(KeyCode::KeyE, KeyCode::KeyQ),
            axis(KeyCode::KeyS, KeyCode::KeyW),
        );
        if local != Vec3::ZERO {
            let fast = keys.any_pressed([KeyCode::ShiftLeft, KeyCode::ShiftRight]);
            let speed = fly.speed * if fast { fly.fast_factor } else { 1.0 };
            let direction = transform.rotation * local.normalize();
            transform.translation += direction * speed * time.delta_secs();
        }
    }
}
