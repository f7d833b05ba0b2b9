//! The cell projection's bind group layouts, shaders and pipeline variants.

use std::collections::HashMap;

use bevy::asset::load_embedded_asset;
use bevy::core_pipeline::FullscreenShader;
use bevy::prelude::*;
use bevy::render::render_resource::binding_types::{
    sampler, storage_buffer_read_only_sized, storage_buffer_sized, texture_2d, texture_3d,
    texture_depth_2d, texture_depth_2d_multisampled, uniform_buffer,
};
use bevy::render::render_resource::*;
use bevy::render::renderer::RenderDevice;
use bevy::shader::ShaderDefVal;
use nebel_core::optics::OpticalMode;

use super::CellProjection;
use super::merge::{SPAN_BLEND, span_format};
use super::resources::CellViewUniform;
use super::tables::CellTablesUniform;
use crate::cell_batch::CellBatchUniform;
use crate::light_shadows::light_shadow_layout;

/// The pipeline variants per optical mode ([`variant_index`]).
pub(super) const VARIANTS: usize = 512;

/// The index of a pipeline variant: modulated segment lengths, single
/// scattering, the handoff to fog layers, keyframe blending, drawing into a
/// merged layer, ray casting a whole grid, local lights, the sun in ground
/// fog and the local lights' shadow maps, each on or off.
pub(super) fn variant_index(
    modulated: bool,
    scattering: bool,
    handoff: bool,
    blended: bool,
    merged: bool,
    ray_cast: bool,
    local_lights: bool,
    ground_sun: bool,
    light_shadows: bool,
) -> usize {
    usize::from(modulated)
        | usize::from(scattering) << 1
        | usize::from(handoff) << 2
        | usize::from(blended) << 3
        | usize::from(merged) << 4
        | usize::from(ray_cast) << 5
        | usize::from(local_lights) << 6
        | usize::from(ground_sun) << 7
        | usize::from(light_shadows) << 8
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
    /// The view's layouts without and with the fragment counter
    /// ([`view_layout_index`]).
    view_layouts: [[BindGroupLayoutDescriptor; 3]; 2],
    pub(super) batch_layout: BindGroupLayoutDescriptor,
    /// Bevy's lights and shadow maps, group 2 of the variants whose lights
    /// cast shadows (`LIGHT_SHADOWS`, [`crate::light_shadows`]).
    pub(super) shadow_layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
    pub(super) composite_layout: BindGroupLayoutDescriptor,
    composite_shader: Handle<Shader>,
    fullscreen_vertex: VertexState,
    /// Marks the pixels whose transmittance fell below
    /// [`CellProjection::TERMINATION_TRANSMITTANCE`] in the stencil (reads
    /// the accumulation through `composite_layout`).
    pub(super) termination: CachedRenderPipelineId,
    /// The device can force the early fragment tests, which some drivers
    /// (lavapipe) leave until after a shader that may discard.
    early_depth_test: bool,
    /// The format of a merged layer's span ([`span_format`]).
    span_format: TextureFormat,
    /// The device has the storage buffer the fragment counter takes.
    pub(super) can_count_fragments: bool,
}

/// The format of the stencil that marks terminated pixels.
pub(super) const STENCIL_FORMAT: TextureFormat = TextureFormat::Stencil8;

/// The stencil bit of pixels the low resolution resolved.
pub(super) const RESOLVED: u32 = 1;

/// The stencil bit of pixels whose transmittance fell below the threshold.
pub(super) const TERMINATED: u32 = 2;

/// A stencil-only state on the bits `mask`: `compare` against the
/// reference, `pass` on success (a test that writes nothing keeps its write
/// mask 0, so the early fragment tests stay on while the cell shader
/// discards).
pub(super) fn stencil_state(
    compare: CompareFunction,
    pass: StencilOperation,
    mask: u32,
) -> DepthStencilState {
    let face = StencilFaceState {
        compare,
        fail_op: StencilOperation::Keep,
        depth_fail_op: StencilOperation::Keep,
        pass_op: pass,
    };
    DepthStencilState::stencil(
        STENCIL_FORMAT,
        StencilState {
            front: face,
            back: face,
            read_mask: mask,
            write_mask: if pass == StencilOperation::Keep {
                0
            } else {
                mask
            },
        },
    )
}

