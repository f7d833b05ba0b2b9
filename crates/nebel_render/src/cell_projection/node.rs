//! The cell projection's draw system in the `Core3d` schedule: every batch
//! into the view's float accumulation target, front to back, in groups
//! between which the terminated pixels are marked; at a lower resolution
//! first, then at full resolution where the upsample left pixels open; then
//! the target over the view's HDR image in one blend.

use std::ops::Range;
use std::sync::atomic::Ordering;

use bevy::pbr::{ViewLightsUniformOffset, ViewShadowBindings};
use bevy::prelude::*;
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderContext, ViewQuery};
use bevy::render::texture::CachedTexture;
use bevy::render::view::{ExtractedView, ViewDepthTexture, ViewTarget};
use nebel_core::optics::OpticalMode;

use super::CellProjectionStats;
use super::low_resolution::{ResamplePipelines, UpsampleUniforms};
use super::merge::{Item, MergePipelines, MergeTargets, items};
use super::pipeline::{CellProjectionPipeline, TERMINATED, mode_index, variant_index};
use super::queries::{CellQueries, ViewQueries};
use super::resources::{
    CellProjectionView, CellViewUniforms, ExtractedCellBatch, ExtractedCellBatches, GpuCellBuffers,
};
use super::tables::GpuCellTables;
use crate::cloud_shadow_maps::CloudShadowTextures;
use crate::light_shadows::LightShadows;

/// Early termination marks the terminated pixels after groups of at least
/// this many cells...
const MIN_GROUP_CELLS: u32 = 1024;
/// ...and at most this many times per round of cell passes.
const MAX_MARKS: u32 = 16;

/// One batch to draw: its pipeline variant, its bind group, what it draws
/// and its instances.
struct Draw {
    mode: OpticalMode,
    variant: usize,
    bind_group: BindGroup,
    /// Its lights read their shadow maps through the view's shadow bind
    /// group (group 2).
    shadowed: bool,
    shape: DrawShape,
    /// Instances: one per cell, one for a grid.
    count: u32,
}

/// What a draw's instances are.
#[derive(Clone, Copy)]
enum DrawShape {
    /// One cell each, a triangle strip of six vertices.
    Cells,
    /// A whole grid of `cells` tetrahedra, ray cast from the 36 vertices of
    /// its box.
    Grid { cells: u32 },
}

impl Draw {
    /// Draws `instances` into `pass` (with the view's shadow bind group
    /// `shadows` at its offset, if the draw reads shadow maps) and counts
    /// their cells.
    fn record(
        &self,
        pass: &mut wgpu::RenderPass<'_>,
        instances: Range<u32>,
        shadows: Option<&(BindGroup, u32)>,
        stats: &CellProjectionStats,
    ) {
        if let (true, Some((group, offset))) = (self.shadowed, shadows) {
            pass.set_bind_group(2, group, &[*offset]);
        }
        let (vertices, cells) = match self.shape {
            DrawShape::Cells => (6, instances.len() as u64),
            DrawShape::Grid { cells } => (36, u64::from(cells)),
        };
        pass.draw(0..vertices, instances);
        stats.0.cells_drawn.fetch_add(cells, Ordering::Relaxed);
    }
}

/// Splits the items, in order, into groups of about `group` cells: each
/// group lists (item, instance range) pieces. An item drawn `whole` (a run
/// of merged batches) is never split.
fn groups(counts: &[u32], whole: &[bool], group: u32) -> Vec<Vec<(usize, Range<u32>)>> {
    let mut groups = vec![Vec::new()];
    let mut room = group;
    for (item, &count) in counts.iter().enumerate() {
        let mut start = 0;
        while start < count {
            if room == 0 {
                groups.push(Vec::new());
                room = group;
            }
            let end = if whole[item] {
                count
            } else {
                count.min(start + room)
            };
            groups
                .last_mut()
                .expect("one group at least")
                .push((item, start..end));
            room = room.saturating_sub(end - start);
            start = end;
        }
    }
    groups
}

