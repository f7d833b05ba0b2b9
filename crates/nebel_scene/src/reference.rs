//! The exact CPU reference of a scene, as `nebel reference` writes it.
//!
//! Every volume integrated by [`nebel_reference::render`] from the
//! camera of the scene's last frame (an animated campfire at that frame's
//! time), cut at the scene's meshes and, with
//! [`reference_image_with_terrain`], at its terrain (the full-resolution
//! bilinear surface, `nebel_core::scene` `opaque` module). The reference
//! shades no surface: a pixel whose ray ends on a mesh or the terrain
//! composites over black, the others over the clear colour, so accuracy
//! scenes use black meshes and no lights on them. Sorted volumes scatter the
//! scene's volumetric point and spot lights
//! ([`SceneDescription::volumetric_lights`]), those that cast shadows shaded
//! by the meshes and the terrain's bilinear heights (Bevy's shadow maps hold
//! both). The sun in a sunlit ground fog and in fog layers is dimmed by the
//! volumes that cast cloud shadows, exactly at every point, and cut by the
//! terrain's shadow heights; a sun that casts shadows is hidden from them by
//! the meshes too, and from scattering volumes by the meshes and the
//! terrain.

use std::path::Path;
use std::sync::Arc;

use crate::{
    BuiltVolume, LightModel, LightingDescription, ReferenceTerrain, SceneDescription, SceneField,
};
use glam::{DAffine3, DVec3, DVec4};
use nebel_core::field::{
    CloudLighting, DensityGrid, PadFill, PlacedHeights, PlacedTerrainShadow, ShadowCaster,
    light_field,
};
use nebel_core::occluder::Occluder;
use nebel_core::optics::OpticalMode;
use nebel_reference::image_metrics::{ImageMetricsError, LinearImage, save_png, srgb_to_linear};
use nebel_reference::{
    Modulation, ReferenceCamera, ReferenceError, ReferenceFog, ReferenceScene, ReferenceVolume,
    RenderProgress, SegmentScattering,
};

/// How far a reference image is: which pass, and its rows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReferenceProgress {
    /// The pass being integrated, from 0: the sorted and emissive volumes
    /// together first, then each MIP volume.
    pub pass: usize,
    /// Passes in the image.
    pub passes: usize,
    /// Rows of this volume finished so far.
    pub rows_done: u32,
    /// Rows of the image.
    pub rows_total: u32,
}

/// Renders `volumes` of `scene` exactly; `progress`, when given, is called
/// as rows finish (from the worker threads).
///
/// A lit volume (Röttger and Ertl 2003 §5) is integrated as the GPU draws it: its grid
/// padded with zero density to `2^n + 1` points, the light field computed on
/// that grid for the scene's sun, and one field as the scalar, the other as
/// the segment-length modulator ([`Modulation::Grid`]), but continuous and in
/// f32 where the GPU draws the octree's 8-bit, level-of-detail cells.
///
/// The sorted and emissive volumes are integrated along each ray together
/// ([`nebel_reference::render_together`]): where they interpenetrate they
/// absorb and emit as one medium, elsewhere they follow each other in their
/// order along the ray. That is the truth the GPU is held to. MIP volumes are
/// integrated on their own and combined with that image the way the GPU
/// combines batches: farthest first by centre (the sorted and emissive
/// volumes at their nearest centre), the maximum of colours with no opacity.
/// The result goes over the clear colour, or over black where the pixel's ray
/// ends on a mesh.
///
/// Errors: [`ReferenceError::OverBudget`] when the image or the opaque depth
/// exceeds the memory budget, before it is allocated, and the errors of
/// [`nebel_reference::render`].
pub fn reference_image(
    scene: &SceneDescription,
    volumes: Vec<BuiltVolume>,
    progress: Option<&(dyn Fn(ReferenceProgress) + Sync)>,
) -> Result<LinearImage, ReferenceError> {
    reference_image_with_terrain(scene, volumes, None, None, None, progress)
}