/// The stencil test of cell fragments: drawn where no bit is set (neither
/// resolved nor terminated), against the reference 0. MIP ignores
/// termination: its maximum is not attenuated by the transmittance.
pub(super) fn cell_stencil(mode: OpticalMode) -> DepthStencilState {
    let mask = match mode {
        OpticalMode::Mip => RESOLVED,
        OpticalMode::Sorted | OpticalMode::Emissive => RESOLVED | TERMINATED,
    };
    stencil_state(CompareFunction::Equal, StencilOperation::Keep, mask)
}

/// The index of a view layout: the depth texture as it is (single or
/// multisampled), or the low resolution's float depth.
fn view_layout_index(multisampled: bool, low_resolution: bool) -> usize {
    if low_resolution {
        2
    } else {
        usize::from(multisampled)
    }
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
    /// The view's fog layers scatter sunlight (`FOG_SUN`).
    pub fog_sun: bool,
    /// The batch's segments end where the view's fog layers begin.
    pub handoff: bool,
    /// Every vertex mixes its scalar and modulator with the next ones (the
    /// field at the end of the batch's span of keyframe blends).
    pub blended: bool,
    /// The accumulation target's format.
    pub target_format: TextureFormat,
    /// Fragments are drawn only where the stencil is 0 (the view marks
    /// terminated pixels).
    pub stencil: bool,
    /// Drawn into the view's low-resolution target.
    pub low_resolution: bool,
    /// Every fragment adds to the fragment counter
    /// ([`CountCellFragments`](super::CountCellFragments)).
    pub count_fragments: bool,
    /// Drawn into a merged layer of its own, with its span along the ray
    /// (see [`super::merge`]).
    pub merged: bool,
    /// A whole grid, ray cast through its tetrahedra (`nebel_lod`'s
    /// `cell_grid`): its box is drawn instead of cells.
    pub ray_cast: bool,
    /// Point and spot lights reach the batch (`crate::local_lights`).
    pub local_lights: bool,
    /// The sun lights the batch as ground fog (`crate::fog_sunlight`).
    pub ground_sun: bool,
    /// A light that reaches the batch (a point or spot light, or the sun
    /// of a ground fog or a scattering volume) reads Bevy's shadow map of
    /// it.
    pub light_shadows: bool,
}

