//! Fog layers on the GPU: the uniform that carries a height fog to the
//! shaders and the WGSL library (`nebel_render::fog_layers`) that integrates
//! it exactly along a ray (Röttger, "Volumetric Methods for the Real-Time
//! Display of Natural Gaseous Phenomena", 2004, §5.3, layered fog).
//!
//! The density depends on the altitude only, so the optical depth of the
//! piece `[t₀, t₁]` of a ray from altitude `h₀` with vertical direction `d_y`
//! is `τ = (t₁ − t₀) · ρ̄`, `ρ̄` the mean density over the altitudes it
//! crosses, evaluated per layer in a form that stays exact for level rays
//! (`nebel_core::height_fog` gives the formulas; the shader computes the
//! altitude range as `d_y (t₁ − t₀)`, never as a difference of altitudes).
//! The fog glows with an ambient colour and scatters sunlight once, with the
//! Henyey-Greenstein phase function at the ray's angle to the sun, dimmed
//! by the fog on its way from the sun and to the eye: closed form too, with
//! the fog above a point, `C(h) = ∫_h^∞ ρ` (`nebel_core::height_fog`'s
//! `HeightFog::sunlit`; the shader's `fog_sunlit`).
//!
//! Two render features read it: the fog-layer pass of `nebel_fog` (the fog
//! from the eye to the opaque depth, over the scene) and the cell projection,
//! which conjugates every cell's segment by the fog in front of it (see
//! [`crate::cell_projection`]). A view carries the fog as the render-world
//! component [`ViewFogLayers`]; without it neither does any fog work.
//!
//! The uniform fits WebGL2-class limits: at most [`MAX_FOG_LAYERS`] layers
//! and [`MAX_FOG_POINTS`] points of piecewise-linear profiles, in one uniform
//! block of 448 bytes.

use bevy::prelude::*;
use bevy::render::render_resource::ShaderType;
use bevy::shader::load_shader_library;
use nebel_core::height_fog::{HeightFog, HeightFogLayer};
use thiserror::Error;

/// Most layers a [`FogLayersUniform`] holds.
pub const MAX_FOG_LAYERS: usize = 8;
/// Most points all piecewise-linear layers of a [`FogLayersUniform`] hold
/// together.
pub const MAX_FOG_POINTS: usize = 32;

/// Largest exponent of an exponential layer the shader evaluates (f32's
/// `exp` overflows near 88): below that depth under its base altitude the
/// layer's density stays at `density · e⁸⁰`.
pub const MAX_FOG_EXPONENT: f32 = 80.0;

/// A height fog as the shaders read it, `FogLayers` in
/// `fog_layers.wgsl`.
#[derive(Clone, Copy, Debug, Default, PartialEq, ShaderType)]
pub struct FogLayersUniform {
    /// Linear RGB the fog converges to without sunlight; w unused.
    pub colour: Vec4,
    /// Linear RGB of the sunlight added on average over directions; w: the
    /// Henyey-Greenstein asymmetry.
    pub sun_colour: Vec4,
    /// xyz: unit direction toward the sun; w unused.
    pub sun_direction: Vec4,
    /// x: start distance, y: largest distance, z: number of layers (as a
    /// float), w unused.
    pub ranges: Vec4,
    /// Per layer, x: kind (0 exponential, 1 constant, 2 piecewise linear);
    /// exponential: y base, z density, w falloff; constant: y bottom, z top,
    /// w density; linear: y first point, z point count.
    pub layers: [Vec4; MAX_FOG_LAYERS],
    /// The linear layers' `(altitude, density)` points, two per element.
    pub points: [Vec4; MAX_FOG_POINTS / 2],
}

/// Why a height fog does not fit the GPU's uniform.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum FogLayersLimitError {
    /// More layers than [`MAX_FOG_LAYERS`].
    #[error("{count} fog layers; the GPU takes at most {MAX_FOG_LAYERS}")]
    TooManyLayers {
        /// Layers given.
        count: usize,
    },
    /// More profile points than [`MAX_FOG_POINTS`].
    #[error("{count} points in the fog's linear layers; the GPU takes at most {MAX_FOG_POINTS}")]
    TooManyPoints {
        /// Points given.
        count: usize,
    },
}

/// What the fog looks like, besides its density.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FogLayersLook {
    /// Linear RGB dense fog converges to without sunlight.
    pub colour: Vec3,
    /// Linear RGB of the sunlight added on average over directions.
    pub sun_colour: Vec3,
    /// Unit direction toward the sun.
    pub sun_direction: Vec3,
    /// Henyey-Greenstein asymmetry of the sunlight's scattering.
    pub sun_asymmetry: f32,
    /// Where the fog begins along each ray, metres.
    pub start_distance: f32,
    /// Where the fog ends along each ray (the sky integrates to here),
    /// metres.
    pub max_distance: f32,
}

impl FogLayersUniform {
    /// Whether the fog scatters sunlight: a sun above the horizon, of some
    /// colour. The shaders take the sunlit variant (`FOG_SUN`) only then.
    pub fn has_sun(&self) -> bool {
        self.sun_direction.y > 0.0 && self.sun_colour.truncate() != Vec3::ZERO
    }

