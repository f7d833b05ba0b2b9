//! The fog-layer pass in the `Core3d` schedule: the fog from the eye to the
//! opaque depth (or to the largest distance), over the view's HDR image.

use std::sync::atomic::Ordering;

use bevy::prelude::*;
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderContext, ViewQuery};
use bevy::render::view::{ViewDepthTexture, ViewTarget};
use nebel_render::cell_projection::draw_over_view;

use super::FogLayersPasses;
use super::resources::{FogLayersPipeline, FogLayersView, FogPassUniforms};

/// Draws the view's fog layers over its scene.
pub fn draw_fog_layers(
    view: ViewQuery<(&ViewTarget, &ViewDepthTexture, &FogLayersView)>,
    uniforms: Res<FogPassUniforms>,
    pipeline: Res<FogLayersPipeline>,
    pipeline_cache: Res<PipelineCache>,
    passes: Res<FogLayersPasses>,
    mut ctx: RenderContext,
) {
    let (view_target, depth, fog_view) = view.into_inner();
    let (Some(binding), Some(render_pipeline)) = (
        uniforms.0.binding(),
        pipeline_cache.get_render_pipeline(fog_view.pipeline),
    ) else {
        return;
    };
    let bind_group = ctx.render_device().create_bind_group(
        "nebel_fog_layers_bind_group",
        &pipeline_cache
            .get_bind_group_layout(&pipeline.layouts[usize::from(fog_view.multisampled)]),
        &BindGroupEntries::sequential((binding, depth.view())),
    );
    draw_over_view(
        &mut ctx,
        "nebel_fog_layers_pass",
        view_target,
        render_pipeline,
        &bind_group,
        &[fog_view.uniform_offset],
    );
    passes.0.fetch_add(1, Ordering::Relaxed);
}