/// [`reference_image`] cut at `terrain` too: the scene terrain's heights in
/// world space (`TerrainDescription::world_heights`) or the triangles the GPU
/// draws (a terrain with fog, [`crate::FogReference::ground`]), drawn black
/// like the meshes, `terrain_shadow` keeping the sun from the fog layers
/// below it ([`SceneDescription::build_terrain_shadow`]), and
/// `terrain_heights` (the bilinear heights, [`SceneDescription::terrain_occluder`])
/// hiding the point and spot lights that cast shadows. `None` ignores each.
pub fn reference_image_with_terrain(
    scene: &SceneDescription,
    volumes: Vec<BuiltVolume>,
    terrain: Option<&ReferenceTerrain>,
    terrain_shadow: Option<PlacedTerrainShadow>,
    terrain_heights: Option<PlacedHeights>,
    progress: Option<&(dyn Fn(ReferenceProgress) + Sync)>,
) -> Result<LinearImage, ReferenceError> {
    let camera = scene.reference_camera();
    LinearImage::check_budget(camera.width, camera.height)?;
    let opaque_depth = scene.opaque_depth_with_terrain(&camera, terrain)?;
    let sun = scene.sun_direction();
    let sky = scene.sky_colour();
    let last_frame = f64::from(scene.frame_time(scene.output.frames.saturating_sub(1)));
    let local_lights = scene.volumetric_lights(last_frame);
    let occluders = scene.occluders();
    let light_occluders: Vec<Occluder> = occluders
        .iter()
        .cloned()
        .chain(terrain_heights.map(Occluder::Terrain))
        .collect();
    let clouds = cloud_casters(&volumes, last_frame)?;
    let fog = scene
        .fog_layers
        .as_ref()
        .map(|fog| {
            let sun = sun.map(|direction| (direction, scene.sun_casts_shadows()));
            fog.reference(sun, local_lights.clone(), light_occluders.clone())
        })
        .transpose()
        .map_err(|invalid| ReferenceError::InvalidFog {
            reason: format!("fog_layers.{}: {}", invalid.field, invalid.reason),
        })?
        .map(|fog| ReferenceFog {
            clouds: clouds.clone(),
            terrain: terrain_shadow,
            ..fog
        });
    let mut joint = Vec::with_capacity(volumes.len());
    let mut mips = Vec::new();
    for volume in volumes {
        let sun = sun.unwrap_or(DVec3::Y);
        // A lit grid's fields as the GPU draws them: the light field as one
        // of scalar and modulator.
        let lit = |field: ReferenceVolume| match (field, &volume.lighting) {
            (ReferenceVolume::Grid(grid), Some(lighting)) => lit_fields(&grid, lighting, sun),
            (field, _) => Ok((field, None)),
        };
        let ((field, modulation), centre) = match volume.field {
            SceneField::Grid(grid) => {
                let centre = (grid.origin() + grid.max_corner()) / 2.0;
                (lit(ReferenceVolume::Grid(grid))?, centre)
            }
            SceneField::Cells(cells) => {
                let points = || cells.iter().flat_map(|cell| cell.positions);
                let min = points().fold(DVec3::INFINITY, DVec3::min);
                let max = points().fold(DVec3::NEG_INFINITY, DVec3::max);
                ((ReferenceVolume::Cells(cells), None), (min + max) / 2.0)
            }
            SceneField::Campfire(campfire) => {
                let centre = (campfire.min + campfire.max) / 2.0;
                (
                    lit(ReferenceVolume::Grid(campfire.grid_at(last_frame)))?,
                    centre,
                )
            }
            SceneField::Cloud(cloud) => {
                let centre = (cloud.min + cloud.max) / 2.0;
                let fields = match cloud.keyframes_at(last_frame) {
                    // In the wind: the blend of both keyframes' fields (and
                    // light fields), as the GPU draws it.
                    Some((times, blend)) => {
                        let [first, second] = times.map(|t| {
                            cloud
                                .grid_at(t)
                                .map_err(invalid)
                                .and_then(|grid| lit(ReferenceVolume::Grid(grid)))
                        });
                        let ((first, first_modulation), (second, second_modulation)) =
                            (first?, second?);
                        let modulation = match (first_modulation, second_modulation) {
                            (Some(Modulation::Grid(a)), Some(Modulation::Grid(b))) => {
                                Some(Modulation::Grid(blend_grids(&a, &b, blend)?))
                            }
                            _ => None,
                        };
                        let field = match (first, second) {
                            (ReferenceVolume::Grid(a), ReferenceVolume::Grid(b)) => {
                                ReferenceVolume::Grid(blend_grids(&a, &b, blend)?)
                            }
                            (first, _) => first,
                        };
                        (field, modulation)
                    }
                    None => lit(ReferenceVolume::Grid(
                        cloud.grid_at(last_frame).map_err(invalid)?,
                    ))?,
                };
                (fields, centre)
            }
        };
        let mut reference_scene =
            ReferenceScene::new(camera, field, volume.transfer_function, volume.mode);
        reference_scene.modulation = modulation;
        reference_scene.scattering = volume.lighting.as_ref().and_then(|lighting| {
            let LightModel::Scattering { asymmetry } = lighting.model else {
                return None;
            };
            Some(SegmentScattering {
                ambient: f64::from(lighting.ambient) * sky,
                sunlight: f64::from(lighting.diffuse),
                sun_direction: sun,
                asymmetry: f64::from(asymmetry),
                shadows: scene.sun_casts_shadows(),
            })
        });
        reference_scene.opaque_depth = opaque_depth.clone();
        reference_scene.fog = fog.clone();
        reference_scene.local_lights = local_lights.clone();
        reference_scene.occluders = light_occluders.clone();
        reference_scene.light_response = volume.light_response;
        reference_scene.sunlight = volume.fog_sunlight.map(|mut sunlight| {
            sunlight.clouds = clouds.clone();
            if scene.sun_casts_shadows() {
                sunlight.occluders = occluders.clone();
            }
            sunlight
        });
        if let Some(start) = fog
            .as_ref()
            .map(|fog| fog.start_distance)
            .filter(|start| volume.ends_where_fog_layers_begin && *start > 0.0)
        {
            reference_scene.opaque_depth =
                Some(depth_within(&camera, opaque_depth.as_deref(), start));
        }
        let distance = camera.position.distance(centre);
        if volume.mode == OpticalMode::Mip {
            mips.push((distance, reference_scene));
        } else {
            joint.push((distance, reference_scene));
        }
    }
    // One image of the sorted and emissive volumes, one per MIP volume.
    let passes = mips.len() + usize::from(!joint.is_empty());
    let report = |pass: usize| {
        move |rows: RenderProgress| {
            if let Some(progress) = progress {
                progress(ReferenceProgress {
                    pass,
                    passes,
                    rows_done: rows.rows_done,
                    rows_total: rows.rows_total,
                });
            }
        }
    };
    let mut layers = Vec::with_capacity(passes);
    if !joint.is_empty() {
        let nearest = joint
            .iter()
            .map(|(distance, _)| *distance)
            .fold(f64::INFINITY, f64::min);
        let scenes: Vec<ReferenceScene> = joint.into_iter().map(|(_, scene)| scene).collect();
        let image = nebel_reference::render_together(&scenes, Some(&report(0)))?;
        layers.push((nearest, OpticalMode::Sorted, image));
    }
    for (distance, scene) in mips {
        let image = nebel_reference::render(&scene, Some(&report(layers.len())))?;
        layers.push((distance, OpticalMode::Mip, image));
    }
    layers.sort_by(|a, b| b.0.total_cmp(&a.0));

    let background = background(scene);
    let pixel_count = camera.width as usize * camera.height as usize;
    let pixels = (0..pixel_count)
        .map(|index| {
            let on_mesh = opaque_depth
                .as_ref()
                .is_some_and(|depth| depth[index].is_finite());
            let mut behind =
                DVec3::from(if on_mesh { [0.0; 3] } else { background }.map(f64::from));
            if let Some(fog) = &fog {
                // The fog from the eye to the surface or the sky, under the
                // volumes (which the integrator saw through it).
                let (x, y) = (index as u32 % camera.width, index as u32 / camera.width);
                let (ray, depth_to_distance) = camera.pixel_ray(x, y);
                let t_far = opaque_depth.as_ref().map_or(f64::INFINITY, |depth| {
                    f64::from(depth[index]) / depth_to_distance
                });
                behind = fog.over(&ray, t_far, behind.extend(1.0)).truncate();
            }
            let mut accumulated = DVec4::ZERO;
            for (_, mode, image) in &layers {
                let mut layer = DVec4::from(image.pixels[index].map(f64::from));
                if *mode == OpticalMode::Mip {
                    // MIP lights the pixel without hiding what is behind.
                    layer.w = 0.0;
                }
                accumulated = mode.composite(layer, accumulated);
            }
            let pixel = accumulated.truncate() + (1.0 - accumulated.w) * behind;
            [pixel.x as f32, pixel.y as f32, pixel.z as f32, 1.0]
        })
        .collect();
    Ok(LinearImage {
        width: camera.width,
        height: camera.height,
        pixels,
    })
}

