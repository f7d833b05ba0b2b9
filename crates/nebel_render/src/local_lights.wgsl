// Point and spot lights scattered along a ray (nebel_render's
// `local_lights` module): the lights' uniform, the stretch of a ray each
// lights, and the nodes of Gauss-Legendre quadrature in the angle γ at which
// the light sees the ray (nebel_core::local_light::LocalLight::scattered).

#define_import_path nebel_render::local_lights

// A point or spot light.
struct LocalLight {
    // xyz: world position; w: range.
    position: vec4<f32>,
    // rgb: the colour factor at unit distance; w: the cone's offset.
    colour: vec4<f32>,
    // xyz: the spot's unit direction; w: the cone's scale (0: a point light).
    cone: vec4<f32>,
    // x: the light's index among Bevy's clustered lights, whose shadow map
    // shades it; −1 for none.
    shadow: vec4<i32>,
}

// The lights that reach a medium and how it scatters them.
struct LocalLights {
    // x: how many of `lights` are used; y: the Henyey-Greenstein asymmetry
    // g; z: the falloff's core radius squared r₀²; w: the factor on the
    // colour they are scattered with.
    response: vec4<f32>,
    // x: the widest interval of the quadrature in the angle.
    quadrature: vec4<f32>,
    lights: array<LocalLight, #{MAX_LOCAL_LIGHTS}u>,
}

// The normalised Henyey-Greenstein phase 4π p_HG(θ) of asymmetry g at cos θ
// (nebel_core::optics::henyey_greenstein): 1 on average over the sphere.
fn henyey_greenstein(g: f32, cos_theta: f32) -> f32 {
    let denominator = 1.0 + g * g - 2.0 * g * cos_theta;
    return (1.0 - g * g) / (denominator * sqrt(denominator));
}

// Gauss-Legendre on [−1, 1], three nodes and their weights.
const GAUSS_NODES = array<f32, 3>(-0.7745966692414834, 0.0, 0.7745966692414834);
const GAUSS_WEIGHTS = array<f32, 3>(0.5555555555555556, 0.8888888888888888, 0.5555555555555556);

// The stretch of the line offset + t direction (offset from the apex) inside
// the cone of cosine c about a spot light's axis: one stretch of a convex
// cone, possibly unbounded or empty (x > y); the whole line where that
// cannot be told (nebel_core::local_light::SpotCone::chord).
fn cone_chord(light: LocalLight, c: f32, offset: vec3<f32>, direction: vec3<f32>) -> vec2<f32> {
    let whole = vec2(-3.0e38, 3.0e38);
    let empty = vec2(3.0e38, -3.0e38);
    let aw = dot(light.cone.xyz, offset);
    let ad = dot(light.cone.xyz, direction);
    let a = ad * ad - c * c;
    let b = aw * ad - c * c * dot(offset, direction);
    let k = aw * aw - c * c * dot(offset, offset);
    let discriminant = b * b - a * k;
    if c <= 1.0e-6 || abs(a) < 1.0e-9 {
        return whole;
    }
    if discriminant < 0.0 {
        return select(whole, empty, a < 0.0);
    }
    let root = sqrt(discriminant);
    let r0 = (-b - root) / a;
    let r1 = (-b + root) / a;
    let lo = min(r0, r1);
    let hi = max(r0, r1);
    if a < 0.0 {
        return select(empty, vec2(lo, hi), aw + 0.5 * (lo + hi) * ad >= 0.0);
    }
    if ad > 0.0 {
        return select(empty, vec2(hi, 3.0e38), aw + hi * ad >= 0.0);
    }
    return select(empty, vec2(-3.0e38, lo), aw + lo * ad >= 0.0);
}

// A light as one ray sees it: the stretch [a, b] of the ray inside its
// range and a spot light's outer cone, where it lights anything, and
// [inner_start, inner_end] ⊆ [a, b] inside the inner cone (the whole
// stretch for a point light), where the cone's factor has a kink.
struct LightOnRay {
    to_light: vec3<f32>,
    foot: f32,
    miss2: f32,
    a: f32,
    b: f32,
    inner_start: f32,
    inner_end: f32,
}

