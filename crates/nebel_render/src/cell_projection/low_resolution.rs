//! Cells at a lower resolution ([`CellResolution`]): the downsampled opaque
//! depth the low-resolution cells are clipped by, and the upsample that
//! fills the smooth pixels of the full-resolution accumulation and marks
//! them in its stencil, so the full-resolution cell passes draw only the
//! edges (`low_resolution.wgsl`).

use std::collections::HashMap;

use bevy::asset::load_embedded_asset;
use bevy::core_pipeline::FullscreenShader;
use bevy::prelude::*;
use bevy::render::render_resource::binding_types::{
    texture_2d, texture_depth_2d, texture_depth_2d_multisampled, uniform_buffer,
};
use bevy::render::render_resource::*;
use bevy::render::renderer::RenderContext;
use bevy::render::texture::CachedTexture;
use bevy::shader::ShaderDefVal;

use super::pipeline::{RESOLVED, stencil_state};
use super::settings::CellResolution;

/// The format of the downsampled depth.
pub(super) const LOW_DEPTH_FORMAT: TextureFormat = TextureFormat::R32Float;

/// The upsample's parameters, as the shader's `Upsample`.
#[derive(Clone, Copy, Default, ShaderType)]
pub struct UpsampleUniform {
    /// x: relative depth tolerance, y: colour and transmittance tolerance,
    /// zw: the low-resolution target's size in pixels.
    tolerances: Vec4,
}

/// Every low-resolution view's [`UpsampleUniform`] of this frame.
#[derive(Resource, Default)]
pub struct UpsampleUniforms(pub(super) DynamicUniformBuffer<UpsampleUniform>);

impl UpsampleUniforms {
    /// Adds the uniform of a low-resolution target of `size` pixels with
    /// the colour and transmittance tolerance `tolerance` and returns its
    /// offset.
    pub(super) fn push(&mut self, size: UVec2, tolerance: f32) -> u32 {
        self.0.push(&UpsampleUniform {
            tolerances: Vec4::new(
                CellResolution::DEPTH_TOLERANCE,
                tolerance,
                size.x as f32,
                size.y as f32,
            ),
        })
    }
}

/// The passes of one view's low resolution.
pub struct LowResolutionView {
    /// The viewport of the low-resolution passes: the view's, divided.
    pub(super) viewport: Vec4,
    pub(super) depth: CachedTexture,
    pub(super) accumulation: CachedTexture,
    /// The low-resolution stencil of early termination.
    pub(super) stencil: Option<CachedTexture>,
    /// Where the view's low-resolution `CellView` uniform sits.
    pub(super) uniform_offset: u32,
    /// Where its [`UpsampleUniform`] sits.
    pub(super) upsample_offset: u32,
    pub(super) downsample: CachedRenderPipelineId,
    pub(super) upsample: CachedRenderPipelineId,
}

/// What a downsample or upsample pipeline depends on.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub(super) struct ResamplePipelineKey {
    pub(super) multisampled: bool,
    pub(super) divisor: u32,
    pub(super) upsample: bool,
    /// The full-resolution accumulation's format (the upsample's target).
    pub(super) format: TextureFormat,
}

/// The layouts and shader of the resampling passes, and their pipelines.
#[derive(Resource)]
pub struct ResamplePipelines {
    /// Per multisampling, the downsample's layout: the depth.
    downsample_layouts: [BindGroupLayoutDescriptor; 2],
    /// Per multisampling, the upsample's layout: the depth, the
    /// low-resolution depth and accumulation, the parameters.
    upsample_layouts: [BindGroupLayoutDescriptor; 2],
    shader: Handle<Shader>,
    fullscreen_vertex: VertexState,
    pipelines: HashMap<ResamplePipelineKey, CachedRenderPipelineId>,
}

/// Creates the resampling layouts and loads the shader.
pub fn init_resample_pipelines(
    mut commands: Commands,
    asset_server: Res<AssetServer>,
    fullscreen_shader: Res<FullscreenShader>,
) {
    let depth = |multisampled: bool| {
        if multisampled {
            texture_depth_2d_multisampled()
        } else {
            texture_depth_2d()
        }
    };
    let unfilterable = TextureSampleType::Float { filterable: false };
    let layouts = |f: &dyn Fn(bool) -> BindGroupLayoutDescriptor| [f(false), f(true)];
    commands.insert_resource(ResamplePipelines {
        downsample_layouts: layouts(&|multisampled| {
            BindGroupLayoutDescriptor::new(
                "nebel_cell_downsample_layout",
                &BindGroupLayoutEntries::single(ShaderStages::FRAGMENT, depth(multisampled)),
            )
        }),
        upsample_layouts: layouts(&|multisampled| {
            BindGroupLayoutDescriptor::new(
                "nebel_cell_upsample_layout",
                &BindGroupLayoutEntries::sequential(
                    ShaderStages::FRAGMENT,
                    (
                        depth(multisampled),
                        texture_2d(unfilterable),
                        texture_2d(unfilterable),
                        uniform_buffer::<UpsampleUniform>(true),
                    ),
                ),
            )
        }),
        shader: load_embedded_asset!(asset_server.as_ref(), "low_resolution.wgsl"),
        fullscreen_vertex: fullscreen_shader.to_vertex_state(),
        pipelines: HashMap::new(),
    });
}

