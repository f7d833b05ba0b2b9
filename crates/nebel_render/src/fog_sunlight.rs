//! The sun in ground fog on the GPU: [`CellFogSunlight`] on a sorted batch
//! adds the sun's single scattering, dimmed by the fog above each point and
//! cut by the terrain's shadow (`nebel_core::fog_sunlight`).
//!
//! The batch's shader (`GROUND_SUN`) reads the map's ground, thickness and
//! shadow height from an `Rgba32Float` texture at the map's grid points,
//! bilinear in between as `nebel_core`'s `HeightField` samples them, and the
//! fog's column `F(u)` from a table of [`COLUMN_TABLE_SIZE`] values, linear
//! in between. Between maps (built when the sun turns by a step) the shadow
//! heights follow the sun's elevation: each moves by `−t* (tan α − tan α₀)`,
//! `t*` the distance of the terrain that casts it (the texel's fourth
//! channel), exact while that terrain stays the caster; a turn about the
//! vertical waits for the next map. `μ` is the sun's sine now. The clouds'
//! shadow maps ([`crate::cloud_shadow_maps`]) dim `T_sun` where the line
//! toward the sun crosses their plane (exact below it; a point above the
//! plane takes the whole cloud's shadow over it). A sun that casts shadows
//! ([`CellFogSunlight::shadows`]) is hidden by opaque meshes as well
//! (`SUN_SHADOWS`): `V` is also Bevy's cascaded shadow map of it
//! ([`crate::light_shadows`]), read at the ends of each piece and at its
//! nodes where the two differ. Each of the segment's four pieces takes its
//! optical depth from the pair table and three Gauss-Legendre nodes of `σ
//! e^{−σ (t − t_a)} V T_sun`; the colour is the segment's mean (exact for a
//! fog of one colour), the phase the one at the ray's angle to the sun. The
//! texture is uploaded when the map changes (by identity), the uniform when
//! anything else does; neither touches the cells.

use std::sync::Arc;

use bevy::math::{DAffine3, DMat3, DMat4, DVec2, DVec3};
use bevy::prelude::*;
use bevy::render::render_resource::{ShaderType, TextureFormat, TextureView};
use bevy::render::renderer::{RenderDevice, RenderQueue};
use nebel_core::field::TerrainShadow;
use nebel_core::fog_sunlight::{FogSunMap, vertical_scale};
use nebel_core::optics::checked_asymmetry;

use crate::cell_batch::finite_non_negative;
use crate::cloud_shadow_maps::CloudShadowMapUniform;
use crate::data_texture::data_texture;

/// Values of the fog's column table `F(u)`, at equal steps of `u` from 0 to 1.
pub const COLUMN_TABLE_SIZE: usize = 65;

/// The sun lighting a sorted [`CellBatch`](crate::CellBatch) of ground fog
/// (see the module docs). A ground fog with a sun colour sets it; changing
/// it costs a uniform write, and a texture upload when the map is a new one.
#[derive(Component, Clone, Debug)]
pub struct CellFogSunlight {
    /// The ground, the fog's thickness, the terrain's shadow height and the
    /// fog's column, in the terrain's frame. Shared with whatever built it.
    pub map: Arc<FogSunMap>,
    /// World space to the map's (terrain's) frame, a rigid motion.
    pub map_from_world: DAffine3,
    /// Unit direction toward the sun, world space.
    pub direction: Vec3,
    /// The sunlight relative to the light the transfer function's colour
    /// stands for, linear RGB, each channel finite and ≥ 0 (others draw as
    /// 0).
    pub colour: Vec3,
    /// The Henyey-Greenstein asymmetry, clamped to ±0.99.
    pub asymmetry: f32,
    /// The sun casts shadows (`shadow_maps_enabled`): in a view with Bevy's
    /// lights, its shadow map hides it from the fog behind opaque meshes.
    pub shadows: bool,
}

/// The shader's `FogSun` uniform (zeros for a batch without the sun).
#[derive(Clone, Copy, Debug, Default, PartialEq, ShaderType)]
pub(crate) struct FogSunUniform {
    /// World position to the map's grid: x and z in grid points, y the
    /// height in the terrain's frame.
    pub grid_from_world: Mat4,
    /// xyz: unit direction toward the sun; w: the asymmetry.
    pub sun: Vec4,
    /// rgb: the colour; w: `s/μ`, the sun's slant through a level layer
    /// (`s` the world length of the map's unit of height, `μ` the sine of
    /// the sun's elevation now, in the map's frame).
    pub colour: Vec4,
    /// x: `tan α − tan α₀`, the tangent of the sun's elevation now less the
    /// map's: the shadow heights move by `−t*` times it (see the module
    /// docs); yzw unused.
    pub elevation: Vec4,
    /// `F(u)` at [`COLUMN_TABLE_SIZE`] steps, four to an element.
    pub column: [Vec4; COLUMN_TABLE_SIZE.div_ceil(4)],
    /// The clouds' shadow maps (no weight without clouds).
    pub clouds: [CloudShadowMapUniform; 2],
}