// `light` on the ray from `eye` along the unit `direction`.
fn light_on_ray(light: LocalLight, eye: vec3<f32>, direction: vec3<f32>) -> LightOnRay {
    let to_light = light.position.xyz - eye;
    let foot = dot(to_light, direction);
    let perpendicular = to_light - foot * direction;
    let miss2 = dot(perpendicular, perpendicular);
    let range = light.position.w;
    let half_chord = sqrt(max(range * range - miss2, 0.0));
    var on_ray = LightOnRay(to_light, foot, miss2, foot - half_chord, foot + half_chord, 0.0, 0.0);
    if range * range <= miss2 {
        on_ray.b = on_ray.a;
    }
    if light.cone.w > 0.0 {
        let outer = cone_chord(light, -light.colour.w / light.cone.w, -to_light, direction);
        on_ray.a = max(on_ray.a, outer.x);
        on_ray.b = min(on_ray.b, outer.y);
        let inner = cone_chord(light, (1.0 - light.colour.w) / light.cone.w, -to_light, direction);
        on_ray.inner_start = clamp(inner.x, on_ray.a, max(on_ray.b, on_ray.a));
        on_ray.inner_end = max(clamp(inner.y, on_ray.a, max(on_ray.b, on_ray.a)), on_ray.inner_start);
    } else {
        on_ray.inner_start = on_ray.a;
        on_ray.inner_end = on_ray.b;
    }
    return on_ray;
}

// The quadrature of a part [a, b] of a ray for one light: `intervals` equal
// intervals in γ = atan((t − t₀) / h) from `gamma_a`, each 2 half_width
// wide, t₀ the foot of the perpendicular from the light and h² its distance
// squared plus r₀², in which dt / (r² + r₀²) = dγ / h.
struct LightQuadrature {
    gamma_a: f32,
    half_width: f32,
    h: f32,
    intervals: u32,
}

// The intervals for [a, b], none wider than `widest` (the lights'
// `quadrature.x`), with r₀² = `core2` (their `response.z`).
fn light_quadrature(on_ray: LightOnRay, a: f32, b: f32, core2: f32, widest: f32) -> LightQuadrature {
    let h = sqrt(on_ray.miss2 + core2);
    let gamma_a = atan((a - on_ray.foot) / h);
    let gamma_b = atan((b - on_ray.foot) / h);
    let intervals = u32(max(ceil((gamma_b - gamma_a) / widest), 1.0));
    return LightQuadrature(gamma_a, 0.5 * (gamma_b - gamma_a) / f32(intervals), h, intervals);
}

// A node of the quadrature: its distance `t` along the ray and its weight,
// the light's W S 4π p_HG there (without its colour) times the node's
// share of dt / (r² + r₀²), so that Σ weight f(t) ≈ ∫ f E 4π p_HG dt.
struct LightNode {
    t: f32,
    weight: f32,
}

// Node k (0 to 2) of interval i of `quadrature` for `light` on the unit ray
// `direction`, scattered with asymmetry g.
fn light_node(
    light: LocalLight,
    on_ray: LightOnRay,
    direction: vec3<f32>,
    quadrature: LightQuadrature,
    i: u32,
    k: u32,
    g: f32,
) -> LightNode {
    let centre = quadrature.gamma_a + quadrature.half_width * (2.0 * f32(i) + 1.0);
    let along = quadrature.h * tan(centre + quadrature.half_width * GAUSS_NODES[k]);
    let t = on_ray.foot + along;
    let r2 = on_ray.miss2 + along * along;
    let r = sqrt(r2);
    let range = light.position.w;
    let u = r2 / (range * range);
    let window = clamp(1.0 - u * u, 0.0, 1.0);
    var cone = 1.0;
    if light.cone.w > 0.0 {
        let toward = select(vec3(0.0), (t * direction - on_ray.to_light) / r, r > 0.0);
        cone = clamp(dot(light.cone.xyz, toward) * light.cone.w + light.colour.w, 0.0, 1.0);
    }
    let cos_theta = select(0.0, along / r, r > 0.0);
    let phase = henyey_greenstein(g, cos_theta);
    let weight = GAUSS_WEIGHTS[k] * window * window * cone * cone * phase * quadrature.half_width / quadrature.h;
    return LightNode(t, weight);
}

// ∫ σ e^{−σ (t − t_a)} E 4π p_HG dt over the stretch of the ray `light`
// sees in the angles [gammas.x, gammas.y], in one interval of three nodes
// (`h` the light's quadrature's, g the asymmetry).
fn light_interval(
    light: LocalLight,
    on_ray: LightOnRay,
    direction: vec3<f32>,
    h: f32,
    gammas: vec2<f32>,
    t_a: f32,
    sigma: f32,
    g: f32,
) -> f32 {
    let quadrature = light_span(h, gammas);
    var sum = 0.0;
    for (var k = 0u; k < 3u; k++) {
        let node = light_node(light, on_ray, direction, quadrature, 0u, k, g);
        sum += node.weight * sigma * exp(-sigma * (node.t - t_a));
    }
    return sum;
}

// One interval of quadrature over the angles [gammas.x, gammas.y] (`h` the
// light's quadrature's).
fn light_span(h: f32, gammas: vec2<f32>) -> LightQuadrature {
    return LightQuadrature(gammas.x, 0.5 * (gammas.y - gammas.x), h, 1u);
}
