//! Grids of values as textures the shaders load texel by texel: one mip
//! level, bound for sampling, uploaded once.

use bevy::render::render_resource::{
    Extent3d, TextureDataOrder, TextureDescriptor, TextureDimension, TextureFormat, TextureUsages,
    TextureView, TextureViewDescriptor,
};
use bevy::render::renderer::{RenderDevice, RenderQueue};

/// A 2D texture of `size` texels (x, then rows along y) of `format`,
/// holding `data`, and its view.
pub fn data_texture(
    device: &RenderDevice,
    queue: &RenderQueue,
    label: &'static str,
    size: [usize; 2],
    format: TextureFormat,
    data: &[u8],
) -> TextureView {
    device
        .create_texture_with_data(
            queue,
            &TextureDescriptor {
                label: Some(label),
                size: Extent3d {
                    width: size[0] as u32,
                    height: size[1] as u32,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: TextureDimension::D2,
                format,
                usage: TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            },
            TextureDataOrder::LayerMajor,
            data,
        )
        .create_view(&TextureViewDescriptor::default())
}
