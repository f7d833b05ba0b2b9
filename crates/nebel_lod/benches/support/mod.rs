//! What the cloud-layer benches share: the camera of a view and the exact
//! CPU image of a lit batch against the scenes' sky.

use glam::{DAffine3, DMat4, DVec3, DVec4, UVec2};
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::TransferFunction;
use nebel_lod::{Cells, GpuCell, View};
use nebel_reference::image_metrics::LinearImage;
use nebel_reference::{Modulation, ReferenceCamera, ReferenceScene, ReferenceVolume, render};

/// The sky colour of the scenes, behind the clouds.
const SKY: DVec4 = DVec4::new(0.36, 0.55, 0.85, 1.0);

/// The view and camera from `eye` toward `target`, 60° vertical field of
/// view, `size` pixels.
pub fn view(eye: DVec3, target: DVec3, size: [u32; 2]) -> (View, ReferenceCamera) {
    let [width, height] = size;
    let aspect = f64::from(width) / f64::from(height);
    let clip_from_world = DMat4::perspective_infinite_reverse_rh(60f64.to_radians(), aspect, 1.0)
        * DMat4::look_at_rh(eye, target, DVec3::Y);
    let view = View::new(DAffine3::IDENTITY, eye, UVec2::new(width, height))
        .with_projection(clip_from_world);
    let camera = ReferenceCamera {
        position: eye,
        vertical_fov: 60f64.to_radians(),
        width,
        height,
        ..ReferenceCamera::default()
    }
    .looking_at(target, DVec3::Y);
    (view, camera)
}

/// The exact image of the lit `batch` (not blended; its modulators scale
/// the segment lengths) drawn with `transfer` from `camera`, over the sky.
pub fn image(batch: &Cells, camera: ReferenceCamera, transfer: &TransferFunction) -> LinearImage {
    let cells = batch
        .tetrahedra
        .iter()
        .map(GpuCell::to_tetrahedron)
        .collect();
    let mut scene = ReferenceScene::new(
        camera,
        ReferenceVolume::Cells(cells),
        transfer.clone(),
        OpticalMode::Sorted,
    );
    scene.modulation = Some(Modulation::Cells(
        batch.modulators.iter().map(|m| m.map(f64::from)).collect(),
    ));
    scene.background = SKY;
    render(&scene, None).expect("reference render")
}