/// Creates the bind group layouts and loads the shaders.
pub fn init_cell_projection_pipeline(
    mut commands: Commands,
    asset_server: Res<AssetServer>,
    fullscreen_shader: Res<FullscreenShader>,
    device: Res<RenderDevice>,
    pipeline_cache: Res<PipelineCache>,
) {
    // The cells, their modulators and their next keyframe are storage
    // buffers, which WebGL2-class devices lack: there nothing is drawn (fog
    // layers still are), and the app goes on. The fragment counter takes a
    // fourth.
    let storage_buffers = device.limits().max_storage_buffers_per_shader_stage;
    if storage_buffers < 3 {
        warn!(
            "nebel: the cell projection is off: the device has {storage_buffers} storage buffers per shader stage, it needs 3"
        );
        commands.insert_resource(CellProjectionUnsupported);
    }
    let unfilterable = TextureSampleType::Float { filterable: false };
    let view_layout = |depth: BindGroupLayoutEntryBuilder, counter: bool| {
        let (uniform, depth) = (uniform_buffer::<CellViewUniform>(true), depth);
        let entries = if counter {
            // The fragment counter (`CountCellFragments`).
            BindGroupLayoutEntries::sequential(
                ShaderStages::VERTEX_FRAGMENT,
                (
                    uniform,
                    depth,
                    storage_buffer_sized(false, None).visibility(ShaderStages::FRAGMENT),
                ),
            )
            .to_vec()
        } else {
            BindGroupLayoutEntries::sequential(ShaderStages::VERTEX_FRAGMENT, (uniform, depth))
                .to_vec()
        };
        BindGroupLayoutDescriptor::new("nebel_cell_view_layout", &entries)
    };
    let composite_layout = BindGroupLayoutDescriptor::new(
        "nebel_cell_composite_layout",
        &BindGroupLayoutEntries::single(ShaderStages::FRAGMENT, texture_2d(unfilterable)),
    );
    let fullscreen_vertex = fullscreen_shader.to_vertex_state();
    let termination = pipeline_cache.queue_render_pipeline(RenderPipelineDescriptor {
        label: Some("nebel_cell_termination_pipeline".into()),
        layout: vec![composite_layout.clone()],
        vertex: fullscreen_vertex.clone(),
        fragment: Some(FragmentState {
            shader: load_embedded_asset!(asset_server.as_ref(), "cell_termination.wgsl"),
            shader_defs: vec![ShaderDefVal::UInt(
                "TERMINATION_TRANSMITTANCE_BITS".into(),
                CellProjection::TERMINATION_TRANSMITTANCE.to_bits(),
            )],
            targets: vec![],
            ..default()
        }),
        // Sets the terminated bit (the pass's reference).
        depth_stencil: Some(stencil_state(
            CompareFunction::Always,
            StencilOperation::Replace,
            TERMINATED,
        )),
        ..default()
    });
    commands.insert_resource(CellProjectionPipeline {
        view_layouts: [false, true].map(|counter| {
            [
                view_layout(texture_depth_2d(), counter),
                view_layout(texture_depth_2d_multisampled(), counter),
                view_layout(texture_2d(unfilterable), counter),
            ]
        }),
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
                    // The sun map of ground fog (`crate::fog_sunlight`).
                    texture_2d(unfilterable),
                    // The clouds' shadow maps over it and their sampler
                    // (`crate::cloud_shadow_maps`).
                    texture_2d(TextureSampleType::Float { filterable: true }),
                    texture_2d(TextureSampleType::Float { filterable: true }),
                    sampler(SamplerBindingType::Filtering),
                ),
            ),
        ),
        shadow_layout: light_shadow_layout(&device),
        shader: load_embedded_asset!(asset_server.as_ref(), "cell_projection.wgsl"),
        composite_layout,
        composite_shader: load_embedded_asset!(asset_server.as_ref(), "cell_composite.wgsl"),
        fullscreen_vertex,
        termination,
        early_depth_test: device
            .features()
            .contains(WgpuFeatures::SHADER_EARLY_DEPTH_TEST),
        span_format: span_format(&device),
        can_count_fragments: storage_buffers >= 4,
    });
}

/// The composite pass: the accumulated cells over the view's HDR target.
#[derive(Resource, Default)]
pub struct CellCompositePipelines(pub(super) HashMap<TextureFormat, CachedRenderPipelineId>);

