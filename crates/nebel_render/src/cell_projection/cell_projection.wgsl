// Cell projection with exact per-pixel ray-tetrahedron segments (Röttger,
// "Volumetric Methods for the Real-Time Display of Natural Gaseous Phenomena",
// 2004, ch. 8-9 and 10.3; Röttger and Ertl, "Fast Volumetric Display of
// Natural Gaseous Phenomena", 2003, §4).
//
// Every tetrahedron is drawn as its back faces only (the faces whose plane has
// the eye on the inner side; the rasterizer culls the others), so each pixel it
// covers runs this fragment shader exactly once, also when the eye is inside
// the cell. The fragment intersects
// the pixel's view ray with the cell's four face planes: entry and exit
// distance, clipped to the near plane and to the opaque scene depth, give the
// segment length l; the cell's linear scalar at entry and exit gives s_f and
// s_b. The segment's colour comes from the pre-integration tables:
//
//   SORTED:   optical depth τ = l ρ̂(s_f, s_b), α = 1 − exp(−τ) (exact opacity,
//             Röttger 2004 eq. 9.2), rgb = α K with K the mean chromaticity from
//             the 3D table at (s_f, s_b, u = τ / (1 + τ)), blended "under"
//             front to back: C += T rgb, T *= 1 − α.
//   EMISSIVE: rgb = l · mean emission(s_f, s_b), added as T rgb (PCP).
//   MIP:      rgb = max emission over [s_f, s_b], blended with max.
//
// A batch's cells are stored back to front (its exact visibility order);
// instance i draws cell n − 1 − i, so the batch goes front to back.
//
// MODULATED (lit clouds, Röttger and Ertl 2003 §5.1 Eq. 9): a second linear field m per
// cell scales the segment length before the lookups, l' = l (m_f + m_b) / 2,
// in MODULATOR_PIECES equal pieces of the segment (a shader def, from
// nebel_core::optics::MODULATOR_PIECES), each with its own mean m,
// composited front to back: the mean over the whole segment put the opacity
// of a cell's dense end into its light end too, and differently for every
// split of the segments (a refined octree splits them differently).
//
// SCATTERING (single scattering of the sun, Nes 2008; sorted only): the
// table's colour C is the sunlight scattered along the segment (its
// transfer function is over the transmittance toward the sun), and the
// segment's colour is ambient · α + sun · 4π p_HG(θ) · C, θ between the view
// ray and the sunlight, constant along the ray.
//
// LOCAL_LIGHTS (point and spot lights reach a sorted batch,
// nebel_render::local_lights): each light's single scattering is added to
// the segment's colour, s ∫ σ κ T E 4π p_HG dt (s the batch's factor on its
// colour), in LIGHT_PIECES equal pieces,
// each with its own optical depth rate σ and mean chromaticity κ (white
// under SCATTERING, whose colour is the sun's light), its transmittance
// e^{−σ (t − t_a)} inside, and one interval of three Gauss-Legendre nodes in
// the angle at which the light sees the ray, which takes the inverse square
// out exactly (nebel_core::local_light::LocalLight::scattered with one interval).
//
// LIGHT_SHADOWS (a light that reaches the batch casts shadows): the light
// is weighted by its visibility V, Bevy's shadow map of the light at the
// point, compared in 2×2 by the hardware, the point moved toward the light
// by the light's depth bias (a medium has no surface normal): light shafts
// behind opaque geometry. V is read at the ends and the middle of each
// interval in the angle; where it changes, the crossing is bisected and
// each side integrated with its own V, so a shadow's edge is placed to
// 1/128 of an interval (a shadow within half an interval may be missed).
//
// GROUND_SUN (the sun lights a ground fog, nebel_render::fog_sunlight): the
// sun's single scattering c ⊙ 4π p_HG(θ) ∫ σ κ T V T_sun dt is added with the
// segment's mean colour κ̄, in LIGHT_PIECES equal pieces, each with its
// optical depth rate σ from the pair table and three Gauss-Legendre nodes of
// σ e^{−σ (t − t_a)} V T_sun behind the pieces in front: V is 0 below the terrain's shadow height,
// T_sun = e^{−s H F(u)/μ} the fog above the point (ground, thickness and
// shadow height bilinear from the sun map, F linear from its table) times the
// clouds' shadow maps where the line toward the sun crosses their plane.
// SUN_SHADOWS (the sun casts shadows): V is also Bevy's cascaded shadow map
// of the sun (nebel_render::light_shadows), read at the ends of each piece
// and, where they differ, at its nodes: opaque meshes shade the fog too (a
// shadow within a piece whose ends are lit may be missed). Under SCATTERING
// (SCATTERED_SUN_SHADOWS) each modulator piece's sunlight, or an unmodulated
// segment's, is weighted by V at its middle; the sky's light stays.
//
// FOG_LAYERS (the view has fog layers, Röttger 2004 §5.3): the segment is
// seen through the fog in front of it. As maps of the radiance behind, a
// segment x ↦ C + (1 − α) x among fog pieces x ↦ F + T x equals the segment
// conjugated by the fog from the eye, (T C + α F, α), followed by the fog
// from the eye to the end of the ray, which the fog-layer pass has already
// put over the scene; so the conjugated segments accumulate and composite
// as before. T and F are taken at the segment's middle: inside the segment
// the two media overlap, and the middle is Strang splitting, exact to
// second order in their optical depths. F = c (1 − T), c the fog's colour
// along the ray (its glow and sunlight, without the clouds' shadow on it).
// Emissive and MIP segments (α = 0) are scaled by T.
//
// FOG_HANDOFF (a batch of fog the view's fog layers take over from their
// start distance): segments end at that distance.
//
// BLENDED (two keyframes of an animated field): every vertex's scalar and
// modulator is (1 − t) current + t next, the field at the two ends of the
// batch's span of keyframe blends mixed; both stay linear over the cell, so
// the segment is exactly that of the mixed field.
//
// MERGED (the batch overlaps others, merge.rs): drawn alone into a layer of
// its own, with a second target that keeps the span of its segments along
// the ray; cell_merge.wgsl composites the layers jointly.
//
// LOW_RESOLUTION (the view draws cells at a fraction of its resolution,
// low_resolution.wgsl): the viewport and the opaque depth are the
// low-resolution target's.
//
// RAY_CAST (a whole density grid, nebel_lod's cell_grid): instead of cells,
// the grid's box is drawn as its back faces, and each fragment walks its
// ray through the voxels (Amanatides and Woo 1987), splitting each voxel's
// stretch where the ray crosses the planes u_a = u_b between Kuhn's six
// tetrahedra: the pieces are exactly the segments of the grid's tetrahedra,
// front to back, each shaded as above (MODULATED: with the modulator at the
// grid's points, linear over the same tetrahedra; BLENDED: every point's
// values mixed toward the next keyframe's) and composited under the ones in
// front; the ray stops once its transmittance is below the early
// termination's threshold; it jumps over bricks without opacity under the
// transfer function (their segments add nothing).
//
// All positions are taken relative to the camera so large world coordinates
// keep their precision.

