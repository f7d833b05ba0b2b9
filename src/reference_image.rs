//! The exact CPU reference of a scene, as `nebel reference` writes it.
//!
//! One volume, integrated by [`nebel_core::reference::render`] from the
//! camera of the scene's last frame (an animated campfire at that frame's
//! time), cut at the scene's meshes. The reference shades no surface: a pixel
//! whose ray ends on a mesh composites over black, the others over the clear
//! colour, so accuracy scenes use black meshes and no lights.

use std::path::Path;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use nebel_core::image_metrics::{ImageMetricsError, save_png, srgb_to_linear};
use nebel_core::reference::{ReferenceError, ReferenceScene, ReferenceVolume, RenderProgress};
use nebel_core::scene::{BuiltVolume, SceneDescription, VolumeField};

/// Renders `volume` of `scene` exactly; with `progress`, reports rows on
/// stderr every two seconds.
pub fn reference_image(
    scene: &SceneDescription,
    volume: BuiltVolume,
    progress: bool,
) -> Result<nebel_core::image_metrics::LinearImage, ReferenceError> {
    let field = match volume.field {
        VolumeField::Grid(grid) => ReferenceVolume::Grid(grid),
        VolumeField::Cells(cells) => ReferenceVolume::Cells(cells),
        VolumeField::Campfire(campfire) => {
            let last_frame = scene.frame_time(scene.output.frames - 1);
            ReferenceVolume::Grid(campfire.grid_at(f64::from(last_frame)))
        }
    };
    let camera = scene.reference_camera();
    let mut reference_scene =
        ReferenceScene::new(camera.clone(), field, volume.transfer_function, volume.mode);
    reference_scene.opaque_depth = scene.opaque_depth(&camera);
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
    let mut image = nebel_core::reference::render(&reference_scene, Some(&report))?;
    if let Some(depth) = &reference_scene.opaque_depth {
        for (pixel, depth) in image.pixels.iter_mut().zip(depth) {
            if depth.is_finite() {
                pixel[3] = 1.0;
            }
        }
    }
    let background = background(scene);
    for pixel in &mut image.pixels {
        let transparency = 1.0 - pixel[3];
        for channel in 0..3 {
            pixel[channel] += transparency * background[channel];
        }
        pixel[3] = 1.0;
    }
    Ok(image)
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
