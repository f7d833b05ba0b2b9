//! Textured terrain: the quadtree C-LOD terrain drawn with a material of the
//! user's own. The terrain mesh carries UVs (0 to 1 over the height map, fixed
//! under geomorphing), so textures map onto it; here an extension of
//! `StandardMaterial` splats grass, rock and snow textures (made in code) by
//! the morphed height and slope (`assets/shaders/terrain_splat.wgsl`), the
//! terrain set to [`TerrainMaterial::Own`] so nebel inserts no material.
//!
//! `cargo run --release --example textured_terrain` opens a window with a fly
//! camera (WASD, Q/E, Shift, right mouse button to look); with no display, or
//! with `-- --headless`, it renders to `target/nebel/textured_terrain.png`.

use std::process::ExitCode;

use bevy::asset::RenderAssetUsages;
use bevy::camera::Hdr;
use bevy::image::{ImageAddressMode, ImageSampler, ImageSamplerDescriptor};
use bevy::pbr::{ExtendedMaterial, MaterialExtension};
use bevy::prelude::*;
use bevy::render::render_resource::{AsBindGroup, Extent3d, TextureDimension, TextureFormat};
use bevy::shader::ShaderRef;
use nebel::prelude::*;
use nebel_tools::example_runner::Example;
use nebel_tools::nebel_scene::OutputSettings;

/// The terrain's vertical scale: its heights lie between 0 and this.
const VERTICAL_SCALE: f32 = 700.0;

fn main() -> ExitCode {
    Example {
        name: "textured_terrain",
        output: OutputSettings {
            width: 640,
            height: 360,
            frames: 3,
            frame_rate: 30.0,
        },
        fly_speed: 200.0,
    }
    .run(|app| {
        app.add_plugins(MaterialPlugin::<SplatMaterial>::default())
            .add_systems(Startup, spawn_scene);
    })
}

/// Grass, rock and snow splatted by height and slope over a
/// `StandardMaterial`.
type SplatMaterial = ExtendedMaterial<StandardMaterial, Splat>;

/// The splatting's textures and settings (bindings after the
/// `StandardMaterial`'s).
#[derive(Asset, AsBindGroup, Reflect, Debug, Clone)]
struct Splat {
    /// The terrain's lowest and highest height, and the textures' repeats
    /// over the terrain.
    #[uniform(100)]
    heights_and_tiling: Vec4,
    #[texture(101)]
    #[sampler(102)]
    grass: Handle<Image>,
    #[texture(103)]
    #[sampler(104)]
    rock: Handle<Image>,
    #[texture(105)]
    #[sampler(106)]
    snow: Handle<Image>,
}

impl MaterialExtension for Splat {
    fn fragment_shader() -> ShaderRef {
        "shaders/terrain_splat.wgsl".into()
    }
}

fn spawn_scene(
    mut commands: Commands,
    mut images: ResMut<Assets<Image>>,
    mut materials: ResMut<Assets<SplatMaterial>>,
) {
    commands.spawn((
        Camera3d::default(),
        Camera {
            clear_color: ClearColorConfig::Custom(Color::srgb(0.36, 0.55, 0.85)),
            ..default()
        },
        Hdr,
        Projection::Perspective(PerspectiveProjection {
            fov: 60f32.to_radians(),
            near: 1.0,
            ..default()
        }),
        Transform::from_xyz(-3000.0, 1400.0, -2600.0)
            .looking_at(Vec3::new(1200.0, 200.0, 800.0), Vec3::Y),
        LodCamera,
    ));
    commands.spawn((
        DirectionalLight {
            illuminance: 10_000.0,
            color: Color::srgb(1.0, 0.95, 0.85),
            ..default()
        },
        Transform::default().looking_to(Vec3::new(-0.45, -0.75, -0.3), Vec3::Y),
    ));
    let mut texture = |base: [f32; 3], variation: f32, scale: f32, seed: u32| {
        images.add(tileable_texture(base, variation, scale, seed))
    };
    let splat = Splat {
        heights_and_tiling: Vec4::new(0.0, VERTICAL_SCALE, 40.0, 0.0),
        grass: texture([0.07, 0.15, 0.035], 0.4, 8.0, 1),
        rock: texture([0.2, 0.18, 0.16], 0.5, 16.0, 2),
        snow: texture([0.92, 0.94, 0.98], 0.06, 4.0, 3),
    };
    commands.spawn((
        Terrain {
            source: TerrainSource::Procedural {
                size: 257,
                noise: TerrainNoise {
                    seed: 4,
                    octaves: 7,
                    wavelength: 3000.0,
                    exponent: 2.0,
                    ..default()
                },
            },
            spacing: 40.0,
            vertical_scale: VERTICAL_SCALE,
            material: TerrainMaterial::Own,
            ..default()
        },
        MeshMaterial3d(materials.add(SplatMaterial {
            base: StandardMaterial {
                perceptual_roughness: 0.95,
                reflectance: 0.2,
                ..default()
            },
            extension: splat,
        })),
    ));
}

/// A tileable 256 × 256 sRGB texture: `base` colour varied by `variation`
/// with a wrapping value noise of `scale` cells across (and a finer octave),
/// repeating in both directions.
fn tileable_texture(base: [f32; 3], variation: f32, scale: f32, seed: u32) -> Image {
    const SIZE: u32 = 256;
    let hash = |x: i32, y: i32, period: i32| {
        let (x, y) = (x.rem_euclid(period) as u32, y.rem_euclid(period) as u32);
        let mut h = x.wrapping_mul(0x27d4_eb2d)
            ^ y.wrapping_mul(0x1656_67b1)
            ^ seed.wrapping_mul(0x9e37_79b9);
        h ^= h >> 15;
        h = h.wrapping_mul(0x85eb_ca6b);
        h ^= h >> 13;
        (h & 0xffff) as f32 / 65535.0
    };
    let noise = |u: f32, v: f32, cells: f32| {
        let (x, y) = (u * cells, v * cells);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
        let period = cells as i32;
        let corner = |dx: i32, dy: i32| hash(x0 as i32 + dx, y0 as i32 + dy, period);
        let top = corner(0, 0) + (corner(1, 0) - corner(0, 0)) * sx;
        let bottom = corner(0, 1) + (corner(1, 1) - corner(0, 1)) * sx;
        top + (bottom - top) * sy
    };
    let mut data = Vec::with_capacity((SIZE * SIZE * 4) as usize);
    for y in 0..SIZE {
        for x in 0..SIZE {
            let (u, v) = (x as f32 / SIZE as f32, y as f32 / SIZE as f32);
            let n = 0.65 * noise(u, v, scale) + 0.35 * noise(u, v, 4.0 * scale);
            let k = 1.0 + variation * (2.0 * n - 1.0);
            for c in base {
                let linear = (c * k).clamp(0.0, 1.0);
                data.push((Color::linear_rgb(linear, 0.0, 0.0).to_srgba().red * 255.0) as u8);
            }
            data.push(255);
        }
    }
    let mut image = Image::new(
        Extent3d {
            width: SIZE,
            height: SIZE,
            depth_or_array_layers: 1,
        },
        TextureDimension::D2,
        data,
        TextureFormat::Rgba8UnormSrgb,
        RenderAssetUsages::RENDER_WORLD,
    );
    image.sampler = ImageSampler::Descriptor(ImageSamplerDescriptor {
        address_mode_u: ImageAddressMode::Repeat,
        address_mode_v: ImageAddressMode::Repeat,
        ..ImageSamplerDescriptor::linear()
    });
    image
}
