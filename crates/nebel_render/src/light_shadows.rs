//! Bevy's shadow maps of point and spot lights, and of the sun, in nebel's
//! passes: light shafts behind opaque geometry.
//!
//! A light that casts shadows (`shadow_maps_enabled`) and reaches a medium
//! carries its index among Bevy's clustered lights of the frame
//! ([`ReachingLights::with_shadow_indices`](crate::local_lights::ReachingLights::with_shadow_indices)).
//! A pass that draws it binds [`LightShadows::bind_group`] (Bevy's view
//! lights, clustered lights, point-light cube maps and spot-light maps with
//! their comparison samplers) at the group its shader definition
//! `LIGHT_SHADOW_GROUP` names, and the WGSL library
//! `nebel_render::light_shadows` reads a light's visibility at a point as
//! Bevy's PBR shader reads it for a surface (with the light's depth bias,
//! without a normal bias), and bisects where it changes along a ray. The
//! sun's visibility comes from the cascade of Bevy's directional light
//! toward it that reaches the point's view depth (the cascades share the
//! spot lights' texture array); the point is moved toward the sun by the
//! light's depth bias plus its normal bias in texels of that cascade, as far
//! as Bevy moves a surface along its normal, so a lit surface's own depth in
//! the map does not shade the medium just above it (shadow acne).

use bevy::ecs::system::SystemParam;
use bevy::pbr::{
    CLUSTERED_FORWARD_STORAGE_BUFFER_COUNT, GlobalClusterableObjectMeta, GpuClusteredLights,
    GpuLights, LightMeta, ShadowSamplers, ViewShadowBindings,
};
use bevy::prelude::*;
use bevy::render::render_resource::binding_types::{
    sampler, texture_2d_array, texture_cube_array, uniform_buffer,
};
use bevy::render::render_resource::*;
use bevy::render::renderer::RenderDevice;
use bevy::shader::load_shader_library;

/// The layout of the shadow bind group on `device`: its clustered lights
/// bound as Bevy binds them there (storage or uniform).
pub fn light_shadow_layout(device: &RenderDevice) -> BindGroupLayoutDescriptor {
    let clustered_lights =
        device.get_supported_read_only_binding_type(CLUSTERED_FORWARD_STORAGE_BUFFER_COUNT);
    BindGroupLayoutDescriptor::new(
        "nebel_light_shadow_layout",
        &BindGroupLayoutEntries::sequential(
            ShaderStages::FRAGMENT,
            (
                uniform_buffer::<GpuLights>(true),
                BindingType::Buffer {
                    ty: clustered_lights,
                    has_dynamic_offset: false,
                    min_binding_size: Some(GpuClusteredLights::min_size(clustered_lights)),
                },
                texture_cube_array(TextureSampleType::Depth),
                sampler(SamplerBindingType::Comparison),
                texture_2d_array(TextureSampleType::Depth),
                sampler(SamplerBindingType::Comparison),
            ),
        ),
    )
}

/// Bevy's lights and shadow samplers of this frame, where Bevy's PBR renders
/// them.
#[derive(SystemParam)]
pub struct LightShadows<'w> {
    light_meta: Option<Res<'w, LightMeta>>,
    clustered: Option<Res<'w, GlobalClusterableObjectMeta>>,
    samplers: Option<Res<'w, ShadowSamplers>>,
}

impl LightShadows<'_> {
    /// The shadow bind group of a view with the shadow maps `maps`, of
    /// layout `layout` ([`light_shadow_layout`]); bound with the view's
    /// `ViewLightsUniformOffset`. `None` without Bevy's lights.
    pub fn bind_group(
        &self,
        device: &RenderDevice,
        layout: &BindGroupLayout,
        maps: &ViewShadowBindings,
    ) -> Option<BindGroup> {
        let lights = self.light_meta.as_ref()?.view_gpu_lights.binding()?;
        let clustered = self.clustered.as_ref()?.gpu_clustered_lights.binding()?;
        let samplers = self.samplers.as_ref()?;
        Some(device.create_bind_group(
            "nebel_light_shadow_bind_group",
            layout,
            &BindGroupEntries::sequential((
                lights,
                clustered,
                &maps.point_light_depth_texture_view,
                &samplers.point_light_comparison_sampler,
                &maps.directional_light_depth_texture_view,
                &samplers.directional_light_comparison_sampler,
            )),
        ))
    }

    /// The index of each render-world light among Bevy's clustered lights
    /// of this frame.
    pub fn light_index(&self, entity: Entity) -> Option<usize> {
        self.clustered
            .as_ref()
            .and_then(|meta| meta.entity_to_index.get(&entity).copied())
    }
}

/// Loads the WGSL library `nebel_render::light_shadows`.
pub(crate) fn load_light_shadows_library(app: &mut App) {
    load_shader_library!(app, "light_shadows.wgsl");
}
