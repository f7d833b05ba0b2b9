//! The exact CPU reference of a scene, as `nebel reference` writes it.
//!
//! Every volume integrated by [`nebel_core::reference::render`] from the
//! camera of the scene's last frame (an animated campfire at that frame's
//! time), cut at the scene's meshes. The reference shades no surface: a pixel
//! whose ray ends on a mesh composites over black, the others over the clear
//! colour, so accuracy scenes use black meshes and no lights.

use std::path::Path;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use glam::{DVec3, DVec4};
use nebel_core::image_metrics::{ImageMetricsError, LinearImage, save_png, srgb_to_linear};
use nebel_core::optics::OpticalMode;
use nebel_core::reference::{ReferenceError, ReferenceScene, ReferenceVolume, RenderProgress};
use nebel_core::scene::{BuiltVolume, SceneDescription, VolumeField};

/// Renders `volumes` of `scene` exactly; with `progress`, reports rows on
/// stderr every two seconds.
///
/// Each volume is integrated on its own and the results are combined the way
/// the GPU pass does: accumulated from transparent, farthest centre first,
/// each with its mode ([`OpticalMode::composite`]: "over" for sorted, sum for
/// emissive, maximum for MIP, the last two with no opacity), then put over
/// the clear colour, or over black where the pixel's ray ends on a mesh. This
/// is exact when the volumes do not interpenetrate along a ray, and for
/// emissive and MIP volumes always.
pub fn reference_image(
    scene: &SceneDescription,
    volumes: Vec<BuiltVolume>,
    progress: bool,
) -> Result<LinearImage, ReferenceError> {
    let camera = scene.reference_camera();
    let opaque_depth = scene.opaque_depth(&camera);
    let mut layers = Vec::with_capacity(volumes.len());
    for volume in volumes {
        let (field, centre) = match volume.field {
            VolumeField::Grid(grid) => {
                let centre = (grid.origin() + grid.max_corner()) / 2.0;
                (ReferenceVolume::Grid(grid), centre)
            }
            VolumeField::Cells(cells) => {
                let points = || cells.iter().flat_map(|cell| cell.positions);
                let min = points().fold(DVec3::INFINITY, DVec3::min);
                let max = points().fold(DVec3::NEG_INFINITY, DVec3::max);
                (ReferenceVolume::Cells(cells), (min + max) / 2.0)
            }
            VolumeField::Campfire(campfire) => {
                let last_frame = scene.frame_time(scene.output.frames - 1);
                let centre = (campfire.min + campfire.max) / 2.0;
                (
                    ReferenceVolume::Grid(campfire.grid_at(f64::from(last_frame))),
                    centre,
                )
            }
        };
        let mut reference_scene =
            ReferenceScene::new(camera, field, volume.transfer_function, volume.mode);
        reference_scene.opaque_depth = opaque_depth.clone();
        let last_report = Mutex::new(Instant::now());
        let report = |rows: RenderProgress| {
            let mut last = last_report
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            if progress && last.elapsed() >= Duration::from_secs(2) {
                eprintln!(
                    "nebel: reference row {}/{}",
                    rows.rows_done, rows.rows_total
                );
                *last = Instant::now();
            }
        };
        let image = nebel_core::reference::render(&reference_scene, Some(&report))?;
        layers.push((camera.position.distance(centre), volume.mode, image));
    }
    layers.sort_by(|a, b| b.0.total_cmp(&a.0));

    let background = background(scene);
    let pixel_count = camera.width as usize * camera.height as usize;
    let pixels = (0..pixel_count)
        .map(|index| {
            let on_mesh = opaque_depth
                .as_ref()
                .is_some_and(|depth| depth[index].is_finite());
            let behind = DVec3::from(if on_mesh { [0.0; 3] } else { background }.map(f64::from));
            let mut accumulated = DVec4::ZERO;
            for (_, mode, image) in &layers {
                let mut layer = DVec4::from(image.pixels[index].map(f64::from));
                if *mode != OpticalMode::Sorted {
                    // Emissive and MIP light the pixel without hiding what is behind.
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

/// The scene's clear colour, linear.
fn background(scene: &SceneDescription) -> [f32; 3] {
    scene
        .clear_color
        .map(|c| srgb_to_linear(f64::from(c)) as f32)
}

/// Writes a reference image as an 8-bit sRGB PNG.
pub fn save_reference(
    image: &nebel_core::image_metrics::LinearImage,
    out: &Path,
) -> Result<(), ImageMetricsError> {
    save_png(image, out, [0.0; 3])
}
