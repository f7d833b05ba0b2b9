// The visibility of point and spot lights, and of the sun, through Bevy's
// shadow maps (nebel_render's `light_shadows` module): Bevy's lights,
// clustered lights, point-light cube maps and the spot lights' and
// directional lights' maps with their comparison samplers in bind group
// LIGHT_SHADOW_GROUP, read as Bevy's PBR shader reads them for a surface,
// and the crossing of a shadow's edge along a ray, bisected in the angle at
// which the light sees the ray.

#define_import_path nebel_render::light_shadows

#import bevy_pbr::mesh_view_types::{ClusteredLights, DIRECTIONAL_LIGHT_FLAGS_SHADOWS_ENABLED_BIT, Lights, POINT_LIGHT_FLAGS_SHADOWS_ENABLED_BIT, POINT_LIGHT_FLAGS_SPOT_LIGHT_BIT, POINT_LIGHT_FLAGS_SPOT_LIGHT_Y_NEGATIVE}
#import bevy_render::maths::orthonormalize
#import nebel_render::local_lights::LocalLight

@group(#{LIGHT_SHADOW_GROUP}) @binding(0) var<uniform> bevy_lights: Lights;
#if AVAILABLE_STORAGE_BUFFER_BINDINGS >= 3
@group(#{LIGHT_SHADOW_GROUP}) @binding(1) var<storage> clustered_lights: ClusteredLights;
#else
@group(#{LIGHT_SHADOW_GROUP}) @binding(1) var<uniform> clustered_lights: ClusteredLights;
#endif
@group(#{LIGHT_SHADOW_GROUP}) @binding(2) var point_shadow_maps: texture_depth_cube_array;
@group(#{LIGHT_SHADOW_GROUP}) @binding(3) var point_shadow_sampler: sampler_comparison;
// The spot lights' maps follow the directional lights' cascades in one array.
@group(#{LIGHT_SHADOW_GROUP}) @binding(4) var spot_shadow_maps: texture_depth_2d_array;
@group(#{LIGHT_SHADOW_GROUP}) @binding(5) var spot_shadow_sampler: sampler_comparison;

// Visibilities closer than this are taken as equal.
const SHADOW_EPSILON: f32 = 1.0e-3;
// Bisections of a change of visibility: the crossing to 1/64 of the
// stretch it was found in.
const SHADOW_BISECTIONS: u32 = 6u;

// The part of `light` that reaches the world point `p` past opaque
// geometry: Bevy's shadow map of it, one 2×2 hardware comparison, the point
// moved toward the light by the light's depth bias (a medium has no surface
// normal, so no normal bias); 1 for a light without a shadow map.
fn light_visibility(light: LocalLight, p: vec3<f32>) -> f32 {
    if light.shadow.x < 0 {
        return 1.0;
    }
    let index = u32(light.shadow.x);
    let source = clustered_lights.data[index];
    if (source.flags & POINT_LIGHT_FLAGS_SHADOWS_ENABLED_BIT) == 0u {
        return 1.0;
    }
    let to_light = source.position_radius.xyz - p;
    // The point relative to the light, moved toward it by the depth bias.
    let biased = -to_light + source.shadow_depth_bias * to_light * inverseSqrt(max(dot(to_light, to_light), 1.0e-12));
    if (source.flags & POINT_LIGHT_FLAGS_SPOT_LIGHT_BIT) == 0u {
        // The cube face's depth from its largest axis; cube maps are
        // left-handed.
        let major = max(abs(biased.x), max(abs(biased.y), abs(biased.z)));
        let zw = -major * source.light_custom_data.xy + source.light_custom_data.zw;
        return textureSampleCompareLevel(point_shadow_maps, point_shadow_sampler, biased * vec3(1.0, 1.0, -1.0), i32(index), zw.x / zw.y);
    }
    var axis = vec3(source.light_custom_data.x, 0.0, source.light_custom_data.y);
    axis.y = sqrt(max(0.0, 1.0 - axis.x * axis.x - axis.z * axis.z));
    if (source.flags & POINT_LIGHT_FLAGS_SPOT_LIGHT_Y_NEGATIVE) != 0u {
        axis.y = -axis.y;
    }
    let projected = biased * orthonormalize(-axis);
    if projected.z >= 0.0 {
        // Behind the spot light, which lights nothing there.
        return 1.0;
    }
    let uv = projected.xy / (source.spot_light_tan_angle * -projected.z) * vec2(0.5, -0.5) + vec2(0.5);
    let layer = i32(index) + bevy_lights.spot_light_shadowmap_offset;
    return textureSampleCompareLevel(spot_shadow_maps, spot_shadow_sampler, uv, layer, source.shadow_map_near_z / -projected.z);
}

// The index of Bevy's directional light toward the unit `sun` that casts
// shadows, or none (n_directional_lights).
fn shadowed_sun(sun: vec3<f32>) -> u32 {
    for (var i = 0u; i < bevy_lights.n_directional_lights; i++) {
        let light = &bevy_lights.directional_lights[i];
        if dot((*light).direction_to_light, sun) > 0.99999 && ((*light).flags & DIRECTIONAL_LIGHT_FLAGS_SHADOWS_ENABLED_BIT) != 0u {
            return i;
        }
    }
    return bevy_lights.n_directional_lights;
}

// How far from the eye, in view depth, Bevy's cascades of the directional
// light `index` (shadowed_sun) reach.
fn sun_shadow_reach(index: u32) -> f32 {
    if index >= bevy_lights.n_directional_lights {
        return 0.0;
    }
    let light = &bevy_lights.directional_lights[index];
    return (*light).cascades[max((*light).num_cascades, 1u) - 1u].far_bound;
}

// The part of the directional light `index` (shadowed_sun) that reaches the
// world point `p` at view depth `depth` past opaque geometry: Bevy's first
// cascade that reaches that depth, one 2×2 hardware comparison, the point
// moved toward the light by its depth bias plus its normal bias in the
// cascade's texels (a medium has no normal; a surface just below the point
// then does not shade it); 1 beyond the cascades and outside the map.
fn sun_visibility(index: u32, p: vec3<f32>, depth: f32) -> f32 {
    if index >= bevy_lights.n_directional_lights {
        return 1.0;
    }
    let light = &bevy_lights.directional_lights[index];
    var cascade = 0u;
    while cascade < (*light).num_cascades && depth >= (*light).cascades[cascade].far_bound {
        cascade++;
    }
    if cascade >= (*light).num_cascades {
        return 1.0;
    }
    let bias = (*light).shadow_depth_bias + (*light).shadow_normal_bias * (*light).cascades[cascade].texel_size;
    let biased = p + bias * (*light).direction_to_light;
    let clip = (*light).cascades[cascade].clip_from_world * vec4(biased, 1.0);
    let ndc = clip.xyz / clip.w;
    if clip.w <= 0.0 || any(ndc.xy < vec2(-1.0)) || ndc.z < 0.0 || any(ndc > vec3(1.0)) {
        return 1.0;
    }
    let uv = ndc.xy * vec2(0.5, -0.5) + vec2(0.5);
    return textureSampleCompareLevel(spot_shadow_maps, spot_shadow_sampler, uv, i32((*light).depth_texture_base_index + cascade), ndc.z);
}

// The visibility of `light` at the point of the ray from `eye` along the
// unit `direction` that the light sees at the angle `gamma` (`foot` and `h`
// the light's quadrature's on the ray: t = foot + h tan γ).
fn light_visibility_at(light: LocalLight, eye: vec3<f32>, direction: vec3<f32>, foot: f32, h: f32, gamma: f32) -> f32 {
    return light_visibility(light, eye + (foot + h * tan(gamma)) * direction);
}

// The angle in [gammas.x, gammas.y], whose ends see the light `visible`,
// where the visibility crosses their mean (bisected).
fn shadow_crossing(
    light: LocalLight,
    eye: vec3<f32>,
    direction: vec3<f32>,
    foot: f32,
    h: f32,
    gammas: vec2<f32>,
    visible: vec2<f32>,
) -> f32 {
    let level = 0.5 * (visible.x + visible.y);
    var bracket = gammas;
    for (var i = 0u; i < SHADOW_BISECTIONS; i++) {
        let middle = 0.5 * (bracket.x + bracket.y);
        if (light_visibility_at(light, eye, direction, foot, h, middle) - level) * (visible.x - level) > 0.0 {
            bracket.x = middle;
        } else {
            bracket.y = middle;
        }
    }
    return 0.5 * (bracket.x + bracket.y);
}

// An interval of a light's quadrature cut where the light's visibility
// changes: up to four stretches (x, y: their angles; z: the visibility
// there), and the visibility at the interval's end.
struct VisibilitySpans {
    spans: array<vec3<f32>, 4>,
    count: u32,
    end: f32,
}

// The interval [start, start + width] in the angle of the ray from `eye`
// along `direction` (`foot` and `h` the light's quadrature's), whose start
// sees `light` `visible`: the visibility is read at its middle and end; a
// half whose ends differ is cut at the bisected crossing (a shadow within a
// half can be missed).
fn visibility_spans(
    light: LocalLight,
    eye: vec3<f32>,
    direction: vec3<f32>,
    foot: f32,
    h: f32,
    start: f32,
    width: f32,
    visible: f32,
) -> VisibilitySpans {
    let middle = start + 0.5 * width;
    let end = start + width;
    let visible_middle = light_visibility_at(light, eye, direction, foot, h, middle);
    let visible_end = light_visibility_at(light, eye, direction, foot, h, end);
    var out = VisibilitySpans(array<vec3<f32>, 4>(), 0u, visible_end);
    if abs(visible - visible_middle) + abs(visible_middle - visible_end) < SHADOW_EPSILON {
        out.spans[0] = vec3(start, end, visible);
        out.count = 1u;
        return out;
    }
    for (var half = 0u; half < 2u; half++) {
        let gammas = select(vec2(start, middle), vec2(middle, end), half == 1u);
        let ends = select(vec2(visible, visible_middle), vec2(visible_middle, visible_end), half == 1u);
        if abs(ends.x - ends.y) < SHADOW_EPSILON {
            out.spans[out.count] = vec3(gammas, ends.x);
            out.count += 1u;
        } else {
            let crossing = shadow_crossing(light, eye, direction, foot, h, gammas, ends);
            out.spans[out.count] = vec3(gammas.x, crossing, ends.x);
            out.spans[out.count + 1u] = vec3(crossing, gammas.y, ends.y);
            out.count += 2u;
        }
    }
    return out;
}
