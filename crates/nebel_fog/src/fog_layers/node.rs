//! The fog-layer pass in the `Core3d` schedule: the fog from the eye to the
//! opaque depth (or to the largest distance), over the view's HDR image.

use std::sync::atomic::Ordering;

use bevy::prelude::*;
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderContext, ViewQuery};
use bevy::render::view::ViewTarget;
use nebel_render::cell_projection::draw_over_view;

use super::FogLayersPasses;
use super::resources::{FogLayersBindGroup, FogLayersView};

/// Draws the view's fog layers over its scene.
pub fn draw_fog_layers(
    view: ViewQuery<(&ViewTarget, &FogLayersView, &FogLayersBindGroup)>,
    pipeline_cache: Res<PipelineCache>,
    passes: Res<FogLayersPasses>,
    mut ctx: RenderContext,
) {
    let (view_target, fog_view, bind_group) = view.into_inner();
    let Some(render_pipeline) = pipeline_cache.get_render_pipeline(fog_view.pipeline) else {
        return;
    };
    draw_over_view(
        &mut ctx,
        "nebel_fog_layers_pass",
        view_target,
        render_pipeline,
        &bind_group.bind_group,
        &[fog_view.uniform_offset],
        None,
    );
    passes.0.fetch_add(1, Ordering::Relaxed);
}