impl CellProjectionPipeline {
    /// The layout of the view's bind group: its depth texture (see
    /// [`view_layout_index`]), and the fragment counter if `counting`.
    pub(super) fn view_layout(
        &self,
        multisampled: bool,
        low_resolution: bool,
        counting: bool,
    ) -> &BindGroupLayoutDescriptor {
        &self.view_layouts[usize::from(counting)][view_layout_index(multisampled, low_resolution)]
    }

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
        let under = under_blend();
        let (mode_def, blend) = match key.mode {
            OpticalMode::Sorted => ("SORTED", under),
            OpticalMode::Emissive => ("EMISSIVE", under),
            // The maximum over the cells, unattenuated; T stays (max(0, T)).
            OpticalMode::Mip => (
                "MIP",
                BlendState {
                    color: BlendComponent {
                        src_factor: BlendFactor::One,
                        dst_factor: BlendFactor::One,
                        operation: BlendOperation::Max,
                    },
                    alpha: BlendComponent {
                        src_factor: BlendFactor::One,
                        dst_factor: BlendFactor::One,
                        operation: BlendOperation::Max,
                    },
                },
            ),
        };
        let mut shader_defs: Vec<ShaderDefVal> = vec![
            mode_def.into(),
            ShaderDefVal::UInt(
                "MAX_LOCAL_LIGHTS".into(),
                nebel_core::local_light::MAX_LOCAL_LIGHTS as u32,
            ),
        ];
        if key.stencil && self.early_depth_test {
            shader_defs.push("EARLY_DEPTH_TEST".into());
        }
        if key.count_fragments {
            shader_defs.push("COUNT_FRAGMENTS".into());
        }
        if key.low_resolution {
            shader_defs.push("LOW_RESOLUTION".into());
        } else if key.multisampled {
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
        if key.fog_sun {
            shader_defs.push("FOG_SUN".into());
        }
        if key.handoff {
            shader_defs.push("FOG_HANDOFF".into());
        }
        if key.blended {
            shader_defs.push("BLENDED".into());
        }
        if key.ground_sun {
            shader_defs.push("GROUND_SUN".into());
        }
        if key.local_lights {
            shader_defs.push("LOCAL_LIGHTS".into());
        }
        let mut layout = vec![
            self.view_layout(key.multisampled, key.low_resolution, key.count_fragments)
                .clone(),
            self.batch_layout.clone(),
        ];
        let sunlit = key.ground_sun || key.scattering;
        if key.light_shadows && (key.local_lights || sunlit) {
            shader_defs.push("SHADOW_MAPS".into());
            shader_defs.push(ShaderDefVal::UInt("LIGHT_SHADOW_GROUP".into(), 2));
            layout.push(self.shadow_layout.clone());
            if key.local_lights {
                shader_defs.push("LIGHT_SHADOWS".into());
            }
            if key.ground_sun {
                shader_defs.push("SUN_SHADOWS".into());
            }
            if key.scattering {
                shader_defs.push("SCATTERED_SUN_SHADOWS".into());
            }
        }
        if key.local_lights || key.ground_sun {
            // A ray cast grid's segments are already pieces of a voxel; a
            // cell's may cross a whole coarse octree leaf.
            shader_defs.push("SCATTERED_LIGHT".into());
            shader_defs.push(ShaderDefVal::UInt(
                "LIGHT_PIECES".into(),
                if key.ray_cast {
                    1
                } else {
                    nebel_core::optics::MODULATOR_PIECES
                },
            ));
        }
        if key.ray_cast {
            shader_defs.push("RAY_CAST".into());
            shader_defs.push(ShaderDefVal::UInt(
                "TERMINATION_TRANSMITTANCE_BITS".into(),
                CellProjection::TERMINATION_TRANSMITTANCE.to_bits(),
            ));
        }
        let mut targets = vec![Some(ColorTargetState {
            format: key.target_format,
            blend: Some(blend),
            write_mask: ColorWrites::ALL,
        })];
        if key.merged {
            shader_defs.push("MERGED".into());
            targets.push(Some(ColorTargetState {
                format: self.span_format,
                blend: Some(SPAN_BLEND),
                write_mask: ColorWrites::ALL,
            }));
        }
        RenderPipelineDescriptor {
            label: Some("nebel_cell_projection_pipeline".into()),
            layout,
            vertex: VertexState {
                shader: self.shader.clone(),
                shader_defs: shader_defs.clone(),
                ..default()
            },
            fragment: Some(FragmentState {
                shader: self.shader.clone(),
                shader_defs,
                targets,
                ..default()
            }),
            // Cells are triangle strips wound inward, a grid's box a list
            // of triangles: back faces are counter-clockwise, so culling
            // "back" (clockwise) keeps them.
            primitive: PrimitiveState {
                topology: if key.ray_cast {
                    PrimitiveTopology::TriangleList
                } else {
                    PrimitiveTopology::TriangleStrip
                },
                front_face: FrontFace::Ccw,
                cull_mode: Some(Face::Back),
                ..default()
            },
            depth_stencil: key.stencil.then(|| cell_stencil(key.mode)),
            ..default()
        }
    }
}

/// The blend of the accumulation: front to back, it holds the colour C and
/// the transmittance T, and a segment (c, α) goes under, C += T c,
/// T *= 1 − α. Emissive segments have α = 0: they add T c and leave T.
pub(super) fn under_blend() -> BlendState {
    BlendState {
        color: BlendComponent {
            src_factor: BlendFactor::DstAlpha,
            dst_factor: BlendFactor::One,
            operation: BlendOperation::Add,
        },
        alpha: BlendComponent {
            src_factor: BlendFactor::Zero,
            dst_factor: BlendFactor::OneMinusSrcAlpha,
            operation: BlendOperation::Add,
        },
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_combination_of_features_has_its_own_variant() {
        let mut seen = [false; VARIANTS];
        for bits in 0..VARIANTS {
            let on = |bit: usize| bits & (1 << bit) != 0;
            let index = variant_index(
                on(0),
                on(1),
                on(2),
                on(3),
                on(4),
                on(5),
                on(6),
                on(7),
                on(8),
            );
            assert!(index < VARIANTS, "{index}");
            assert!(!seen[index], "{bits:b} shares variant {index}");
            seen[index] = true;
        }
    }
}
