// Batches whose bounds intersect, composited jointly per pixel: the GPU's
// copy of nebel_core::overlap. Layer k holds member k alone: its colour C_k
// and transmittance T_k, and its span along the ray, entry a_k and negated
// exit −b_k (cleared beyond every exit where it drew nothing). Over its span
// a member is uniform, σ_k = τ_k / (b_k − a_k) with τ_k = −ln T_k, emitting
// j_k = C_k τ_k / ((1 − T_k)(b_k − a_k)); the ray is split at every end and
// each piece, where the members present absorb and emit together, goes
// front to back. The result is one segment (C, 1 − T) under the
// accumulation.

#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput

@group(0) @binding(0) var colours: texture_2d_array<f32>;
@group(0) @binding(1) var spans: texture_2d_array<f32>;

// The shortest span, relative to 1 + |a|, and the smallest transmittance
// taken literally (as in nebel_core::overlap).
const MIN_SPAN: f32 = 1.0e-6;
const MIN_TRANSMITTANCE: f32 = 1.0e-30;

// τ / (1 − e^{−τ}), 1 at τ = 0.
fn depth_per_opacity(tau: f32) -> f32 {
    if tau < 1.0e-2 {
        return 1.0 + tau * (0.5 + tau / 12.0);
    }
    return tau / (1.0 - exp(-tau));
}

@fragment
fn fragment(in: FullscreenVertexOutput) -> @location(0) vec4<f32> {
    let pixel = vec2<i32>(floor(in.position.xy));
    let layers = min(textureNumLayers(colours), #{MAX_MERGED}u);
    var extinction: array<f32, #{MAX_MERGED}>;
    var emission: array<vec3<f32>, #{MAX_MERGED}>;
    var entry: array<f32, #{MAX_MERGED}>;
    var exit: array<f32, #{MAX_MERGED}>;
    var ends: array<f32, #{MAX_ENDS}>;
    var members = 0u;
    for (var k = 0u; k < layers; k++) {
        let span = textureLoad(spans, pixel, k, 0).xy;
        let a = span.x;
        if !(-span.y >= a) {
            continue;
        }
        let b = max(-span.y, a + MIN_SPAN * (1.0 + abs(a)));
        let alone = textureLoad(colours, pixel, k, 0);
        let tau = -log(clamp(alone.a, MIN_TRANSMITTANCE, 1.0));
        extinction[members] = tau / (b - a);
        emission[members] = alone.rgb * depth_per_opacity(tau) / (b - a);
        entry[members] = a;
        exit[members] = b;
        // Insertion into the sorted ends.
        for (var end = 0u; end < 2u; end++) {
            let value = select(a, b, end == 1u);
            var i = 2u * members + end;
            while i > 0u && ends[i - 1u] > value {
                ends[i] = ends[i - 1u];
                i--;
            }
            ends[i] = value;
        }
        members++;
    }
    var colour = vec3(0.0);
    var transmittance = 1.0;
    for (var i = 0u; i + 1u < 2u * members; i++) {
        let near = ends[i];
        let far = ends[i + 1u];
        if far <= near {
            continue;
        }
        var sigma = 0.0;
        var j = vec3(0.0);
        for (var k = 0u; k < members; k++) {
            if entry[k] <= near && far <= exit[k] {
                sigma += extinction[k];
                j += emission[k];
            }
        }
        let tau = sigma * (far - near);
        colour += transmittance * j * (far - near) / depth_per_opacity(tau);
        transmittance *= exp(-tau);
    }
    return vec4(colour, 1.0 - transmittance);
}