/// The opaque depth (view-space, per pixel) cut at `distance` along every
/// ray.
fn depth_within(camera: &ReferenceCamera, depth: Option<&[f32]>, distance: f64) -> Vec<f32> {
    (0..camera.height)
        .flat_map(|y| (0..camera.width).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (_, depth_to_distance) = camera.pixel_ray(x, y);
            let cut = (distance * depth_to_distance) as f32;
            depth.map_or(cut, |depth| depth[(y * camera.width + x) as usize].min(cut))
        })
        .collect()
}

fn invalid(error: impl ToString) -> ReferenceError {
    ReferenceError::InvalidVolume {
        reason: error.to_string(),
    }
}

/// The volumes that cast cloud shadows (`lighting: (ground_shadow: true)`)
/// at `time` seconds, as the sun in ground fog meets them: their density
/// with the shadow's extinction, in the world.
fn cloud_casters(volumes: &[BuiltVolume], time: f64) -> Result<Vec<ShadowCaster>, ReferenceError> {
    let mut casters = Vec::new();
    for volume in volumes {
        let Some(lighting) = volume.lighting.as_ref().filter(|l| l.ground_shadow) else {
            continue;
        };
        let grid = match &volume.field {
            SceneField::Grid(grid) => grid.clone(),
            SceneField::Campfire(campfire) => campfire.grid_at(time),
            SceneField::Cloud(cloud) => cloud.grid_at(time).map_err(invalid)?,
            SceneField::Cells(_) => continue,
        };
        casters.push(ShadowCaster {
            grid: Arc::new(grid),
            world_from_local: DAffine3::IDENTITY,
            extinction: f64::from(lighting.shadow_extinction),
        });
    }
    Ok(casters)
}

