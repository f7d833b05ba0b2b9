//! Which camera drives nebel's level of detail, visibility order and culling.
//!
//! Every view-dependent nebel system (volume batches, terrain meshes) refines
//! and sorts for one camera per frame: the active 3D camera with a
//! [`LodCamera`] marker, or, when no active camera is marked, the active 3D
//! camera with the lowest [`Camera::order`] (ties broken by entity, so the
//! choice is stable from frame to frame). A camera whose projection Bevy has
//! not computed yet (its first frame) is skipped: a batch refined or culled
//! for the placeholder projection would be wrong. [`LodCameras::view`] gives
//! the chosen camera's [`LodView`].

use bevy::ecs::system::SystemParam;
use bevy::math::{DAffine3, DMat4, DVec3};
use bevy::prelude::*;
use nebel_lod::quadtree::TerrainView;

/// Marks the camera whose view drives nebel's level of detail (see the
/// module docs). Put it on one camera, e.g. the player's when a minimap
/// camera renders too. Without it, the active 3D camera with the lowest
/// `order` is used.
#[derive(Component, Clone, Copy, Debug, Default, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(Camera3d)]
pub struct LodCamera;

/// The view of the camera that drives the level of detail, this frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LodView {
    /// The camera entity.
    pub camera: Entity,
    /// The eye, world units (f64, so large worlds keep their precision).
    pub eye: DVec3,
    /// The camera's orientation in the world.
    pub rotation: Quat,
    /// The camera's projection: view space to clip space.
    pub clip_from_view: Mat4,
    /// World space to clip space, in f64 (the projection times the inverse
    /// of the camera's transform).
    pub clip_from_world: DMat4,
    /// The camera's world transform.
    pub world_from_view: GlobalTransform,
    /// The size of the camera's render target, physical pixels.
    pub viewport: UVec2,
}

/// Finds the camera that drives the level of detail (see the module docs).
#[derive(SystemParam)]
pub struct LodCameras<'w, 's> {
    cameras: Query<
        'w,
        's,
        (
            Entity,
            &'static Camera,
            &'static GlobalTransform,
            Has<LodCamera>,
        ),
        With<Camera3d>,
    >,
}

impl LodCameras<'_, '_> {
    /// The view of the marked active camera, else of the active 3D camera
    /// with the lowest order; `None` when no active camera has its
    /// projection yet.
    pub fn view(&self) -> Option<LodView> {
        let (camera, settings, transform, _) = self
            .cameras
            .iter()
            .filter(|(_, camera, _, _)| camera.is_active && camera.physical_target_size().is_some())
            .min_by_key(|(entity, camera, _, marked)| (!marked, camera.order, *entity))?;
        let clip_from_view = settings.clip_from_view();
        let world_from_view = transform.to_matrix();
        Some(LodView {
            camera,
            eye: transform.translation().as_dvec3(),
            rotation: transform.rotation(),
            clip_from_view,
            clip_from_world: to_double(clip_from_view) * to_double(world_from_view).inverse(),
            world_from_view: *transform,
            viewport: settings.physical_target_size()?,
        })
    }
}

/// `matrix` in f64.
pub fn to_double(matrix: Mat4) -> DMat4 {
    DMat4::from_cols_array(&matrix.to_cols_array().map(f64::from))
}

/// The world-from-local map of `transform` in f64.
pub fn to_double_affine(transform: &GlobalTransform) -> DAffine3 {
    DAffine3::from_mat4(to_double(transform.to_matrix()))
}

impl LodView {
    /// This camera seen from a surface placed by `world_from_local` (a
    /// terrain, a layer between two surfaces).
    pub fn seen_from(&self, world_from_local: DAffine3) -> TerrainView {
        TerrainView {
            world_from_view: to_double_affine(&self.world_from_view),
            clip_from_view: to_double(self.clip_from_view),
            world_from_terrain: world_from_local,
        }
    }
}

#[cfg(test)]
mod tests {
    use bevy::camera::{ComputedCameraValues, RenderTargetInfo};

    use super::*;

    fn camera(order: isize, active: bool, projected: bool) -> Camera {
        Camera {
            order,
            is_active: active,
            computed: ComputedCameraValues {
                clip_from_view: Mat4::perspective_infinite_reverse_rh(1.0, 1.0, 0.1),
                target_info: projected.then_some(RenderTargetInfo {
                    physical_size: UVec2::new(64, 48),
                    scale_factor: 1.0,
                }),
                ..default()
            },
            ..default()
        }
    }

    fn chosen(world: &mut World) -> Option<LodView> {
        world
            .run_system_once(|cameras: LodCameras| cameras.view())
            .unwrap()
    }

    use bevy::ecs::system::RunSystemOnce;

    #[test]
    fn the_marked_camera_wins_else_the_lowest_order() {
        let mut world = World::new();
        assert_eq!(chosen(&mut world), None, "no camera");
        let at = |x: f32| GlobalTransform::from_translation(Vec3::new(x, 0.0, 0.0));
        world.spawn((Camera3d::default(), camera(0, true, false), at(9.0)));
        assert_eq!(chosen(&mut world), None, "no projection yet");
        let second = world
            .spawn((Camera3d::default(), camera(2, true, true), at(2.0)))
            .id();
        let first = world
            .spawn((Camera3d::default(), camera(1, true, true), at(1.0)))
            .id();
        world.spawn((Camera3d::default(), camera(-1, false, true), at(5.0)));
        let view = chosen(&mut world).unwrap();
        assert_eq!(view.camera, first, "the lowest active order");
        assert_eq!(view.eye, DVec3::X);
        assert_eq!(view.viewport, UVec2::new(64, 48));

        world.entity_mut(second).insert(LodCamera);
        assert_eq!(chosen(&mut world).unwrap().camera, second, "the marker");
        world.get_mut::<Camera>(second).unwrap().is_active = false;
        assert_eq!(chosen(&mut world).unwrap().camera, first, "inactive");
    }

    #[test]
    fn clip_from_world_is_the_projection_of_the_inverse_transform() {
        let mut world = World::new();
        let transform = Transform::from_xyz(3.0, 4.0, 5.0).looking_at(Vec3::ZERO, Vec3::Y);
        world.spawn((
            Camera3d::default(),
            camera(0, true, true),
            GlobalTransform::from(transform),
        ));
        let view = chosen(&mut world).unwrap();
        let origin = view.clip_from_world * bevy::math::DVec4::new(0.0, 0.0, 0.0, 1.0);
        // The origin lies straight ahead: the centre of the image.
        assert!((origin.x / origin.w).abs() < 1e-6 && (origin.y / origin.w).abs() < 1e-6);
    }
}
