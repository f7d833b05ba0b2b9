//! The cell-projection render system: draws every [`CellBatch`] into the HDR
//! view target after the opaque pass (DESIGN.md §3-4; paper 001 ch. 8-10,
//! paper 000 §4).
//!
//! Bevy 0.19 has no render-graph nodes: the pass is [`draw_cell_batches`], a
//! system in the [`Core3d`] schedule between the main pass and the early post
//! process, reading the scene depth. The render world is a row of small
//! systems, as in Bevy's volumetric fog:
//!
//! 1. [`init_cell_projection_pipeline`] (startup): bind group layouts and shader.
//! 2. [`extract_cell_batches`]: drawable batches of the main world.
//! 3. [`prepare_cell_buffers`]: one storage buffer per batch, re-uploaded only
//!    when the batch's generation changed.
//! 4. [`prepare_cell_tables`]: pre-integration tables, cached by transfer
//!    function hash and segment length, built once per change on the CPU
//!    ([`PreintegrationTable`], 64×64×128 colour, 64×64 pair table).
//! 5. [`prepare_cell_views`]: per-view uniforms and pipelines, and the depth
//!    texture made readable.
//! 6. [`draw_cell_batches`]: batches back to front by the distance of their
//!    bounds' centre, inside a batch in buffer order (the batch's exact
//!    order), into a per-view float accumulation target that starts
//!    transparent; then one full-screen pass (`cell_composite.wgsl`) puts the
//!    result over the scene: `I = C + (1 − α) scene`.
//!
//! The accumulation target is `Rgba32Float` where the device can blend it
//! (`FLOAT32_BLENDABLE`; lavapipe can), `Rgba16Float` otherwise: a ray may
//! cross hundreds of cells and every blend rounds, and the 16-bit HDR target
//! of Bevy's views made the 64³ cloud measurably darker. Emissive and MIP
//! cells write no opacity, so they add to the scene rather than hide it (MIP
//! takes the maximum over the cells, then adds it).
//!
//! Each pixel of a cell is computed exactly under perspective: the fragment
//! shader intersects the view ray with the cell's planes, clips the segment to
//! the near plane and to the opaque depth and looks up the tables (see
//! `cell_projection.wgsl`). With no drawable batch, none of these systems does
//! any work: no table is built, no buffer written, no pass begun; the
//! [`CellProjectionStats`] counters prove it.

use std::collections::HashMap;
use std::num::NonZeroU64;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use bevy::asset::{embedded_asset, load_embedded_asset};
use bevy::core_pipeline::FullscreenShader;
use bevy::core_pipeline::core_3d::prepare_core_3d_depth_textures;
use bevy::core_pipeline::schedule::{Core3d, Core3dSystems};
use bevy::prelude::*;
use bevy::render::camera::ExtractedCamera;
use bevy::render::render_resource::binding_types::{
    storage_buffer_read_only_sized, texture_2d, texture_3d, texture_depth_2d,
    texture_depth_2d_multisampled, uniform_buffer, uniform_buffer_sized,
};
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderContext, RenderDevice, RenderQueue, ViewQuery};
use bevy::render::texture::{CachedTexture, TextureCache};
use bevy::render::view::{ExtractedView, Msaa, ViewDepthTexture, ViewTarget};
use bevy::render::{Extract, ExtractSchedule, Render, RenderApp, RenderStartup, RenderSystems};
use bevy::shader::ShaderDefVal;
use nebel_core::optics::OpticalMode;
use nebel_core::preintegration::{PreintegrationConfig, PreintegrationTable};
use nebel_core::transfer::TransferFunction;
use nebel_lod::GpuCell;

use crate::cell_batch::{CellBatch, CellScattering};

/// Samples along `s_f` and `s_b` of the GPU tables.
const TABLE_SCALAR_SIZE: u32 = 64;
/// Samples along `l` of the GPU colour table.
const TABLE_LENGTH_SIZE: u32 = 128;

/// Draws [`CellBatch`]es.
#[derive(Default)]
pub struct CellProjectionPlugin;

/// Work counters of the cell-projection render system, shared by the main and
/// the render world (an `Arc`), so tests and `nebel render --stats` can show
/// that a scene without cells costs nothing.
#[derive(Resource, Clone, Default, Debug)]
pub struct CellProjectionStats(Arc<CellProjectionCounters>);

