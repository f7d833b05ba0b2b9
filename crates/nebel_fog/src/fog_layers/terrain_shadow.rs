//! The terrain's shadow in the fog layers' sunlight: the shadow heights of
//! the first terrain (`nebel_core::field::TerrainShadow`) keep the sun from
//! the fog below them.
//!
//! While a camera's [`FogLayers`](super::FogLayers) scatter sunlight, the
//! first `TerrainLod` with a quadtree gets a map of its shadow heights for
//! the first `DirectionalLight`, at up to `TerrainShadow::MAX_POINTS` points
//! a side, built on the task pool again when the terrain or its transform
//! changes or the sun turns (in the terrain's frame) by more than
//! [`SUN_STEP`], one build at a time; the fog keeps the last map until the
//! new one lands. The render world uploads it when it is a new map, as an
//! `R32Float` texture and the lowest and highest height of each block of
//! [`TERRAIN_SHADOW_BLOCK`] cells a side (`Rg32Float`). The pass walks the
//! map along each ray, crossing blocks whole where the ray passes above or
//! below all their heights, and holds back the closed-form sunlight of
//! every stretch below the shadow heights
//! (`nebel_core::field::PlacedTerrainShadow`, exact for the map's bilinear
//! heights). Without sunlit fog layers, a sun or a terrain there is no map,
//! no build and no upload; the pass reads a 2 × 2 map with no weight.

use std::sync::Arc;
use std::time::Instant;

use bevy::diagnostic::Diagnostics;
use bevy::math::{DAffine3, DMat4, DVec2, DVec3};
use bevy::prelude::*;
use bevy::render::extract_resource::ExtractResource;
use bevy::render::render_resource::{ShaderType, TextureFormat, TextureView};
use bevy::render::renderer::{RenderDevice, RenderQueue};
use nebel_core::field::{HeightField, PlacedTerrainShadow, TerrainShadow};
use nebel_render::camera::to_double_affine;
use nebel_render::data_texture::data_texture;
use nebel_render::{HeavyBuild, HeavyBuilds};
use nebel_terrain::TerrainLod;

use super::{FogLayersPlugin, PreparedFogLayers};
use crate::sunlight::SUN_STEP;

/// Cells per side of the blocks whose lowest and highest shadow heights let
/// the pass cross them whole where the ray passes wholly above or below.
pub const TERRAIN_SHADOW_BLOCK: usize = 4;

/// The terrain's shadow heights over sunlit fog layers (module docs), placed
/// in the world; `None` without one.
#[derive(Resource, Clone, Debug, Default, PartialEq, ExtractResource)]
pub struct FogLayersTerrainShadow(pub Option<PlacedTerrainShadow>);

/// What a map was built from: the quadtree (by identity) and the terrain's
/// transform.
type ShadowKey = (usize, GlobalTransform);

/// The map's build in flight and what the last one was built for.
#[derive(Resource, Default)]
pub(super) struct TerrainShadowBuild {
    built: Option<(ShadowKey, DVec3)>,
    building: Option<(
        ShadowKey,
        DVec3,
        DAffine3,
        HeavyBuild<(Option<TerrainShadow>, f32)>,
    )>,
}

/// Builds and hands over the terrain's shadow heights (module docs).
pub(super) fn update_terrain_shadow(
    fogs: Query<&PreparedFogLayers>,
    terrains: Query<(&TerrainLod, &GlobalTransform)>,
    suns: Query<&GlobalTransform, With<DirectionalLight>>,
    mode: Option<Res<HeavyBuilds>>,
    mut state: ResMut<TerrainShadowBuild>,
    mut shadow: ResMut<FogLayersTerrainShadow>,
    mut diagnostics: Diagnostics,
) {
    let sunlit = fogs
        .iter()
        .any(|fog| fog.0.is_some_and(|uniform| uniform.has_sun()));
    let sun = suns.iter().next().map(|sun| sun.back().as_dvec3());
    let terrain = terrains
        .iter()
        .find_map(|(lod, transform)| Some((lod.quadtree()?.clone(), *transform)));
    let (true, Some(sun), Some((quadtree, transform))) = (sunlit, sun, terrain) else {
        if state.built.is_some() || state.building.is_some() {
            *state = TerrainShadowBuild::default();
        }
        shadow.set_if_neq(FogLayersTerrainShadow(None));
        return;
    };
    let map_from_world = to_double_affine(&transform).inverse();
    let local_sun = map_from_world.transform_vector3(sun).normalize_or(DVec3::Y);
    let key = (Arc::as_ptr(&quadtree) as usize, transform);
    let fresh = state.built.as_ref().is_some_and(|(built, built_sun)| {
        *built == key && built_sun.angle_between(local_sun) <= SUN_STEP
    });
    if !fresh && state.building.is_none() {
        let build = HeavyBuild::spawn(move || {
            let started = Instant::now();
            let map = TerrainShadow::of_field(quadtree.field(), local_sun);
            (map, started.elapsed().as_secs_f32() * 1e3)
        });
        state.building = Some((key, local_sun, map_from_world, build));
    }
    if let Some((_, _, _, build)) = state.building.as_mut()
        && let Some((map, ms)) = build.poll(mode.map_or_else(HeavyBuilds::default, |mode| *mode))
        && let Some((key, built_sun, map_from_world, _)) = state.building.take()
    {
        state.built = Some((key, built_sun));
        diagnostics.add_measurement(&FogLayersPlugin::TERRAIN_SHADOW_MS, || f64::from(ms));
        shadow.set_if_neq(FogLayersTerrainShadow(
            map.map(|map| PlacedTerrainShadow::new(Arc::new(map), map_from_world)),
        ));
    }
}