/// The scalar volume and modulator of a lit grid (see [`reference_image`]).
fn lit_fields(
    grid: &DensityGrid,
    lighting: &LightingDescription,
    sun: DVec3,
) -> Result<(ReferenceVolume, Option<Modulation>), ReferenceError> {
    let padded = grid
        .padded_to_power_of_two_plus_one(PadFill::Value(0.0))
        .map_err(invalid)?;
    let extinction = lighting.shadow_extinction;
    let settings = CloudLighting {
        scattering_octaves: lighting.scattering_octaves,
        sky_occlusion: lighting.sky_occlusion,
        ..match lighting.model {
            LightModel::Scattering { .. } => CloudLighting::transmittance(sun, extinction),
            LightModel::Isotropic | LightModel::NonPhysical => {
                CloudLighting::shaded(lighting.ambient, lighting.diffuse, sun, extinction)
            }
        }
    };
    let light = light_field(&padded, &settings).map_err(invalid)?;
    Ok(match lighting.model {
        LightModel::Isotropic | LightModel::Scattering { .. } => {
            (ReferenceVolume::Grid(light), Some(Modulation::Grid(padded)))
        }
        LightModel::NonPhysical => (ReferenceVolume::Grid(padded), Some(Modulation::Grid(light))),
    })
}

/// `(1 − blend) · a + blend · b` point by point, on `a`'s points (both
/// keyframes of one cloud share them).
fn blend_grids(
    a: &DensityGrid,
    b: &DensityGrid,
    blend: f64,
) -> Result<DensityGrid, ReferenceError> {
    a.mixed(b, blend as f32).map_err(invalid)
}

/// The scene's clear colour, linear.
fn background(scene: &SceneDescription) -> [f32; 3] {
    scene
        .clear_color
        .map(|c| srgb_to_linear(f64::from(c)) as f32)
}

/// Writes a reference image as an 8-bit sRGB PNG.
pub fn save_reference(image: &LinearImage, out: &Path) -> Result<(), ImageMetricsError> {
    save_png(image, out, [0.0; 3])
}
