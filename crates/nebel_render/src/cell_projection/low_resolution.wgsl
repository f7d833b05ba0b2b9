// Cells at a lower resolution, mixed with full resolution where it differs
// (mixed-resolution rendering: low-resolution passes, a full-resolution
// pass only where an edge needs it).
//
// downsample: each low-resolution pixel covers a block of DIVISOR²
// full-resolution pixels and takes the mean of their depths. Reversed-Z
// NDC depth is affine in screen space over a plane, so over a plane the
// mean is the depth at the block's centre, where the low-resolution ray
// goes.
//
// upsample: a full-resolution pixel takes the bilinear mix of the four
// low-resolution pixels around it only when (1) the mix of their depths
// predicts its own depth within a relative tolerance (no edge of opaque
// geometry, no sky against geometry) and (2) the error of the bilinear
// interpolation at the pixel's weights (w_x, w_y), estimated from the second
// differences of colour and transmittance around the four as
// (w_x (1 − w_x) |f_xx| + w_y (1 − w_y) |f_yy|) h² / 2, is within a
// tolerance (no edge or fine detail of the volume). It then writes the mix and marks the
// stencil; every other pixel keeps the cleared accumulation and is drawn by
// the full-resolution cell passes, which test the stencil.

#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput

struct Upsample {
    // x: relative depth tolerance, y: interpolation error tolerance,
    // zw: the low-resolution target's size in pixels.
    tolerances: vec4<f32>,
}

#ifdef MULTISAMPLED
@group(0) @binding(0) var depth_texture: texture_depth_multisampled_2d;
#else
@group(0) @binding(0) var depth_texture: texture_depth_2d;
#endif
@group(0) @binding(1) var low_depth: texture_2d<f32>;
@group(0) @binding(2) var low_accumulation: texture_2d<f32>;
@group(0) @binding(3) var<uniform> upsample_parameters: Upsample;

fn full_depth(pixel: vec2<i32>) -> f32 {
    return textureLoad(depth_texture, pixel, 0);
}

@fragment
fn downsample(in: FullscreenVertexOutput) -> @location(0) vec4<f32> {
    let size = vec2<i32>(textureDimensions(depth_texture));
    let origin = vec2<i32>(floor(in.position.xy)) * #{DIVISOR};
    var sum = 0.0;
    var count = 0.0;
    for (var y = 0; y < #{DIVISOR}; y++) {
        for (var x = 0; x < #{DIVISOR}; x++) {
            let pixel = origin + vec2(x, y);
            if all(pixel < size) {
                sum += full_depth(pixel);
                count += 1.0;
            }
        }
    }
    return vec4(sum / max(count, 1.0), 0.0, 0.0, 0.0);
}

fn low_value(pixel: vec2<i32>) -> vec4<f32> {
    let last = vec2<i32>(upsample_parameters.tolerances.zw) - 1;
    return textureLoad(low_accumulation, clamp(pixel, vec2(0), last), 0);
}

@fragment
fn upsample(in: FullscreenVertexOutput) -> @location(0) vec4<f32> {
    let pixel = vec2<i32>(floor(in.position.xy));
    // The pixel's centre in low-resolution pixels, from their centres.
    let position = (vec2<f32>(pixel) + 0.5) / f32(#{DIVISOR}) - 0.5;
    let lower = vec2<i32>(floor(position));
    let weight = position - floor(position);
    let last = vec2<i32>(upsample_parameters.tolerances.zw) - 1;
    // The 4 × 4 low-resolution pixels around it: the inner 2 × 2 mix, the
    // ring gives each inner one its second differences.
    var values: array<array<vec4<f32>, 4>, 4>;
    for (var y = 0; y < 4; y++) {
        for (var x = 0; x < 4; x++) {
            values[y][x] = low_value(lower + vec2(x - 1, y - 1));
        }
    }
    var curvature_x = vec4(0.0);
    var curvature_y = vec4(0.0);
    var predicted = 0.0;
    for (var y = 1; y < 3; y++) {
        for (var x = 1; x < 3; x++) {
            let second_x = values[y][x - 1] - 2.0 * values[y][x] + values[y][x + 1];
            let second_y = values[y - 1][x] - 2.0 * values[y][x] + values[y + 1][x];
            curvature_x = max(curvature_x, abs(second_x));
            curvature_y = max(curvature_y, abs(second_y));
            let w = mix(1.0 - weight.x, weight.x, f32(x - 1)) * mix(1.0 - weight.y, weight.y, f32(y - 1));
            predicted += w * textureLoad(low_depth, clamp(lower + vec2(x - 1, y - 1), vec2(0), last), 0).r;
        }
    }
    let mixed = mix(
        mix(values[1][1], values[1][2], weight.x),
        mix(values[2][1], values[2][2], weight.x),
        weight.y,
    );
    // Bilinear interpolation between samples h apart, at weights w, is off
    // by w (1 − w) h² |f''| / 2 along each axis, to leading order (it
    // reproduces the mixed term exactly).
    let spread = 0.5 * weight * (1.0 - weight);
    let error = spread.x * curvature_x + spread.y * curvature_y;
    let interpolation_error = max(max(error.r, error.g), max(error.b, error.a));
    let depth = full_depth(pixel);
    // Along the border the ring is cut: no estimate there.
    let inside = all(lower >= vec2(1)) && all(lower + 2 <= last);
    if !inside || abs(predicted - depth) > upsample_parameters.tolerances.x * max(depth, predicted)
        || interpolation_error > upsample_parameters.tolerances.y {
        discard;
    }
    return mixed;
}