/// The map as the pass reads it (`TerrainShadowMap` in `fog_layers.wgsl`).
#[derive(Clone, Copy, Debug, Default, PartialEq, ShaderType)]
pub struct TerrainShadowUniform {
    /// World space to the map's grid: x and z in grid units (point `(i,
    /// j)` at `(i, j)`), y the height in the terrain's frame.
    pub grid_from_world: Mat4,
    /// Points along x and z, the highest shadow height, and the weight: 1
    /// with a map, 0 without.
    pub size: Vec4,
}

impl TerrainShadowUniform {
    /// The uniform of `placed`.
    pub fn new(placed: &PlacedTerrainShadow) -> Self {
        let grid = &placed.shadow.heights;
        let spacing = grid.spacing();
        let grid_from_map = DMat4::from_scale(DVec3::new(1.0 / spacing.x, 1.0, 1.0 / spacing.y))
            * DMat4::from_translation(DVec3::new(-grid.origin().x, 0.0, -grid.origin().y));
        let [nx, nz] = grid.dims();
        Self {
            grid_from_world: (grid_from_map * DMat4::from(placed.map_from_world)).as_mat4(),
            size: Vec4::new(nx as f32, nz as f32, placed.top() as f32, 1.0),
        }
    }
}

/// The lowest and highest shadow height of each block of
/// [`TERRAIN_SHADOW_BLOCK`] cells a side (the blocks along the map's last
/// rows and columns cut short), and the blocks along x and z.
fn block_bounds(heights: &HeightField) -> ([usize; 2], Vec<[f32; 2]>) {
    let [nx, nz] = heights.dims();
    let blocks = [nx, nz].map(|n| (n - 1).div_ceil(TERRAIN_SHADOW_BLOCK).max(1));
    let mut bounds = vec![[f32::MAX, f32::MIN]; blocks[0] * blocks[1]];
    for j in 0..nz {
        for i in 0..nx {
            let h = heights.height(i, j);
            // A point on a block's edge bounds the blocks on both sides.
            for bj in [j.saturating_sub(1), j.min(nz - 2)].map(|c| c / TERRAIN_SHADOW_BLOCK) {
                for bi in [i.saturating_sub(1), i.min(nx - 2)].map(|c| c / TERRAIN_SHADOW_BLOCK) {
                    let block = &mut bounds[bi + blocks[0] * bj];
                    *block = [block[0].min(h), block[1].max(h)];
                }
            }
        }
    }
    (blocks, bounds)
}

/// The map's textures and uniform in the render world, and the map they
/// are of (held, so that its identity stays its own).
#[derive(Resource)]
pub struct TerrainShadowTexture {
    source: Option<Arc<TerrainShadow>>,
    /// The shadow heights, one texel per point (2 × 2 without a map).
    pub view: TextureView,
    /// The blocks' lowest and highest shadow heights, one texel per block.
    pub blocks: TextureView,
    /// What the pass reads of the map (no weight without one).
    pub uniform: TerrainShadowUniform,
}

