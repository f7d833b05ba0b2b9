//! The cell projection's bind group layouts, shaders and pipeline variants.

use std::collections::HashMap;

use bevy::asset::load_embedded_asset;
use bevy::core_pipeline::FullscreenShader;
use bevy::prelude::*;
use bevy::render::render_resource::binding_types::{
    storage_buffer_read_only_sized, texture_2d, texture_3d, texture_depth_2d,
    texture_depth_2d_multisampled, uniform_buffer,
};
use bevy::render::render_resource::*;
use bevy::render::renderer::RenderDevice;
use bevy::shader::ShaderDefVal;
use nebel_core::optics::OpticalMode;

use super::resources::{CellTablesUniform, CellViewUniform};
use crate::cell_batch::CellBatchUniform;

/// The pipeline variants per optical mode ([`variant_index`]).
pub(super) const VARIANTS: usize = 16;

/// The index of a pipeline variant: modulated segment lengths, single
/// scattering, the handoff to fog layers and keyframe blending, each on or
/// off.
pub(super) fn variant_index(
    modulated: bool,
    scattering: bool,
    handoff: bool,
    blended: bool,
) -> usize {
    usize::from(modulated)
        | usize::from(scattering) << 1
        | usize::from(handoff) << 2
        | usize::from(blended) << 3
}

pub(super) fn mode_index(mode: OpticalMode) -> usize {
    match mode {
        OpticalMode::Sorted => 0,
        OpticalMode::Emissive => 1,
        OpticalMode::Mip => 2,
    }
}

/// Present when the device cannot run the cell projection (no storage
/// buffers): no batch is extracted.
#[derive(Resource)]
pub struct CellProjectionUnsupported;

/// Bind group layouts and shaders of the cell-projection pass and of the
/// composite pass.
#[derive(Resource)]
pub struct CellProjectionPipeline {
    pub(super) view_layouts: [BindGroupLayoutDescriptor; 2],
    pub(super) batch_layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
    pub(super) composite_layout: BindGroupLayoutDescriptor,
    composite_shader: Handle<Shader>,
    fullscreen_vertex: VertexState,
}

/// What a cell-projection pipeline depends on.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct CellProjectionPipelineKey {
    /// How the segments combine.
    pub mode: OpticalMode,
    /// Segment lengths scaled by a per-cell modulator.
    pub modulated: bool,
    /// Single scattering of the sun.
    pub scattering: bool,
    /// The depth texture is multisampled.
    pub multisampled: bool,
    /// The view has fog layers: segments are seen through them.
    pub fog_layers: bool,
    /// The batch's segments end where the view's fog layers begin.
    pub handoff: bool,
    /// Every vertex mixes its scalar and modulator with the next ones (the
    /// field at the end of the batch's span of keyframe blends).
    pub blended: bool,
    /// The accumulation target's format.
    pub target_format: TextureFormat,
}

/// Creates the bind group layouts and loads the shaders.
pub fn init_cell_projection_pipeline(
    mut commands: Commands,
    asset_server: Res<AssetServer>,
    fullscreen_shader: Res<FullscreenShader>,
    device: Res<RenderDevice>,
) {
    // The cells, their modulators and their next keyframe are storage
    // buffers, which WebGL2-class devices lack: there nothing is drawn (fog
    // layers still are), and the app goes on.
    let storage_buffers = device.limits().max_storage_buffers_per_shader_stage;
    if storage_buffers < 3 {
        warn!(
            "nebel: the cell projection is off: the device has {storage_buffers} storage buffers per shader stage, it needs 3"
        );
        commands.insert_resource(CellProjectionUnsupported);
    }
    let view_layout = |multisampled: bool| {
        BindGroupLayoutDescriptor::new(
            "nebel_cell_view_layout",
            &BindGroupLayoutEntries::sequential(
                ShaderStages::VERTEX_FRAGMENT,
                (
                    uniform_buffer::<CellViewUniform>(true),
                    if multisampled {
                        texture_depth_2d_multisampled()
                    } else {
                        texture_depth_2d()
                    },
                ),
            ),
        )
    };
    let unfilterable = TextureSampleType::Float { filterable: false };
    commands.insert_resource(CellProjectionPipeline {
        view_layouts: [view_layout(false), view_layout(true)],
        batch_layout: BindGroupLayoutDescriptor::new(
            "nebel_cell_batch_layout",
            &BindGroupLayoutEntries::sequential(
                ShaderStages::VERTEX_FRAGMENT,
                (
                    storage_buffer_read_only_sized(false, None),
                    texture_3d(unfilterable),
                    texture_2d(unfilterable),
                    uniform_buffer::<CellTablesUniform>(false),
                    storage_buffer_read_only_sized(false, None),
                    uniform_buffer::<CellBatchUniform>(false),
                    storage_buffer_read_only_sized(false, None),
                ),
            ),
        ),
        shader: load_embedded_asset!(asset_server.as_ref(), "cell_projection.wgsl"),
        composite_layout: BindGroupLayoutDescriptor::new(
            "nebel_cell_composite_layout",
            &BindGroupLayoutEntries::single(ShaderStages::FRAGMENT, texture_2d(unfilterable)),
        ),
        composite_shader: load_embedded_asset!(asset_server.as_ref(), "cell_composite.wgsl"),
        fullscreen_vertex: fullscreen_shader.to_vertex_state(),
    });
}

