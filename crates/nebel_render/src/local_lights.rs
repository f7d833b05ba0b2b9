//! Point and spot lights that scatter in sorted cell batches and fog layers:
//! Bevy's `PointLight` and `SpotLight` opted in with `VolumetricLight`, as
//! Bevy's own volumetric fog takes them.
//!
//! Each frame the render world takes the opted-in lights (visible, with a
//! positive intensity and range) as [`nebel_core::local_light::LocalLight`]s:
//! colour times intensity over the reference sun's illuminance, Bevy's range
//! window and cone. A sorted batch is lit by the lights whose range reaches
//! its bounds, at most [`MAX_LOCAL_LIGHTS`], the brightest at the batch's
//! centre first; a batch no light reaches draws as before, without the
//! lighting's pipeline variant. The shader integrates each light over the
//! segment's pieces in the angle seen from the light
//! ([`LocalLight::scattered`] with one interval), with the batch's Henyey-Greenstein
//! asymmetry and a factor on its colour
//! ([`CellBatch::light_response`](crate::CellBatch::light_response)).
//! The fog layers take the same lights, the brightest at the camera
//! first. A batch's medium does not attenuate the light on its way to a
//! point (the fog layers' does).
//!
//! A light with shadows (`shadows_enabled`) is shaded in sorted batches by
//! Bevy's own shadow map of it, read at each node of the quadrature with
//! the light's depth bias and Bevy's 2×2 hardware comparison (see
//! [`ReachingLights::with_shadow_indices`]); the fog layers do not read
//! shadow maps.
//!
//! The WGSL library `nebel_render::local_lights` holds the lights' uniform
//! ([`LocalLightsUniform`]), each light's stretch on a ray and the nodes of
//! the quadrature; a shader that imports it needs the shader definition
//! `MAX_LOCAL_LIGHTS`.

use bevy::light::VolumetricLight;
use bevy::prelude::*;
use bevy::render::render_resource::ShaderType;
use bevy::render::sync_world::RenderEntity;
use bevy::shader::load_shader_library;
use nebel_core::local_light::{
    CORE_RADIUS, LightResponse, LocalLight, MAX_LOCAL_LIGHTS, SpotCone, interval_angle,
};

/// One light in a uniform, as the shader's `LocalLight`.
#[derive(Clone, Copy, Debug, Default, PartialEq, ShaderType)]
pub struct LocalLightUniform {
    /// xyz: world position; w: range.
    pub position: Vec4,
    /// rgb: the colour factor at unit distance; w: the cone's offset (1 for
    /// a point light).
    pub colour: Vec4,
    /// xyz: the spot's unit direction; w: the cone's scale (0 for a point
    /// light, so its factor is 1 everywhere).
    pub cone: Vec4,
    /// x: the light's index among Bevy's clustered lights, whose shadow map
    /// shades it; −1 for none. yzw unused.
    pub shadow: IVec4,
}

impl LocalLightUniform {
    fn new(light: &LocalLight) -> Self {
        let (direction, scale, offset) = light.cone.map_or((Vec3::ZERO, 0.0, 1.0), |cone| {
            (
                cone.direction.as_vec3(),
                cone.scale as f32,
                cone.offset as f32,
            )
        });
        Self {
            position: light.position.as_vec3().extend(light.range as f32),
            colour: light.colour.as_vec3().extend(offset),
            cone: direction.extend(scale),
            shadow: IVec4::new(-1, 0, 0, 0),
        }
    }
}

/// An opted-in light of the scene: its optics, and the render-world entity
/// of a light that casts shadows (where Bevy keeps its shadow map).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneLight {
    /// The light's optics.
    pub light: LocalLight,
    /// The render-world entity of a light with shadows; `None` for one
    /// without.
    pub shadow_source: Option<Entity>,
}

/// The lights of one medium: up to [`MAX_LOCAL_LIGHTS`], the first `count`
/// used.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ReachingLights {
    /// The lights, the first `count` used.
    pub lights: [LocalLightUniform; MAX_LOCAL_LIGHTS],
    /// How many are used.
    pub count: u32,
    /// Per light, the render-world entity of one that casts shadows.
    pub shadow_sources: [Option<Entity>; MAX_LOCAL_LIGHTS],
}

/// The lights that reach a medium and how it scatters them, as the shader's
/// `LocalLights`.
#[derive(Clone, Copy, Debug, Default, PartialEq, ShaderType)]
pub struct LocalLightsUniform {
    /// x: how many of `lights` are used; y: the Henyey-Greenstein
    /// asymmetry, clamped to ±0.99; z: the square of the falloff's core
    /// radius ([`CORE_RADIUS`]); w: the factor on the colour
    /// ([`LightResponse::strength`]).
    pub response: Vec4,
    /// x: the widest interval of the quadrature in the angle
    /// ([`interval_angle`]); yzw unused.
    pub quadrature: Vec4,
    /// The lights.
    pub lights: [LocalLightUniform; MAX_LOCAL_LIGHTS],
}