/// The targets of one round of cell passes (low or full resolution).
struct Round<'a> {
    accumulation: &'a CachedTexture,
    stencil: Option<&'a CachedTexture>,
    view_bind_group: BindGroup,
    uniform_offset: u32,
    pipelines: &'a [[Option<CachedRenderPipelineId>; super::pipeline::VARIANTS]; 3],
    /// The layers of merged batches, where batches overlap.
    merge: Option<&'a MergeTargets>,
    /// The viewport the passes set, if not the whole target.
    viewport: Option<Vec4>,
    /// Whether the first pass clears the accumulation and the stencil.
    clear: bool,
}

/// What the passes of a round have still to do once: clear the
/// accumulation, clear the stencil, write the view's first timestamp.
struct Pending {
    accumulation: bool,
    stencil: bool,
    timestamp: bool,
}

/// Everything a round needs besides its targets.
struct Passes<'a> {
    draws: &'a [Draw],
    /// The drawing order: batches alone and runs of merged batches.
    items: &'a [Item],
    pipeline: &'a CellProjectionPipeline,
    merge: &'a MergePipelines,
    pipeline_cache: &'a PipelineCache,
    stats: &'a CellProjectionStats,
    /// Whether to mark terminated pixels: the view asks for early
    /// termination and a segment has opacity to mark.
    terminates: bool,
    /// The view's lights and shadow maps, and its lights' offset, where a
    /// draw reads them.
    shadows: Option<&'a (BindGroup, u32)>,
}

/// Begins a pass of the round into `colour`, with the round's stencil and
/// viewport, clearing the stencil and writing the first timestamp if still
/// pending.
fn begin_pass<'c>(
    ctx: &'c mut RenderContext,
    label: &str,
    colour: &[Option<RenderPassColorAttachment>],
    round: &Round,
    counters: &ViewQueries,
    pending: &mut Pending,
) -> wgpu::RenderPass<'c> {
    let clear_stencil = std::mem::take(&mut pending.stencil);
    let timestamp = std::mem::take(&mut pending.timestamp);
    let mut pass = ctx
        .command_encoder()
        .begin_render_pass(&RenderPassDescriptor {
            label: Some(label),
            color_attachments: colour,
            depth_stencil_attachment: round.stencil.map(|stencil| {
                RenderPassDepthStencilAttachment {
                    view: &stencil.default_view,
                    depth_ops: None,
                    stencil_ops: Some(Operations {
                        load: if clear_stencil {
                            LoadOp::Clear(0)
                        } else {
                            LoadOp::Load
                        },
                        store: StoreOp::Store,
                    }),
                }
            }),
            timestamp_writes: if timestamp {
                counters.timestamp(false)
            } else {
                None
            },
            occlusion_query_set: None,
            multiview_mask: None,
        });
    if let Some(viewport) = round.viewport {
        pass.set_viewport(viewport.x, viewport.y, viewport.z, viewport.w, 0.0, 1.0);
    }
    pass
}

/// The round's accumulation as a colour attachment, cleared to colour 0 and
/// transmittance 1 if still pending.
fn accumulation_attachment<'a>(
    round: &'a Round,
    pending: &mut Pending,
) -> [Option<RenderPassColorAttachment<'a>>; 1] {
    [Some(RenderPassColorAttachment {
        view: &round.accumulation.default_view,
        depth_slice: None,
        resolve_target: None,
        ops: Operations {
            load: if std::mem::take(&mut pending.accumulation) {
                LoadOp::Clear(LinearRgba::BLACK.into())
            } else {
                LoadOp::Load
            },
            store: StoreOp::Store,
        },
    })]
}

