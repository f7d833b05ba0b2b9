//! The fog-layer pass in the `Core3d` schedule: the fog from the eye to the
//! opaque depth (or to the largest distance), over the view's HDR image.

use std::sync::atomic::Ordering;

use bevy::pbr::{ViewLightsUniformOffset, ViewShadowBindings};
use bevy::prelude::*;
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderContext, ViewQuery};
use bevy::render::view::ViewTarget;
use nebel_render::cell_projection::draw_over_view;
use nebel_render::light_shadows::LightShadows;

use super::FogLayersPasses;
use super::resources::{FogLayersBindGroup, FogLayersPipeline, FogLayersView};

/// Draws the view's fog layers over its scene, with Bevy's shadow maps
/// where a light that reaches the fog casts shadows.
pub fn draw_fog_layers(
    view: ViewQuery<(
        &ViewTarget,
        &FogLayersView,
        &FogLayersBindGroup,
        Option<&ViewShadowBindings>,
        Option<&ViewLightsUniformOffset>,
    )>,
    pipeline_cache: Res<PipelineCache>,
    pipeline: Res<FogLayersPipeline>,
    light_shadows: LightShadows,
    passes: Res<FogLayersPasses>,
    mut ctx: RenderContext,
) {
    let (view_target, fog_view, bind_group, shadow_maps, lights_offset) = view.into_inner();
    let Some(render_pipeline) = pipeline_cache.get_render_pipeline(fog_view.pipeline) else {
        return;
    };
    let uniform_offset = [fog_view.uniform_offset];
    let mut bind_groups = vec![(&bind_group.bind_group, &uniform_offset[..])];
    let shadows = if fog_view.shadowed {
        let (Some(maps), Some(offset)) = (shadow_maps, lights_offset) else {
            return;
        };
        let layout = pipeline_cache.get_bind_group_layout(&pipeline.shadow_layout);
        let Some(group) = light_shadows.bind_group(ctx.render_device(), &layout, maps) else {
            return;
        };
        Some((group, [offset.offset]))
    } else {
        None
    };
    if let Some((group, offset)) = &shadows {
        bind_groups.push((group, &offset[..]));
    }
    draw_over_view(
        &mut ctx,
        "nebel_fog_layers_pass",
        view_target,
        render_pipeline,
        &bind_groups,
        None,
    );
    passes.0.fetch_add(1, Ordering::Relaxed);
}