/// Uploads the extracted map when it is a new one (render world).
pub(super) fn prepare_terrain_shadow_texture(
    mut commands: Commands,
    placed: Option<Res<FogLayersTerrainShadow>>,
    current: Option<Res<TerrainShadowTexture>>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
) {
    let placed = placed.as_ref().and_then(|placed| placed.0.as_ref());
    let source = placed.map(|placed| placed.shadow.clone());
    // A map and its placement come together: the same map, the same
    // uniform.
    let same = |current: &TerrainShadowTexture| match (&current.source, &source) {
        (Some(a), Some(b)) => Arc::ptr_eq(a, b),
        (a, b) => a.is_none() && b.is_none(),
    };
    if current.is_some_and(|current| same(&current)) {
        return;
    }
    // A flat 2 × 2 map, without weight, stands in for none.
    let none = HeightField::new([2, 2], DVec2::ONE, DVec2::ZERO, vec![0.0; 4]).ok();
    let Some(heights) = placed
        .map(|placed| &placed.shadow.heights)
        .or(none.as_ref())
    else {
        return;
    };
    let view = data_texture(
        &device,
        &queue,
        "nebel_fog_layers_terrain_shadow",
        heights.dims(),
        TextureFormat::R32Float,
        bytemuck::cast_slice(heights.heights()),
    );
    let (size, bounds) = block_bounds(heights);
    let blocks = data_texture(
        &device,
        &queue,
        "nebel_fog_layers_terrain_shadow_blocks",
        size,
        TextureFormat::Rg32Float,
        bytemuck::cast_slice(&bounds),
    );
    commands.insert_resource(TerrainShadowTexture {
        source,
        view,
        blocks,
        uniform: placed.map_or_else(TerrainShadowUniform::default, TerrainShadowUniform::new),
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::math::DQuat;

    /// The uniform takes a world point over the map's point `(i, j)` at
    /// height `h` in the terrain's frame to `(i, h, j)`, under a turned,
    /// moved terrain, and carries the map's points, top and weight.
    #[test]
    fn the_map_is_packed_as_the_pass_reads_it() {
        let heights = HeightField::new(
            [4, 3],
            DVec2::new(7.0, 5.0),
            DVec2::new(-40.0, 15.0),
            vec![
                1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.5,
            ],
        )
        .unwrap();
        let world_from_map = DAffine3::from_rotation_translation(
            DQuat::from_rotation_y(0.7),
            DVec3::new(300.0, -20.0, 45.0),
        );
        let placed = PlacedTerrainShadow::new(
            Arc::new(TerrainShadow {
                distances: heights.clone(),
                heights,
                sun: DVec3::Y,
            }),
            world_from_map.inverse(),
        );
        let uniform = TerrainShadowUniform::new(&placed);
        assert_eq!(uniform.size, Vec4::new(4.0, 3.0, 12.5, 1.0));
        let world = world_from_map.transform_point3(DVec3::new(-40.0 + 2.0 * 7.0, 6.5, 15.0 + 5.0));
        let grid = uniform.grid_from_world * world.as_vec3().extend(1.0);
        assert!(
            grid.truncate().distance(Vec3::new(2.0, 6.5, 1.0)) < 1e-4,
            "{grid}"
        );
        assert_eq!(TerrainShadowUniform::default().size.w, 0.0);
    }

    /// Every block's bounds are the lowest and highest of the points of its
    /// cells, on maps of whole and cut-short blocks.
    #[test]
    fn each_block_holds_the_lowest_and_highest_of_its_points() {
        for dims in [[2, 2], [9, 9], [17, 12], [20, 3]] {
            let values = (0..dims[0] * dims[1])
                .map(|n| ((n * 7919) % 101) as f32 - 50.0)
                .collect();
            let heights = HeightField::new(dims, DVec2::ONE, DVec2::ZERO, values).unwrap();
            let (blocks, bounds) = block_bounds(&heights);
            assert_eq!(blocks, dims.map(|n| (n - 1).div_ceil(TERRAIN_SHADOW_BLOCK)));
            for bj in 0..blocks[1] {
                for bi in 0..blocks[0] {
                    let points = |b: usize, n: usize| {
                        b * TERRAIN_SHADOW_BLOCK..=((b + 1) * TERRAIN_SHADOW_BLOCK).min(n - 1)
                    };
                    let inside: Vec<f32> = points(bj, dims[1])
                        .flat_map(|j| points(bi, dims[0]).map(move |i| (i, j)))
                        .map(|(i, j)| heights.height(i, j))
                        .collect();
                    let low = inside.iter().copied().fold(f32::MAX, f32::min);
                    let high = inside.iter().copied().fold(f32::MIN, f32::max);
                    assert_eq!(
                        bounds[bi + blocks[0] * bj],
                        [low, high],
                        "{dims:?} {bi} {bj}"
                    );
                }
            }
        }
    }
}