impl Passes<'_> {
    /// Draws every batch into the round's targets, front to back, marking
    /// the terminated pixels between groups when the round has a stencil.
    /// Returns false when a pipeline is not ready yet.
    fn draw(
        &self,
        ctx: &mut RenderContext,
        round: &Round,
        counters: &mut ViewQueries,
        first_of_view: bool,
    ) -> bool {
        let cache = self.pipeline_cache;
        let Some(pipelines) = self
            .draws
            .iter()
            .map(|draw| {
                round.pipelines[mode_index(draw.mode)][draw.variant]
                    .and_then(|id| cache.get_render_pipeline(id))
            })
            .collect::<Option<Vec<_>>>()
        else {
            return false;
        };
        let merge = round.merge.and_then(|targets| {
            cache
                .get_render_pipeline(targets.pipeline)
                .map(|pipeline| (targets, pipeline))
        });
        if merge.is_none() && self.items.iter().any(|item| item.merged) {
            return false;
        }
        let termination = round
            .stencil
            .filter(|_| self.terminates)
            .zip(cache.get_render_pipeline(self.pipeline.termination));
        let counts: Vec<u32> = self
            .items
            .iter()
            .map(|item| item.draws.iter().map(|&draw| self.draws[draw].count).sum())
            .collect();
        let whole: Vec<bool> = self.items.iter().map(|item| item.merged).collect();
        let group = match termination {
            Some(_) => counts
                .iter()
                .sum::<u32>()
                .div_ceil(MAX_MARKS)
                .max(MIN_GROUP_CELLS),
            None => u32::MAX,
        };
        // The marking pass reads the accumulation.
        let termination = termination.map(|(stencil, pipeline)| {
            let bind_group = ctx.render_device().create_bind_group(
                "nebel_cell_accumulation_bind_group",
                &cache.get_bind_group_layout(&self.pipeline.composite_layout),
                &BindGroupEntries::single(&round.accumulation.default_view),
            );
            (stencil, pipeline, bind_group)
        });
        let mut pending = Pending {
            accumulation: round.clear,
            stencil: round.clear,
            timestamp: first_of_view,
        };
        for (index, pieces) in groups(&counts, &whole, group).iter().enumerate() {
            if let (false, Some((stencil, termination_pipeline, accumulation_bind_group))) =
                (index == 0, &termination)
            {
                // Pixels that are (nearly) opaque by now take no more cells.
                let mut pass = ctx
                    .command_encoder()
                    .begin_render_pass(&RenderPassDescriptor {
                        label: Some("nebel_cell_termination_pass"),
                        color_attachments: &[],
                        depth_stencil_attachment: Some(RenderPassDepthStencilAttachment {
                            view: &stencil.default_view,
                            depth_ops: None,
                            stencil_ops: Some(Operations {
                                load: LoadOp::Load,
                                store: StoreOp::Store,
                            }),
                        }),
                        timestamp_writes: None,
                        occlusion_query_set: None,
                        multiview_mask: None,
                    });
                pass.set_pipeline(termination_pipeline);
                pass.set_bind_group(0, accumulation_bind_group, &[]);
                pass.set_stencil_reference(TERMINATED);
                pass.draw(0..3, 0..1);
            }
            // Batches alone go into the accumulation a run at a time; a run
            // of merged batches into their layers, then merged under it.
            let mut run = Vec::new();
            for (item, instances) in pieces {
                let item = &self.items[*item];
                if !item.merged {
                    run.push((item.draws[0], instances.clone()));
                    continue;
                }
                self.cells_pass(ctx, round, counters, &mut pending, &pipelines, &run);
                run.clear();
                let (targets, merge_pipeline) = merge.expect("checked above");
                for (layer, &draw) in item.draws.iter().enumerate() {
                    let count = self.draws[draw].count;
                    let mut pass = begin_pass(
                        ctx,
                        "nebel_cell_merged_layer_pass",
                        &targets.attachments(layer),
                        round,
                        counters,
                        &mut pending,
                    );
                    self.stats.0.passes.fetch_add(1, Ordering::Relaxed);
                    pass.set_bind_group(0, &round.view_bind_group, &[round.uniform_offset]);
                    pass.set_pipeline(pipelines[draw]);
                    pass.set_bind_group(1, &self.draws[draw].bind_group, &[]);
                    self.draws[draw].record(&mut pass, 0..count, self.shadows, self.stats);
                    self.stats.0.merged_batches.fetch_add(1, Ordering::Relaxed);
                }
                let bind_group =
                    targets.bind_group(ctx, cache, self.merge, item.draws.len() as u32);
                let colour = accumulation_attachment(round, &mut pending);
                let mut pass = begin_pass(
                    ctx,
                    "nebel_cell_merge_pass",
                    &colour,
                    round,
                    counters,
                    &mut pending,
                );
                pass.set_pipeline(merge_pipeline);
                pass.set_bind_group(0, &bind_group, &[]);
                pass.draw(0..3, 0..1);
            }
            if !run.is_empty() || pending.accumulation {
                self.cells_pass(ctx, round, counters, &mut pending, &pipelines, &run);
            }
        }
        true
    }

    /// One pass of batches alone (`run`: draw, instances) into the round's
    /// accumulation; none for an empty run.
    fn cells_pass(
        &self,
        ctx: &mut RenderContext,
        round: &Round,
        counters: &ViewQueries,
        pending: &mut Pending,
        pipelines: &[&RenderPipeline],
        run: &[(usize, Range<u32>)],
    ) {
        if run.is_empty() && !pending.accumulation {
            return;
        }
        let colour = accumulation_attachment(round, pending);
        let mut pass = begin_pass(
            ctx,
            "nebel_cell_projection_pass",
            &colour,
            round,
            counters,
            pending,
        );
        self.stats.0.passes.fetch_add(1, Ordering::Relaxed);
        pass.set_bind_group(0, &round.view_bind_group, &[round.uniform_offset]);
        for (draw, instances) in run {
            pass.set_pipeline(pipelines[*draw]);
            pass.set_bind_group(1, &self.draws[*draw].bind_group, &[]);
            self.draws[*draw].record(&mut pass, instances.clone(), self.shadows, self.stats);
        }
    }
}

