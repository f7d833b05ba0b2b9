//! The cell projection's draw system in the `Core3d` schedule: every batch
//! into the view's float accumulation target, back to front, then the target
//! over the view's HDR image in one blend.

use std::sync::atomic::Ordering;

use bevy::prelude::*;
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderContext, ViewQuery};
use bevy::render::view::{ExtractedView, ViewDepthTexture, ViewTarget};
use nebel_core::optics::OpticalMode;

use super::CellProjectionStats;
use super::pipeline::{CellProjectionPipeline, mode_index, variant_index};
use super::resources::{
    CellProjectionView, CellViewUniforms, ExtractedCellBatch, ExtractedCellBatches, GpuCellBuffers,
    GpuCellTables,
};

/// Draws every batch into the view's HDR target, back to front.
pub fn draw_cell_batches(
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
        let (Some(buffer), Some(table)) =
            (buffers.0.get(entity), tables.tables.get(&batch.table_key))
        else {
            continue;
        };
        let Some(render_pipeline) = cell_view.pipelines[mode_index(batch.mode)][variant_index(
            buffer.modulated,
            buffer.scattered,
            batch.hands_off && cell_view.hands_off,
            buffer.blended,
        )]
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
                table.parameters.binding().expect("written when built"),
                buffer.modulators.as_entire_binding(),
                buffer.parameters.binding().expect("written when uploaded"),
                buffer.next_keyframe.as_entire_binding(),
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
    draw_over_view(
        &mut ctx,
        "nebel_cell_composite_pass",
        view_target,
        composite_pipeline,
        &composite_bind_group,
        &[],
    );
}

/// One full-screen triangle of `pipeline` (bind group 0: `bind_group` at
/// `offsets`) blended over the view's HDR image, in a pass of its own.
pub fn draw_over_view(
    ctx: &mut RenderContext,
    label: &str,
    view_target: &ViewTarget,
    pipeline: &RenderPipeline,
    bind_group: &BindGroup,
    offsets: &[u32],
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
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
    pass.set_pipeline(pipeline);
    pass.set_bind_group(0, bind_group, offsets);
    pass.draw(0..3, 0..1);
}