/// The counters behind [`CellProjectionStats`]; each only grows.
#[derive(Default, Debug)]
pub struct CellProjectionCounters {
    /// Render passes begun (one per view that had batches, per frame).
    pub passes: AtomicU64,
    /// Pre-integration tables built.
    pub tables_built: AtomicU64,
    /// Cell buffers uploaded.
    pub uploads: AtomicU64,
    /// Cells drawn, summed over passes.
    pub cells_drawn: AtomicU64,
}

impl CellProjectionStats {
    /// The counters.
    pub fn counters(&self) -> &CellProjectionCounters {
        &self.0
    }
}

impl CellProjectionCounters {
    /// Current values: passes, tables built, uploads, cells drawn.
    pub fn snapshot(&self) -> [u64; 4] {
        [
            &self.passes,
            &self.tables_built,
            &self.uploads,
            &self.cells_drawn,
        ]
        .map(|c| c.load(Ordering::Relaxed))
    }
}

impl Plugin for CellProjectionPlugin {
    fn build(&self, app: &mut App) {
        embedded_asset!(app, "cell_projection.wgsl");
        embedded_asset!(app, "cell_composite.wgsl");
        let stats = CellProjectionStats::default();
        app.insert_resource(stats.clone());
        let Some(render_app) = app.get_sub_app_mut(RenderApp) else {
            return;
        };
        render_app
            .insert_resource(stats)
            .init_resource::<ExtractedCellBatches>()
            .init_resource::<GpuCellBuffers>()
            .init_resource::<GpuCellTables>()
            .init_resource::<SpecializedRenderPipelines<CellProjectionPipeline>>()
            .init_resource::<CellViewUniforms>()
            .init_resource::<CellCompositePipelines>()
            .add_systems(RenderStartup, init_cell_projection_pipeline)
            .add_systems(ExtractSchedule, extract_cell_batches)
            .add_systems(
                Render,
                (
                    make_depth_readable
                        .in_set(RenderSystems::Prepare)
                        .before(prepare_core_3d_depth_textures),
                    (
                        prepare_cell_buffers,
                        prepare_cell_tables,
                        prepare_cell_views,
                    )
                        .in_set(RenderSystems::PrepareResources),
                ),
            )
            .add_systems(
                Core3d,
                draw_cell_batches
                    .after(Core3dSystems::MainPass)
                    .before(Core3dSystems::EarlyPostProcess),
            );
    }
}

/// A batch as the render world sees it.
#[derive(Clone)]
struct ExtractedCellBatch {
    cells: Arc<Vec<GpuCell>>,
    modulators: Option<Arc<Vec<[f32; 4]>>>,
    scattering: Option<CellScattering>,
    generation: u64,
    transfer_function: Arc<TransferFunction>,
    mode: OpticalMode,
    table_key: TableKey,
    centre: Vec3,
}

/// The drawable batches of this frame, keyed by main-world entity.
#[derive(Resource, Default)]
struct ExtractedCellBatches(Vec<(Entity, ExtractedCellBatch)>);

/// Pre-integration tables are shared by batches with the same transfer
/// function and maximum segment length.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
struct TableKey {
    transfer_hash: u64,
    max_length_bits: u32,
}

/// Copies the drawable batches into the render world.
fn extract_cell_batches(
    mut extracted: ResMut<ExtractedCellBatches>,
    batches: Extract<Query<(Entity, &CellBatch)>>,
) {
    extracted.0.clear();
    for (entity, batch) in &batches {
        if !batch.is_drawable() {
            continue;
        }
        let Some(transfer_function) = batch.transfer_function.clone() else {
            continue;
        };
        if let Some(modulators) = &batch.modulators
            && modulators.len() != batch.cells.len()
        {
            error_once!(
                "nebel: a CellBatch has {} modulators for {} cells; it is not drawn",
                modulators.len(),
                batch.cells.len()
            );
            continue;
        }
        extracted.0.push((
            entity,
            ExtractedCellBatch {
                cells: batch.cells.clone(),
                modulators: batch.modulators.clone(),
                scattering: batch
                    .scattering
                    .filter(|_| batch.mode == OpticalMode::Sorted),
                generation: batch.generation,
                table_key: TableKey {
                    transfer_hash: transfer_function.content_hash(),
                    max_length_bits: batch.max_segment_length.to_bits(),
                },
                transfer_function,
                mode: batch.mode,
                centre: (batch.bounds_min + batch.bounds_max) / 2.0,
            },
        ));
    }
}

