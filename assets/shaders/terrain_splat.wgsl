// Texture splatting for the textured_terrain example: grass, rock and snow textures blended by the
// terrain's morphed height and slope (the weights of nebel's default height-and-slope colours), tiled
// through the terrain mesh's UVs, then lit by Bevy's PBR as the StandardMaterial it extends.

#import bevy_pbr::{
    forward_io::{VertexOutput, FragmentOutput},
    pbr_fragment::pbr_input_from_standard_material,
    pbr_functions::{alpha_discard, apply_pbr_lighting, main_pass_post_lighting_processing},
}

struct Splat {
    // The terrain's lowest and highest height (world units), then the UV tiling.
    heights_and_tiling: vec4<f32>,
}

@group(#{MATERIAL_BIND_GROUP}) @binding(100) var<uniform> splat: Splat;
@group(#{MATERIAL_BIND_GROUP}) @binding(101) var grass_texture: texture_2d<f32>;
@group(#{MATERIAL_BIND_GROUP}) @binding(102) var grass_sampler: sampler;
@group(#{MATERIAL_BIND_GROUP}) @binding(103) var rock_texture: texture_2d<f32>;
@group(#{MATERIAL_BIND_GROUP}) @binding(104) var rock_sampler: sampler;
@group(#{MATERIAL_BIND_GROUP}) @binding(105) var snow_texture: texture_2d<f32>;
@group(#{MATERIAL_BIND_GROUP}) @binding(106) var snow_sampler: sampler;

@fragment
fn fragment(in: VertexOutput, @builtin(front_facing) is_front: bool) -> FragmentOutput {
    var pbr_input = pbr_input_from_standard_material(in, is_front);
    let low = splat.heights_and_tiling.x;
    let high = splat.heights_and_tiling.y;
    let uv = in.uv * splat.heights_and_tiling.z;
    let h = clamp((in.world_position.y - low) / max(high - low, 1e-3), 0.0, 1.0);
    let up = normalize(in.world_normal).y;
    let rock = 1.0 - smoothstep(0.72, 0.92, up);
    let snow = smoothstep(0.72, 0.86, h) * smoothstep(0.70, 0.85, up);
    var colour = textureSample(grass_texture, grass_sampler, uv).rgb;
    colour = mix(colour, textureSample(rock_texture, rock_sampler, uv).rgb, rock);
    colour = mix(colour, textureSample(snow_texture, snow_sampler, uv).rgb, snow);
    pbr_input.material.base_color = vec4(colour, 1.0) * pbr_input.material.base_color;
    pbr_input.material.base_color = alpha_discard(pbr_input.material, pbr_input.material.base_color);
    var out: FragmentOutput;
    out.color = apply_pbr_lighting(pbr_input);
    out.color = main_pass_post_lighting_processing(pbr_input, out.color);
    return out;
}