#import nebel_render::fog_layers::{FogLayers, fog_stretch}
#import nebel_render::local_lights::{GAUSS_NODES, GAUSS_WEIGHTS, LocalLights, henyey_greenstein, light_interval, light_on_ray, light_quadrature}
#ifdef SHADOW_MAPS
#import nebel_render::light_shadows::{SHADOW_EPSILON, light_visibility_at, shadowed_sun, sun_visibility, visibility_spans}
#endif
#import nebel_render::cloud_shadow_maps::{CloudShadowMapPair, cloud_transmittance}

struct CellView {
    clip_from_world: mat4x4<f32>,
    world_from_clip: mat4x4<f32>,
    camera_position: vec4<f32>,
    // xyz: the view's forward axis (view depth per unit along it).
    forward: vec4<f32>,
    // x, y, width, height of the viewport in pixels.
    viewport: vec4<f32>,
    // The view's fog layers (read only by the FOG_LAYERS variant).
    fog: FogLayers,
}

struct Cell {
    // xyz: world position, w: scalar in [0, 1].
    vertices: array<vec4<f32>, 4>,
}

struct FogSun {
    // World position to the sun map's grid: x and z in grid points, y the
    // height in the terrain's frame.
    grid_from_world: mat4x4<f32>,
    // xyz: unit direction toward the sun; w: Henyey-Greenstein asymmetry g.
    sun: vec4<f32>,
    // rgb: the sunlight's colour; w: s/μ, its slant through a level layer (s
    // the world length of the map's unit of height, μ the sun's sine now).
    colour: vec4<f32>,
    // x: tan α − tan α₀, the sun's elevation now against the map's: the
    // shadow heights move by −t* times it.
    elevation: vec4<f32>,
    // The fog's column F(u) at 65 equal steps of u, four to an element.
    column: array<vec4<f32>, 17>,
    // The clouds' shadow maps (no weight without clouds).
    clouds: CloudShadowMapPair,
}

struct CellTables {
    // Samples along s_f and s_b.
    scalar_size: u32,
    // Samples along u = τ / (1 + τ).
    depth_size: u32,
}

@group(0) @binding(0) var<uniform> view: CellView;
#ifdef LOW_RESOLUTION
// The opaque depth of each low-resolution pixel (low_resolution.wgsl).
@group(0) @binding(1) var depth_texture: texture_2d<f32>;
#else ifdef MULTISAMPLED
@group(0) @binding(1) var depth_texture: texture_depth_multisampled_2d;
#else
@group(0) @binding(1) var depth_texture: texture_depth_2d;
#endif

#ifdef COUNT_FRAGMENTS
// Fragments run, for the fragments-per-pixel diagnostic (a debug setting).
@group(0) @binding(2) var<storage, read_write> fragment_count: atomic<u32>;
#endif

#ifdef GROUND_SUN
// Per grid point of the sun map: (shadow height, ground, thickness, the
// distance t* of the shadow's caster).
@group(1) @binding(7) var sun_map: texture_2d<f32>;
// The clouds' shadow maps (nebel_render::cloud_shadow_maps).
@group(1) @binding(8) var first_cloud_map: texture_2d<f32>;
@group(1) @binding(9) var second_cloud_map: texture_2d<f32>;
@group(1) @binding(10) var cloud_map_sampler: sampler;
#endif

fn opaque_depth(pixel: vec2<i32>) -> f32 {
#ifdef LOW_RESOLUTION
    return textureLoad(depth_texture, pixel, 0).r;
#else
    return textureLoad(depth_texture, pixel, 0);
#endif
}

#ifdef RAY_CAST
// The grid's scalars, x fastest (nebel_core's DensityGrid); BLENDED: each
// beside the next keyframe's.
#ifdef BLENDED
@group(1) @binding(0) var<storage, read> grid_values: array<vec2<f32>>;
#else
@group(1) @binding(0) var<storage, read> grid_values: array<f32>;
#endif
#else
@group(1) @binding(0) var<storage, read> cells: array<Cell>;
#endif
@group(1) @binding(1) var colour_table: texture_3d<f32>;
@group(1) @binding(2) var pair_table: texture_2d<f32>;
@group(1) @binding(3) var<uniform> tables: CellTables;
#ifdef RAY_CAST
// Where the grid lies.
struct CellGrid {
    // Grid index coordinates to world.
    world_from_index: mat4x4<f32>,
    // World offsets to index offsets (the linear part only).
    index_from_world: mat4x4<f32>,
    // xyz: voxels per axis; w: 1 when world_from_index mirrors.
    voxels: vec4<u32>,
    // xyz: bricks per axis of `occupied`; w: voxels per brick edge.
    bricks: vec4<u32>,
    // x: the value at or below which the grid has no opacity (negative for
    // none); y: 1 when that value is the modulator's, 0 the scalar's.
    clear: vec4<f32>,
#ifdef MODULATED
    // The modulator at each point, as the scalars.
#ifdef BLENDED
    modulators: array<vec2<f32>>,
#else
    modulators: array<f32>,
#endif
#endif
}
@group(1) @binding(4) var<storage, read> grid: CellGrid;
#else
// Per cell, the segment-length modulator at its four vertices (read only by
// the MODULATED variant).
@group(1) @binding(4) var<storage, read> modulators: array<vec4<f32>>;
#endif

// Per batch: the sun and sky of single scattering (read only by the
// SCATTERING variant) and the keyframe mix factor (BLENDED).
struct CellBatchParameters {
    // xyz: unit direction toward the sun; w: Henyey-Greenstein asymmetry g.
    sun: vec4<f32>,
    sun_colour: vec4<f32>,
    ambient_colour: vec4<f32>,
    // x: the mix factor t toward the next scalars (the end of the batch's
    // span of keyframe blends).
    blend: vec4<f32>,
    // rgb: the sunlight's colour and strength as a factor on lit colours.
    sunlight: vec4<f32>,
    // The local lights that reach the batch (read only by the LOCAL_LIGHTS
    // variant).
    lights: LocalLights,
    // The sun in ground fog (read only by the GROUND_SUN variant).
    fog_sun: FogSun,
}
@group(1) @binding(5) var<uniform> parameters: CellBatchParameters;
#ifdef RAY_CAST
// Per brick of the grid (x fastest), 1 where it may have opacity.
@group(1) @binding(6) var<storage, read> occupied: array<u32>;
#else
// Per cell, the next keyframe's scalars (entry 2i) and modulators (2i + 1) at
// its four vertices (read only by the BLENDED variant).
@group(1) @binding(6) var<storage, read> next_keyframe: array<vec4<f32>>;
#endif