impl FogSunUniform {
    pub(crate) fn new(sunlight: &CellFogSunlight, clouds: [CloudShadowMapUniform; 2]) -> Self {
        let grid = &sunlight.map.shadow.heights;
        let (origin, spacing) = (grid.origin(), grid.spacing());
        let grid_from_map = DAffine3::from_mat3_translation(
            DMat3::from_diagonal(DVec3::new(1.0 / spacing.x, 1.0, 1.0 / spacing.y)),
            DVec3::new(-origin.x / spacing.x, 0.0, -origin.y / spacing.y),
        );
        let mut column = [Vec4::ZERO; COLUMN_TABLE_SIZE.div_ceil(4)];
        for (k, value) in sunlight
            .map
            .column
            .table(COLUMN_TABLE_SIZE)
            .into_iter()
            .enumerate()
        {
            column[k / 4][k % 4] = value;
        }
        // The sun now, in the map's frame; below the map's lowest sun it
        // lights nothing.
        let map_sun = sunlight.map.shadow.sun;
        let now = sunlight
            .map_from_world
            .transform_vector3(sunlight.direction.as_dvec3())
            .try_normalize()
            .unwrap_or(map_sun);
        let tan = |sun: DVec3| (sun.y / DVec2::new(sun.x, sun.z).length().max(1e-6)).min(1e6);
        let lit = now.y >= TerrainShadow::MIN_SUN_SINE;
        let colour = if lit {
            finite_non_negative(sunlight.colour)
        } else {
            Vec3::ZERO
        };
        let asymmetry = checked_asymmetry(sunlight.asymmetry);
        Self {
            grid_from_world: DMat4::from(grid_from_map * sunlight.map_from_world).as_mat4(),
            sun: sunlight.direction.normalize_or(Vec3::Y).extend(asymmetry),
            colour: colour.extend(
                (vertical_scale(&sunlight.map_from_world) / now.y.max(TerrainShadow::MIN_SUN_SINE))
                    as f32,
            ),
            elevation: Vec4::new((tan(now) - tan(map_sun)) as f32, 0.0, 0.0, 0.0),
            column,
            clouds,
        }
    }
}

/// The map's texels as a texture: `(shadow height, ground, thickness, 0)`
/// per grid point.
pub(crate) fn sun_map_texture(
    device: &RenderDevice,
    queue: &RenderQueue,
    map: Option<&FogSunMap>,
) -> TextureView {
    let (size, texels) = map.map_or(([1, 1], vec![[0.0f32; 4]]), |map| {
        (map.shadow.heights.dims(), map.texels())
    });
    data_texture(
        device,
        queue,
        "nebel_fog_sun_map",
        size,
        TextureFormat::Rgba32Float,
        bytemuck::cast_slice(&texels),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::math::{DQuat, DVec2};
    use nebel_core::field::HeightField;
    use nebel_core::fog_sunlight::FogColumn;
    use nebel_core::transfer::{ControlPoint, TransferFunction};

    #[test]
    fn the_uniform_maps_world_points_onto_the_grid_and_packs_the_column() {
        let field = |value: f32| {
            HeightField::new(
                [5, 3],
                DVec2::new(2.0, 4.0),
                DVec2::new(-4.0, 10.0),
                vec![value; 15],
            )
            .unwrap()
        };
        let tf = TransferFunction::new([ControlPoint {
            s: 0.0,
            kappa: [1.0; 3],
            rho: 0.5,
        }])
        .unwrap();
        let column = FogColumn::new(&[[0.0, 1.0], [1.0, 0.0]], &tf);
        let sun = DVec3::new(0.0, 0.5, 3f64.sqrt() / 2.0);
        let map = FogSunMap::compute(&field(1.0), &field(8.0), column, sun, [5, 3], 1).unwrap();
        // A terrain rotated and scaled by 2: its columns are twice as long.
        let world_from_map = DAffine3::from_scale_rotation_translation(
            DVec3::splat(2.0),
            DQuat::from_rotation_y(0.7),
            DVec3::new(100.0, -3.0, 50.0),
        );
        // The sun now a little higher than the map's (in the map's frame
        // (0, 0.6, 0.8) against (0, 0.5, 0.87)).
        let now = world_from_map
            .transform_vector3(DVec3::new(0.0, 0.6, 0.8))
            .as_vec3();
        let sunlight = CellFogSunlight {
            map: Arc::new(map),
            map_from_world: world_from_map.inverse(),
            direction: now,
            colour: Vec3::new(f32::NAN, -1.0, 2.0),
            asymmetry: 3.0,
            shadows: false,
        };
        let uniform = FogSunUniform::new(&sunlight, Default::default());
        // Grid point (3, 2) at map (2, 6, 18), put into the world.
        let world = world_from_map.transform_point3(DVec3::new(2.0, 6.0, 18.0));
        let grid = uniform.grid_from_world.transform_point3(world.as_vec3());
        assert!(
            (grid - Vec3::new(3.0, 6.0, 2.0)).abs().max_element() < 1e-4,
            "{grid}"
        );
        assert!(
            (uniform.sun.truncate() - now.normalize())
                .abs()
                .max_element()
                < 1e-6
        );
        assert_eq!(uniform.sun.w, 0.99);
        // The slant s/μ for the sun now: 2 / 0.6; the elevation's tangent
        // 0.75 against the map's 1/√3.
        let expected = Vec4::new(0.0, 0.0, 2.0, 2.0 / 0.6);
        assert!(
            (uniform.colour - expected).abs().max_element() < 1e-5,
            "{}",
            uniform.colour
        );
        assert!((uniform.elevation.x - (0.75 - 1.0 / 3f32.sqrt())).abs() < 1e-5);
        // A sun below the horizon lights nothing.
        let set = FogSunUniform::new(
            &CellFogSunlight {
                direction: Vec3::new(0.0, -0.2, 1.0),
                colour: Vec3::ONE,
                ..sunlight.clone()
            },
            Default::default(),
        );
        assert_eq!(set.colour.truncate(), Vec3::ZERO);
        // F(u) = 0.5 (1 − u): the first, the middle and the last value.
        assert_eq!(uniform.column[0].x, 0.5);
        assert_eq!(uniform.column[8].x, 0.25);
        assert_eq!(uniform.column[16].x, 0.0);
    }
}
