// Composites the accumulated cells of a view over the scene:
// the cells were blended into a float accumulation target that started
// transparent, so the premultiplied result C, α goes over the scene in one
// step, I = C + (1 − α) scene, with the hardware blender
// (src One, dst OneMinusSrcAlpha).

#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput

@group(0) @binding(0) var accumulated: texture_2d<f32>;

@fragment
fn fragment(in: FullscreenVertexOutput) -> @location(0) vec4<f32> {
    return textureLoad(accumulated, vec2<i32>(floor(in.position.xy)), 0);
}
