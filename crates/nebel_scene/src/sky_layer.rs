//! What the aurora's and the cloud layer's descriptions share: a layer
//! between two surfaces seen whole (unculled) from an eye, as a volume of
//! cells for the reference, the way the sky plugins draw it.

use glam::{DAffine3, DVec3};
use nebel_core::local_light::LightResponse;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::TransferFunction;
use nebel_lod::{
    CellOrder, FogProfile, GpuCell, LayerView, LodSettings, PrismScalar, SurfaceLayer, TerrainMesh,
};

use super::{BuiltVolume, InvalidField, SceneField};

/// How a sky layer is drawn for the reference: where, its quadtree's
/// accuracy, its prisms' levels, scalar and order, and its optics.
pub(crate) struct LayerDrawing<'a> {
    /// The layer's centre, world space.
    pub center: [f32; 3],
    /// The quadtree's accuracy `c`.
    pub accuracy: f32,
    /// The prisms' levels.
    pub profile: &'a FogProfile,
    /// What the prisms carry.
    pub scalar: PrismScalar,
    /// Sorted or unordered.
    pub order: CellOrder,
    /// κ and ρ, the layer's factor applied.
    pub transfer_function: &'a TransferFunction,
    /// How it scatters volumetric point and spot lights.
    pub light_response: LightResponse,
    /// How the segments combine.
    pub mode: OpticalMode,
}

/// `layer`'s cells seen from `eye` (world space) as `drawing` draws them;
/// `None` when it has none. A refused refinement names the accuracy.
pub(crate) fn layer_reference(
    layer: &SurfaceLayer,
    drawing: &LayerDrawing,
    eye: DVec3,
) -> Result<Option<BuiltVolume>, InvalidField> {
    let view = LayerView {
        world_from_field: DAffine3::from_translation(DVec3::from(drawing.center.map(f64::from))),
        eye,
        frustum: None,
        lod: LodSettings {
            accuracy: drawing.accuracy,
            ..LodSettings::default()
        },
        order: drawing.order,
        profile: drawing.profile,
        scalar: drawing.scalar,
    };
    let mut cells = Vec::new();
    layer
        .cells(&view, &mut TerrainMesh::new(), &mut cells)
        .map_err(|error| InvalidField::new("accuracy", error.to_string()))?;
    Ok((!cells.is_empty()).then(|| BuiltVolume {
        field: SceneField::Cells(cells.iter().map(GpuCell::to_tetrahedron).collect()),
        transfer_function: drawing.transfer_function.clone(),
        mode: drawing.mode,
        lod: None,
        lighting: None,
        projected_cells: false,
        ends_where_fog_layers_begin: false,
        fog_sunlight: None,
        light_response: drawing.light_response,
    }))
}
