//! The render world's data of the cell projection and the systems that keep
//! it: the extracted batches, their GPU buffers and the per-view uniforms and
//! accumulation targets.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::sync::atomic::Ordering;

use bevy::math::DMat4;
use bevy::pbr::{ViewLightsUniformOffset, ViewShadowBindings};
use bevy::prelude::*;
use bevy::render::Extract;
use bevy::render::camera::ExtractedCamera;
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderDevice, RenderQueue};
use bevy::render::texture::{CachedTexture, TextureCache};
use bevy::render::view::{ExtractedView, Msaa};
use nebel_core::field::DensityGrid;
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::TransferFunction;
use nebel_lod::{CellGrid, Cells};

use super::CellProjectionStats;
use super::low_resolution::{
    LOW_DEPTH_FORMAT, LowResolutionView, ResamplePipelineKey, ResamplePipelines, UpsampleUniforms,
};
use super::merge::{MAX_MERGED, MergePipelines, MergeTargets, merges, overlap_groups, span_format};
use super::pipeline::{
    CellCompositePipelines, CellProjectionPipeline, CellProjectionPipelineKey,
    CellProjectionUnsupported, STENCIL_FORMAT, VARIANTS, accumulation_format, mode_index,
    variant_index,
};
use super::queries::CountCellFragments;
use super::settings::CellProjection;
use crate::cell_batch::{CellBatch, CellBatchUniform, CellBlend, CellScattering, CellSunlight};
use crate::cloud_shadow_maps::{CloudShadowMapUniform, CloudShadowMaps};
use crate::fog_layers::{FogLayersUniform, ViewFogLayers};
use crate::fog_sunlight::{CellFogSunlight, sun_map_texture};
use crate::light_shadows::LightShadows;
use crate::local_lights::{
    ReachingLights, VolumetricPointLights, VolumetricSpotLights, visible_volumetric_lights,
};

/// A batch as the render world sees it.
#[derive(Clone)]
pub struct ExtractedCellBatch {
    cells: Arc<Cells>,
    pub(super) scattering: Option<CellScattering>,
    /// The batch's segments end where the view's fog layers begin.
    pub(super) hands_off: bool,
    /// The main-world component changed since the last extraction: upload
    /// the cells again.
    changed: bool,
    pub(super) transfer_function: Arc<TransferFunction>,
    pub(super) mode: OpticalMode,
    pub(super) table_key: TableKey,
    pub(super) centre: Vec3,
    /// The group of batches whose bounds this one's intersect, directly or
    /// through others ([`overlap_groups`]): drawn merged with them.
    pub(super) group: Option<usize>,
    /// The blend factor toward the next keyframe, clamped ([`CellBlend`]);
    /// 0 for a batch that is not blended.
    blend: f32,
    /// The sunlight factor ([`CellSunlight`], checked).
    sunlight: Vec3,
    /// The point and spot lights that reach a sorted batch.
    lights: ReachingLights,
    /// How it scatters them ([`CellBatch::light_response`]).
    light_response: LightResponse,
    /// The sun lighting a sorted batch of ground fog.
    fog_sunlight: Option<CellFogSunlight>,
}

impl ExtractedCellBatch {
    /// Whether the batch carries segment-length modulators.
    pub(super) fn is_modulated(&self) -> bool {
        self.cells.is_modulated()
    }

    /// Whether the batch blends toward a next keyframe.
    pub(super) fn is_blended(&self) -> bool {
        self.cells.is_blended()
    }

    /// Whether point or spot lights reach the batch.
    pub(super) fn is_lit_locally(&self) -> bool {
        self.lights.count > 0
    }

    /// Whether a light that reaches the batch reads Bevy's shadow map of
    /// it: a point or spot light ([`resolve_light_shadows`]), or the sun of
    /// a ground fog or of a scattering volume.
    pub(super) fn is_shadowed(&self) -> bool {
        self.lights.is_shadowed()
            || self
                .fog_sunlight
                .as_ref()
                .is_some_and(|sunlight| sunlight.shadows)
            || self
                .scattering
                .as_ref()
                .is_some_and(|scattering| scattering.shadows)
    }