// The three vertices of face f, which omits vertex f.
const FACE_VERTICES = array<u32, 12>(1u, 2u, 3u, 0u, 3u, 2u, 0u, 1u, 3u, 0u, 2u, 1u);

struct VertexOutput {
    @builtin(position) clip_position: vec4<f32>,
    // Position on the face relative to the camera.
    @location(0) relative_position: vec3<f32>,
    @location(1) @interpolate(flat) cell_index: u32,
}

#ifdef RAY_CAST
// The grid box's twelve triangles, corners x + 2y + 4z of the index box,
// each wound with its normal pointing inward like a cell's faces, so the
// rasterizer keeps the back faces: every pixel of the box runs once.
const BOX_TRIANGLES = array<u32, 36>(
    0u, 2u, 4u, 2u, 6u, 4u, 1u, 5u, 3u, 3u, 5u, 7u, 0u, 4u, 1u, 1u, 4u, 5u,
    2u, 3u, 6u, 3u, 7u, 6u, 0u, 1u, 2u, 1u, 3u, 2u, 4u, 6u, 5u, 5u, 6u, 7u,
);

@vertex
fn vertex(@builtin(vertex_index) vertex_index: u32) -> VertexOutput {
    // A mirroring placement turns the winding: swap each triangle's last two.
    var index = vertex_index;
    if grid.voxels.w == 1u && index % 3u != 0u {
        index = select(index + 1u, index - 1u, index % 3u == 2u);
    }
    let corner = BOX_TRIANGLES[index];
    let bits = vec3<u32>(corner & 1u, (corner >> 1u) & 1u, corner >> 2u);
    let position = (grid.world_from_index * vec4(vec3<f32>(bits * grid.voxels.xyz), 1.0)).xyz;
    var out: VertexOutput;
    out.cell_index = 0u;
    out.relative_position = position - view.camera_position.xyz;
    out.clip_position = view.clip_from_world * vec4(position, 1.0);
    return out;
}
#else
fn relative_vertex(cell: Cell, index: u32) -> vec3<f32> {
    return cell.vertices[index].xyz - view.camera_position.xyz;
}

// Outward normal of face f (not normalised), with the camera at the origin.
fn outward_normal(cell: Cell, face: u32) -> vec3<f32> {
    let a = relative_vertex(cell, FACE_VERTICES[face * 3u]);
    let b = relative_vertex(cell, FACE_VERTICES[face * 3u + 1u]);
    let c = relative_vertex(cell, FACE_VERTICES[face * 3u + 2u]);
    let n = cross(b - a, c - a);
    let opposite = relative_vertex(cell, face);
    return select(n, -n, dot(n, opposite - a) > 0.0);
}

@vertex
fn vertex(@builtin(vertex_index) vertex_index: u32, @builtin(instance_index) instance_index: u32) -> VertexOutput {
    let cell_index = arrayLength(&cells) - 1u - instance_index;
    // One instance per cell, drawn as the triangle strip 0 1 2 3 0 1, which
    // covers the four faces. With the cell positively oriented (v0 and v1
    // swapped otherwise) every face winds with its normal pointing inward, so
    // the rasterizer keeps exactly the back faces (counter-clockwise on
    // screen) and culls the front ones; two cells sharing a face see it with
    // opposite winding, so the choice is watertight.
    let cell = cells[cell_index];
    let v0 = relative_vertex(cell, 0u);
    let orientation = dot(relative_vertex(cell, 1u) - v0, cross(relative_vertex(cell, 2u) - v0, relative_vertex(cell, 3u) - v0));
    var strip = array<u32, 6>(0u, 1u, 2u, 3u, 0u, 1u);
    if orientation < 0.0 {
        strip = array<u32, 6>(1u, 0u, 2u, 3u, 1u, 0u);
    }
    let vertex = cell.vertices[strip[vertex_index]].xyz;

    var out: VertexOutput;
    out.cell_index = cell_index;
    out.relative_position = vertex - view.camera_position.xyz;
    out.clip_position = view.clip_from_world * vec4(vertex, 1.0);
    return out;
}

#endif

// Distance along the unit ray `direction` from the camera to the point at NDC
// (x, y, depth).
fn ray_distance_at_depth(ndc: vec2<f32>, depth: f32) -> f32 {
    let world = view.world_from_clip * vec4(ndc, depth, 1.0);
    return length(world.xyz / world.w - view.camera_position.xyz);
}

// The angle between the unit ray `direction` through NDC `ndc` and the ray
// through the pixel above it, radians.
fn pixel_angle(ndc: vec2<f32>, direction: vec3<f32>) -> f32 {
    let above = view.world_from_clip * vec4(ndc.x, ndc.y + 2.0 / view.viewport.w, 1.0, 1.0);
    return length(normalize(above.xyz / above.w - view.camera_position.xyz) - direction);
}

// The NDC of a fragment's pixel centre in the view's viewport.
fn pixel_ndc(clip_position: vec4<f32>) -> vec2<f32> {
    return vec2(
        (clip_position.x - view.viewport.x) / view.viewport.z * 2.0 - 1.0,
        1.0 - (clip_position.y - view.viewport.y) / view.viewport.w * 2.0,
    );
}

// Table coordinates: node i at s = i / (n − 1); returns the lower node and the weight of the upper.
fn table_position(x: f32, nodes: u32) -> vec2<f32> {
    let scaled = clamp(x, 0.0, 1.0) * f32(nodes - 1u);
    let lower = min(floor(scaled), f32(nodes - 2u));
    return vec2(lower, scaled - lower);
}

fn pair_lookup(s_front: f32, s_back: f32) -> vec4<f32> {
    let x = table_position(s_front, tables.scalar_size);
    let y = table_position(s_back, tables.scalar_size);
    let i = vec2<i32>(i32(x.x), i32(y.x));
    let v00 = textureLoad(pair_table, i, 0);
    let v10 = textureLoad(pair_table, i + vec2(1, 0), 0);
    let v01 = textureLoad(pair_table, i + vec2(0, 1), 0);
    let v11 = textureLoad(pair_table, i + vec2(1, 1), 0);
    return mix(mix(v00, v10, x.y), mix(v01, v11, x.y), y.y);
}

