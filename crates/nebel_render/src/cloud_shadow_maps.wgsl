// The clouds' shadow maps (nebel_render's `cloud_shadow_maps` module): the
// transmittance toward the sun on a plane under the cloud volumes, read where
// the line from a point toward the map's sun crosses the plane.

#define_import_path nebel_render::cloud_shadow_maps

// One map (`CloudShadowMapUniform`).
struct CloudShadowMap {
    // The plane's height, the texel's side, the map's lower corner (x, z).
    plane: vec4<f32>,
    // Toward the map's sun (xyz) and the map's weight.
    sun_and_weight: vec4<f32>,
    // The map's texels along x and z, the texture's side, and the height of
    // the casters' top (above it nothing is shaded).
    size: vec4<f32>,
}

// Both maps, the newest fading in over the one before (`[CloudShadowMapUniform; 2]`).
struct CloudShadowMapPair {
    first: CloudShadowMap,
    second: CloudShadowMap,
}

// The light the map holds back at the world point `p`, times its weight:
// w (1 − T), T bilinear between texel centres; 0 outside the map (whose
// border texels are lit), above the casters' top or without weight, with no
// texture read.
fn held_back(
    plane: vec4<f32>,
    sun_and_weight: vec4<f32>,
    size: vec4<f32>,
    map_texture: texture_2d<f32>,
    map_sampler: sampler,
    p: vec3<f32>,
) -> f32 {
    let sun = sun_and_weight.xyz;
    let q = p + sun * ((plane.x - p.y) / sun.y);
    let texels = (q.xz - plane.zw) / plane.y;
    if sun_and_weight.w <= 0.0 || p.y > size.w || any(texels < vec2(0.5)) || any(texels > size.xy - 0.5) {
        return 0.0;
    }
    let t = textureSampleLevel(map_texture, map_sampler, texels / size.z, 0.0).r;
    return sun_and_weight.w * (1.0 - t);
}

// The clouds' transmittance toward the sun at the world point `p`: both maps
// weighed, the rest of the weight lit.
fn cloud_transmittance(
    maps: CloudShadowMapPair,
    first_map: texture_2d<f32>,
    second_map: texture_2d<f32>,
    map_sampler: sampler,
    p: vec3<f32>,
) -> f32 {
    return 1.0
        - held_back(maps.first.plane, maps.first.sun_and_weight, maps.first.size, first_map, map_sampler, p)
        - held_back(maps.second.plane, maps.second.sun_and_weight, maps.second.size, second_map, map_sampler, p);
}
