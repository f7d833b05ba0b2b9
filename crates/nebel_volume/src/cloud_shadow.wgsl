// A StandardMaterial whose sunlight the clouds' shadow dims: Bevy's PBR lighting, less the part of the
// sun's light (as Bevy adds it, with its shadow map) that the clouds above hold back.

#import bevy_pbr::{
    forward_io::{VertexOutput, FragmentOutput},
    mesh_types::MESH_FLAGS_SHADOW_RECEIVER_BIT,
    mesh_view_bindings as view_bindings,
    mesh_view_types,
    pbr_fragment::pbr_input_from_standard_material,
    pbr_functions::{
        alpha_discard, apply_pbr_lighting, calculate_diffuse_color, calculate_F0,
        calculate_F0_dielectric, main_pass_post_lighting_processing,
    },
    lighting,
    pbr_types,
    shadows,
}
#import nebel_render::cloud_shadow_maps::{CloudShadowMapPair, cloud_transmittance}

struct ShadowMaps {
    maps: CloudShadowMapPair,
    // Toward the sun now (xyz), to find its light: the maps' suns may lie ahead of it.
    sun: vec4<f32>,
}

@group(#{MATERIAL_BIND_GROUP}) @binding(100) var first_map: texture_2d<f32>;
@group(#{MATERIAL_BIND_GROUP}) @binding(101) var map_sampler: sampler;
@group(#{MATERIAL_BIND_GROUP}) @binding(102) var second_map: texture_2d<f32>;
@group(#{MATERIAL_BIND_GROUP}) @binding(103) var<storage, read> shadow_maps: ShadowMaps;

// The directional light nearest the sun, if one is within about 8 degrees of it.
fn sun_light_index() -> i32 {
    let sun = shadow_maps.sun.xyz;
    var best = -1;
    var closest = 0.99;
    for (var i = 0u; i < view_bindings::lights.n_directional_lights; i += 1u) {
        let c = dot(view_bindings::lights.directional_lights[i].direction_to_light, sun);
        if c > closest {
            closest = c;
            best = i32(i);
        }
    }
    return best;
}

// The sun's direct light at this fragment as apply_pbr_lighting adds it (base layer), with its shadow.
fn sun_light(in: pbr_types::PbrInput, light: u32) -> vec3<f32> {
    let base = in.material.base_color.rgb;
    let perceptual_roughness = in.material.perceptual_roughness;
    let NdotV = max(dot(in.N, in.V), 0.0001);
    var input: lighting::LightingInput;
    input.layers[0].NdotV = NdotV;
    input.layers[0].N = in.N;
    input.layers[0].R = reflect(-in.V, in.N);
    input.layers[0].perceptual_roughness = perceptual_roughness;
    input.layers[0].roughness = lighting::perceptualRoughnessToRoughness(perceptual_roughness);
    input.P = in.world_position.xyz;
    input.V = in.V;
    input.diffuse_color = calculate_diffuse_color(
        base,
        in.material.metallic,
        in.material.specular_transmission,
        in.material.diffuse_transmission,
    );
    input.metallic = in.material.metallic;
    input.F0_dielectric = calculate_F0_dielectric(in.material.reflectance);
    input.F0_metallic = base;
    input.F_ab = lighting::F_AB(perceptual_roughness, NdotV);
    var shadow = 1.0;
    let flags = view_bindings::lights.directional_lights[light].flags;
    if (in.flags & MESH_FLAGS_SHADOW_RECEIVER_BIT) != 0u
            && (flags & mesh_view_types::DIRECTIONAL_LIGHT_FLAGS_SHADOWS_ENABLED_BIT) != 0u {
        let view_z = dot(vec4(
            view_bindings::view.view_from_world[0].z,
            view_bindings::view.view_from_world[1].z,
            view_bindings::view.view_from_world[2].z,
            view_bindings::view.view_from_world[3].z,
        ), in.world_position);
        shadow = shadows::fetch_directional_shadow(
            light, in.world_position, in.world_normal, view_z, in.frag_coord.xy);
    }
    return lighting::directional_light(light, &input, true) * shadow;
}

@fragment
fn fragment(in: VertexOutput, @builtin(front_facing) is_front: bool) -> FragmentOutput {
    var pbr_input = pbr_input_from_standard_material(in, is_front);
    pbr_input.material.base_color = alpha_discard(pbr_input.material, pbr_input.material.base_color);
    var out: FragmentOutput;
    out.color = pbr_input.material.base_color;
    if (pbr_input.material.flags & pbr_types::STANDARD_MATERIAL_FLAGS_UNLIT_BIT) == 0u {
        out.color = apply_pbr_lighting(pbr_input);
        let t = cloud_transmittance(shadow_maps.maps, first_map, second_map, map_sampler, pbr_input.world_position.xyz);
        let light = sun_light_index();
        if t < 1.0 && light >= 0 {
            let held_back = (1.0 - t) * view_bindings::view.exposure * sun_light(pbr_input, u32(light));
            out.color = vec4(out.color.rgb - held_back, out.color.a);
        }
    }
    out.color = main_pass_post_lighting_processing(pbr_input, out.color);
    return out;
}