impl LocalLightsUniform {
    /// `lights` scattered with `response` (checked here).
    pub fn new(lights: &ReachingLights, response: LightResponse) -> Self {
        let response = response.checked();
        let core = CORE_RADIUS as f32;
        Self {
            response: Vec4::new(
                lights.count as f32,
                response.asymmetry,
                core * core,
                response.strength,
            ),
            quadrature: Vec4::new(
                interval_angle(f64::from(response.asymmetry)) as f32,
                0.0,
                0.0,
                0.0,
            ),
            lights: lights.lights,
        }
    }
}

/// Loads the WGSL library `nebel_render::local_lights`.
pub(crate) fn load_local_lights_library(app: &mut App) {
    load_shader_library!(app, "local_lights.wgsl");
}

impl ReachingLights {
    /// The lights of `lights` that reach the box `[min, max]`, the brightest
    /// at its centre first.
    pub fn reaching(lights: &[SceneLight], min: Vec3, max: Vec3) -> Self {
        let (min, max) = (min.as_dvec3(), max.as_dvec3());
        let centre = (min + max) / 2.0;
        let mut reaching: Vec<(f64, &SceneLight)> = lights
            .iter()
            .filter(|scene| scene.light.reaches_box(min, max))
            .map(|scene| {
                let light = &scene.light;
                let at_centre =
                    light.colour.max_element() / (light.position.distance_squared(centre) + 1.0);
                (at_centre, scene)
            })
            .collect();
        reaching.sort_by(|a, b| b.0.total_cmp(&a.0));
        let mut batch = Self::default();
        for (slot, (_, scene)) in reaching.iter().take(MAX_LOCAL_LIGHTS).enumerate() {
            batch.lights[slot] = LocalLightUniform::new(&scene.light);
            batch.shadow_sources[slot] = scene.shadow_source;
            batch.count += 1;
        }
        batch
    }

    /// The lights with the index among Bevy's clustered lights of each that
    /// casts shadows (`index` of its render-world entity; Bevy's
    /// `GlobalClusterableObjectMeta`), so the shader reads its shadow map
    /// there; −1 for the others and for a light Bevy does not list.
    pub fn with_shadow_indices(&self, index: impl Fn(Entity) -> Option<usize>) -> Self {
        let mut lights = *self;
        for (light, source) in lights.lights.iter_mut().zip(self.shadow_sources) {
            light.shadow.x = source
                .and_then(&index)
                .and_then(|index| i32::try_from(index).ok())
                .unwrap_or(-1);
        }
        lights
    }

    /// Whether a light reads a shadow map ([`Self::with_shadow_indices`]).
    pub fn is_shadowed(&self) -> bool {
        self.lights[..self.count as usize]
            .iter()
            .any(|light| light.shadow.x >= 0)
    }
}

/// The lights of `points` and `spots` (the opted-in, visible ones, with
/// their render-world entities) that light anything: their colour,
/// intensity and range finite and positive.
pub(crate) fn volumetric_lights(
    points: impl Iterator<Item = (PointLight, GlobalTransform, Option<Entity>)>,
    spots: impl Iterator<Item = (SpotLight, GlobalTransform, Option<Entity>)>,
) -> Vec<SceneLight> {
    let light = |color: Color, intensity: f32, range: f32, transform: &GlobalTransform| {
        let linear = color.to_linear();
        let light = LocalLight::from_lumens(
            transform.translation().as_dvec3(),
            Vec3::new(linear.red, linear.green, linear.blue).as_dvec3(),
            f64::from(intensity),
            f64::from(range),
        );
        (light.invalid().is_none() && light.colour.max_element() > 0.0).then_some(light)
    };
    let scene = |mut light: LocalLight, shadows: bool, entity: Option<Entity>| {
        light.shadows = shadows;
        SceneLight {
            light,
            shadow_source: entity.filter(|_| shadows),
        }
    };
    points
        .filter_map(|(point, transform, entity)| {
            let light = light(point.color, point.intensity, point.range, &transform)?;
            Some(scene(light, point.shadow_maps_enabled, entity))
        })
        .chain(spots.filter_map(|(spot, transform, entity)| {
            let mut light = light(spot.color, spot.intensity, spot.range, &transform)?;
            light.cone = Some(SpotCone::new(
                transform.forward().as_vec3().as_dvec3(),
                f64::from(spot.inner_angle),
                f64::from(spot.outer_angle),
            ));
            Some(scene(light, spot.shadow_maps_enabled, entity))
        }))
        .collect()
}

