// The fog-layer pass (Röttger 2004 §5.3, layered fog): per pixel, the fog
// from the eye to the opaque depth, or to the largest distance where nothing
// is opaque, as the premultiplied layer (c α, α), α = 1 − e^{−τ}, blended
// over the scene (src One, dst OneMinusSrcAlpha). The ray comes from the
// inverse projection and the camera's rotation, so large world coordinates
// cost no precision; only the camera's altitude is absolute.

#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput
#import nebel_render::fog_layers::{FogLayers, fog_colour, fog_opacity, fog_optical_depth}

struct FogPass {
    view_from_clip: mat4x4<f32>,
    world_from_view: mat4x4<f32>,
    camera_position: vec4<f32>,
    viewport: vec4<f32>,
    fog: FogLayers,
}

@group(0) @binding(0) var<uniform> fog_pass: FogPass;
// The depth is bound as an unfilterable float texture, which WebGPU allows
// for depth formats: GLSL (WebGL2-class devices) can load its texels, where
// it cannot load those of a depth texture.
#ifdef MULTISAMPLED
@group(0) @binding(1) var depth_texture: texture_multisampled_2d<f32>;
#else
@group(0) @binding(1) var depth_texture: texture_2d<f32>;
#endif

// The fog's opacity along the ray `direction` through `ndc` to `depth` (0:
// nothing opaque, to the largest distance).
fn fog_alpha(ndc: vec2<f32>, direction: vec3<f32>, depth: f32) -> f32 {
    var distance = fog_pass.fog.ranges.y;
    if depth > 0.0 {
        let surface = fog_pass.view_from_clip * vec4(ndc, depth, 1.0);
        distance = length(surface.xyz / surface.w);
    }
    return fog_opacity(fog_optical_depth(fog_pass.fog, fog_pass.camera_position.y, direction.y, 0.0, distance));
}

@fragment
fn fragment(in: FullscreenVertexOutput) -> @location(0) vec4<f32> {
    let viewport = fog_pass.viewport;
    let ndc = vec2(
        (in.position.x - viewport.x) / viewport.z * 2.0 - 1.0,
        1.0 - (in.position.y - viewport.y) / viewport.w * 2.0,
    );
    // Reversed Z: depth 1 is the near plane, 0 the cleared far plane.
    let near = fog_pass.view_from_clip * vec4(ndc, 1.0, 1.0);
    let direction = normalize((fog_pass.world_from_view * vec4(near.xyz / near.w, 0.0)).xyz);
    let pixel = vec2<i32>(floor(in.position.xy));
#ifdef MULTISAMPLED
    // The resolved pixel averages its samples, each fogged to its own depth:
    // the fog's colour is the same for all, so their opacities average.
    let samples = textureNumSamples(depth_texture);
    var alpha = 0.0;
    for (var i = 0u; i < samples; i++) {
        alpha += fog_alpha(ndc, direction, textureLoad(depth_texture, pixel, i32(i)).r);
    }
    alpha /= f32(samples);
#else
    let alpha = fog_alpha(ndc, direction, textureLoad(depth_texture, pixel, 0).r);
#endif
    if alpha <= 0.0 {
        discard;
    }
    return vec4(fog_colour(fog_pass.fog, direction) * alpha, alpha);
}
