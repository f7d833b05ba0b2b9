//! nebel against Bevy's own `FogVolume` ray marcher on the same density grid.
//!
//! Bevy 0.19's fog (`bevy_pbr` `volumetric_fog.wgsl`), lit by one directional
//! light with `VolumetricLight`, with white fog colour and light tint,
//! absorption 0, scattering σ, asymmetry 0 (phase 1/4π) and no ambient term,
//! marches per unit length
//!
//! ```text
//! extinction  ρ(s) = σ D s
//! emission    E(s) = L · exposure · σ D s · exp(−σ D s R) / 4π
//! ```
//!
//! with `s` the density texture's value, `D` the density factor, `L` the
//! light's linear colour times its illuminance, `exposure = 2^−EV100 / 1.2`
//! (Bevy's default EV100 9.7) and `R` the fog box's bounding radius (half its
//! diagonal: Bevy's cheap self-shadowing factor). The same optics in nebel's
//! model is the transfer function
//!
//! ```text
//! ρ(s) = σ D s,   κ(s) = L · exposure · exp(−σ D R s) / 4π
//! ```
//!
//! written with [`EQUIVALENT_POINTS`] control points (the linear pieces of κ
//! deviate from the exponential by at most `(σDR / 128)² / 8`, relative). One
//! exact reference ([`nebel_reference::render`]) then scores both renderers.
//!
//! The density texture holds the grid's points at texel centres, so the fog
//! box is the grid's box grown by half a voxel on every side; the scenes used
//! (ellipsoid clouds) are zero on their faces, so the extra border adds
//! nothing. Known differences of Bevy's marcher, which this comparison
//! measures rather than hides: it marches a length equal to the difference of
//! view-space depths, short by cos θ off the view axis, with a fixed step count.

use std::sync::Arc;

use bevy::asset::RenderAssetUsages;
use bevy::camera::Exposure;
use bevy::light::{FogVolume, VolumetricFog, VolumetricLight};
use bevy::prelude::*;
use bevy::render::render_resource::{Extent3d, TextureDimension, TextureFormat};
use nebel_core::field::DensityGrid;
use nebel_core::transfer::{ControlPoint, TransferError, TransferFunction};

/// Control points of the equivalent transfer function.
pub const EQUIVALENT_POINTS: usize = 129;

/// The settings of Bevy's fog that [`BevyFog::equivalent_transfer_function`]
/// matches.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BevyFog {
    /// `FogVolume::scattering` σ, 1/metre per unit density. Absorption is 0.
    pub scattering: f32,
    /// `FogVolume::density_factor` D.
    pub density_factor: f32,
    /// `VolumetricFog::step_count`: samples along each ray.
    pub step_count: u32,
}

impl BevyFog {
    /// nebel's transfer function for the same optics, for a fog box with
    /// bounding radius `bounding_radius` lit by `light` (linear RGB times
    /// illuminance) through a camera of default exposure.
    pub fn equivalent_transfer_function(
        &self,
        light: Vec3,
        bounding_radius: f32,
    ) -> Result<TransferFunction, TransferError> {
        let exposure = Exposure::default().exposure();
        let extinction = self.scattering * self.density_factor;
        let points: Vec<ControlPoint> = (0..EQUIVALENT_POINTS)
            .map(|i| {
                let s = i as f32 / (EQUIVALENT_POINTS - 1) as f32;
                let kappa = light * exposure * (-extinction * bounding_radius * s).exp()
                    / (4.0 * std::f32::consts::PI);
                ControlPoint {
                    s,
                    kappa: kappa.to_array(),
                    rho: extinction * s,
                }
            })
            .collect();
        TransferFunction::new(points)
    }
}

/// The fog box of a grid: its box grown by half a voxel (points at texel
/// centres), as a transform of Bevy's unit fog cube.
pub fn fog_box(grid: &DensityGrid) -> Transform {
    let spacing = grid.spacing().as_vec3();
    let min = grid.origin().as_vec3() - spacing / 2.0;
    let max = grid.max_corner().as_vec3() + spacing / 2.0;
    Transform::from_translation((min + max) / 2.0).with_scale(max - min)
}

/// Bounding radius Bevy computes for a fog box: half its diagonal.
pub fn bounding_radius(fog_box: &Transform) -> f32 {
    (fog_box.scale / 2.0).length()
}

