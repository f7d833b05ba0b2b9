//! The clouds' shadow maps as every sunlit medium reads them: the
//! transmittance toward the sun under cloud volumes
//! (`nebel_core::field::GroundShadow`, Nes 2008 §6.1), two maps, the newest
//! fading in over the one before.
//!
//! `nebel_volume`'s cloud shadows keep [`CloudShadowMaps`] up to date; the
//! ground fog's sunlit cells (`GROUND_SUN`) and the sunlit fog layers read
//! it as the ground's meshes do, through the WGSL library
//! `nebel_render::cloud_shadow_maps`. A world without the resource, or a map
//! without weight, reads no texture.

use bevy::ecs::system::SystemParam;
use bevy::prelude::*;
use bevy::render::RenderApp;
use bevy::render::extract_resource::ExtractResource;
use bevy::render::render_asset::RenderAssets;
use bevy::render::render_resource::{Sampler, ShaderType, TextureView};
use bevy::render::texture::{FallbackImage, GpuImage};
use bevy::shader::load_shader_library;
use nebel_core::field::GroundShadow;

/// One map as the shaders read it.
#[derive(Clone, Copy, Debug, Default, PartialEq, ShaderType)]
pub struct CloudShadowMapUniform {
    /// The plane's height, the texel's side, the map's lower corner (x, z).
    pub plane: Vec4,
    /// Toward the map's sun (xyz), and the map's weight.
    pub sun_and_weight: Vec4,
    /// The map's texels along x and z, the texture's side, and the height
    /// of the casters' top (above it nothing is shaded).
    pub size: Vec4,
}

impl CloudShadowMapUniform {
    /// `map` in a square texture of `side` texels a side, at `weight`.
    pub fn new(map: &GroundShadow, side: u32, weight: f32) -> Self {
        Self {
            plane: Vec4::new(
                map.height as f32,
                map.texel as f32,
                map.min.x as f32,
                map.min.y as f32,
            ),
            sun_and_weight: map.sun.as_vec3().extend(weight),
            size: Vec4::new(
                map.size[0] as f32,
                map.size[1] as f32,
                side as f32,
                map.top as f32,
            ),
        }
    }
}

/// The clouds' two shadow maps of this frame: their textures (R8, the
/// transmittance, lit beyond the map) and where they lie, with weights that
/// sum to at most one (the rest lit).
#[derive(Resource, Clone, Debug, Default, PartialEq, ExtractResource)]
pub struct CloudShadowMaps {
    /// The maps' textures.
    pub textures: [Handle<Image>; 2],
    /// The maps.
    pub maps: [CloudShadowMapUniform; 2],
}

impl CloudShadowMaps {
    /// The maps of the extracted resource, or none.
    pub fn of(maps: Option<&Self>) -> [CloudShadowMapUniform; 2] {
        maps.map_or_else(Default::default, |maps| maps.maps)
    }
}

/// The maps' textures in the render world.
#[derive(SystemParam)]
pub struct CloudShadowTextures<'w> {
    maps: Option<Res<'w, CloudShadowMaps>>,
    images: Res<'w, RenderAssets<GpuImage>>,
    fallback: Res<'w, FallbackImage>,
}

impl CloudShadowTextures<'_> {
    /// The textures and their sampler as a bind group takes them: the
    /// fallback image where a map has no texture (yet); its weight is then
    /// 0 or it reads as lit.
    pub fn bindings(&self) -> ([&TextureView; 2], &Sampler) {
        let image = |n: usize| {
            self.maps
                .as_ref()
                .and_then(|maps| self.images.get(&maps.textures[n]))
                .unwrap_or(&self.fallback.d2)
        };
        let (first, second) = (image(0), image(1));
        ([&first.texture_view, &second.texture_view], &first.sampler)
    }
}

/// Loads the WGSL library `nebel_render::cloud_shadow_maps` (nothing in an
/// app without a renderer, which has no shaders).
pub fn load_cloud_shadow_maps_library(app: &mut App) {
    if app.get_sub_app(RenderApp).is_some() {
        load_shader_library!(app, "cloud_shadow_maps.wgsl");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bevy::math::{DVec2, DVec3};

    /// A map's plane, corner, texel, sun, weight, size and top reach the
    /// shaders where `cloud_shadow_maps.wgsl` reads them; without the
    /// resource no map has weight.
    #[test]
    fn a_map_is_packed_as_the_shaders_read_it() {
        let map = GroundShadow {
            height: 300.0,
            top: 320.0,
            min: DVec2::new(-12.5, 40.0),
            texel: 0.75,
            size: [200, 120],
            sun: DVec3::new(0.6, 0.8, 0.0),
            transmittance: vec![1.0; 200 * 120],
        };
        let uniform = CloudShadowMapUniform::new(&map, 256, 0.25);
        assert_eq!(uniform.plane, Vec4::new(300.0, 0.75, -12.5, 40.0));
        assert_eq!(uniform.sun_and_weight, Vec4::new(0.6, 0.8, 0.0, 0.25));
        assert_eq!(uniform.size, Vec4::new(200.0, 120.0, 256.0, 320.0));
        assert!(
            CloudShadowMaps::of(None)
                .iter()
                .all(|map| map.sun_and_weight.w == 0.0)
        );
    }
}
