// Fog layers: a height fog integrated exactly along a ray (Röttger 2004
// §5.3, layered fog). See nebel_render's `fog_layers` module for the uniform.
//
// The optical depth of the piece [t0, t1] of a ray starting at altitude h
// with vertical direction d_y is (t1 − t0) times the mean density over the
// altitudes it crosses, [low, low + range] with range = |d_y| (t1 − t0),
// computed from the range itself so that level rays keep their precision.

#define_import_path nebel_render::fog_layers

#import nebel_render::local_lights::henyey_greenstein

struct FogLayers {
    colour: vec4<f32>,
    // w: Henyey-Greenstein asymmetry.
    sun_colour: vec4<f32>,
    sun_direction: vec4<f32>,
    // x: start distance, y: largest distance, z: layer count.
    ranges: vec4<f32>,
    layers: array<vec4<f32>, 8>,
    points: array<vec4<f32>, 16>,
}

const MAX_FOG_EXPONENT: f32 = 80.0;

// (1 − e^{−x}) / x for x ≥ 0, without cancellation near 0.
fn one_minus_exp_over(x: f32) -> f32 {
    if x < 1.0e-3 {
        return 1.0 - x * (0.5 - x / 6.0);
    }
    return (1.0 - exp(-x)) / x;
}

// The part of [low, low + range] inside [bottom, top], as a length that is
// exactly `range` when the whole range lies inside.
fn overlap(low: f32, range: f32, bottom: f32, top: f32) -> f32 {
    let below = clamp(bottom - low, 0.0, range);
    let above = clamp((low - top) + range, 0.0, range);
    return max(range - below - above, 0.0);
}

fn fog_point(fog: FogLayers, index: u32) -> vec2<f32> {
    let pair = fog.points[index / 2u];
    return select(pair.xy, pair.zw, index % 2u == 1u);
}

// The mean density of layer `layer` over [low, low + range] (its density at
// `low` for no range).
fn layer_mean(fog: FogLayers, layer: vec4<f32>, low: f32, range: f32) -> f32 {
    return layer_mean_and_columns(fog, layer, low, range).x;
}

// The optical depth of the fog over [t0, t1] (clipped to the fog's start and
// largest distance) along a ray from `altitude` with vertical direction `d_y`.
fn fog_optical_depth(fog: FogLayers, altitude: f32, d_y: f32, t0: f32, t1: f32) -> f32 {
    return fog_depth_and_columns(fog, altitude, d_y, t0, t1).x;
}

// ∫ of the linear piece from point `a` to point `b` over `span` metres from
// altitude `start` (0 for no span).
fn linear_piece(a: vec2<f32>, b: vec2<f32>, start: f32, span: f32) -> f32 {
    if span <= 0.0 {
        return 0.0;
    }
    return span * mix(a.y, b.y, (start + 0.5 * span - a.x) / (b.x - a.x));
}

// Layer `layer` over the altitudes [low, low + range]: its mean density there (its density at `low`
// for no range) and the fog above each end, (mean, ∫_low^∞, ∫_{low + range}^∞). Callers that read
// only the mean leave the columns to the compiler to drop.
fn layer_mean_and_columns(fog: FogLayers, layer: vec4<f32>, low: f32, range: f32) -> vec3<f32> {
    let high = low + range;
    if layer.x < 0.5 {
        let at_low = layer.z * exp(min(-layer.w * (low - layer.y), MAX_FOG_EXPONENT));
        let x = layer.w * range;
        let column_low = at_low / layer.w;
        return vec3(at_low * one_minus_exp_over(x), column_low, column_low * exp(-x));
    }
    if layer.x < 1.5 {
        var mean = select(0.0, layer.w, low >= layer.y && low <= layer.z);
        if range > 0.0 {
            mean = layer.w * overlap(low, range, layer.y, layer.z) / range;
        }
        let above = vec2(layer.z - max(low, layer.y), layer.z - max(high, layer.y));
        return vec3(mean, layer.w * max(above, vec2(0.0)));
    }
    let first = u32(layer.y);
    let count = u32(layer.z);
    var integral = 0.0;
    var at_low = 0.0;
    var found = false;
    var column_low = 0.0;
    var column_high = 0.0;
    for (var i = first; i + 1u < first + count; i++) {
        let a = fog_point(fog, i);
        let b = fog_point(fog, i + 1u);
        integral += linear_piece(a, b, max(a.x, low), overlap(low, range, a.x, b.x));
        if !found && low >= a.x && low <= b.x {
            at_low = mix(a.y, b.y, (low - a.x) / (b.x - a.x));
            found = true;
        }
        column_low += linear_piece(a, b, max(a.x, low), b.x - max(a.x, low));
        column_high += linear_piece(a, b, max(a.x, high), b.x - max(a.x, high));
    }
    return vec3(select(integral / range, at_low, range <= 0.0), column_low, column_high);
}