    /// Whether the sun lights the batch as ground fog.
    pub(super) fn is_sunlit(&self) -> bool {
        self.fog_sunlight.is_some()
    }

    /// The identity of the batch's sun map, 0 without one.
    fn sun_map_key(&self) -> usize {
        self.fog_sunlight
            .as_ref()
            .map_or(0, |sunlight| Arc::as_ptr(&sunlight.map) as usize)
    }

    /// Whether the batch is a whole grid, ray cast.
    pub(super) fn is_ray_cast(&self) -> bool {
        self.cells.grid.is_some()
    }

    /// The batch's per-batch uniform, a sunlit fog's under the clouds'
    /// shadow maps `clouds`.
    fn uniform(&self, clouds: [CloudShadowMapUniform; 2]) -> CellBatchUniform {
        CellBatchUniform::new(
            self.scattering.as_ref(),
            self.blend,
            self.sunlight,
            (&self.lights, self.light_response),
            self.fog_sunlight
                .as_ref()
                .map(|sunlight| (sunlight, clouds)),
        )
    }
}

/// The drawable batches of this frame, keyed by main-world entity.
#[derive(Resource, Default)]
pub struct ExtractedCellBatches(pub(super) Vec<(Entity, ExtractedCellBatch)>);

/// Pre-integration tables are shared by batches with the same transfer
/// function (the tables do not depend on the cells).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub struct TableKey {
    pub(super) transfer_hash: u64,
}

/// Copies the drawable batches into the render world, each sorted one with
/// the opted-in point and spot lights that reach it. A batch whose
/// modulators or next keyframe do not match its cells, or whose grid does
/// not fit the device's storage-buffer binding, is not drawn; the error is
/// logged once per entity.
pub fn extract_cell_batches(
    mut extracted: ResMut<ExtractedCellBatches>,
    batches: Extract<
        Query<(
            Entity,
            Ref<CellBatch>,
            Option<&CellBlend>,
            Option<&CellSunlight>,
            Option<&CellFogSunlight>,
        )>,
    >,
    (points, spots): (
        Extract<VolumetricPointLights>,
        Extract<VolumetricSpotLights>,
    ),
    unsupported: Option<Res<CellProjectionUnsupported>>,
    device: Res<RenderDevice>,
    mut refused: Local<HashSet<Entity>>,
) {
    extracted.0.clear();
    if unsupported.is_some() {
        return;
    }
    let lights = visible_volumetric_lights(&points, &spots);
    // Forget entities that are gone, so the set stays as small as the world.
    refused.retain(|entity| batches.contains(*entity));
    for (entity, batch, blend, sunlight, fog_sunlight) in &batches {
        if !batch.is_drawable() {
            continue;
        }
        let Some(transfer_function) = batch.transfer_function.clone() else {
            continue;
        };
        let cells = &batch.cells;
        let mismatch =
            |what: &str, count: usize| Some(format!("{count} {what} for {} cells", cells.len()));
        let limit = device.limits().max_storage_buffer_binding_size;
        let grid_bytes = cells.grid.as_deref().map(grid_binding_bytes);
        let refusal = if let Some(bytes) = grid_bytes
            && bytes > limit
        {
            Some(format!(
                "a grid binding of {bytes} bytes, more than the device's storage-buffer binding holds ({limit} bytes; draw it through the octree)"
            ))
        } else if cells.grid.is_some() {
            None
        } else if cells.is_modulated() && cells.modulators.len() != cells.len() {
            mismatch("modulators", cells.modulators.len())
        } else if cells.is_blended() && cells.next_scalars.len() != cells.len() {
            mismatch("next scalars", cells.next_scalars.len())
        } else if cells.is_blended()
            && cells.is_modulated()
            && cells.next_modulators.len() != cells.len()
        {
            mismatch("next modulators", cells.next_modulators.len())
        } else {
            None
        };
        if let Some(refusal) = refusal {
            if refused.insert(entity) {
                error!("nebel: the CellBatch of {entity} has {refusal}; it is not drawn");
            }
            continue;
        }
        refused.remove(&entity);
        extracted.0.push((
            entity,
            ExtractedCellBatch {
                cells: batch.cells.clone(),
                scattering: batch
                    .scattering
                    .filter(|_| batch.mode == OpticalMode::Sorted),
                hands_off: batch.ends_where_fog_layers_begin,
                changed: batch.is_changed(),
                table_key: TableKey {
                    transfer_hash: transfer_function.content_hash(),
                },
                transfer_function,
                mode: batch.mode,
                centre: (batch.cells.bounds_min + batch.cells.bounds_max) / 2.0,
                group: None,
                blend: if cells.is_blended() {
                    blend.map_or(0.0, CellBlend::clamped)
                } else {
                    0.0
                },
                sunlight: sunlight.map_or(Vec3::ONE, CellSunlight::checked),
                lights: if batch.mode == OpticalMode::Sorted {
                    ReachingLights::reaching(&lights, cells.bounds_min, cells.bounds_max)
                } else {
                    ReachingLights::default()
                },
                light_response: batch.light_response,
                fog_sunlight: fog_sunlight
                    .filter(|_| batch.mode == OpticalMode::Sorted)
                    .cloned(),
            },
        ));
    }
    let bounds: Vec<_> = extracted
        .0
        .iter()
        .map(|(_, batch)| {
            let cells = &batch.cells;
            (cells.bounds_min, cells.bounds_max, merges(batch.mode))
        })
        .collect();
    for ((_, batch), group) in extracted.0.iter_mut().zip(overlap_groups(&bounds)) {
        batch.group = group;
    }
}