/// Draws every batch into the view's accumulation target, front to back,
/// and the result over the view's HDR target.
pub fn draw_cell_batches(
    view: ViewQuery<(
        &ViewTarget,
        &ViewDepthTexture,
        &ExtractedView,
        &CellProjectionView,
        Option<&ViewShadowBindings>,
        Option<&ViewLightsUniformOffset>,
    )>,
    extracted: Res<ExtractedCellBatches>,
    buffers: Res<GpuCellBuffers>,
    tables: Res<GpuCellTables>,
    uniforms: Res<CellViewUniforms>,
    upsample_uniforms: Res<UpsampleUniforms>,
    pipeline: Res<CellProjectionPipeline>,
    resample: Res<ResamplePipelines>,
    merge: Res<MergePipelines>,
    pipeline_cache: Res<PipelineCache>,
    stats: Res<CellProjectionStats>,
    mut queries: ResMut<CellQueries>,
    light_shadows: LightShadows,
    cloud_shadows: CloudShadowTextures,
    mut ctx: RenderContext,
) {
    if extracted.0.is_empty() {
        return;
    }
    let (cloud_maps, cloud_sampler) = cloud_shadows.bindings();
    let (view_target, depth, extracted_view, cell_view, shadow_maps, lights_offset) =
        view.into_inner();
    let Some(view_binding) = uniforms.0.binding() else {
        return;
    };
    let eye = extracted_view.world_from_view.translation();
    let mut order: Vec<&(Entity, ExtractedCellBatch)> = extracted.0.iter().collect();
    order.sort_by(|(_, a), (_, b)| {
        a.centre
            .distance_squared(eye)
            .total_cmp(&b.centre.distance_squared(eye))
    });

    // Bevy's lights and shadow maps of the view, for lights that cast
    // shadows (prepare_cell_views specialised their variants for a view
    // with shadow maps).
    let shadows = shadow_maps
        .zip(lights_offset)
        .filter(|_| order.iter().any(|(_, batch)| batch.is_shadowed()))
        .and_then(|(maps, offset)| {
            let layout = pipeline_cache.get_bind_group_layout(&pipeline.shadow_layout);
            let group = light_shadows.bind_group(ctx.render_device(), &layout, maps)?;
            Some((group, offset.offset))
        });
    let mut draws = Vec::with_capacity(order.len());
    let mut draw_groups = Vec::with_capacity(order.len());
    for (entity, batch) in order {
        let (Some(buffer), Some(table)) = (buffers.0.get(entity), tables.drawn(*entity)) else {
            continue;
        };
        let pair_table = match batch.mode {
            OpticalMode::Mip => &table.maximum,
            OpticalMode::Sorted | OpticalMode::Emissive => &table.emission,
        };
        let bind_group = ctx.render_device().create_bind_group(
            "nebel_cell_batch_bind_group",
            &pipeline_cache.get_bind_group_layout(&pipeline.batch_layout),
            &BindGroupEntries::sequential((
                buffer.buffer.as_entire_binding(),
                &table.colour,
                pair_table,
                table.parameters.binding().expect("written when built"),
                buffer.modulators.as_entire_binding(),
                buffer.parameters.binding().expect("written when uploaded"),
                buffer.next_keyframe.as_entire_binding(),
                &buffer.sun_map,
                cloud_maps[0],
                cloud_maps[1],
                cloud_sampler,
            )),
        );
        draws.push(Draw {
            mode: batch.mode,
            variant: variant_index(
                buffer.modulated,
                buffer.scattered,
                batch.hands_off && cell_view.hands_off,
                buffer.blended,
                batch.group.is_some(),
                buffer.ray_cast,
                batch.is_lit_locally(),
                batch.is_sunlit(),
                shadows.is_some() && batch.is_shadowed(),
            ),
            bind_group,
            shadowed: shadows.is_some() && batch.is_shadowed(),
            shape: if buffer.ray_cast {
                DrawShape::Grid {
                    cells: buffer.count,
                }
            } else {
                DrawShape::Cells
            },
            count: if buffer.ray_cast { 1 } else { buffer.count },
        });
        draw_groups.push(batch.group);
    }
    let items = items(&draw_groups);
    let Some(composite_pipeline) = pipeline_cache.get_render_pipeline(cell_view.composite) else {
        return;
    };
    if draws.is_empty() {
        return;
    }
    let passes = Passes {
        draws: &draws,
        items: &items,
        pipeline: &pipeline,
        merge: &merge,
        pipeline_cache: &pipeline_cache,
        stats: &stats,
        terminates: cell_view.early_termination
            && draws.iter().any(|draw| draw.mode == OpticalMode::Sorted),
        shadows: shadows.as_ref(),
    };
    let viewport = extracted_view.viewport;
    let mut counters = queries.view(
        u64::from(viewport.z) * u64::from(viewport.w),
        cell_view.count_fragments,
    );
    let view_bind_group = |ctx: &mut RenderContext,
                           counters: &ViewQueries,
                           low_resolution: bool,
                           depth: &TextureView| {
        let layout = pipeline_cache.get_bind_group_layout(pipeline.view_layout(
            cell_view.multisampled,
            low_resolution,
            cell_view.count_fragments,
        ));
        let device = ctx.render_device();
        if cell_view.count_fragments {
            device.create_bind_group(
                "nebel_cell_view_bind_group",
                &layout,
                &BindGroupEntries::sequential((
                    view_binding.clone(),
                    depth,
                    BindingResource::Buffer(counters.fragment_counter()),
                )),
            )
        } else {
            device.create_bind_group(
                "nebel_cell_view_bind_group",
                &layout,
                &BindGroupEntries::sequential((view_binding.clone(), depth)),
            )
        }
    };

    // At a lower resolution: the depth down, the cells, the smooth pixels up.
    let low = cell_view.low.as_ref().and_then(|(low, low_pipelines)| {
        let downsample = pipeline_cache.get_render_pipeline(low.downsample)?;
        let upsample = pipeline_cache.get_render_pipeline(low.upsample)?;
        Some((low, low_pipelines, downsample, upsample))
    });
    if let (Some((low, low_pipelines, downsample, upsample)), Some(stencil)) =
        (low, cell_view.stencil.as_ref())
    {
        resample.downsample(
            &mut ctx,
            &pipeline_cache,
            low,
            downsample,
            depth.view(),
            cell_view.multisampled,
        );
        let round = Round {
            accumulation: &low.accumulation,
            stencil: low.stencil.as_ref(),
            view_bind_group: view_bind_group(&mut ctx, &counters, true, &low.depth.default_view),
            uniform_offset: low.uniform_offset,
            pipelines: low_pipelines,
            merge: cell_view.low_merge.as_ref(),
            viewport: Some(low.viewport),
            clear: true,
        };
        if !passes.draw(&mut ctx, &round, &mut counters, true) {
            return;
        }
        resample.upsample(
            &mut ctx,
            &pipeline_cache,
            low,
            upsample,
            &upsample_uniforms,
            (depth.view(), cell_view.multisampled),
            (&cell_view.accumulation.default_view, &stencil.default_view),
        );
    }
    // At full resolution: every pixel, or those the upsample left open.
    let round = Round {
        accumulation: &cell_view.accumulation,
        stencil: cell_view.stencil.as_ref(),
        view_bind_group: view_bind_group(&mut ctx, &counters, false, depth.view()),
        uniform_offset: cell_view.uniform_offset,
        pipelines: &cell_view.pipelines,
        merge: cell_view.merge.as_ref(),
        viewport: None,
        clear: low.is_none(),
    };
    if !passes.draw(&mut ctx, &round, &mut counters, low.is_none()) {
        return;
    }

    // ...and go over the scene in one blend.
    let composite_bind_group = ctx.render_device().create_bind_group(
        "nebel_cell_composite_bind_group",
        &pipeline_cache.get_bind_group_layout(&pipeline.composite_layout),
        &BindGroupEntries::single(&cell_view.accumulation.default_view),
    );
    draw_over_view(
        &mut ctx,
        "nebel_cell_composite_pass",
        view_target,
        composite_pipeline,
        &[(&composite_bind_group, &[])],
        counters.timestamp(true),
    );
    counters.timed();
}

