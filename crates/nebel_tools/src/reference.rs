//! The exact CPU reference of a whole scene file, as `nebel reference` and
//! `nebel bench-lod` draw it: its volumes, and its terrain as the opaque
//! ground, with the terrain's fog (the cells the plugin draws for the
//! reference camera, on the triangles the GPU draws,
//! `nebel_scene::TerrainDescription::fog_reference`) or, without fog, as the
//! full-resolution bilinear surface, and its aurora (the cells the plugin
//! draws for the reference camera at the last frame's time,
//! `nebel_scene::AuroraDescription::reference`) and its cloud layer
//! (likewise, `nebel_scene::CloudLayerDescription::reference`).

use std::path::Path;

use nebel_reference::image_metrics::LinearImage;
use nebel_scene::reference::reference_image_with_terrain;
use nebel_scene::{ReferenceTerrain, SceneDescription};

use crate::error::CommandError;
use crate::progress::reference_bar;

/// The reference image of `scene` (read from `scene_path`, which resolves
/// its files), with a progress bar when `progress`.
pub fn scene_reference(
    scene_path: &Path,
    scene: &SceneDescription,
    progress: bool,
) -> Result<LinearImage, CommandError> {
    let mut volumes = scene.build_volumes(scene_path)?;
    let unit_heights = scene.build_terrain(scene_path)?;
    let fog = match (&unit_heights, scene.build_ground_fog(scene_path)?) {
        (Some(unit), Some(fog)) => scene.build_fog_reference(scene_path, unit, &fog)?,
        _ => None,
    };
    // A fogged terrain is drawn as the triangles the fog's cells lie on.
    let terrain = match fog {
        Some(fog) => {
            volumes.extend(fog.volume);
            Some(ReferenceTerrain::Triangles(fog.ground))
        }
        None => scene
            .terrain
            .as_ref()
            .zip(unit_heights.as_ref())
            .map(|(terrain, unit)| ReferenceTerrain::Bilinear(terrain.world_heights(unit))),
    };
    if let Some(aurora) = scene.build_aurora(scene_path)? {
        volumes.extend(scene.build_aurora_reference(scene_path, &aurora)?);
    }
    if let Some(layer) = scene.build_cloud_layer(scene_path)? {
        volumes.extend(scene.build_cloud_layer_reference(scene_path, &layer)?);
    }
    let terrain_shadow = match &unit_heights {
        Some(unit) => scene.build_terrain_shadow(scene_path, unit)?,
        None => None,
    };
    let terrain_heights = unit_heights
        .as_ref()
        .and_then(|unit| scene.terrain_occluder(unit));
    let (bar, report) = reference_bar(progress);
    let image = reference_image_with_terrain(
        scene,
        volumes,
        terrain.as_ref(),
        terrain_shadow,
        terrain_heights,
        Some(&report),
    )?;
    bar.finish_and_clear();
    Ok(image)
}