/// The grid as Bevy's density texture: a 3D `R16Float` image, x fastest.
fn density_texture(grid: &DensityGrid) -> Image {
    let [nx, ny, nz] = grid.dims();
    let data = grid
        .values()
        .iter()
        .flat_map(|v| half::f16::from_f32(*v).to_le_bytes())
        .collect();
    Image::new(
        Extent3d {
            width: nx as u32,
            height: ny as u32,
            depth_or_array_layers: nz as u32,
        },
        TextureDimension::D3,
        data,
        TextureFormat::R16Float,
        RenderAssetUsages::RENDER_WORLD,
    )
}

/// Spawns `grid` as a Bevy `FogVolume` and turns on volumetric fog on every
/// camera and volumetric light on every directional light.
pub(crate) fn spawn_bevy_fog(
    commands: &mut Commands,
    images: &mut Assets<Image>,
    grid: &Arc<DensityGrid>,
    fog: &BevyFog,
) {
    commands.spawn((
        FogVolume {
            fog_color: Color::WHITE,
            density_factor: fog.density_factor,
            density_texture: Some(images.add(density_texture(grid))),
            absorption: 0.0,
            scattering: fog.scattering,
            scattering_asymmetry: 0.0,
            light_tint: Color::WHITE,
            light_intensity: 1.0,
            ..default()
        },
        fog_box(grid),
    ));
}

/// Volumetric fog on the cameras and volumetric light on the suns, for
/// [`spawn_bevy_fog`].
pub(crate) fn enable_bevy_fog(
    mut commands: Commands,
    cameras: Query<Entity, With<Camera3d>>,
    suns: Query<Entity, With<DirectionalLight>>,
    fog: Option<Res<BevyFogSettings>>,
) {
    let Some(fog) = fog else {
        return;
    };
    for camera in &cameras {
        commands.entity(camera).insert(VolumetricFog {
            ambient_intensity: 0.0,
            step_count: fog.0.step_count,
            jitter: 0.0,
            ..default()
        });
    }
    for sun in &suns {
        commands.entity(sun).insert(VolumetricLight);
    }
}

/// The fog settings of a scene drawn with Bevy's fog.
#[derive(Resource, Clone, Copy, Debug)]
pub(crate) struct BevyFogSettings(pub BevyFog);

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::math::DVec3;

    #[test]
    fn equivalent_transfer_function_matches_the_fog_formula() {
        let fog = BevyFog {
            scattering: 0.5,
            density_factor: 4.0,
            step_count: 64,
        };
        let light = Vec3::new(1000.0, 800.0, 600.0);
        let tf = fog.equivalent_transfer_function(light, 2.0).unwrap();
        let exposure = f64::from(Exposure::default().exposure());
        for s in [0.0, 0.3, 0.77, 1.0] {
            let sample = tf.evaluate(s);
            let rho = 2.0 * s;
            assert!((sample.rho - rho).abs() < 1e-6);
            let emission = sample.kappa.x * sample.rho;
            let expected =
                1000.0 * exposure * rho * (-rho * 2.0).exp() / (4.0 * std::f64::consts::PI);
            // The documented bound of the linear pieces, (σDR / 128)² / 8, plus f32 rounding.
            let bound = (2.0 * 2.0 / 128.0_f64).powi(2) / 8.0 + 1e-6;
            assert!(
                (emission - expected).abs() <= bound * expected,
                "{s}: {emission} vs {expected}"
            );
        }
    }

    #[test]
    fn fog_box_puts_grid_points_at_texel_centres() {
        let grid = DensityGrid::new(
            [3, 2, 5],
            DVec3::new(1.0, 2.0, 0.5),
            DVec3::new(-1.0, 0.0, 3.0),
            vec![0.0; 30],
        )
        .unwrap();
        let transform = fog_box(&grid);
        // Texel i of n sits at (i + 0.5) / n of the box: point i of the grid.
        let min = transform.translation - transform.scale / 2.0;
        for (axis, n) in [(0, 3.0), (1, 2.0), (2, 5.0)] {
            let texel_centre = min[axis] + 0.5 / n * transform.scale[axis];
            assert!((texel_centre - grid.origin().as_vec3()[axis]).abs() < 1e-6);
        }
        assert!((bounding_radius(&transform) - (transform.scale / 2.0).length()).abs() < 1e-6);
    }
}