/// The GPU copy of one batch.
struct GpuCellBuffer {
    generation: u64,
    buffer: Buffer,
    /// The per-cell modulators, or one zero entry for an unmodulated batch
    /// (the binding must exist; the unmodulated pipeline never reads it).
    modulators: Buffer,
    modulated: bool,
    /// The [`CellScattering`] uniform (zeros when the batch has none).
    scattering: Buffer,
    scattered: bool,
    count: u32,
}

#[derive(Resource, Default)]
struct GpuCellBuffers(HashMap<Entity, GpuCellBuffer>);

/// Uploads batches whose generation changed and drops those that are gone.
fn prepare_cell_buffers(
    extracted: Res<ExtractedCellBatches>,
    mut buffers: ResMut<GpuCellBuffers>,
    device: Res<RenderDevice>,
    stats: Res<CellProjectionStats>,
) {
    if extracted.0.is_empty() && buffers.0.is_empty() {
        return;
    }
    buffers
        .0
        .retain(|entity, _| extracted.0.iter().any(|(e, _)| e == entity));
    for (entity, batch) in &extracted.0 {
        if buffers
            .0
            .get(entity)
            .is_some_and(|gpu| gpu.generation == batch.generation)
        {
            continue;
        }
        let buffer = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("nebel_cell_batch"),
            contents: bytemuck::cast_slice(batch.cells.as_slice()),
            usage: BufferUsages::STORAGE,
        });
        let unmodulated = [[0.0f32; 4]];
        let modulators = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("nebel_cell_modulators"),
            contents: bytemuck::cast_slice(
                batch
                    .modulators
                    .as_deref()
                    .map_or(&unmodulated[..], Vec::as_slice),
            ),
            usage: BufferUsages::STORAGE,
        });
        let scattering = device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("nebel_cell_scattering"),
            contents: bytemuck::cast_slice(
                &batch
                    .scattering
                    .map_or([[0.0f32; 4]; 3], |scattering| scattering.uniform()),
            ),
            usage: BufferUsages::UNIFORM,
        });
        stats.0.uploads.fetch_add(1, Ordering::Relaxed);
        buffers.0.insert(
            *entity,
            GpuCellBuffer {
                generation: batch.generation,
                buffer,
                modulators,
                modulated: batch.modulators.is_some(),
                scattering,
                scattered: batch.scattering.is_some(),
                count: batch.cells.len() as u32,
            },
        );
    }
}

/// The GPU copy of one [`PreintegrationTable`].
struct GpuCellTable {
    colour: TextureView,
    emission: TextureView,
    maximum: TextureView,
    parameters: Buffer,
}

#[derive(Resource, Default)]
struct GpuCellTables(HashMap<TableKey, GpuCellTable>);

/// Parameters of the tables, as the shader's `CellTables`.
#[derive(Clone, Copy, ShaderType, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
struct CellTablesUniform {
    max_length: f32,
    scalar_size: u32,
    length_size: u32,
    padding: u32,
}

