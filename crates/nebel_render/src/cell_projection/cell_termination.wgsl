// Early ray termination (Krüger and Westermann 2003, "Acceleration
// Techniques for GPU-based Volume Rendering", §4): between groups of cells
// drawn front to back, marks in the stencil every pixel whose transmittance
// (the accumulation's alpha) has fallen below the threshold, so the later
// cells' fragments there are rejected by the early stencil test.

#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput

@group(0) @binding(0) var accumulated: texture_2d<f32>;

@fragment
fn fragment(in: FullscreenVertexOutput) {
    let transmittance = textureLoad(accumulated, vec2<i32>(floor(in.position.xy)), 0).a;
    if transmittance >= bitcast<f32>(#{TERMINATION_TRANSMITTANCE_BITS}u) {
        discard;
    }
}