/// Gives each light that reaches a batch and casts shadows its index among
/// Bevy's clustered lights of this frame, where the shader finds its shadow
/// map; none without Bevy's lights (no `PbrPlugin`).
pub fn resolve_light_shadows(
    mut extracted: ResMut<ExtractedCellBatches>,
    light_shadows: LightShadows,
) {
    for (_, batch) in &mut extracted.0 {
        batch.lights = batch
            .lights
            .with_shadow_indices(|entity| light_shadows.light_index(entity));
    }
}

/// The bytes of a ray-cast grid's largest binding: its scalars, or its
/// placement and modulators, each value beside its next keyframe's when
/// blended.
fn grid_binding_bytes(grid: &CellGrid) -> u64 {
    let field = (size_of_val(grid.grid().values()) * if grid.is_blended() { 2 } else { 1 }) as u64;
    let placement = size_of::<GpuCellGrid>() as u64;
    field.max(
        placement
            + if grid.modulators().is_some() {
                field
            } else {
                0
            },
    )
}

/// A storage buffer of `header` followed by the values of `field`, each
/// beside its value in `next` when given (the shader's `vec2` of a blended
/// field), written in place a chunk at a time: a copy of a large grid's
/// values would double its memory for the upload.
fn field_buffer(
    device: &RenderDevice,
    label: &'static str,
    header: &[u8],
    field: &[f32],
    next: Option<&[f32]>,
) -> Buffer {
    const CHUNK: usize = 1 << 16;
    let stride = if next.is_some() { 2 } else { 1 };
    let size = header.len() + stride * size_of_val(field);
    let buffer = device.create_buffer(&BufferDescriptor {
        label: Some(label),
        size: size.max(4) as u64,
        usage: BufferUsages::STORAGE,
        mapped_at_creation: true,
    });
    {
        let mut mapped = buffer.slice(..).get_mapped_range_mut();
        if !header.is_empty() {
            mapped.slice(..header.len()).copy_from_slice(header);
        }
        let mut offset = header.len();
        let mut pairs = Vec::with_capacity(if next.is_some() { CHUNK } else { 0 });
        for (index, chunk) in field.chunks(CHUNK).enumerate() {
            let bytes: &[u8] = match next {
                Some(next) => {
                    pairs.clear();
                    let next = &next[index * CHUNK..][..chunk.len()];
                    pairs.extend(chunk.iter().zip(next).map(|(&a, &b)| [a, b]));
                    bytemuck::cast_slice(&pairs)
                }
                None => bytemuck::cast_slice(chunk),
            };
            mapped
                .slice(offset..offset + bytes.len())
                .copy_from_slice(bytes);
            offset += bytes.len();
        }
    }
    buffer.unmap();
    buffer
}