// The mean chromaticity K of a sorted segment of optical depth τ (+∞ reads the
// last node: 1 / (1 + τ) is 0 there).
fn colour_lookup(s_front: f32, s_back: f32, depth: f32) -> vec3<f32> {
    let x = table_position(s_front, tables.scalar_size);
    let y = table_position(s_back, tables.scalar_size);
    let z = table_position(1.0 - 1.0 / (1.0 + depth), tables.depth_size);
    let i = vec3<i32>(i32(x.x), i32(y.x), i32(z.x));
    var layers: array<vec4<f32>, 2>;
    for (var dz = 0; dz < 2; dz++) {
        let v00 = textureLoad(colour_table, i + vec3(0, 0, dz), 0);
        let v10 = textureLoad(colour_table, i + vec3(1, 0, dz), 0);
        let v01 = textureLoad(colour_table, i + vec3(0, 1, dz), 0);
        let v11 = textureLoad(colour_table, i + vec3(1, 1, dz), 0);
        layers[dz] = mix(mix(v00, v10, x.y), mix(v01, v11, x.y), y.y);
    }
    return mix(layers[0], layers[1], z.y).rgb;
}

#ifdef LOCAL_LIGHTS
// ∫ σ e^{−σ (t − t_a)} E(x(t)) 4π p_HG(θ(t)) dt over the piece [t_a, t_b]
// along the unit ray `direction` from the eye for light i: over the part
// inside its stretch on the ray, cut at the inner cone (whose factor has a
// kink there), each part in intervals in the angle no wider than the
// batch's, as nebel_core::local_light::LocalLight::scattered with one
// interval; under LIGHT_SHADOWS each node weighted by its shadow map.
fn light_piece(i: u32, direction: vec3<f32>, t_a: f32, t_b: f32, sigma: f32) -> vec3<f32> {
    let light = parameters.lights.lights[i];
    let on_ray = light_on_ray(light, view.camera_position.xyz, direction);
    let a = max(t_a, on_ray.a);
    let b = min(t_b, on_ray.b);
    if b <= a {
        return vec3(0.0);
    }
    var cuts = array<f32, 4>(a, clamp(on_ray.inner_start, a, b), max(clamp(on_ray.inner_end, a, b), clamp(on_ray.inner_start, a, b)), b);
    var sum = 0.0;
    for (var part = 0u; part < 3u; part++) {
        if cuts[part + 1u] <= cuts[part] {
            continue;
        }
        let quadrature = light_quadrature(on_ray, cuts[part], cuts[part + 1u], parameters.lights.response.z, parameters.lights.quadrature.x);
        let width = 2.0 * quadrature.half_width;
#ifdef LIGHT_SHADOWS
        let eye = view.camera_position.xyz;
        var visible = light_visibility_at(light, eye, direction, on_ray.foot, quadrature.h, quadrature.gamma_a);
#endif
        for (var interval = 0u; interval < quadrature.intervals; interval++) {
            let start = quadrature.gamma_a + width * f32(interval);
#ifdef LIGHT_SHADOWS
            // Stretches of the interval with their visibility.
            let cut = visibility_spans(light, eye, direction, on_ray.foot, quadrature.h, start, width, visible);
            visible = cut.end;
            for (var span = 0u; span < cut.count; span++) {
                sum += cut.spans[span].z * light_interval(light, on_ray, direction, quadrature.h, cut.spans[span].xy, t_a, sigma, parameters.lights.response.y);
            }
#else
            sum += light_interval(light, on_ray, direction, quadrature.h, vec2(start, start + width), t_a, sigma, parameters.lights.response.y);
#endif
        }
    }
    return light.colour.rgb * sum;
}

#endif

#ifdef SCATTERED_LIGHT
// The optical depth of the piece from a to b (fractions of the segment from
// s_front to s_back, with modulator m_front to m_back) of length
// `piece_length`: its mean modulator times its mean density from the pair
// table.
fn piece_depth(s_front: f32, s_back: f32, m_front: f32, m_back: f32, piece_length: f32, a: f32, b: f32) -> f32 {
    return piece_length * 0.5 * (mix(m_front, m_back, a) + mix(m_front, m_back, b))
        * pair_lookup(mix(s_front, s_back, a), mix(s_front, s_back, b)).a;
}
#endif

#ifdef SHADOW_MAPS
// Bevy's shadow map of the directional light `sun` (shadowed_sun) at
// distance `t` along the unit ray `direction` from the eye, its cascade the
// one for that point's view depth.
fn sun_visible_at(sun: u32, direction: vec3<f32>, t: f32) -> f32 {
    return sun_visibility(sun, view.camera_position.xyz + t * direction, t * dot(direction, view.forward.xyz));
}
#endif

#ifdef GROUND_SUN
// The clouds' transmittance toward the sun at the world point `p`.
fn cloud_sun_transmittance(p: vec3<f32>) -> f32 {
    return cloud_transmittance(parameters.fog_sun.clouds, first_cloud_map, second_cloud_map, cloud_map_sampler, p);
}

// The sun's transmittance at the world point `p`: 0 below the terrain's
// shadow height, else e^{−H F(u)/μ} (nebel_core::fog_sunlight::FogSunMap)
// times the clouds'.
fn ground_sun_transmittance(p: vec3<f32>) -> f32 {
    let q = (parameters.fog_sun.grid_from_world * vec4(p, 1.0)).xyz;
    let size = vec2<i32>(textureDimensions(sun_map));
    let g = clamp(q.xz, vec2(0.0), vec2<f32>(size - 1));
    let corner = min(vec2<i32>(floor(g)), size - 2);
    let f = g - vec2<f32>(corner);
    let row0 = mix(textureLoad(sun_map, corner, 0), textureLoad(sun_map, corner + vec2(1, 0), 0), f.x);
    let row1 = mix(textureLoad(sun_map, corner + vec2(0, 1), 0), textureLoad(sun_map, corner + vec2(1, 1), 0), f.x);
    let texel = mix(row0, row1, f.y);
    if q.y < texel.x - texel.w * parameters.fog_sun.elevation.x {
        return 0.0;
    }
    if texel.z <= 0.0 {
        return cloud_sun_transmittance(p);
    }
    let x = clamp((q.y - texel.y) / texel.z, 0.0, 1.0) * 64.0;
    let k = min(u32(x), 63u);
    let column = mix(
        parameters.fog_sun.column[k / 4u][k % 4u],
        parameters.fog_sun.column[(k + 1u) / 4u][(k + 1u) % 4u],
        x - f32(k),
    );
    return exp(-texel.z * column * parameters.fog_sun.colour.w) * cloud_sun_transmittance(p);
}

