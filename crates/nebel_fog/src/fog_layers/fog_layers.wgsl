// The fog-layer pass (Röttger 2004 §5.3, layered fog): per pixel, the fog
// from the eye to the opaque depth, or to the largest distance where nothing
// is opaque, as the premultiplied layer (c α, α), α = 1 − e^{−τ}, blended
// over the scene (src One, dst OneMinusSrcAlpha). The ray comes from the
// inverse projection and the camera's rotation, so large world coordinates
// cost no precision; only the camera's altitude is absolute (the lights'
// offsets from the camera are differences of world positions).
//
// LOCAL_LIGHTS (point and spot lights reach the fog,
// nebel_render::local_lights): each adds
// s c ∫ ρ(h(t)) e^{−τ(0, t) − τ(x(t), p)} E(t) 4π p_HG dt over its stretch
// of the ray, where τ(x, p) is the fog's optical depth from the point to the
// light, in closed form like that of any straight segment. The stretch is
// cut where the density has a jump or a kink and at the inner cone; each
// part into equal pieces, one per MAX_PART_CHANGE of its optical depth plus
// exponential falloff times the altitude crossed (at most MAX_PART_PIECES);
// each piece in Gauss-Legendre intervals in the angle the light sees. The
// reference's ReferenceFog::lit cuts the same way, finer.
//
// LIGHT_SHADOWS (a light that reaches the fog casts shadows): each interval
// is cut where Bevy's shadow map of the light changes its visibility
// (nebel_render::light_shadows), each stretch weighted by its visibility.
//
// FOG_SUN with the clouds' shadow maps (nebel_render::cloud_shadow_maps):
// each map with weight w holds back c 4π p_HG ∫ ρ e^{−τ(0, t) − C(h)/μ}
// w (1 − T_map) dt of the closed-form sunlight, over the stretch of the ray
// whose line toward the map's sun crosses the map, below the casters' top
// (equal pieces of three Gauss-Legendre nodes, one per CLOUD_PIECE_TEXELS
// texels the crossing moves over, at most MAX_CLOUD_PIECES; T_map bilinear,
// read where that line crosses the map's plane; a point between the plane
// and the top takes the whole column's shadow). The optical depth to a node
// is that to the stretch's start plus the difference of the fog's columns
// over d_y (a ray within LEVEL_RAY of level: the prefix integral). Nodes in
// the terrain's shadow hold back nothing more, and with SUN_SHADOWS nodes
// hold back their part by the visibility through Bevy's map of the sun.
//
// SUN_SHADOWS (FOG_SUN, and the sun casts shadows; LIGHT_SHADOWS binds
// Bevy's maps): where Bevy's cascades reach, the sun's visibility V through
// them is read at SUN_SHADOW_STEPS equal steps of the ray and the first
// SUN_SHADOW_CHANGES changes bisected to the mean of their ends
// (SUN_SHADOW_BISECTIONS); every stretch of one weight w = 1 − V (0 in the
// terrain's shadow, held back there already) holds back w (F(end) −
// F(start)), F the closed-form sunlight from the eye.
//
// FOG_SUN with the terrain's shadow heights (the fog layers' terrain_shadow
// module): the ray's stretches below them hold back their closed-form
// sunlight, each seen through the fog before it. The walk crosses the map's
// blocks along the ray (Amanatides and Woo), below its highest shadow
// height: a block the ray passes wholly above its highest shadow height is
// lit, wholly below its lowest shaded, and the others are walked cell by
// cell; in each cell the bilinear height along the ray is a quadratic,
// whose roots cut the shaded pieces (nebel_core's
// PlacedTerrainShadow::shaded, which walks every cell).

#import bevy_core_pipeline::fullscreen_vertex_shader::FullscreenVertexOutput
#import nebel_render::fog_layers::{FogLayers, fog_depth_and_columns, fog_opacity, fog_optical_depth, fog_point, fog_stretch, fog_sunlit_scalar, layer_mean, layer_mean_and_columns}
#import nebel_render::local_lights::{GAUSS_NODES, GAUSS_WEIGHTS, LocalLights, henyey_greenstein, light_node, light_on_ray, light_quadrature, light_span}
#import nebel_render::cloud_shadow_maps::{CloudShadowMapPair, held_back}
#ifdef LIGHT_SHADOWS
#import nebel_render::light_shadows::{light_visibility_at, shadowed_sun, sun_shadow_reach, sun_visibility, visibility_spans}
#endif

