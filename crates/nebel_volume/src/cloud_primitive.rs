//! Cloud primitives: implicit ellipsoids a designer places under a cloud.
//!
//! A [`CloudPrimitive`] on a child entity of a [`CloudVolume`] is one of the
//! implicit ellipsoids of Schpok et al. 2003 §3.1 that shape the cloud: its
//! [`Transform`] (relative to the cloud, as Bevy's hierarchy has it) places a
//! unit sphere, so the translation is the centre, the rotation the axes and
//! the scale the radii, at time 0 of the app's clock: a primitive that moves
//! or grows is where `velocity` and `growth` have taken it by the elapsed
//! time. Their fields blend by Wyvill's function and scale the
//! cloud's coverage (`nebel_core::field::CloudShape`): the noise fills their
//! cores and frays their surfaces. Moving or growing ones animate the cloud
//! through its keyframes like the wind.
//!
//! [`VolumePlugin`](crate::VolumePlugin) keeps [`CloudVolume::primitives`]
//! equal to the children's whenever they change, and clears it when the last
//! is removed.

use bevy::math::DQuat;
use bevy::prelude::*;
use nebel_core::field::CloudEllipsoid;

use crate::CloudVolume;

/// An implicit ellipsoid shaping its parent [`CloudVolume`]: the unit sphere
/// placed by the entity's [`Transform`] (centre, axes and radii), with the
/// weight and motion below.
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(Transform)]
pub struct CloudPrimitive {
    /// Weight of its field, ≥ 0: 1 gives the cloud's full coverage at the
    /// centre; overlapping primitives add up to at most 1. Default 1.
    pub density: f32,
    /// Drift of its centre, the cloud's local units per second (a path, or a
    /// rise where `y > 0`). Default zero.
    pub velocity: Vec3,
    /// Growth of its radii per second: `(1 + growth · t)` times the scale;
    /// it vanishes once that reaches 0. Default 0.
    pub growth: f32,
}

impl Default for CloudPrimitive {
    fn default() -> Self {
        Self {
            density: 1.0,
            velocity: Vec3::ZERO,
            growth: 0.0,
        }
    }
}

impl CloudPrimitive {
    /// The ellipsoid this primitive places with `transform`.
    pub fn ellipsoid(&self, transform: &Transform) -> CloudEllipsoid {
        CloudEllipsoid {
            centre: transform.translation.as_dvec3(),
            radii: transform.scale.abs().as_dvec3(),
            rotation: DQuat::from_array(transform.rotation.to_array().map(f64::from)),
            density: self.density,
            velocity: self.velocity.as_dvec3(),
            growth: f64::from(self.growth),
        }
    }
}

/// Marks a cloud whose primitives came from its children, so removing the
/// last child clears them (internal).
#[derive(Component, Default)]
pub(crate) struct PrimitivesFromChildren(bool);

/// Writes each cloud's [`CloudPrimitive`] children into
/// [`CloudVolume::primitives`] when one changed (a child's primitive or
/// transform, a child added or removed) and the list differs, so the cloud is
/// generated again; a cloud that never had such children is left as set.
pub(crate) fn gather_cloud_primitives(
    mut clouds: Query<(
        &mut CloudVolume,
        Option<Ref<Children>>,
        &mut PrimitivesFromChildren,
    )>,
    primitives: Query<(&CloudPrimitive, &Transform)>,
    changed: Query<
        (),
        (
            With<CloudPrimitive>,
            Or<(Changed<CloudPrimitive>, Changed<Transform>)>,
        ),
    >,
    mut removed: RemovedComponents<CloudPrimitive>,
) {
    let removed = removed.read().count() > 0;
    for (mut cloud, children, mut from_children) in &mut clouds {
        let touched = match &children {
            Some(children) => {
                removed
                    || children.is_changed()
                    || children.iter().any(|child| changed.contains(child))
            }
            // The last child gone takes the children's primitives with it.
            None => from_children.0,
        };
        if !touched {
            continue;
        }
        let gathered: Vec<CloudEllipsoid> = children
            .iter()
            .flat_map(|children| children.iter())
            .filter_map(|child| primitives.get(child).ok())
            .map(|(primitive, transform)| primitive.ellipsoid(transform))
            .collect();
        if gathered.is_empty() && !from_children.0 {
            continue;
        }
        from_children.0 = !gathered.is_empty();
        if cloud.primitives != gathered {
            cloud.primitives = gathered;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::math::DVec3;

    #[test]
    fn a_primitives_transform_places_its_ellipsoid() {
        let transform = Transform::from_xyz(1.0, 2.0, 3.0)
            .with_rotation(Quat::from_rotation_y(0.5))
            .with_scale(Vec3::new(4.0, 5.0, 6.0));
        let primitive = CloudPrimitive {
            density: 0.5,
            velocity: Vec3::new(0.0, 1.0, 0.0),
            growth: 0.1,
        };
        let e = primitive.ellipsoid(&transform);
        assert_eq!(e.centre, DVec3::new(1.0, 2.0, 3.0));
        assert_eq!(e.radii, DVec3::new(4.0, 5.0, 6.0));
        // The ellipsoid's x axis turns with the transform's.
        let axis = e.rotation * DVec3::X;
        assert!((axis - (transform.rotation * Vec3::X).as_dvec3()).length() < 1e-6);
        assert_eq!(
            (e.density, e.velocity, e.growth),
            (0.5, DVec3::Y, f64::from(0.1f32))
        );
    }

    #[test]
    fn a_clouds_primitives_follow_its_children() {
        let mut app = App::new();
        app.add_systems(Update, gather_cloud_primitives);
        let own = CloudEllipsoid {
            centre: DVec3::splat(5.0),
            ..CloudEllipsoid::default()
        };
        let cloud = app
            .world_mut()
            .spawn((
                CloudVolume {
                    primitives: vec![own],
                    ..default()
                },
                PrimitivesFromChildren::default(),
            ))
            .id();
        // Without children the cloud keeps the primitives set by hand.
        app.update();
        assert_eq!(
            app.world().get::<CloudVolume>(cloud).unwrap().primitives,
            vec![own]
        );

        let child = app
            .world_mut()
            .spawn((
                CloudPrimitive::default(),
                Transform::from_xyz(1.0, 0.0, 0.0).with_scale(Vec3::splat(2.0)),
                ChildOf(cloud),
            ))
            .id();
        app.update();
        let primitives = |app: &App| {
            app.world()
                .get::<CloudVolume>(cloud)
                .unwrap()
                .primitives
                .clone()
        };
        assert_eq!(primitives(&app).len(), 1);
        assert_eq!(primitives(&app)[0].centre, DVec3::X);
        assert_eq!(primitives(&app)[0].radii, DVec3::splat(2.0));

        app.world_mut()
            .get_mut::<Transform>(child)
            .unwrap()
            .translation
            .y = 3.0;
        app.update();
        assert_eq!(primitives(&app)[0].centre, DVec3::new(1.0, 3.0, 0.0));

        // An unchanged child changes nothing: the cloud is not regenerated.
        let changed = |app: &App| {
            app.world()
                .entity(cloud)
                .get_ref::<CloudVolume>()
                .unwrap()
                .last_changed()
        };
        let before = changed(&app);
        app.update();
        assert_eq!(changed(&app), before);

        app.world_mut().entity_mut(child).despawn();
        app.update();
        assert!(primitives(&app).is_empty());
    }
}