/// One full-screen triangle of `pipeline` (bind groups 0, 1, …:
/// `bind_groups`, each at its offsets) blended over the view's HDR image,
/// in a pass of its own (with `timestamp_writes`, if any).
pub fn draw_over_view(
    ctx: &mut RenderContext,
    label: &str,
    view_target: &ViewTarget,
    pipeline: &RenderPipeline,
    bind_groups: &[(&BindGroup, &[u32])],
    timestamp_writes: Option<wgpu::RenderPassTimestampWrites>,
) {
    let mut pass = ctx
        .command_encoder()
        .begin_render_pass(&RenderPassDescriptor {
            label: Some(label),
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
            timestamp_writes,
            occlusion_query_set: None,
            multiview_mask: None,
        });
    pass.set_pipeline(pipeline);
    for (index, (bind_group, offsets)) in bind_groups.iter().enumerate() {
        pass.set_bind_group(index as u32, *bind_group, offsets);
    }
    pass.draw(0..3, 0..1);
}

#[cfg(test)]
mod tests {
    use super::groups;

    /// Every instance of every item lands in exactly one group, in order,
    /// no group holds more than the group size unless it holds a whole item
    /// alone at its end, and whole items are never split.
    #[test]
    fn groups_cover_every_cell_once_in_order() {
        for (counts, whole, group) in [
            (vec![10, 0, 7, 3], vec![false; 4], 4),
            (vec![1], vec![false], 1),
            (vec![5, 5], vec![false; 2], 5),
            (vec![3, 9, 1], vec![false; 3], 100),
            (vec![0], vec![false], 3),
            (vec![3, 9, 1, 6], vec![false, true, false, true], 4),
            (vec![2, 0, 5], vec![true, true, false], 3),
        ] {
            let groups = groups(&counts, &whole, group);
            let mut expected =
                (0..counts.len()).flat_map(|item| (0..counts[item]).map(move |i| (item, i)));
            for pieces in &groups {
                let size: u32 = pieces.iter().map(|(_, range)| range.len() as u32).sum();
                let last = pieces.last().map(|(_, range)| range.len() as u32);
                assert!(
                    size <= group || (size - last.unwrap_or(0) < group),
                    "{counts:?} by {group}: a group of {size}"
                );
                for (item, range) in pieces {
                    assert!(!range.is_empty());
                    if whole[*item] {
                        assert_eq!(range.len() as u32, counts[*item]);
                    }
                    for i in range.clone() {
                        assert_eq!(expected.next(), Some((*item, i)));
                    }
                }
            }
            assert_eq!(expected.next(), None, "{counts:?} by {group}");
            if !whole.contains(&true) {
                let total: u32 = counts.iter().sum();
                assert_eq!(groups.len() as u32, total.div_ceil(group).max(1));
            }
        }
    }
}