// The sun's single scattering by the segment from s_front to s_back (with
// modulator m_front to m_back) of mean colour `kappa` from t_front to t_back
// along the unit ray `direction` (see the header): in LIGHT_PIECES equal
// pieces, each with its own optical depth rate σ from the pair table and
// three Gauss-Legendre nodes of σ e^{−σ (t − t_a)} V T_sun behind the
// pieces in front.
fn ground_sun_colour(
    kappa: vec3<f32>,
    s_front: f32,
    s_back: f32,
    m_front: f32,
    m_back: f32,
    t_front: f32,
    t_back: f32,
    direction: vec3<f32>,
) -> vec3<f32> {
    let sun = parameters.fog_sun.sun;
    let phase = henyey_greenstein(sun.w, dot(direction, sun.xyz));
#ifdef SUN_SHADOWS
    let shadowing = shadowed_sun(sun.xyz);
    var visible = sun_visible_at(shadowing, direction, t_front);
#endif
    let pieces = f32(#{LIGHT_PIECES}u);
    let half = 0.5 * (t_back - t_front) / pieces;
    var sum = 0.0;
    var transmittance = 1.0;
    for (var piece = 0u; piece < #{LIGHT_PIECES}u; piece++) {
        let a = f32(piece) / pieces;
        let b = f32(piece + 1u) / pieces;
        let depth = piece_depth(s_front, s_back, m_front, m_back, 2.0 * half, a, b);
        let sigma = depth / (2.0 * half);
        let middle = mix(t_front, t_back, a) + half;
#ifdef SUN_SHADOWS
        let visible_end = sun_visible_at(shadowing, direction, middle + half);
        let changes = abs(visible_end - visible) >= SHADOW_EPSILON;
#endif
        for (var k = 0u; k < 3u; k++) {
            let offset = half * (1.0 + GAUSS_NODES[k]);
            let t = middle + half * GAUSS_NODES[k];
            let p = view.camera_position.xyz + t * direction;
            var lit = ground_sun_transmittance(p);
#ifdef SUN_SHADOWS
            if changes {
                lit *= sun_visible_at(shadowing, direction, t);
            } else {
                lit *= visible;
            }
#endif
            sum += transmittance * GAUSS_WEIGHTS[k] * half * sigma * exp(-sigma * offset) * lit;
        }
#ifdef SUN_SHADOWS
        visible = visible_end;
#endif
        transmittance *= exp(-depth);
    }
    return parameters.fog_sun.colour.rgb * phase * sum * kappa;
}
#endif

#ifdef LOCAL_LIGHTS
// The local lights scattered toward the eye by the segment from t_front to
// t_back (see the header), premultiplied as its colour: nothing is looked up
// for a segment no light's stretch on the ray reaches, and a piece's colour
// only where one does.
fn local_light_colour(
    s_front: f32,
    s_back: f32,
    m_front: f32,
    m_back: f32,
    t_front: f32,
    t_back: f32,
    direction: vec3<f32>,
) -> vec3<f32> {
    let count = min(u32(parameters.lights.response.x), #{MAX_LOCAL_LIGHTS}u);
    // (Taken again per piece: an array of them costs CPU drivers more.)
    var reach = vec2(3.0e38, -3.0e38);
    for (var i = 0u; i < count; i++) {
        let on_ray = light_on_ray(parameters.lights.lights[i], view.camera_position.xyz, direction);
        if on_ray.b > on_ray.a {
            reach = vec2(min(reach.x, on_ray.a), max(reach.y, on_ray.b));
        }
    }
    if reach.x >= t_back || reach.y <= t_front {
        return vec3(0.0);
    }
    let span = t_back - t_front;
    var colour = vec3(0.0);
    var transmittance = 1.0;
    for (var piece = 0u; piece < #{LIGHT_PIECES}u; piece++) {
        let a = f32(piece) / f32(#{LIGHT_PIECES}u);
        let b = f32(piece + 1u) / f32(#{LIGHT_PIECES}u);
        let t_a = t_front + span * a;
        let piece_length = span * (b - a);
        if t_a >= reach.y {
            break;
        }
        let s_a = mix(s_front, s_back, a);
        let s_b = mix(s_front, s_back, b);
        let depth = piece_depth(s_front, s_back, m_front, m_back, piece_length, a, b);
        if depth > 0.0 && piece_length > 0.0 && t_a + piece_length > reach.x {
            var light = vec3(0.0);
            for (var i = 0u; i < count; i++) {
                light += light_piece(i, direction, t_a, t_a + piece_length, depth / piece_length);
            }
#ifdef SCATTERING
            colour += transmittance * light;
#else
            if any(light > vec3(0.0)) {
                colour += transmittance * colour_lookup(s_a, s_b, depth) * light;
            }
#endif
        }
        transmittance *= exp(-depth);
    }
    return parameters.lights.response.w * colour;
}
#endif

// The premultiplied colour and opacity of a segment from s_front to s_back
// (with modulator m_front to m_back under MODULATED) from distance t_front
// to t_back along the unit ray `direction` from the eye, seen through the
// fog layers in front of it from its middle (see the header).
fn segment_colour(
    s_front: f32,
    s_back: f32,
    m_front: f32,
    m_back: f32,
    t_front: f32,
    t_back: f32,
    direction: vec3<f32>,
) -> vec4<f32> {
    let segment_length = t_back - t_front;
    let middle = 0.5 * (t_front + t_back);
#ifdef SORTED
#ifdef SCATTERED_SUN_SHADOWS
    let sun_shadowing = shadowed_sun(parameters.sun.xyz);
#endif
#ifdef MODULATED
    // A modulator of 0 at both ends gives the segment no length: nothing to
    // look up (the modulators are clamped to [0, 1]).
    if max(m_front, m_back) <= 0.0 {
        return vec4(0.0);
    }
    // Piece by piece, front to back: premultiplied colour and transmittance;
    // a piece without optical depth adds nothing.
    var colour = vec3(0.0);
    var transmittance = 1.0;
    for (var piece = 0u; piece < #{MODULATOR_PIECES}u; piece++) {
        let a = f32(piece) / f32(#{MODULATOR_PIECES}u);
        let b = f32(piece + 1u) / f32(#{MODULATOR_PIECES}u);
        let s_a = mix(s_front, s_back, a);
        let s_b = mix(s_front, s_back, b);
        let modulated = segment_length * (b - a) * 0.5 * (mix(m_front, m_back, a) + mix(m_front, m_back, b));
        let depth = modulated * pair_lookup(s_a, s_b).a;
        if depth > 0.0 {
            let piece_alpha = 1.0 - exp(-depth);
            var piece_colour = colour_lookup(s_a, s_b, depth);
#ifdef SCATTERED_SUN_SHADOWS
            piece_colour *= sun_visible_at(sun_shadowing, direction, mix(t_front, t_back, 0.5 * (a + b)));
#endif
            colour += transmittance * piece_alpha * piece_colour;
            transmittance *= 1.0 - piece_alpha;
        }
    }
    let alpha = 1.0 - transmittance;
#else
    let optical_depth = segment_length * pair_lookup(s_front, s_back).a;
    let alpha = 1.0 - exp(-optical_depth);
    var colour = vec3(0.0);
    if optical_depth > 0.0 {
        colour = alpha * colour_lookup(s_front, s_back, optical_depth);
#ifdef SCATTERED_SUN_SHADOWS
        colour *= sun_visible_at(sun_shadowing, direction, middle);
#endif
    }
#endif
#ifdef SCATTERING
    let phase = henyey_greenstein(parameters.sun.w, dot(direction, parameters.sun.xyz));
    var segment = vec4(parameters.ambient_colour.rgb * alpha + parameters.sunlight.rgb * parameters.sun_colour.rgb * phase * colour, alpha);
#else
    var segment = vec4(parameters.sunlight.rgb * colour, alpha);
#endif
#ifdef LOCAL_LIGHTS
    segment = vec4(
        segment.rgb + local_light_colour(s_front, s_back, m_front, m_back, t_front, t_back, direction),
        segment.a,
    );
#endif
#ifdef GROUND_SUN
    if alpha > 0.0 {
        let kappa = colour / alpha;
        segment = vec4(
            segment.rgb + ground_sun_colour(kappa, s_front, s_back, m_front, m_back, t_front, t_back, direction),
            segment.a,
        );
    }
#endif
#endif
#ifdef EMISSIVE
#ifdef MODULATED
    var emitted = vec3(0.0);
    for (var piece = 0u; piece < #{MODULATOR_PIECES}u; piece++) {
        let a = f32(piece) / f32(#{MODULATOR_PIECES}u);
        let b = f32(piece + 1u) / f32(#{MODULATOR_PIECES}u);
        let modulated = segment_length * (b - a) * 0.5 * (mix(m_front, m_back, a) + mix(m_front, m_back, b));
        emitted += modulated * pair_lookup(mix(s_front, s_back, a), mix(s_front, s_back, b)).rgb;
    }
    var segment = vec4(emitted, 0.0);
#else
    var segment = vec4(segment_length * pair_lookup(s_front, s_back).rgb, 0.0);
#endif
#endif
#ifdef MIP
    var segment = vec4(pair_lookup(s_front, s_back).rgb, 0.0);
#endif
#ifdef FOG_HANDOFF
    // The segment ends before the fog layers begin: none of them is in front.
#else ifdef FOG_LAYERS
    let fog_in_front = fog_stretch(view.fog, view.camera_position.y, direction, 0.0, middle);
    segment = vec4(exp(-fog_in_front.w) * segment.rgb + segment.a * fog_in_front.rgb, segment.a);
#endif
    return segment;
}

// A fragment's premultiplied colour and opacity, and its entry and
// negated exit distance along the ray (read by the MERGED variant).
struct Shaded {
    segment: vec4<f32>,
    span: vec2<f32>,
}

#ifdef MERGED
// A batch drawn alone into its merged layer (merge.rs): the segment, and its
// entry and negated exit distance, min-blended into the batch's span along
// the ray.
struct MergedOutput {
    @location(0) segment: vec4<f32>,
    @location(1) span: vec2<f32>,
}
#endif

#ifdef RAY_CAST
#ifdef MODULATED
// A grid point's scalar and modulator.
alias GridPoint = vec2<f32>;
#else
// A grid point's scalar.
alias GridPoint = f32;
#endif

// The scalar of a grid point.
fn point_scalar(point: GridPoint) -> f32 {
#ifdef MODULATED
    return point.x;
#else
    return point;
#endif
}

// The modulator of a grid point (1 without modulators).
fn point_modulator(point: GridPoint) -> f32 {
#ifdef MODULATED
    return point.y;
#else
    return 1.0;
#endif
}

// The grid's values at point p.
fn grid_point(p: vec3<u32>) -> GridPoint {
    let points = grid.voxels.xyz + 1u;
    let index = p.x + points.x * (p.y + points.y * p.z);
#ifdef BLENDED
    let t = parameters.blend.x;
    let scalars = grid_values[index];
#ifdef MODULATED
    let modulators = grid.modulators[index];
    return vec2(mix(scalars.x, scalars.y, t), mix(modulators.x, modulators.y, t));
#else
    return mix(scalars.x, scalars.y, t);
#endif
#else
#ifdef MODULATED
    return vec2(grid_values[index], grid.modulators[index]);
#else
    return grid_values[index];
#endif
#endif
}

// A point of a voxel as the barycentric combination of the corners of its
// Kuhn tetrahedron (corner x + 2y + 4z): corners 0, e_a, e_a + e_b and 7.
struct KuhnPoint {
    side: u32,
    diagonal: u32,
    weights: vec4<f32>,
}

// The point at local coordinates u in [0, 1]³: with the axes ordered
// u_a ≥ u_b ≥ u_c, the weights 1 − u_a, u_a − u_b, u_b − u_c and u_c.
fn kuhn_point(u: vec3<f32>) -> KuhnPoint {
    var a = 0u;
    var b = 1u;
    var c = 2u;
    if u[b] > u[a] {
        let swap = a;
        a = b;
        b = swap;
    }
    if u[c] > u[b] {
        let swap = b;
        b = c;
        c = swap;
    }
    if u[b] > u[a] {
        let swap = a;
        a = b;
        b = swap;
    }
    let side = 1u << a;
    return KuhnPoint(side, side | (1u << b), vec4(1.0 - u[a], u[a] - u[b], u[b] - u[c], u[c]));
}

// The values of Kuhn's linear fields in a voxel with corner values
// `corners` at `point`.
fn kuhn_value(corners: ptr<function, array<GridPoint, 8>>, point: KuhnPoint) -> GridPoint {
    let w = point.weights;
    return (*corners)[0] * w.x + (*corners)[point.side] * w.y + (*corners)[point.diagonal] * w.z
        + (*corners)[7] * w.w;
}

// The ray's accumulated colour and transmittance, front to back.
struct Accumulated {
    colour: vec3<f32>,
    transmittance: f32,
}

// Composites the pieces of the ray's stretch [t0, t1] through `voxel`
// (the ray at index coordinates origin + t step) under `accumulated`.
fn shade_voxel(
    voxel: vec3<i32>,
    origin: vec3<f32>,
    step: vec3<f32>,
    direction: vec3<f32>,
    t0: f32,
    t1: f32,
    accumulated: ptr<function, Accumulated>,
) {
    let low = vec3<u32>(voxel);
    var corners: array<GridPoint, 8>;
    var peak = GridPoint(-1.0);
    for (var c = 0u; c < 8u; c++) {
        corners[c] = grid_point(low + vec3<u32>(c & 1u, (c >> 1u) & 1u, c >> 2u));
        peak = max(peak, corners[c]);
    }
    // No corner above the clear range: no value in the voxel is.
    if select(point_scalar(peak), point_modulator(peak), grid.clear.y != 0.0) <= grid.clear.x {
        return;
    }
    let local = origin - vec3<f32>(voxel);
    // Where the ray crosses u_x = u_y, u_y = u_z and u_x = u_z, sorted.
    var breaks = vec3(t1);
    let rates = vec3(step.x - step.y, step.y - step.z, step.x - step.z);
    let offsets = vec3(local.x - local.y, local.y - local.z, local.x - local.z);
    for (var k = 0; k < 3; k++) {
        if rates[k] != 0.0 {
            let t = -offsets[k] / rates[k];
            if t > t0 && t < t1 {
                breaks[k] = t;
            }
        }
    }
    // Sorted by comparisons only: no rounding may put an end past t1.
    let lowest = min(min(breaks.x, breaks.y), breaks.z);
    let middle = max(min(breaks.x, breaks.y), min(max(breaks.x, breaks.y), breaks.z));
    let highest = max(max(breaks.x, breaks.y), breaks.z);
    var ends = array<f32, 4>(lowest, middle, highest, t1);
    var start = t0;
    var s_start = kuhn_value(&corners, kuhn_point(clamp(local + start * step, vec3(0.0), vec3(1.0))));
    for (var k = 0; k < 4; k++) {
        let end = ends[k];
        if end > start {
            let s_end = kuhn_value(&corners, kuhn_point(clamp(local + end * step, vec3(0.0), vec3(1.0))));
            let segment = segment_colour(
                clamp(point_scalar(s_start), 0.0, 1.0),
                clamp(point_scalar(s_end), 0.0, 1.0),
                clamp(point_modulator(s_start), 0.0, 1.0),
                clamp(point_modulator(s_end), 0.0, 1.0),
                start,
                end,
                direction,
            );
#ifdef MIP
            (*accumulated).colour = max((*accumulated).colour, segment.rgb);
#else
            (*accumulated).colour += (*accumulated).transmittance * segment.rgb;
            (*accumulated).transmittance *= 1.0 - segment.a;
#endif
            start = end;
            s_start = s_end;
        }
    }
}

// The segment of the grid along the fragment's ray: every piece through
// its tetrahedra, composited front to back.
fn ray_cast(in: VertexOutput) -> Shaded {
    let ndc = pixel_ndc(in.clip_position);
    // The pixel's ray from its centre on the near plane, not interpolated
    // over the box's faces (large triangles, whose interpolation rounds more).
    let near = view.world_from_clip * vec4(ndc, 1.0, 1.0);
    let direction = normalize(near.xyz / near.w - view.camera_position.xyz);
    // The ray in index coordinates: origin + t step, t the world distance.
    let index_from_world = mat3x3(
        grid.index_from_world[0].xyz,
        grid.index_from_world[1].xyz,
        grid.index_from_world[2].xyz,
    );
    let origin = index_from_world * (view.camera_position.xyz - grid.world_from_index[3].xyz);
    let step = index_from_world * direction;
    let voxels = vec3<f32>(grid.voxels.xyz);

    // The ray inside the box, after the near plane and before the opaque
    // scene (depth 0 is the cleared far plane, reversed Z).
    var t_entry = ray_distance_at_depth(ndc, 1.0);
    var t_exit = 3.0e38;
    let depth = opaque_depth(vec2<i32>(floor(in.clip_position.xy)));
    if depth > 0.0 {
        t_exit = min(t_exit, ray_distance_at_depth(ndc, depth));
    }
#ifdef FOG_HANDOFF
    t_exit = min(t_exit, view.fog.ranges.x);
#endif
    for (var axis = 0; axis < 3; axis++) {
        if step[axis] == 0.0 {
            if origin[axis] < 0.0 || origin[axis] > voxels[axis] {
                discard;
            }
        } else {
            let a = -origin[axis] / step[axis];
            let b = (voxels[axis] - origin[axis]) / step[axis];
            t_entry = max(t_entry, min(a, b));
            t_exit = min(t_exit, max(a, b));
        }
    }
    if t_exit <= t_entry {
        discard;
    }

    // The voxel the ray enters (on a grid plane, the one it moves into) and
    // the distances to its next plane along each axis.
    let entry = origin + t_entry * step;
    var voxel = vec3<i32>(0);
    var next = vec3(3.0e38);
    var advance = vec3(3.0e38);
    for (var axis = 0; axis < 3; axis++) {
        let p = entry[axis];
        var cell = floor(p);
        if step[axis] < 0.0 && p == cell {
            cell -= 1.0;
        }
        voxel[axis] = clamp(i32(cell), 0, i32(grid.voxels[axis]) - 1);
        if step[axis] != 0.0 {
            let boundary = f32(voxel[axis] + select(0, 1, step[axis] > 0.0));
            next[axis] = (boundary - origin[axis]) / step[axis];
            advance[axis] = 1.0 / abs(step[axis]);
        }
    }

    var accumulated = Accumulated(vec3(0.0), 1.0);
    var t = t_entry;
    let steps = grid.voxels.x + grid.voxels.y + grid.voxels.z + 3u;
    for (var i = 0u; i < steps; i++) {
        var axis = 0;
        if next.y < next[axis] {
            axis = 1;
        }
        if next.z < next[axis] {
            axis = 2;
        }
        let brick = vec3<u32>(voxel) / grid.bricks.w;
        if occupied[brick.x + grid.bricks.x * (brick.y + grid.bricks.y * brick.z)] == 0u {
            // An empty brick: on to the voxel where the ray leaves it.
            let low = vec3<f32>(brick * grid.bricks.w);
            let high = min(low + f32(grid.bricks.w), voxels);
            var leave = 3.0e38;
            var leave_axis = 0;
            for (var a = 0; a < 3; a++) {
                if step[a] != 0.0 {
                    let crossing = (select(low[a], high[a], step[a] > 0.0) - origin[a]) / step[a];
                    if crossing < leave {
                        leave = crossing;
                        leave_axis = a;
                    }
                }
            }
            t = max(t, leave);
            if t >= t_exit {
                break;
            }
            let p = origin + t * step;
            for (var a = 0; a < 3; a++) {
                voxel[a] = clamp(i32(floor(p[a])), i32(low[a]), i32(high[a]) - 1);
            }
            voxel[leave_axis] = i32(select(low[leave_axis] - 1.0, high[leave_axis], step[leave_axis] > 0.0));
            if voxel[leave_axis] < 0 || voxel[leave_axis] >= i32(grid.voxels[leave_axis]) {
                break;
            }
            for (var a = 0; a < 3; a++) {
                if step[a] != 0.0 {
                    next[a] = (f32(voxel[a] + select(0, 1, step[a] > 0.0)) - origin[a]) / step[a];
                }
            }
            continue;
        }
        let end = min(next[axis], t_exit);
        if end > t {
            shade_voxel(voxel, origin, step, direction, t, end, &accumulated);
        }
        t = max(t, end);
        if t >= t_exit || accumulated.transmittance < bitcast<f32>(#{TERMINATION_TRANSMITTANCE_BITS}u) {
            break;
        }
        voxel[axis] += select(-1, 1, step[axis] > 0.0);
        if voxel[axis] < 0 || voxel[axis] >= i32(grid.voxels[axis]) {
            break;
        }
        next[axis] += advance[axis];
    }
    return Shaded(vec4(accumulated.colour, 1.0 - accumulated.transmittance), vec2(t_entry, -t));
}
#else
// The segment of the fragment's cell along its ray.
fn project_cell(in: VertexOutput) -> Shaded {
    let cell = cells[in.cell_index];
    let direction = normalize(in.relative_position);

    // Entry and exit through the four face planes. When the eye lies on a
    // face's plane (up to the f32 rounding of camera-relative positions,
    // which grows with the distance from the world origin and the cell's
    // size), the plane meets every ray at t = 0: a pixel whose ray grazes
    // that plane would otherwise divide two rounding errors and be lost to
    // both cells on either side (a one-pixel crack through the eye). A ray
    // along the plane itself (within 1/16 of a pixel; its pixel lies on the
    // plane's edge-on line, which the rasterizer, snapping vertices to a
    // fraction of a pixel, gives to the faces of the cell on either side)
    // has no side to choose: that face does not clip it, so the cell that
    // got the pixel draws the ray.
    let ndc = pixel_ndc(in.clip_position);
    let v0 = relative_vertex(cell, 0u);
    let e1 = relative_vertex(cell, 1u) - v0;
    let e2 = relative_vertex(cell, 2u) - v0;
    let e3 = relative_vertex(cell, 3u) - v0;
    let scale = max(max(dot(e1, e1), dot(e2, e2)), dot(e3, e3));
    let on_plane = 1.0e-6 * (length(view.camera_position.xyz) + length(v0) + sqrt(scale));
    // Once per fragment: in the loop's branch, CPU drivers evaluate it for
    // every face (lavapipe: 5× slower fragments inside fog).
    let in_plane = 0.0625 * pixel_angle(ndc, direction);
    var t_entry = 0.0;
    var t_exit = 3.0e38;
    for (var face = 0u; face < 4u; face++) {
        let normal = outward_normal(cell, face);
        let denominator = dot(normal, direction);
        var height = dot(normal, relative_vertex(cell, FACE_VERTICES[face * 3u]));
        if abs(height) <= on_plane * length(normal) {
            if abs(denominator) <= in_plane * length(normal) {
                continue;
            }
            height = 0.0;
        }
        let t = height / denominator;
        if denominator < 0.0 {
            t_entry = max(t_entry, t);
        } else if denominator > 0.0 {
            t_exit = min(t_exit, t);
        }
    }

    // Clip to the near plane (the camera may stand inside the cell) and to the
    // opaque scene: depth 0 is the cleared far plane (reversed Z).
    let pixel = vec2<i32>(floor(in.clip_position.xy));
    t_entry = max(t_entry, ray_distance_at_depth(ndc, 1.0));
    let depth = opaque_depth(pixel);
    if depth > 0.0 {
        t_exit = min(t_exit, ray_distance_at_depth(ndc, depth));
    }
#ifdef FOG_HANDOFF
    // Fog that the view's fog layers take over from their start distance.
    t_exit = min(t_exit, view.fog.ranges.x);
#endif
    if t_exit <= t_entry {
        discard;
    }

    // The cell's linear scalar: s(x) = s0 + g · (x − v0).
    let determinant = dot(e1, cross(e2, e3));
    if abs(determinant) <= 1.0e-9 * scale * sqrt(scale) {
        discard;
    }
    var scalars = vec4(cell.vertices[0].w, cell.vertices[1].w, cell.vertices[2].w, cell.vertices[3].w);
#ifdef BLENDED
    scalars = mix(scalars, next_keyframe[2u * in.cell_index], parameters.blend.x);
#endif
    let s0 = scalars.x;
    let gradient = ((scalars.y - s0) * cross(e2, e3) + (scalars.z - s0) * cross(e3, e1)
        + (scalars.w - s0) * cross(e1, e2)) / determinant;
    let s_front = clamp(s0 + dot(gradient, t_entry * direction - v0), 0.0, 1.0);
    let s_back = clamp(s0 + dot(gradient, t_exit * direction - v0), 0.0, 1.0);
#ifdef MODULATED
    var m = modulators[in.cell_index];
#ifdef BLENDED
    m = mix(m, next_keyframe[2u * in.cell_index + 1u], parameters.blend.x);
#endif
    let m_gradient = ((m.y - m.x) * cross(e2, e3) + (m.z - m.x) * cross(e3, e1)
        + (m.w - m.x) * cross(e1, e2)) / determinant;
    let m_front = clamp(m.x + dot(m_gradient, t_entry * direction - v0), 0.0, 1.0);
    let m_back = clamp(m.x + dot(m_gradient, t_exit * direction - v0), 0.0, 1.0);
#endif

#ifndef MODULATED
    let m_front = 1.0;
    let m_back = 1.0;
#endif
    let segment = segment_colour(s_front, s_back, m_front, m_back, t_entry, t_exit, direction);
    return Shaded(segment, vec2(t_entry, -t_exit));
}
#endif

// The stencil of early termination and of the low resolution's resolved
// pixels rejects fragments before they run: the shader writes no depth or
// stencil, so its discards do not change what the test sees.
#ifdef EARLY_DEPTH_TEST
@early_depth_test(force)
#endif
@fragment
#ifdef MERGED
fn fragment(in: VertexOutput) -> MergedOutput {
#else
fn fragment(in: VertexOutput) -> @location(0) vec4<f32> {
#endif
#ifdef COUNT_FRAGMENTS
    atomicAdd(&fragment_count, 1u);
#endif
#ifdef RAY_CAST
    let shaded = ray_cast(in);
#else
    let shaded = project_cell(in);
#endif
#ifdef MERGED
    return MergedOutput(shaded.segment, shaded.span);
#else
    return shaded.segment;
#endif
}