/// Builds the tables that a batch needs and nobody has built, drops unused ones.
fn prepare_cell_tables(
    extracted: Res<ExtractedCellBatches>,
    mut tables: ResMut<GpuCellTables>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    stats: Res<CellProjectionStats>,
) {
    if extracted.0.is_empty() && tables.0.is_empty() {
        return;
    }
    tables
        .0
        .retain(|key, _| extracted.0.iter().any(|(_, b)| b.table_key == *key));
    for (_, batch) in &extracted.0 {
        if tables.0.contains_key(&batch.table_key) {
            continue;
        }
        let config = PreintegrationConfig {
            scalar_size: TABLE_SCALAR_SIZE,
            length_size: TABLE_LENGTH_SIZE,
            max_length: f32::from_bits(batch.table_key.max_length_bits),
        };
        let table = match PreintegrationTable::build(&batch.transfer_function, config) {
            Ok(table) => table,
            Err(error) => {
                error!("nebel: cannot build the pre-integration table: {error}");
                continue;
            }
        };
        stats.0.tables_built.fetch_add(1, Ordering::Relaxed);
        let texture = |label: &'static str,
                       size: Extent3d,
                       dimension: TextureDimension,
                       data: &[[f32; 4]]| {
            device
                .create_texture_with_data(
                    &queue,
                    &TextureDescriptor {
                        label: Some(label),
                        size,
                        mip_level_count: 1,
                        sample_count: 1,
                        dimension,
                        format: TextureFormat::Rgba32Float,
                        usage: TextureUsages::TEXTURE_BINDING,
                        view_formats: &[],
                    },
                    TextureDataOrder::LayerMajor,
                    bytemuck::cast_slice(data),
                )
                .create_view(&TextureViewDescriptor::default())
        };
        let pair = Extent3d {
            width: TABLE_SCALAR_SIZE,
            height: TABLE_SCALAR_SIZE,
            depth_or_array_layers: 1,
        };
        let volume = Extent3d {
            depth_or_array_layers: TABLE_LENGTH_SIZE,
            ..pair
        };
        let parameters = CellTablesUniform {
            max_length: config.max_length,
            scalar_size: TABLE_SCALAR_SIZE,
            length_size: TABLE_LENGTH_SIZE,
            padding: 0,
        };
        tables.0.insert(
            batch.table_key,
            GpuCellTable {
                colour: texture(
                    "nebel_colour_table",
                    volume,
                    TextureDimension::D3,
                    table.colour(),
                ),
                emission: texture(
                    "nebel_emission_table",
                    pair,
                    TextureDimension::D2,
                    table.emission(),
                ),
                maximum: texture(
                    "nebel_maximum_table",
                    pair,
                    TextureDimension::D2,
                    table.maximum(),
                ),
                parameters: device.create_buffer_with_data(&BufferInitDescriptor {
                    label: Some("nebel_cell_tables"),
                    contents: bytemuck::bytes_of(&parameters),
                    usage: BufferUsages::UNIFORM,
                }),
            },
        );
    }
}

/// The camera data the shader needs, as its `CellView`.
#[derive(Clone, Copy, ShaderType)]
struct CellViewUniform {
    clip_from_world: Mat4,
    world_from_clip: Mat4,
    camera_position: Vec4,
    viewport: Vec4,
}

#[derive(Resource, Default)]
struct CellViewUniforms(DynamicUniformBuffer<CellViewUniform>);

/// Per view: where its uniform sits, its accumulation target and its
/// pipelines (three modes drawing into the target, one compositing it).
#[derive(Component)]
struct CellProjectionView {
    uniform_offset: u32,
    multisampled: bool,
    accumulation: CachedTexture,
    /// Per optical mode, the pipeline of each variant ([`variant_index`]),
    /// where a batch of this frame needs it.
    pipelines: [[Option<CachedRenderPipelineId>; 4]; 3],
    composite: CachedRenderPipelineId,
}

/// The index of a pipeline variant: modulated segment lengths and single
/// scattering, each on or off.
fn variant_index(modulated: bool, scattering: bool) -> usize {
    usize::from(modulated) | usize::from(scattering) << 1
}

fn mode_index(mode: OpticalMode) -> usize {
    match mode {
        OpticalMode::Sorted => 0,
        OpticalMode::Emissive => 1,
        OpticalMode::Mip => 2,
    }
}

/// Bind group layouts and shaders of the cell-projection pass and of the
/// composite pass.
#[derive(Resource)]
pub struct CellProjectionPipeline {
    view_layouts: [BindGroupLayoutDescriptor; 2],
    batch_layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
    composite_layout: BindGroupLayoutDescriptor,
    composite_shader: Handle<Shader>,
    fullscreen_vertex: VertexState,
}

/// What a cell-projection pipeline depends on.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct CellProjectionPipelineKey {
    mode: OpticalMode,
    modulated: bool,
    scattering: bool,
    multisampled: bool,
    target_format: TextureFormat,
}