/// A ray-cast grid's buffers: its scalars (binding 0), its placement and
/// modulators (binding 4), each value beside its next keyframe's when
/// blended, and its brick occupancy (binding 6).
fn grid_buffers(device: &RenderDevice, grid: &CellGrid) -> (Buffer, Buffer, Buffer) {
    let next = grid.next_keyframe();
    let scalars = field_buffer(
        device,
        "nebel_cell_grid_values",
        &[],
        grid.grid().values(),
        next.map(|(scalars, _)| scalars.values()),
    );
    let placement = GpuCellGrid::new(grid);
    let placement = bytemuck::bytes_of(&placement);
    let modulators = match grid.modulators() {
        Some(modulators) => field_buffer(
            device,
            "nebel_cell_grid",
            placement,
            modulators.values(),
            next.and_then(|(_, modulators)| modulators)
                .map(DensityGrid::values),
        ),
        None => device.create_buffer_with_data(&BufferInitDescriptor {
            label: Some("nebel_cell_grid"),
            contents: placement,
            usage: BufferUsages::STORAGE,
        }),
    };
    let occupancy = device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some("nebel_cell_grid_occupancy"),
        contents: bytemuck::cast_slice(grid.occupied()),
        usage: BufferUsages::STORAGE,
    });
    (scalars, modulators, occupancy)
}

/// The GPU copy of one batch.
pub struct GpuCellBuffer {
    pub(super) buffer: Buffer,
    /// The per-cell modulators, or one zero entry for an unmodulated batch
    /// (the binding must exist; the unmodulated pipeline never reads it).
    pub(super) modulators: Buffer,
    pub(super) modulated: bool,
    /// Per cell, the next scalars then the next modulators (zeros when not
    /// modulated: the field at the end of the batch's span of keyframe
    /// blends), or one zero entry for a batch that is not
    /// blended (the binding must exist; the unblended pipeline never reads
    /// it); a ray-cast grid's brick occupancy.
    pub(super) next_keyframe: Buffer,
    pub(super) blended: bool,
    /// The [`CellScattering`] (zeros when the batch has none) and the blend
    /// factor.
    pub(super) parameters: UniformBuffer<CellBatchUniform>,
    pub(super) scattered: bool,
    /// A whole grid, ray cast: `buffer` holds its scalars, `modulators` its
    /// [`GpuCellGrid`] followed by its modulators, and `next_keyframe` its
    /// brick occupancy (each value beside its next keyframe's when
    /// blended).
    pub(super) ray_cast: bool,
    /// The cells: the tetrahedra, or the grid's.
    pub(super) count: u32,
    /// The sun map of a sunlit ground fog, or a texel for a batch without
    /// (the binding must exist; the pipeline without the sun never reads
    /// it).
    pub(super) sun_map: TextureView,
    /// The identity of the map it holds, 0 for none.
    sun_map_key: usize,
}

/// Where a ray-cast grid lies, as the shader's `CellGrid`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct GpuCellGrid {
    world_from_index: [f32; 16],
    /// The linear part of `index_from_world`, in a 4×4 matrix.
    index_from_world: [f32; 16],
    /// Voxels per axis; 1 in the last when `world_from_index` mirrors.
    voxels: [u32; 4],
    /// Bricks per axis of the occupancy; voxels per brick edge in the last.
    bricks: [u32; 4],
    /// The value at or below which the grid has no opacity (negative for
    /// none), and 1 when it is the modulator's instead of the scalar's; the
    /// rest unused.
    clear: [f32; 4],
}