// The optical depth of the fog over [t0, t1] (clipped to the fog's start and largest distance) along a
// ray from `altitude` with vertical direction `d_y`, and the fog above the clipped ends:
// (τ, C(h₀), C(h₁)), C(h) = ∫_h^∞ ρ.
fn fog_depth_and_columns(fog: FogLayers, altitude: f32, d_y: f32, t0_in: f32, t1_in: f32) -> vec3<f32> {
    let t0 = max(t0_in, fog.ranges.x);
    let t1 = min(t1_in, fog.ranges.y);
    if !(t1 > t0) {
        return vec3(0.0);
    }
    let length = t1 - t0;
    let rise = d_y * length;
    let low = altitude + d_y * t0 + min(rise, 0.0);
    let range = abs(rise);
    var sum = vec3(0.0);
    for (var i = 0u; i < u32(fog.ranges.z); i++) {
        sum += layer_mean_and_columns(fog, fog.layers[i], low, range);
    }
    let columns = select(sum.yz, sum.zy, rise < 0.0);
    return vec3(length * sum.x, columns);
}

// The sunlight a stretch of fog scatters once toward its start, dimmed on its way from the sun and to
// the start, before the sun's colour and phase: `τ e^{−τ − s₁} (e^x − 1) / x`, x = τ − (s₀ − s₁), with
// `depths` the stretch's (τ, C(h₀), C(h₁)) (fog_depth_and_columns) and s = C/μ the sun's optical depths
// at its ends (nebel_core's `HeightFog::sunlit`). For a sun above the horizon (`FogLayersUniform::has_sun`).
fn fog_sunlit_scalar(fog: FogLayers, depths: vec3<f32>) -> f32 {
    let view_depth = depths.x;
    if view_depth <= 0.0 {
        return 0.0;
    }
    let mu = fog.sun_direction.y;
    let s0 = depths.y / mu;
    let s1 = depths.z / mu;
    let x = view_depth - (s0 - s1);
    // e^{−τ − s₁} (e^x − 1) = e^{−s₀} − e^{−τ − s₁}; its series near x = 0 (f32 loses 10⁻⁴ of it at
    // |x| = 10⁻³).
    let end = exp(-view_depth - s1);
    let series = view_depth * end * (1.0 + x * (0.5 + x / 6.0));
    return select(series, view_depth * (exp(-s0) - end) / x, abs(x) >= 1.0e-3);
}

// The sunlight a stretch of fog along a ray of unit `direction` scatters toward its start
// (fog_sunlit_scalar), in the sun's colour and at the ray's phase.
fn fog_sunlit(fog: FogLayers, direction: vec3<f32>, depths: vec3<f32>) -> vec3<f32> {
    let phase = henyey_greenstein(fog.sun_colour.w, dot(direction, fog.sun_direction.xyz));
    return fog.sun_colour.rgb * phase * fog_sunlit_scalar(fog, depths);
}

// The fog over [t0, t1] along a ray from `altitude` of unit `direction`, seen from t0: its optical depth
// and the premultiplied colour it adds (its glow, and with FOG_SUN the sunlight it scatters).
fn fog_stretch(fog: FogLayers, altitude: f32, direction: vec3<f32>, t0: f32, t1: f32) -> vec4<f32> {
#ifdef FOG_SUN
    let depths = fog_depth_and_columns(fog, altitude, direction.y, t0, t1);
    return vec4(fog.colour.rgb * fog_opacity(depths.x) + fog_sunlit(fog, direction, depths), depths.x);
#else
    let depth = fog_optical_depth(fog, altitude, direction.y, t0, t1);
    return vec4(fog.colour.rgb * fog_opacity(depth), depth);
#endif
}

// 1 − e^{−τ}, accurate for small τ.
fn fog_opacity(optical_depth: f32) -> f32 {
    return optical_depth * one_minus_exp_over(optical_depth);
}