/// The composite pass: the accumulated cells over the view's HDR target.
#[derive(Resource, Default)]
pub struct CellCompositePipelines(pub(super) HashMap<TextureFormat, CachedRenderPipelineId>);

impl CellProjectionPipeline {
    pub(super) fn composite_descriptor(
        &self,
        target_format: TextureFormat,
    ) -> RenderPipelineDescriptor {
        RenderPipelineDescriptor {
            label: Some("nebel_cell_composite_pipeline".into()),
            layout: vec![self.composite_layout.clone()],
            vertex: self.fullscreen_vertex.clone(),
            fragment: Some(FragmentState {
                shader: self.composite_shader.clone(),
                targets: vec![Some(ColorTargetState {
                    format: target_format,
                    blend: Some(BlendState::PREMULTIPLIED_ALPHA_BLENDING),
                    write_mask: ColorWrites::ALL,
                })],
                ..default()
            }),
            ..default()
        }
    }
}

impl SpecializedRenderPipeline for CellProjectionPipeline {
    type Key = CellProjectionPipelineKey;

    fn specialize(&self, key: Self::Key) -> RenderPipelineDescriptor {
        let (mode_def, blend) = match key.mode {
            OpticalMode::Sorted => ("SORTED", BlendState::PREMULTIPLIED_ALPHA_BLENDING),
            OpticalMode::Emissive => (
                "EMISSIVE",
                BlendState {
                    color: BlendComponent {
                        src_factor: BlendFactor::One,
                        dst_factor: BlendFactor::One,
                        operation: BlendOperation::Add,
                    },
                    alpha: BlendComponent::OVER,
                },
            ),
            OpticalMode::Mip => (
                "MIP",
                BlendState {
                    color: BlendComponent {
                        src_factor: BlendFactor::One,
                        dst_factor: BlendFactor::One,
                        operation: BlendOperation::Max,
                    },
                    alpha: BlendComponent::OVER,
                },
            ),
        };
        let mut shader_defs: Vec<ShaderDefVal> = vec![mode_def.into()];
        if key.multisampled {
            shader_defs.push("MULTISAMPLED".into());
        }
        if key.modulated {
            shader_defs.push("MODULATED".into());
            shader_defs.push(ShaderDefVal::UInt(
                "MODULATOR_PIECES".into(),
                nebel_core::optics::MODULATOR_PIECES,
            ));
        }
        if key.scattering {
            shader_defs.push("SCATTERING".into());
        }
        if key.fog_layers {
            shader_defs.push("FOG_LAYERS".into());
        }
        if key.handoff {
            shader_defs.push("FOG_HANDOFF".into());
        }
        if key.blended {
            shader_defs.push("BLENDED".into());
        }
        RenderPipelineDescriptor {
            label: Some("nebel_cell_projection_pipeline".into()),
            layout: vec![
                self.view_layouts[usize::from(key.multisampled)].clone(),
                self.batch_layout.clone(),
            ],
            vertex: VertexState {
                shader: self.shader.clone(),
                shader_defs: shader_defs.clone(),
                ..default()
            },
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                shader_defs,
                targets: vec![Some(ColorTargetState {
                    format: key.target_format,
                    blend: Some(blend),
                    write_mask: ColorWrites::ALL,
                })],
                ..default()
            }),
            // Cells are triangle strips wound inward: back faces are
            // counter-clockwise, so culling "back" (clockwise) keeps them.
            primitive: PrimitiveState {
                topology: PrimitiveTopology::TriangleStrip,
                front_face: FrontFace::Ccw,
                cull_mode: Some(Face::Back),
                ..default()
            },
            ..default()
        }
    }
}

/// The format cells accumulate in: 32-bit float where the device can blend
/// it (every blend rounds; a ray crosses up to hundreds of cells), 16-bit
/// float otherwise.
pub(super) fn accumulation_format(device: &RenderDevice) -> TextureFormat {
    if device.features().contains(WgpuFeatures::FLOAT32_BLENDABLE) {
        TextureFormat::Rgba32Float
    } else {
        TextureFormat::Rgba16Float
    }
}