impl GpuCellGrid {
    fn new(grid: &CellGrid) -> Self {
        let world_from_index = grid.world_from_index();
        let [x, y, z] = grid.voxels().map(|n| n as u32);
        let [bx, by, bz] = grid.brick_counts().map(|n| n as u32);
        Self {
            world_from_index: DMat4::from(world_from_index).as_mat4().to_cols_array(),
            index_from_world: DMat4::from_mat3(grid.index_from_world().matrix3)
                .as_mat4()
                .to_cols_array(),
            voxels: [
                x,
                y,
                z,
                u32::from(world_from_index.matrix3.determinant() < 0.0),
            ],
            bricks: [bx, by, bz, grid.brick_size() as u32],
            clear: [
                grid.clear_below(),
                f32::from(u8::from(grid.clears_modulators())),
                0.0,
                0.0,
            ],
        }
    }
}

/// The GPU copies of this frame's batches, by main-world entity.
#[derive(Resource, Default)]
pub struct GpuCellBuffers(pub(super) HashMap<Entity, GpuCellBuffer>);

/// Uploads batches that are new or changed, writes the per-batch uniform
/// (blend factor, sunlight, the clouds' shadow maps over a sunlit fog) of
/// those where only it changed, and drops those
/// that are gone.
pub fn prepare_cell_buffers(
    extracted: Res<ExtractedCellBatches>,
    mut buffers: ResMut<GpuCellBuffers>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    stats: Res<CellProjectionStats>,
    clouds: Option<Res<CloudShadowMaps>>,
) {
    if extracted.0.is_empty() && buffers.0.is_empty() {
        return;
    }
    let clouds = CloudShadowMaps::of(clouds.as_deref());
    buffers
        .0
        .retain(|entity, _| extracted.0.iter().any(|(e, _)| e == entity));
    for (entity, batch) in &extracted.0 {
        if !batch.changed
            && let Some(buffer) = buffers.0.get_mut(entity)
        {
            if buffer.sun_map_key != batch.sun_map_key() {
                buffer.sun_map = sun_map_texture(
                    &device,
                    &queue,
                    batch.fog_sunlight.as_ref().map(|sunlight| &*sunlight.map),
                );
                buffer.sun_map_key = batch.sun_map_key();
            }
            let uniform = batch.uniform(clouds);
            if *buffer.parameters.get() != uniform {
                buffer.parameters.set(uniform);
                buffer.parameters.write_buffer(&device, &queue);
            }
            continue;
        }
        let (buffer, modulators, next_keyframe) = if let Some(grid) = &batch.cells.grid {
            grid_buffers(&device, grid)
        } else {
            let unmodulated = [[0.0f32; 4]];
            (
                device.create_buffer_with_data(&BufferInitDescriptor {
                    label: Some("nebel_cell_batch"),
                    contents: bytemuck::cast_slice(batch.cells.tetrahedra.as_slice()),
                    usage: BufferUsages::STORAGE,
                }),
                device.create_buffer_with_data(&BufferInitDescriptor {
                    label: Some("nebel_cell_modulators"),
                    contents: bytemuck::cast_slice(if batch.is_modulated() {
                        batch.cells.modulators.as_slice()
                    } else {
                        &unmodulated[..]
                    }),
                    usage: BufferUsages::STORAGE,
                }),
                next_keyframe_buffer(&device, &batch.cells),
            )
        };
        let sun_map = match buffers.0.get(entity) {
            Some(old) if old.sun_map_key == batch.sun_map_key() => old.sun_map.clone(),
            _ => sun_map_texture(
                &device,
                &queue,
                batch.fog_sunlight.as_ref().map(|sunlight| &*sunlight.map),
            ),
        };
        let mut parameters = UniformBuffer::from(batch.uniform(clouds));
        parameters.set_label(Some("nebel_cell_batch_parameters"));
        parameters.write_buffer(&device, &queue);
        stats.0.uploads.fetch_add(1, Ordering::Relaxed);
        buffers.0.insert(
            *entity,
            GpuCellBuffer {
                buffer,
                modulators,
                modulated: batch.is_modulated(),
                next_keyframe,
                blended: batch.is_blended(),
                parameters,
                scattered: batch.scattering.is_some(),
                ray_cast: batch.is_ray_cast(),
                count: batch.cells.len() as u32,
                sun_map,
                sun_map_key: batch.sun_map_key(),
            },
        );
    }
}