impl ResamplePipelines {
    /// The pipeline of `key`, queued the first time it is asked for.
    pub(super) fn get(
        &mut self,
        pipeline_cache: &PipelineCache,
        key: ResamplePipelineKey,
    ) -> CachedRenderPipelineId {
        if let Some(id) = self.pipelines.get(&key) {
            return *id;
        }
        let mut shader_defs = vec![ShaderDefVal::Int("DIVISOR".into(), key.divisor as i32)];
        if key.multisampled {
            shader_defs.push("MULTISAMPLED".into());
        }
        let (name, layouts, format, depth_stencil) = if key.upsample {
            // The pixels it fills are marked resolved.
            let resolve =
                stencil_state(CompareFunction::Always, StencilOperation::Replace, RESOLVED);
            (
                "upsample",
                &self.upsample_layouts,
                key.format,
                Some(resolve),
            )
        } else {
            (
                "downsample",
                &self.downsample_layouts,
                LOW_DEPTH_FORMAT,
                None,
            )
        };
        let descriptor = RenderPipelineDescriptor {
            label: Some(format!("nebel_cell_{name}_pipeline").into()),
            layout: vec![layouts[usize::from(key.multisampled)].clone()],
            vertex: self.fullscreen_vertex.clone(),
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                shader_defs,
                entry_point: Some(name.into()),
                targets: vec![Some(ColorTargetState {
                    format,
                    blend: None,
                    write_mask: ColorWrites::ALL,
                })],
            }),
            depth_stencil,
            ..default()
        };
        let id = pipeline_cache.queue_render_pipeline(descriptor);
        self.pipelines.insert(key, id);
        id
    }

    /// Downsamples the view's depth into `low.depth`.
    pub(super) fn downsample(
        &self,
        ctx: &mut RenderContext,
        pipeline_cache: &PipelineCache,
        low: &LowResolutionView,
        pipeline: &RenderPipeline,
        depth: &TextureView,
        multisampled: bool,
    ) {
        let bind_group = ctx.render_device().create_bind_group(
            "nebel_cell_downsample_bind_group",
            &pipeline_cache
                .get_bind_group_layout(&self.downsample_layouts[usize::from(multisampled)]),
            &BindGroupEntries::single(depth),
        );
        let mut pass = ctx
            .command_encoder()
            .begin_render_pass(&RenderPassDescriptor {
                label: Some("nebel_cell_downsample_pass"),
                color_attachments: &[Some(RenderPassColorAttachment {
                    view: &low.depth.default_view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: Operations {
                        load: LoadOp::Clear(default()),
                        store: StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: None,
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.draw(0..3, 0..1);
    }

    /// Clears the full-resolution `accumulation` and its `stencil`, fills
    /// the pixels the low resolution resolves and marks them.
    pub(super) fn upsample(
        &self,
        ctx: &mut RenderContext,
        pipeline_cache: &PipelineCache,
        low: &LowResolutionView,
        pipeline: &RenderPipeline,
        uniforms: &UpsampleUniforms,
        (depth, multisampled): (&TextureView, bool),
        (accumulation, stencil): (&TextureView, &TextureView),
    ) {
        let Some(binding) = uniforms.0.binding() else {
            return;
        };
        let bind_group = ctx.render_device().create_bind_group(
            "nebel_cell_upsample_bind_group",
            &pipeline_cache
                .get_bind_group_layout(&self.upsample_layouts[usize::from(multisampled)]),
            &BindGroupEntries::sequential((
                depth,
                &low.depth.default_view,
                &low.accumulation.default_view,
                binding,
            )),
        );
        let mut pass = ctx
            .command_encoder()
            .begin_render_pass(&RenderPassDescriptor {
                label: Some("nebel_cell_upsample_pass"),
                color_attachments: &[Some(RenderPassColorAttachment {
                    view: accumulation,
                    depth_slice: None,
                    resolve_target: None,
                    ops: Operations {
                        load: LoadOp::Clear(LinearRgba::BLACK.into()),
                        store: StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(RenderPassDepthStencilAttachment {
                    view: stencil,
                    depth_ops: None,
                    stencil_ops: Some(Operations {
                        load: LoadOp::Clear(0),
                        store: StoreOp::Store,
                    }),
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &bind_group, &[low.upsample_offset]);
        pass.set_stencil_reference(RESOLVED);
        pass.draw(0..3, 0..1);
    }
}