struct FogPass {
    view_from_clip: mat4x4<f32>,
    world_from_view: mat4x4<f32>,
    camera_position: vec4<f32>,
    viewport: vec4<f32>,
    fog: FogLayers,
    // The point and spot lights that reach the fog (read only by the
    // LOCAL_LIGHTS variant).
    lights: LocalLights,
    // The clouds' shadow maps over sunlit fog (no weight otherwise).
    clouds: CloudShadowMapPair,
    // The terrain's shadow heights over sunlit fog (no weight otherwise).
    terrain: TerrainShadowMap,
}

struct TerrainShadowMap {
    // World space to the map's grid: x and z in grid units, y the height in
    // the terrain's frame.
    grid_from_world: mat4x4<f32>,
    // Points along x and z, the highest shadow height, and the weight (0:
    // no map).
    size: vec4<f32>,
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

#ifdef FOG_SUN
@group(0) @binding(2) var first_cloud_map: texture_2d<f32>;
@group(0) @binding(3) var second_cloud_map: texture_2d<f32>;
@group(0) @binding(4) var cloud_map_sampler: sampler;
@group(0) @binding(5) var terrain_shadow_map: texture_2d<f32>;
// Per block of TERRAIN_SHADOW_BLOCK cells a side, its lowest and highest
// shadow height.
@group(0) @binding(6) var terrain_shadow_blocks: texture_2d<f32>;

// Map texels the crossing moves over per piece of a map's stretch of the
// ray, and the most pieces.
const CLOUD_PIECE_TEXELS: f32 = 4.0;
const MAX_CLOUD_PIECES: f32 = 64.0;
// The vertical direction below which a ray counts as level.
const LEVEL_RAY: f32 = 1.0e-3;

// The fog's density at altitude `h` and the fog above it, C(h) = ∫_h^∞ ρ.
fn fog_density_and_column(h: f32) -> vec2<f32> {
    var fog = vec2(0.0);
    for (var i = 0u; i < u32(fog_pass.fog.ranges.z); i++) {
        fog += layer_mean_and_columns(fog_pass.fog, fog_pass.fog.layers[i], h, 0.0).xy;
    }
    return fog;
}

// The part of [t0, t1] along the unit ray `direction` from the eye below
// the casters' top whose line toward the map's sun crosses the map between
// its texel centres (the crossing moves linearly with t).
fn map_stretch(plane: vec4<f32>, sun: vec3<f32>, size: vec4<f32>, direction: vec3<f32>, t0: f32, t1: f32) -> vec2<f32> {
    let eye = fog_pass.camera_position.xyz;
    let start = eye.xz + sun.xz * ((plane.x - eye.y) / sun.y);
    let rate = direction.xz - sun.xz * (direction.y / sun.y);
    let low = plane.zw + 0.5 * plane.y;
    let high = plane.zw + (size.xy - 0.5) * plane.y;
    var stretch = vec2(t0, t1);
    let top = (size.w - eye.y) / direction.y;
    if direction.y > 0.0 {
        stretch.y = min(stretch.y, top);
    } else if direction.y < 0.0 {
        stretch.x = max(stretch.x, top);
    } else if eye.y > size.w {
        return vec2(0.0);
    }
    for (var axis = 0; axis < 2; axis++) {
        if rate[axis] == 0.0 {
            if start[axis] < low[axis] || start[axis] > high[axis] {
                return vec2(0.0);
            }
            continue;
        }
        let a = (low[axis] - start[axis]) / rate[axis];
        let b = (high[axis] - start[axis]) / rate[axis];
        stretch = vec2(max(stretch.x, min(a, b)), min(stretch.y, max(a, b)));
    }
    return stretch;
}

// ∫ ρ e^{−τ(0, t) − C(h)/μ} w (1 − T_map) dt over [t0, t1] for one map (see
// the header).
fn map_held_back(
    plane: vec4<f32>,
    sun_and_weight: vec4<f32>,
    size: vec4<f32>,
    map_texture: texture_2d<f32>,
    direction: vec3<f32>,
    t0: f32,
    t1: f32,
) -> f32 {
    if sun_and_weight.w <= 0.0 {
        return 0.0;
    }
    let sun = sun_and_weight.xyz;
    let stretch = map_stretch(plane, sun, size, direction, t0, t1);
    if stretch.y <= stretch.x {
        return 0.0;
    }
    let eye = fog_pass.camera_position.xyz;
    let mu = fog_pass.fog.sun_direction.y;
    let d_y = direction.y;
    let texels = length(direction.xz - sun.xz * (d_y / sun.y)) * (stretch.y - stretch.x) / plane.y;
    let pieces = u32(clamp(ceil(texels / CLOUD_PIECE_TEXELS), 1.0, MAX_CLOUD_PIECES));
    let half = 0.5 * (stretch.y - stretch.x) / f32(pieces);
    // The optical depth from the eye to a node: to the stretch's start, then
    // the difference of the columns over d_y (ρ dt = −dC/d_y); a ray within
    // LEVEL_RAY of level, where that difference loses its precision, takes
    // the prefix integral itself.
    let level = abs(d_y) < LEVEL_RAY;
    let start_depth = fog_optical_depth(fog_pass.fog, eye.y, d_y, 0.0, stretch.x);
    let start_column = fog_density_and_column(eye.y + d_y * stretch.x).y;
    var sum = 0.0;
    for (var piece = 0u; piece < pieces; piece++) {
        let middle = stretch.x + (2.0 * f32(piece) + 1.0) * half;
        for (var k = 0u; k < 3u; k++) {
            let t = middle + half * GAUSS_NODES[k];
            let p = eye + t * direction;
            var held = held_back(plane, sun_and_weight, size, map_texture, cloud_map_sampler, p);
#ifdef SUN_SHADOWS
            // Where Bevy's map of the sun shades the node, the clouds hold
            // back only the part it lets through.
            held *= sun_visibility(shadowed_sun(fog_pass.fog.sun_direction.xyz), p, t * -dot(direction, fog_pass.world_from_view[2].xyz));
#endif
            if held > 0.0 && !in_terrain_shadow(p) {
                let fog = fog_density_and_column(p.y);
                var seen = start_depth + (start_column - fog.y) / d_y;
                if level {
                    seen = fog_optical_depth(fog_pass.fog, eye.y, d_y, 0.0, t);
                }
                sum += GAUSS_WEIGHTS[k] * half * fog.x * exp(-seen - fog.y / mu) * held;
            }
        }
    }
    return sum;
}

// The sunlight the clouds' shadow maps hold back from the fog over
// [t0, t1] (see the header).
fn clouds_held_back(direction: vec3<f32>, t0: f32, t1: f32) -> vec3<f32> {
    let first = fog_pass.clouds.first;
    let second = fog_pass.clouds.second;
    let held = map_held_back(first.plane, first.sun_and_weight, first.size, first_cloud_map, direction, t0, t1)
        + map_held_back(second.plane, second.sun_and_weight, second.size, second_cloud_map, direction, t0, t1);
    let sun = fog_pass.fog.sun_direction.xyz;
    let phase = henyey_greenstein(fog_pass.fog.sun_colour.w, dot(direction, sun));
    return fog_pass.fog.sun_colour.rgb * phase * held;
}
#endif

#ifdef FOG_SUN
// The shadow heights at the corners of the map's cell `cell`: (i, j),
// (i + 1, j), (i, j + 1), (i + 1, j + 1).
fn shadow_corners(cell: vec2<f32>) -> vec4<f32> {
    let c = vec2<i32>(cell);
    return vec4(
        textureLoad(terrain_shadow_map, c, 0).r,
        textureLoad(terrain_shadow_map, c + vec2(1, 0), 0).r,
        textureLoad(terrain_shadow_map, c + vec2(0, 1), 0).r,
        textureLoad(terrain_shadow_map, c + vec2(1, 1), 0).r,
    );
}

// Whether the world point `p` lies below the terrain's shadow heights,
// inside the map.
fn in_terrain_shadow(p: vec3<f32>) -> bool {
    let map = fog_pass.terrain;
    if map.size.w <= 0.0 {
        return false;
    }
    let g = (map.grid_from_world * vec4(p, 1.0)).xyz;
    let last = map.size.xy - 1.0;
    if any(g.xz < vec2(0.0)) || any(g.xz > last) {
        return false;
    }
    let cell = min(floor(g.xz), last - 1.0);
    let f = g.xz - cell;
    let h = shadow_corners(cell);
    return g.y < mix(mix(h.x, h.y, f.x), mix(h.z, h.w, f.x), f.y);
}

// The sunlight of the fog over [0, t] along a ray of vertical direction
// `d_y`, seen from the eye, before the sun's colour and phase: a shaded
// stretch [t0, t1] holds back F(t1) − F(t0).
fn sunlight_to(d_y: f32, t: f32) -> f32 {
    let depths = fog_depth_and_columns(fog_pass.fog, fog_pass.camera_position.y, d_y, 0.0, t);
    return fog_sunlit_scalar(fog_pass.fog, depths);
}

// The edges of the shaded stretches a walk keeps before it sums their
// sunlight.
const SHADE_EDGES: u32 = 16u;

// The shaded stretches found so far along a ray: the edges not yet summed
// (a stretch's start at an even index, its end at the odd one after it),
// whether the ray is in one, and the sunlight the summed ones hold back
// (before the sun's colour and phase).
struct ShadeWalk {
    edges: array<f32, SHADE_EDGES>,
    count: u32,
    open: bool,
    held: f32,
}

// Sums the kept edges' sunlight, F(end) − F(start) per stretch.
fn shade_flush(walk: ptr<function, ShadeWalk>, d_y: f32) {
    for (var k = 0u; k < (*walk).count; k++) {
        let f = sunlight_to(d_y, (*walk).edges[k]);
        (*walk).held += select(-f, f, k % 2u == 1u);
    }
    (*walk).count = 0u;
}

// The ray of vertical direction `d_y` enters a lit (`dark` false) or
// shaded stretch at `t`. The edges'
// sunlight is summed after the walk (or when SHADE_EDGES are kept), out of
// the walk's divergent loop.
fn shade_edge(walk: ptr<function, ShadeWalk>, d_y: f32, t: f32, dark: bool) {
    if dark != (*walk).open {
        if (*walk).count == SHADE_EDGES {
            shade_flush(walk, d_y);
        }
        (*walk).open = dark;
        (*walk).edges[(*walk).count] = t;
        (*walk).count += 1u;
    }
}

// The cell of the grid's box [lo, hi) that the ray g(t) = start + t e is in
// at `t` (on a cell's edge moving backward, the cell below).
fn cell_at(start: vec2<f32>, e: vec2<f32>, t: f32, lo: vec2<f32>, hi: vec2<f32>) -> vec2<f32> {
    let g = start + t * e;
    let cell = floor(g);
    return clamp(select(cell, cell - 1.0, e < vec2(0.0) & cell == g), lo, hi - 1.0);
}

// Where the ray g(t) = start + t e leaves the box [lo, hi] across each axis
// (1e30 along an axis it does not move on).
fn box_exit(start: vec2<f32>, e: vec2<f32>, lo: vec2<f32>, hi: vec2<f32>) -> vec2<f32> {
    let bound = select(lo, hi, e > vec2(0.0));
    return select(vec2(1.0e30), (bound - start) / e, e != vec2(0.0));
}

// Walks the cells of the box [lo, hi) over [t_from, t_to] along the ray
// `start + t e` (the map's grid; `d_y` its world vertical direction), each
// cell's quadratic cut at its roots.
fn walk_cells(walk: ptr<function, ShadeWalk>, d_y: f32, start: vec3<f32>, e: vec3<f32>, t_from: f32, t_to: f32, lo: vec2<f32>, hi: vec2<f32>) {
    var cell = cell_at(start.xz, e.xz, t_from, lo, hi);
    var h = shadow_corners(cell);
    var t = t_from;
    for (var n = 0u; n < 2u * #{TERRAIN_SHADOW_BLOCK}u + 1u; n++) {
        let next = box_exit(start.xz, e.xz, cell, cell + 1.0);
        let end = max(min(min(next.x, next.y), t_to), t);
        // d(s) = y − h_s along the cell, s = t' − t: a quadratic.
        let bx = h.y - h.x;
        let cz = h.z - h.x;
        let k = h.w - h.y - h.z + h.x;
        let p = start.xz + t * e.xz - cell;
        let constant = start.y + t * e.y - (h.x + bx * p.x + cz * p.y + k * p.x * p.y);
        let linear = e.y - (bx * e.x + cz * e.z + k * (p.x * e.z + p.y * e.x));
        let quadratic = -k * e.x * e.z;
        let length = end - t;
        var cuts = vec2(length);
        if quadratic == 0.0 {
            if linear != 0.0 {
                cuts.x = -constant / linear;
            }
        } else {
            let discriminant = linear * linear - 4.0 * quadratic * constant;
            if discriminant >= 0.0 {
                let big = -0.5 * (linear + select(-1.0, 1.0, linear >= 0.0) * sqrt(discriminant));
                if big != 0.0 {
                    cuts = vec2(big / quadratic, constant / big);
                }
            }
        }
        cuts = select(vec2(length), cuts, cuts > vec2(0.0) & cuts < vec2(length));
        cuts = vec2(min(cuts.x, cuts.y), max(cuts.x, cuts.y));
        var pieces = array(vec2(0.0, cuts.x), vec2(cuts.x, cuts.y), vec2(cuts.y, length));
        for (var m = 0; m < 3; m++) {
            let piece = pieces[m];
            if piece.y > piece.x {
                let s = 0.5 * (piece.x + piece.y);
                shade_edge(walk, d_y, t + piece.x, constant + s * (linear + s * quadratic) < 0.0);
            }
        }
        t = end;
        if end >= t_to {
            break;
        }
        let along_z = next.y < next.x;
        let axis = select(0, 1, along_z);
        let forward = e.xz[axis] > 0.0;
        cell[axis] += sign(e.xz)[axis];
        if cell[axis] < lo[axis] || cell[axis] > hi[axis] - 1.0 {
            break;
        }
        // The next cell shares two corners with this one: load the other two.
        let c = vec2<i32>(cell);
        let far = select(vec2(0), select(vec2(1, 0), vec2(0, 1), along_z), forward);
        let side = select(vec2(0, 1), vec2(1, 0), along_z);
        let a = textureLoad(terrain_shadow_map, c + far, 0).r;
        let b = textureLoad(terrain_shadow_map, c + far + side, 0).r;
        let across_x = select(vec4(a, h.x, b, h.z), vec4(h.y, a, h.w, b), forward);
        let across_z = select(vec4(a, b, h.x, h.y), vec4(h.z, h.w, a, b), forward);
        h = select(across_x, across_z, along_z);
    }
}

// The sunlight the terrain's shadow holds back from the fog over [t0, t1]
// along the ray `direction` (see the header).
fn terrain_held_back(direction: vec3<f32>, t0: f32, t1: f32) -> vec3<f32> {
    let map = fog_pass.terrain;
    if map.size.w <= 0.0 {
        return vec3(0.0);
    }
    // The ray in the map's grid: g(t) = start + t e.
    let start = (map.grid_from_world * vec4(fog_pass.camera_position.xyz, 1.0)).xyz;
    let e = (map.grid_from_world * vec4(direction, 0.0)).xyz;
    let last = map.size.xy - 1.0;
    var a = t0;
    var b = t1;
    if e.y > 0.0 {
        b = min(b, (map.size.z - start.y) / e.y);
    } else if e.y < 0.0 {
        a = max(a, (map.size.z - start.y) / e.y);
    } else if start.y > map.size.z {
        return vec3(0.0);
    }
    let enter = box_exit(start.xz, e.xz, last, vec2(0.0));
    let leave = box_exit(start.xz, e.xz, vec2(0.0), last);
    for (var axis = 0; axis < 2; axis++) {
        if e.xz[axis] == 0.0 {
            if start.xz[axis] < 0.0 || start.xz[axis] > last[axis] {
                return vec3(0.0);
            }
        } else {
            a = max(a, enter[axis]);
            b = min(b, leave[axis]);
        }
    }
    if !(b > a) {
        return vec3(0.0);
    }
    // Blocks of TERRAIN_SHADOW_BLOCK cells a side whose lowest and highest
    // shadow heights the ray passes wholly above (lit) or below (shaded)
    // are crossed whole; the others cell by cell.
    let size = f32(#{TERRAIN_SHADOW_BLOCK});
    let blocks = ceil(last / size);
    var block = floor(cell_at(start.xz, e.xz, a, vec2(0.0), last) / size);
    var walk: ShadeWalk;
    var t = a;
    for (var n = 0u; n < u32(blocks.x + blocks.y); n++) {
        let lo = block * size;
        let hi = min(lo + size, last);
        let next = box_exit(start.xz, e.xz, lo, hi);
        let end = max(min(min(next.x, next.y), b), t);
        let heights = start.y + vec2(t, end) * e.y;
        let bounds = textureLoad(terrain_shadow_blocks, vec2<i32>(block), 0).rg;
        if min(heights.x, heights.y) >= bounds.y {
            shade_edge(&walk, direction.y, t, false);
        } else if max(heights.x, heights.y) < bounds.x {
            shade_edge(&walk, direction.y, t, true);
        } else {
            walk_cells(&walk, direction.y, start, e, t, end, lo, hi);
        }
        t = end;
        if end >= b {
            break;
        }
        let axis = select(0, 1, next.y < next.x);
        block[axis] += sign(e.xz)[axis];
        if block[axis] < 0.0 || block[axis] > blocks[axis] - 1.0 {
            break;
        }
    }
    shade_edge(&walk, direction.y, t, false);
    shade_flush(&walk, direction.y);
    let phase = henyey_greenstein(fog_pass.fog.sun_colour.w, dot(direction, fog_pass.fog.sun_direction.xyz));
    return fog_pass.fog.sun_colour.rgb * phase * walk.held;
}
#endif

#ifdef SUN_SHADOWS
// Equal steps over the stretch of a ray Bevy's cascades reach, the changes
// of the sun's visibility between two of them that are bisected (after the
// march, out of its divergent loop; later ones are taken at their steps'
// middles), and the bisections of each.
const SUN_SHADOW_STEPS: u32 = 32u;
const SUN_SHADOW_CHANGES: u32 = 8u;
const SUN_SHADOW_BISECTIONS: u32 = 6u;
// Weights closer than this are taken as equal.
const SUN_SHADOW_EPSILON: f32 = 1.0e-3;

// The share of the sunlight Bevy's map of the sun (light `sun`) holds back
// at `t` along the ray `direction` (`forward` its view depth per metre):
// 1 − V, and none in the terrain's shadow.
fn sun_shadow_weight(sun: u32, direction: vec3<f32>, forward: f32, t: f32) -> f32 {
    let p = fog_pass.camera_position.xyz + t * direction;
    return select(1.0 - sun_visibility(sun, p, t * forward), 0.0, in_terrain_shadow(p));
}

// The sunlight Bevy's map of the sun holds back from the fog over [t0, t1]
// along the ray `direction` (see the header).
fn sun_shadow_held_back(direction: vec3<f32>, t0: f32, t1: f32) -> vec3<f32> {
    let sun = shadowed_sun(fog_pass.fog.sun_direction.xyz);
    // View depth per metre along the ray (the view looks down its −z).
    let forward = -dot(direction, fog_pass.world_from_view[2].xyz);
    var b = t1;
    if forward > 0.0 {
        b = min(b, sun_shadow_reach(sun) / forward);
    }
    if !(b > t0) {
        return vec3(0.0);
    }
    // The march: where the weight changes, (step's start, end, weight
    // before, weight after).
    let step = (b - t0) / f32(SUN_SHADOW_STEPS);
    let first = sun_shadow_weight(sun, direction, forward, t0);
    var changes: array<vec4<f32>, SUN_SHADOW_CHANGES>;
    var count = 0u;
    var weight = first;
    var before = t0;
    var held = 0.0;
    var start = t0;
    var start_weight = first;
    for (var k = 1u; k <= SUN_SHADOW_STEPS; k++) {
        let t = select(t0 + step * f32(k), b, k == SUN_SHADOW_STEPS);
        let next = sun_shadow_weight(sun, direction, forward, t);
        if abs(next - weight) > SUN_SHADOW_EPSILON {
            if count < SUN_SHADOW_CHANGES {
                changes[count] = vec4(before, t, weight, next);
                count++;
            }
        }
        weight = next;
        before = t;
    }
    let d_y = direction.y;
    for (var i = 0u; i < count; i++) {
        let change = changes[i];
        var low = change.x;
        var high = change.y;
        let middle = 0.5 * (change.z + change.w);
        for (var n = 0u; n < SUN_SHADOW_BISECTIONS; n++) {
            let m = 0.5 * (low + high);
            if (sun_shadow_weight(sun, direction, forward, m) > middle) == (change.z > middle) {
                low = m;
            } else {
                high = m;
            }
        }
        let crossing = 0.5 * (low + high);
        if start_weight > 0.0 {
            held += start_weight * (sunlight_to(d_y, crossing) - sunlight_to(d_y, start));
        }
        start = crossing;
        start_weight = change.w;
    }
    if count == SUN_SHADOW_CHANGES {
        // More changes than are bisected: the rest of the ray by the
        // steps' weights, each change at its step's middle.
        weight = start_weight;
        before = changes[SUN_SHADOW_CHANGES - 1u].y;
        for (var k = 1u; k <= SUN_SHADOW_STEPS; k++) {
            let t = select(t0 + step * f32(k), b, k == SUN_SHADOW_STEPS);
            if t <= before {
                continue;
            }
            let next = sun_shadow_weight(sun, direction, forward, t);
            if abs(next - weight) > SUN_SHADOW_EPSILON {
                let crossing = t - 0.5 * step;
                if weight > 0.0 {
                    held += weight * (sunlight_to(d_y, crossing) - sunlight_to(d_y, start));
                }
                start = crossing;
                weight = next;
            }
        }
        start_weight = weight;
    }
    if start_weight > 0.0 {
        held += start_weight * (sunlight_to(d_y, b) - sunlight_to(d_y, start));
    }
    let phase = henyey_greenstein(fog_pass.fog.sun_colour.w, dot(direction, fog_pass.fog.sun_direction.xyz));
    return fog_pass.fog.sun_colour.rgb * phase * held;
}
#endif

#ifdef LOCAL_LIGHTS
// The optical depth, plus exponential falloff times the altitude crossed,
// per piece of a part of a light's stretch.
const MAX_PART_CHANGE: f32 = 0.5;
// The most pieces one part is cut into for that.
const MAX_PART_PIECES: f32 = 64.0;
// The most parts a light's stretch is cut into: every layer bound and
// profile point, and the inner cone's two.
const MAX_LIGHT_PARTS: u32 = 52u;

// The fog at a node `along` metres past the start of a piece (at altitude
// `start_height`) on a ray of vertical direction d_y, at altitude `height`: x its
// density there (a layer's mean over no range), y the optical depth back to
// the piece's start (its altitude range from the rise itself, as
// fog_optical_depth), z that on to the light at altitude `light_height`,
// `to_light` metres away, whatever its distance from the eye.
fn node_fog(start_height: f32, d_y: f32, along: f32, height: f32, light_height: f32, to_light: f32) -> vec3<f32> {
    let rise = d_y * along;
    let low = start_height + min(rise, 0.0);
    var sums = vec3(0.0);
    for (var i = 0u; i < u32(fog_pass.fog.ranges.z); i++) {
        let layer = fog_pass.fog.layers[i];
        sums += vec3(
            layer_mean(fog_pass.fog, layer, height, 0.0),
            layer_mean(fog_pass.fog, layer, low, abs(rise)),
            layer_mean(fog_pass.fog, layer, min(height, light_height), abs(light_height - height)),
        );
    }
    return vec3(sums.x, along * sums.y, to_light * sums.z);
}

// The sum of the exponential layers' falloffs.
fn fog_falloff() -> f32 {
    var falloff = 0.0;
    for (var i = 0u; i < u32(fog_pass.fog.ranges.z); i++) {
        let layer = fog_pass.fog.layers[i];
        falloff += select(0.0, layer.w, layer.x < 0.5);
    }
    return falloff;
}

// `next`, or the distance at which the ray from `altitude` with vertical
// direction `d_y` crosses `kink` if that lies between `after` and `next`.
fn kink_before(kink: f32, altitude: f32, d_y: f32, after: f32, next: f32) -> f32 {
    let t = (kink - altitude) / d_y;
    return select(next, t, t > after && t < next);
}

// The first distance after `after` and before `limit` at which the ray
// crosses an altitude where the density has a jump or a kink (a constant
// layer's bounds, a linear layer's points; nebel_core::height_fog's kinks).
fn next_kink(altitude: f32, d_y: f32, after: f32, limit: f32) -> f32 {
    var next = limit;
    if d_y == 0.0 {
        return next;
    }
    for (var i = 0u; i < u32(fog_pass.fog.ranges.z); i++) {
        let layer = fog_pass.fog.layers[i];
        if layer.x > 0.5 && layer.x < 1.5 {
            next = kink_before(layer.y, altitude, d_y, after, next);
            next = kink_before(layer.z, altitude, d_y, after, next);
        } else if layer.x > 1.5 {
            for (var j = u32(layer.y); j < u32(layer.y) + u32(layer.z); j++) {
                next = kink_before(fog_point(fog_pass.fog, j).x, altitude, d_y, after, next);
            }
        }
    }
    return next;
}

// ∫ ρ(h(t)) e^{−τ(0, t) − τ(x(t), p)} E(t) 4π p_HG dt over [t0, t1] along
// the unit ray `direction` from the eye for light i (see the header).
fn fog_light(i: u32, direction: vec3<f32>, t0: f32, t1: f32) -> vec3<f32> {
    let light = fog_pass.lights.lights[i];
    let eye = fog_pass.camera_position.xyz;
    let altitude = fog_pass.camera_position.y;
    let d_y = direction.y;
    let on_ray = light_on_ray(light, eye, direction);
    let b = min(t1, on_ray.b);
    var start = max(t0, on_ray.a);
    if b <= start {
        return vec3(0.0);
    }
    let falloff = fog_falloff();
    var sum = 0.0;
    for (var part = 0u; part < MAX_LIGHT_PARTS && start < b; part++) {
        var end = next_kink(altitude, d_y, start, b);
        end = select(end, on_ray.inner_start, on_ray.inner_start > start && on_ray.inner_start < end);
        end = select(end, on_ray.inner_end, on_ray.inner_end > start && on_ray.inner_end < end);
        let change = fog_optical_depth(fog_pass.fog, altitude, d_y, start, end) + falloff * (end - start) * abs(d_y);
        let pieces = clamp(ceil(change / MAX_PART_CHANGE), 1.0, MAX_PART_PIECES);
        for (var piece = 0.0; piece < pieces; piece += 1.0) {
            let piece_a = mix(start, end, piece / pieces);
            let piece_b = mix(start, end, (piece + 1.0) / pieces);
            let quadrature = light_quadrature(on_ray, piece_a, piece_b, fog_pass.lights.response.z, fog_pass.lights.quadrature.x);
            let before = fog_optical_depth(fog_pass.fog, altitude, d_y, 0.0, piece_a);
            let start_height = altitude + d_y * piece_a;
            let width = 2.0 * quadrature.half_width;
#ifdef LIGHT_SHADOWS
            var visible = light_visibility_at(light, eye, direction, on_ray.foot, quadrature.h, quadrature.gamma_a);
#endif
            for (var interval = 0u; interval < quadrature.intervals; interval++) {
                let start = quadrature.gamma_a + width * f32(interval);
#ifdef LIGHT_SHADOWS
                // Stretches of the interval with their visibility.
                let cut = visibility_spans(light, eye, direction, on_ray.foot, quadrature.h, start, width, visible);
                visible = cut.end;
                let count = cut.count;
#else
                let count = 1u;
#endif
                for (var span = 0u; span < count; span++) {
#ifdef LIGHT_SHADOWS
                    let gammas = cut.spans[span].xy;
                    let seen = cut.spans[span].z;
#else
                    let gammas = vec2(start, start + width);
                    let seen = 1.0;
#endif
                    let stretch = light_span(quadrature.h, gammas);
                    for (var k = 0u; k < 3u; k++) {
                        let node = light_node(light, on_ray, direction, stretch, 0u, k, fog_pass.lights.response.y);
                        let height = altitude + d_y * node.t;
                        let to_light = length(on_ray.to_light - node.t * direction);
                        let fog = node_fog(start_height, d_y, node.t - piece_a, height, light.position.y, to_light);
                        sum += seen * node.weight * fog.x * exp(-(before + fog.y + fog.z));
                    }
                }
            }
        }
        start = end;
    }
    return light.colour.rgb * sum;
}
#endif

// The fog along the ray `direction` through `ndc` to `depth` (0: nothing
// opaque, to the largest distance), premultiplied.
fn fog_sample(ndc: vec2<f32>, direction: vec3<f32>, depth: f32) -> vec4<f32> {
    var distance = fog_pass.fog.ranges.y;
    if depth > 0.0 {
        let surface = fog_pass.view_from_clip * vec4(ndc, depth, 1.0);
        distance = length(surface.xyz / surface.w);
    }
    let stretch = fog_stretch(fog_pass.fog, fog_pass.camera_position.y, direction, 0.0, distance);
    let alpha = fog_opacity(stretch.w);
    var colour = stretch.rgb;
#ifdef FOG_SUN
    let lit_from = fog_pass.fog.ranges.x;
    let lit_to = min(distance, fog_pass.fog.ranges.y);
    var held = clouds_held_back(direction, lit_from, lit_to) + terrain_held_back(direction, lit_from, lit_to);
#ifdef SUN_SHADOWS
    held += sun_shadow_held_back(direction, lit_from, lit_to);
#endif
    colour = max(colour - held, vec3(0.0));
#endif
#ifdef LOCAL_LIGHTS
    let t0 = fog_pass.fog.ranges.x;
    let t1 = min(distance, fog_pass.fog.ranges.y);
    var lit = vec3(0.0);
    for (var i = 0u; i < min(u32(fog_pass.lights.response.x), #{MAX_LOCAL_LIGHTS}u); i++) {
        lit += fog_light(i, direction, t0, t1);
    }
    colour += fog_pass.lights.response.w * fog_pass.fog.colour.rgb * lit;
#endif
    return vec4(colour, alpha);
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
    // The resolved pixel averages its samples, each fogged to its own depth
    // (a sample at the depth of the one before it takes its fog).
    let samples = textureNumSamples(depth_texture);
    var depth = textureLoad(depth_texture, pixel, 0).r;
    var sample = fog_sample(ndc, direction, depth);
    var fog = sample;
    for (var i = 1u; i < samples; i++) {
        let next = textureLoad(depth_texture, pixel, i32(i)).r;
        if next != depth {
            depth = next;
            sample = fog_sample(ndc, direction, depth);
        }
        fog += sample;
    }
    fog /= f32(samples);
#else
    let fog = fog_sample(ndc, direction, textureLoad(depth_texture, pixel, 0).r);
#endif
    if fog.a <= 0.0 {
        discard;
    }
    return fog;
}