/// Per cell, the next scalars then the next modulators of a blended batch
/// (zeros when not modulated), or one zero entry for a batch that is not
/// blended (the binding must exist; the unblended pipeline never reads it).
fn next_keyframe_buffer(device: &RenderDevice, cells: &Cells) -> Buffer {
    let next_keyframe: Vec<[f32; 4]> = if cells.is_blended() {
        (0..cells.len())
            .flat_map(|i| {
                let modulators = cells.next_modulators.get(i).copied().unwrap_or_default();
                [cells.next_scalars[i], modulators]
            })
            .collect()
    } else {
        vec![[0.0; 4]]
    };
    device.create_buffer_with_data(&BufferInitDescriptor {
        label: Some("nebel_cell_next_keyframe"),
        contents: bytemuck::cast_slice(next_keyframe.as_slice()),
        usage: BufferUsages::STORAGE,
    })
}

/// The camera data the shader needs, as its `CellView`.
#[derive(Clone, Copy, ShaderType)]
pub struct CellViewUniform {
    clip_from_world: Mat4,
    world_from_clip: Mat4,
    camera_position: Vec4,
    /// xyz: the view's forward axis in the world (view depth per unit
    /// along it).
    forward: Vec4,
    viewport: Vec4,
    fog: FogLayersUniform,
}

/// Every view's [`CellViewUniform`] of this frame.
#[derive(Resource, Default)]
pub struct CellViewUniforms(pub(super) DynamicUniformBuffer<CellViewUniform>);

/// Per view: where its uniform sits, its targets and its pipelines (three
/// modes drawing into the accumulation, one compositing it).
#[derive(Component)]
pub struct CellProjectionView {
    pub(super) uniform_offset: u32,
    pub(super) multisampled: bool,
    pub(super) accumulation: CachedTexture,
    /// The stencil of the full-resolution cells: the pixels the low
    /// resolution resolved and, with early termination, the terminated
    /// ones are marked.
    pub(super) stencil: Option<CachedTexture>,
    /// Per optical mode, the pipeline of each variant ([`variant_index`]),
    /// where a batch of this frame needs it.
    pub(super) pipelines: [[Option<CachedRenderPipelineId>; VARIANTS]; 3],
    /// The low resolution's targets and the pipelines of its cells, if the
    /// view draws at a lower resolution.
    pub(super) low: Option<(
        LowResolutionView,
        [[Option<CachedRenderPipelineId>; VARIANTS]; 3],
    )>,
    /// The layers of merged batches at full resolution, where batches of
    /// this frame overlap...
    pub(super) merge: Option<MergeTargets>,
    /// ...and at the low resolution.
    pub(super) low_merge: Option<MergeTargets>,
    pub(super) composite: CachedRenderPipelineId,
    /// Whether the view's fog layers begin beyond the eye, where batches
    /// that hand off to them end.
    pub(super) hands_off: bool,
    /// Whether the cell shader counts its fragments.
    pub(super) count_fragments: bool,
    /// Whether pixels stop taking cells once nearly opaque (the camera's
    /// `CellProjection::early_termination`).
    pub(super) early_termination: bool,
}

/// Lets the pass read the scene depth, only while there is something to draw.
pub fn make_depth_readable(
    extracted: Res<ExtractedCellBatches>,
    mut cameras: Query<&mut Camera3d>,
) {
    if extracted.0.is_empty() {
        return;
    }
    for mut camera in &mut cameras {
        camera.depth_texture_usages.0 |= TextureUsages::TEXTURE_BINDING.bits();
    }
}

