// Composites the accumulated cells of a view over the scene: the cells were
// blended front to back into a float target that started as colour 0 and
// transmittance 1, so the result C, T goes over the scene in one step,
// I = C + T scene, with the hardware blender (src One, dst OneMinusSrcAlpha
// on the premultiplied pair (C, 1 − T)).

#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput

@group(0) @binding(0) var accumulated: texture_2d<f32>;

@fragment
fn fragment(in: FullscreenVertexOutput) -> @location(0) vec4<f32> {
    let accumulated = textureLoad(accumulated, vec2<i32>(floor(in.position.xy)), 0);
    return vec4(accumulated.rgb, 1.0 - accumulated.a);
}