/// Creates the bind group layouts and loads the shaders.
pub fn init_cell_projection_pipeline(
    mut commands: Commands,
    asset_server: Res<AssetServer>,
    fullscreen_shader: Res<FullscreenShader>,
) {
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
                    uniform_buffer_sized(false, NonZeroU64::new(48)),
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
struct CellCompositePipelines(HashMap<TextureFormat, CachedRenderPipelineId>);

impl CellProjectionPipeline {
    fn composite_descriptor(&self, target_format: TextureFormat) -> RenderPipelineDescriptor {
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
        }
        if key.scattering {
            shader_defs.push("SCATTERING".into());
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

/// Lets the pass read the scene depth, only while there is something to draw.
fn make_depth_readable(extracted: Res<ExtractedCellBatches>, mut cameras: Query<&mut Camera3d>) {
    if extracted.0.is_empty() {
        return;
    }
    for mut camera in &mut cameras {
        camera.depth_texture_usages.0 |= TextureUsages::TEXTURE_BINDING.bits();
    }
}

/// The format cells accumulate in: 32-bit float where the device can blend
/// it (every blend rounds; a ray crosses up to hundreds of cells), 16-bit
/// float otherwise.
fn accumulation_format(device: &RenderDevice) -> TextureFormat {
    if device.features().contains(WgpuFeatures::FLOAT32_BLENDABLE) {
        TextureFormat::Rgba32Float
    } else {
        TextureFormat::Rgba16Float
    }
}

/// Writes each view's uniform, gets its accumulation target and
/// specialises its pipelines.
#[allow(clippy::too_many_arguments)]
fn prepare_cell_views(
    mut commands: Commands,
    extracted: Res<ExtractedCellBatches>,
    views: Query<(Entity, &ExtractedView, &ExtractedCamera, &Msaa)>,
    mut texture_cache: ResMut<TextureCache>,
    mut composites: ResMut<CellCompositePipelines>,
    mut uniforms: ResMut<CellViewUniforms>,
    pipeline: Res<CellProjectionPipeline>,
    mut pipelines: ResMut<SpecializedRenderPipelines<CellProjectionPipeline>>,
    pipeline_cache: Res<PipelineCache>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
) {
    if extracted.0.is_empty() {
        return;
    }
    uniforms.0.clear();
    let format = accumulation_format(&device);
    for (entity, view, camera, msaa) in &views {
        let Some(size) = camera.physical_target_size else {
            continue;
        };
        let accumulation = texture_cache.get(
            &device,
            TextureDescriptor {
                label: Some("nebel_cell_accumulation"),
                size: Extent3d {
                    width: size.x,
                    height: size.y,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: TextureDimension::D2,
                format,
                usage: TextureUsages::RENDER_ATTACHMENT | TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            },
        );
        let composite = *composites.0.entry(view.target_format).or_insert_with(|| {
            pipeline_cache.queue_render_pipeline(pipeline.composite_descriptor(view.target_format))
        });
        let world_from_view = view.world_from_view.to_matrix();
        let clip_from_world = view
            .clip_from_world
            .unwrap_or_else(|| view.clip_from_view * world_from_view.inverse());
        let uniform_offset = uniforms.0.push(&CellViewUniform {
            clip_from_world,
            world_from_clip: clip_from_world.inverse(),
            camera_position: view.world_from_view.translation().extend(1.0),
            viewport: view.viewport.as_vec4(),
        });
        let multisampled = *msaa != Msaa::Off;
        // Only the variants some batch of this frame needs.
        let mut variants = [[None; 4]; 3];
        for (_, batch) in &extracted.0 {
            let (modulated, scattering) = (batch.modulators.is_some(), batch.scattering.is_some());
            variants[mode_index(batch.mode)][variant_index(modulated, scattering)] =
                Some(pipelines.specialize(
                    &pipeline_cache,
                    &pipeline,
                    CellProjectionPipelineKey {
                        mode: batch.mode,
                        modulated,
                        scattering,
                        multisampled,
                        target_format: format,
                    },
                ));
        }
        commands.entity(entity).insert(CellProjectionView {
            uniform_offset,
            multisampled,
            accumulation,
            pipelines: variants,
            composite,
        });
    }
    uniforms.0.write_buffer(&device, &queue);
}

/// Draws every batch into the view's HDR target, back to front.
#[allow(clippy::too_many_arguments)]
fn draw_cell_batches(
    view: ViewQuery<(
        &ViewTarget,
        &ViewDepthTexture,
        &ExtractedView,
        &CellProjectionView,
    )>,
    extracted: Res<ExtractedCellBatches>,
    buffers: Res<GpuCellBuffers>,
    tables: Res<GpuCellTables>,
    uniforms: Res<CellViewUniforms>,
    pipeline: Res<CellProjectionPipeline>,
    pipeline_cache: Res<PipelineCache>,
    stats: Res<CellProjectionStats>,
    mut ctx: RenderContext,
) {
    if extracted.0.is_empty() {
        return;
    }
    let (view_target, depth, extracted_view, cell_view) = view.into_inner();
    let Some(view_binding) = uniforms.0.binding() else {
        return;
    };
    let eye = extracted_view.world_from_view.translation();
    let mut order: Vec<&(Entity, ExtractedCellBatch)> = extracted.0.iter().collect();
    order.sort_by(|(_, a), (_, b)| {
        b.centre
            .distance_squared(eye)
            .total_cmp(&a.centre.distance_squared(eye))
    });

    let view_bind_group = ctx.render_device().create_bind_group(
        "nebel_cell_view_bind_group",
        &pipeline_cache
            .get_bind_group_layout(&pipeline.view_layouts[usize::from(cell_view.multisampled)]),
        &BindGroupEntries::sequential((view_binding, depth.view())),
    );
    let mut draws = Vec::with_capacity(order.len());
    for (entity, batch) in order {
        let (Some(buffer), Some(table)) = (buffers.0.get(entity), tables.0.get(&batch.table_key))
        else {
            continue;
        };
        let Some(render_pipeline) = cell_view.pipelines[mode_index(batch.mode)]
            [variant_index(buffer.modulated, buffer.scattered)]
        .and_then(|id| pipeline_cache.get_render_pipeline(id)) else {
            continue;
        };
        let pair_table = match batch.mode {
            OpticalMode::Mip => &table.maximum,
            OpticalMode::Sorted | OpticalMode::Emissive => &table.emission,
        };
        let batch_bind_group = ctx.render_device().create_bind_group(
            "nebel_cell_batch_bind_group",
            &pipeline_cache.get_bind_group_layout(&pipeline.batch_layout),
            &BindGroupEntries::sequential((
                buffer.buffer.as_entire_binding(),
                &table.colour,
                pair_table,
                table.parameters.as_entire_binding(),
                buffer.modulators.as_entire_binding(),
                buffer.scattering.as_entire_binding(),
            )),
        );
        draws.push((render_pipeline, batch_bind_group, buffer.count));
    }
    let Some(composite_pipeline) = pipeline_cache.get_render_pipeline(cell_view.composite) else {
        return;
    };
    if draws.is_empty() {
        return;
    }

    // The cells accumulate from transparent black in float, back to front...
    let accumulation = &cell_view.accumulation.default_view;
    let mut pass = ctx
        .command_encoder()
        .begin_render_pass(&RenderPassDescriptor {
            label: Some("nebel_cell_projection_pass"),
            color_attachments: &[Some(RenderPassColorAttachment {
                view: accumulation,
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
    stats.0.passes.fetch_add(1, Ordering::Relaxed);
    pass.set_bind_group(0, &view_bind_group, &[cell_view.uniform_offset]);
    for (render_pipeline, batch_bind_group, count) in &draws {
        pass.set_pipeline(render_pipeline);
        pass.set_bind_group(1, batch_bind_group, &[]);
        pass.draw(0..6, 0..*count);
        stats
            .0
            .cells_drawn
            .fetch_add(u64::from(*count), Ordering::Relaxed);
    }
    drop(pass);

    // ...and go over the scene in one blend.
    let composite_bind_group = ctx.render_device().create_bind_group(
        "nebel_cell_composite_bind_group",
        &pipeline_cache.get_bind_group_layout(&pipeline.composite_layout),
        &BindGroupEntries::single(accumulation),
    );
    let mut pass = ctx
        .command_encoder()
        .begin_render_pass(&RenderPassDescriptor {
            label: Some("nebel_cell_composite_pass"),
            color_attachments: &[Some(RenderPassColorAttachment {
                view: view_target.main_texture_view(),
                depth_slice: None,
                resolve_target: None,
                ops: Operations {
                    load: LoadOp::Load,
                    store: StoreOp::Store,
                },
            })],
            depth_stencil_attachment: None,
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
    pass.set_pipeline(composite_pipeline);
    pass.set_bind_group(0, &composite_bind_group, &[]);
    pass.draw(0..3, 0..1);
}