/// Writes each view's uniforms, gets its targets and specialises its
/// pipelines.
pub fn prepare_cell_views(
    mut commands: Commands,
    extracted: Res<ExtractedCellBatches>,
    views: Query<(
        Entity,
        &ExtractedView,
        &ExtractedCamera,
        &Msaa,
        Option<&ViewFogLayers>,
        Option<&CellProjection>,
        (Has<ViewShadowBindings>, Has<ViewLightsUniformOffset>),
    )>,
    mut texture_cache: ResMut<TextureCache>,
    mut composites: ResMut<CellCompositePipelines>,
    mut resample: ResMut<ResamplePipelines>,
    mut merge_pipelines: ResMut<MergePipelines>,
    mut uniforms: ResMut<CellViewUniforms>,
    mut upsample_uniforms: ResMut<UpsampleUniforms>,
    count_fragments: Res<CountCellFragments>,
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
    upsample_uniforms.0.clear();
    let format = accumulation_format(&device);
    if count_fragments.0 && !pipeline.can_count_fragments {
        warn_once!(
            "nebel: fragments are not counted: the device lacks the counter's storage buffer"
        );
    }
    let count_fragments = count_fragments.0 && pipeline.can_count_fragments;
    // The largest group of overlapping batches sets the merged layers.
    let mut members = HashMap::new();
    for (_, batch) in &extracted.0 {
        if let Some(group) = batch.group {
            *members.entry(group).or_insert(0_u32) += 1;
        }
    }
    let merged_layers = members
        .into_values()
        .max()
        .map(|n| n.min(MAX_MERGED as u32));
    for (entity, view, camera, msaa, fog, settings, (shadow_maps, lights_offset)) in &views {
        // As the draw binds them.
        let has_shadow_maps = shadow_maps && lights_offset;
        let Some(size) = camera.physical_target_size else {
            continue;
        };
        let settings = settings.copied().unwrap_or_default();
        let divisor = settings.resolution.divisor();
        let mut target = |label, size, format| {
            render_target(&mut texture_cache, &device, label, size, 1, format)
        };
        let accumulation = target("nebel_cell_accumulation", size, format);
        let stencil = (settings.early_termination || divisor > 1)
            .then(|| target("nebel_cell_stencil", size, STENCIL_FORMAT));
        let low_size = UVec2::new(size.x.div_ceil(divisor), size.y.div_ceil(divisor));
        let low_targets = (divisor > 1).then(|| {
            (
                target("nebel_cell_low_depth", low_size, LOW_DEPTH_FORMAT),
                target("nebel_cell_low_accumulation", low_size, format),
                settings
                    .early_termination
                    .then(|| target("nebel_cell_low_stencil", low_size, STENCIL_FORMAT)),
            )
        });
        let composite = *composites.0.entry(view.target_format).or_insert_with(|| {
            pipeline_cache.queue_render_pipeline(pipeline.composite_descriptor(view.target_format))
        });
        let world_from_view = view.world_from_view.to_matrix();
        let clip_from_world = view
            .clip_from_world
            .unwrap_or_else(|| view.clip_from_view * world_from_view.inverse());
        let view_uniform = CellViewUniform {
            clip_from_world,
            world_from_clip: clip_from_world.inverse(),
            camera_position: view.world_from_view.translation().extend(1.0),
            forward: view.world_from_view.forward().extend(0.0),
            viewport: view.viewport.as_vec4(),
            fog: fog.map(|fog| fog.0).unwrap_or_default(),
        };
        let uniform_offset = uniforms.0.push(&view_uniform);
        let multisampled = *msaa != Msaa::Off;
        // Only the variants some batch of this frame needs.
        let mut specialize = |stencil: bool, low_resolution: bool| {
            let mut variants = [[None; VARIANTS]; 3];
            for (_, batch) in &extracted.0 {
                let (modulated, scattering) = (batch.is_modulated(), batch.scattering.is_some());
                let handoff = batch.hands_off && fog.is_some_and(|fog| fog.0.ranges.x > 0.0);
                let blended = batch.is_blended();
                let merged = batch.group.is_some();
                let ray_cast = batch.is_ray_cast();
                let lit = batch.is_lit_locally();
                let sunlit = batch.is_sunlit();
                let shadowed = has_shadow_maps && batch.is_shadowed();
                variants[mode_index(batch.mode)][variant_index(
                    modulated, scattering, handoff, blended, merged, ray_cast, lit, sunlit,
                    shadowed,
                )] = Some(pipelines.specialize(
                    &pipeline_cache,
                    &pipeline,
                    CellProjectionPipelineKey {
                        mode: batch.mode,
                        modulated,
                        scattering,
                        multisampled,
                        fog_layers: fog.is_some(),
                        fog_sun: fog.is_some_and(|fog| fog.0.has_sun()),
                        handoff,
                        blended,
                        target_format: format,
                        stencil,
                        low_resolution,
                        count_fragments,
                        merged,
                        ray_cast,
                        local_lights: lit,
                        ground_sun: sunlit,
                        light_shadows: shadowed,
                    },
                ));
            }
            variants
        };
        let variants = specialize(stencil.is_some(), false);
        let low = low_targets.map(|(depth, low_accumulation, low_stencil)| {
            let low_variants = specialize(low_stencil.is_some(), true);
            let viewport = view.viewport.as_vec4() / divisor as f32;
            let low_view = LowResolutionView {
                viewport,
                depth,
                accumulation: low_accumulation,
                stencil: low_stencil,
                uniform_offset: uniforms.0.push(&CellViewUniform {
                    viewport,
                    ..view_uniform
                }),
                upsample_offset: upsample_uniforms
                    .push(low_size, settings.checked_upsample_tolerance()),
                downsample: resample.get(
                    &pipeline_cache,
                    ResamplePipelineKey {
                        multisampled,
                        divisor,
                        upsample: false,
                        format,
                    },
                ),
                upsample: resample.get(
                    &pipeline_cache,
                    ResamplePipelineKey {
                        multisampled,
                        divisor,
                        upsample: true,
                        format,
                    },
                ),
            };
            (low_view, low_variants)
        });
        let mut merge_targets = |size, stencil: bool| {
            merged_layers.map(|layers| {
                let pipeline = merge_pipelines.get(&pipeline_cache, stencil, format);
                MergeTargets::new(
                    &mut texture_cache,
                    &device,
                    size,
                    layers,
                    (format, span_format(&device)),
                    pipeline,
                )
            })
        };
        let merge = merge_targets(size, stencil.is_some());
        let low_merge = low
            .as_ref()
            .and_then(|(low, _)| merge_targets(low_size, low.stencil.is_some()));
        commands.entity(entity).insert(CellProjectionView {
            merge,
            low_merge,
            early_termination: settings.early_termination,
            uniform_offset,
            multisampled,
            accumulation,
            stencil,
            pipelines: variants,
            low,
            composite,
            hands_off: fog.is_some_and(|fog| fog.0.ranges.x > 0.0),
            count_fragments,
        });
    }
    uniforms.0.write_buffer(&device, &queue);
    upsample_uniforms.0.write_buffer(&device, &queue);
}

/// A 2D render target of `layers` layers from the texture cache, one that
/// later passes also sample.
pub(super) fn render_target(
    texture_cache: &mut TextureCache,
    device: &RenderDevice,
    label: &'static str,
    size: UVec2,
    layers: u32,
    format: TextureFormat,
) -> CachedTexture {
    texture_cache.get(
        device,
        TextureDescriptor {
            label: Some(label),
            size: Extent3d {
                width: size.x,
                height: size.y,
                depth_or_array_layers: layers,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: TextureDimension::D2,
            format,
            usage: TextureUsages::RENDER_ATTACHMENT | TextureUsages::TEXTURE_BINDING,
            view_formats: &[],
        },
    )
}