    /// Packs `fog` and its look. Errors when it has more layers or points
    /// than the uniform holds.
    pub fn new(fog: &HeightFog, look: &FogLayersLook) -> Result<Self, FogLayersLimitError> {
        let layers = fog.layers();
        if layers.len() > MAX_FOG_LAYERS {
            return Err(FogLayersLimitError::TooManyLayers {
                count: layers.len(),
            });
        }
        let point_count: usize = layers
            .iter()
            .map(|layer| match layer {
                HeightFogLayer::Linear(points) => points.len(),
                _ => 0,
            })
            .sum();
        if point_count > MAX_FOG_POINTS {
            return Err(FogLayersLimitError::TooManyPoints { count: point_count });
        }
        let mut uniform = Self {
            colour: look.colour.extend(0.0),
            sun_colour: look
                .sun_colour
                .extend(look.sun_asymmetry.clamp(-0.99, 0.99)),
            sun_direction: look.sun_direction.normalize_or(Vec3::Y).extend(0.0),
            ranges: Vec4::new(
                look.start_distance,
                look.max_distance,
                layers.len() as f32,
                0.0,
            ),
            ..default()
        };
        let mut points = Vec::with_capacity(point_count);
        for (slot, layer) in uniform.layers.iter_mut().zip(layers) {
            *slot = match layer {
                HeightFogLayer::Exponential {
                    base,
                    density,
                    falloff,
                } => Vec4::new(0.0, *base as f32, *density as f32, *falloff as f32),
                HeightFogLayer::Constant {
                    bottom,
                    top,
                    density,
                } => Vec4::new(1.0, *bottom as f32, *top as f32, *density as f32),
                HeightFogLayer::Linear(profile) => {
                    let first = points.len() as f32;
                    points.extend(profile.iter().map(|[h, d]| Vec2::new(*h as f32, *d as f32)));
                    Vec4::new(2.0, first, profile.len() as f32, 0.0)
                }
            };
        }
        for (pair, slot) in points.chunks(2).zip(&mut uniform.points) {
            *slot = pair[0].extend(0.0).extend(0.0);
            if let Some(second) = pair.get(1) {
                slot.z = second.x;
                slot.w = second.y;
            }
        }
        Ok(uniform)
    }
}

/// A view's fog layers in the render world (on the view entity); both the
/// fog-layer pass and the cell projection read it.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct ViewFogLayers(pub FogLayersUniform);

/// Loads the WGSL library `nebel_render::fog_layers`.
pub(crate) fn load_fog_layers_library(app: &mut App) {
    load_shader_library!(app, "fog_layers.wgsl");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layers_and_points_pack_in_order() {
        let fog = HeightFog::new(vec![
            HeightFogLayer::Linear(vec![[0.0, 0.1], [10.0, 0.2], [20.0, 0.0]]),
            HeightFogLayer::Exponential {
                base: 5.0,
                density: 0.01,
                falloff: 0.1,
            },
            HeightFogLayer::Linear(vec![[30.0, 0.0], [40.0, 0.3]]),
            HeightFogLayer::Constant {
                bottom: -1.0,
                top: 2.0,
                density: 0.5,
            },
        ])
        .unwrap();
        let look = FogLayersLook {
            colour: Vec3::new(0.1, 0.2, 0.3),
            sun_colour: Vec3::ONE,
            sun_direction: Vec3::new(0.0, 2.0, 0.0),
            sun_asymmetry: 1.5,
            start_distance: 3.0,
            max_distance: 1e4,
        };
        let uniform = FogLayersUniform::new(&fog, &look).unwrap();
        assert_eq!(uniform.ranges, Vec4::new(3.0, 1e4, 4.0, 0.0));
        assert_eq!(uniform.sun_direction, Vec4::new(0.0, 1.0, 0.0, 0.0));
        assert_eq!(uniform.sun_colour.w, 0.99);
        assert_eq!(uniform.layers[0], Vec4::new(2.0, 0.0, 3.0, 0.0));
        assert_eq!(uniform.layers[1], Vec4::new(0.0, 5.0, 0.01, 0.1));
        assert_eq!(uniform.layers[2], Vec4::new(2.0, 3.0, 2.0, 0.0));
        assert_eq!(uniform.layers[3], Vec4::new(1.0, -1.0, 2.0, 0.5));
        assert_eq!(uniform.points[0], Vec4::new(0.0, 0.1, 10.0, 0.2));
        assert_eq!(uniform.points[1], Vec4::new(20.0, 0.0, 30.0, 0.0));
        assert_eq!(uniform.points[2], Vec4::new(40.0, 0.3, 0.0, 0.0));
        assert!(uniform.has_sun());
        // No sunlight: black, or the sun at or below the horizon.
        for (sun_colour, sun_direction) in [
            (Vec3::ZERO, Vec3::Y),
            (Vec3::ONE, Vec3::X),
            (Vec3::ONE, Vec3::new(0.3, -0.2, 0.0)),
        ] {
            let look = FogLayersLook {
                sun_colour,
                sun_direction,
                ..look
            };
            assert!(!FogLayersUniform::new(&fog, &look).unwrap().has_sun());
        }
    }
}