/// The opted-in lights of the main world's queries that are visible and
/// light anything: their colour, intensity and range finite and positive.
pub fn visible_volumetric_lights(
    points: &VolumetricPointLights,
    spots: &VolumetricSpotLights,
) -> Vec<SceneLight> {
    volumetric_lights(
        points
            .iter()
            .filter(|(_, _, visible, _)| visible.get())
            .map(|(light, transform, _, entity)| {
                (*light, *transform, entity.map(RenderEntity::id))
            }),
        spots.iter().filter(|(_, _, visible, _)| visible.get()).map(
            |(light, transform, _, entity)| (*light, *transform, entity.map(RenderEntity::id)),
        ),
    )
}

/// The main world's query of opted-in point lights.
pub type VolumetricPointLights<'w, 's> = Query<
    'w,
    's,
    (
        &'static PointLight,
        &'static GlobalTransform,
        &'static ViewVisibility,
        Option<&'static RenderEntity>,
    ),
    With<VolumetricLight>,
>;

/// The main world's query of opted-in spot lights.
pub type VolumetricSpotLights<'w, 's> = Query<
    'w,
    's,
    (
        &'static SpotLight,
        &'static GlobalTransform,
        &'static ViewVisibility,
        Option<&'static RenderEntity>,
    ),
    With<VolumetricLight>,
>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_take_the_lights_that_reach_them_brightest_first() {
        let at = |x: f32, lumens: f32, range: f32| {
            (
                PointLight {
                    intensity: lumens,
                    range,
                    ..default()
                },
                GlobalTransform::from_translation(Vec3::new(x, 0.0, 0.0)),
                None,
            )
        };
        let spot = (
            SpotLight {
                intensity: 1e5,
                range: 10.0,
                inner_angle: 0.2,
                outer_angle: 0.4,
                shadow_maps_enabled: true,
                ..default()
            },
            GlobalTransform::from(
                Transform::from_xyz(0.0, 5.0, 0.0).looking_to(Vec3::NEG_Y, Vec3::X),
            ),
            Some(Entity::from_raw_u32(7).expect("a valid index")),
        );
        let lights = volumetric_lights(
            [
                at(0.0, 1e5, 5.0),
                at(3.0, 3e6, 5.0),
                at(50.0, 1e6, 5.0),
                at(1.0, 0.0, 5.0),
                at(1.0, 1e5, f32::NAN),
            ]
            .into_iter(),
            [spot].into_iter(),
        );
        // The dark and the broken lights are dropped.
        assert_eq!(lights.len(), 4);
        let cone = lights[3].light.cone.expect("a spot light has a cone");
        assert!((cone.direction - bevy::math::DVec3::NEG_Y).length() < 1e-6);
        let batch = ReachingLights::reaching(&lights, Vec3::splat(-1.0), Vec3::splat(1.0));
        assert_eq!(batch.count, 3);
        // The light at x = 3 is thirty times as strong, three times brighter at the centre: first.
        assert_eq!(batch.lights[0].position.x, 3.0);
        assert_eq!(batch.lights[0].cone.w, 0.0);
        assert_eq!(batch.lights[0].colour.w, 1.0);
        assert!(batch.lights[..3].iter().any(|light| light.cone.w > 0.0));
        assert_eq!(batch.lights[3], LocalLightUniform::default());
        // Only the spot light casts shadows: its entity's index in Bevy's
        // list of lights, none for the others or a light Bevy does not list.
        assert!(!batch.is_shadowed());
        let spot_slot = (0..3).find(|&i| batch.lights[i].cone.w > 0.0).unwrap();
        let spot_entity = Entity::from_raw_u32(7).unwrap();
        assert_eq!(batch.shadow_sources[spot_slot], Some(spot_entity));
        let indexed = batch.with_shadow_indices(|entity| (entity == spot_entity).then_some(5));
        assert!(indexed.is_shadowed());
        for (slot, light) in indexed.lights.iter().enumerate() {
            assert_eq!(light.shadow.x, if slot == spot_slot { 5 } else { -1 });
        }
        assert!(!batch.with_shadow_indices(|_| None).is_shadowed());
        let none = ReachingLights::reaching(&lights, Vec3::splat(20.0), Vec3::splat(21.0));
        assert_eq!(none, ReachingLights::default());
        // More lights than a batch takes: the brightest.
        let many: Vec<_> = (0..12)
            .map(|i| SceneLight {
                light: LocalLight::from_lumens(
                    bevy::math::DVec3::ZERO,
                    bevy::math::DVec3::ONE,
                    f64::from(i + 1),
                    5.0,
                ),
                shadow_source: None,
            })
            .collect();
        let batch = ReachingLights::reaching(&many, Vec3::ZERO, Vec3::ONE);
        assert_eq!(batch.count as usize, MAX_LOCAL_LIGHTS);
        assert!(batch.lights[0].colour.x > batch.lights[MAX_LOCAL_LIGHTS - 1].colour.x);
    }
}
