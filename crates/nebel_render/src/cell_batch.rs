//! The common currency of every volumetric effect: a batch of cells to draw.
//!
//! An effect plugin (volumes, ...) gives an entity a [`CellBatch`] and
//! rewrites it when the view or its data changes; the cell-projection render
//! system ([`crate::cell_projection`]) uploads it again when Bevy's change
//! detection says it changed, and draws it. A batch is drawn only while it has
//! cells and a transfer function that is not transparent everywhere.

use std::sync::Arc;

use bevy::prelude::*;
use bevy::render::render_resource::ShaderType;
use nebel_core::local_light::LightResponse;
use nebel_core::optics::{OpticalMode, henyey_greenstein};
use nebel_core::transfer::TransferFunction;
use nebel_lod::Cells;

use crate::cloud_shadow_maps::CloudShadowMapUniform;
use crate::fog_sunlight::{CellFogSunlight, FogSunUniform};
use crate::local_lights::{LocalLightsUniform, ReachingLights};

/// The sun and sky of a scattering batch ([`CellBatch::scattering`]).
#[derive(Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Default, Clone)]
pub struct CellScattering {
    /// Unit direction toward the sun, world space. Default `+Y`.
    pub sun_direction: Vec3,
    /// Sunlight that reaches the volume, linear RGB in the transfer
    /// function's colour units (times the normalised phase `4π p_HG`, 1 for
    /// isotropic scattering). Default white (1, 1, 1).
    pub sun_colour: Vec3,
    /// Sky light scattered toward the eye by every unit of opacity, linear
    /// RGB, isotropic and unshadowed. Default (0.3, 0.33, 0.4).
    pub ambient_colour: Vec3,
    /// Henyey-Greenstein asymmetry `g`, in (−1, 1): > 0 scatters forward, so
    /// a cloud between the eye and the sun gets a bright rim. Clamped to
    /// ±0.99 by the render system. Default 0.6.
    pub asymmetry: f32,
    /// The sun casts shadows (`shadow_maps_enabled`): in a view with Bevy's
    /// lights, its shadow map hides it from the volume behind opaque meshes
    /// (the sky's light stays). Default false.
    pub shadows: bool,
}

impl Default for CellScattering {
    fn default() -> Self {
        Self {
            sun_direction: Vec3::Y,
            sun_colour: Vec3::ONE,
            ambient_colour: Vec3::new(0.3, 0.33, 0.4),
            asymmetry: 0.6,
            shadows: false,
        }
    }
}

impl CellScattering {
    /// The normalised Henyey-Greenstein phase `4π p_HG(θ)` for the unit view
    /// ray `direction` (from the eye outward): `(1 − g²) / (1 + g² − 2g
    /// cos θ)^{3/2}` with `cos θ = direction · sun_direction` (light from the
    /// sun travels along `−sun_direction` and reaches the eye along
    /// `−direction`). 1 for `g = 0`; it integrates to 4π over the sphere.
    pub fn phase(&self, direction: Vec3) -> f32 {
        henyey_greenstein(
            f64::from(self.asymmetry),
            f64::from(direction.dot(self.sun_direction)),
        ) as f32
    }
}

/// The shader's per-batch `CellBatchParameters` uniform: a batch's
/// [`CellScattering`] (zeros without one) and its [`CellBlend`].
#[derive(Clone, Copy, Debug, Default, PartialEq, ShaderType)]
pub(crate) struct CellBatchUniform {
    /// xyz: unit direction toward the sun; w: the asymmetry `g`, clamped to
    /// ±0.99.
    pub sun: Vec4,
    /// The sun colour; w unused.
    pub sun_colour: Vec4,
    /// The ambient colour; w unused.
    pub ambient_colour: Vec4,
    /// x: the blend factor β toward the next keyframe, in [0, 1]; yzw unused.
    pub blend: Vec4,
    /// The [`CellSunlight`] factor; w unused.
    pub sunlight: Vec4,
    /// The local lights that reach the batch ([`crate::local_lights`]).
    pub lights: LocalLightsUniform,
    /// The sun in ground fog ([`crate::fog_sunlight`]).
    pub fog_sun: FogSunUniform,
}

impl CellBatchUniform {
    /// The uniform of a batch with `scattering` blended by `blend` (already
    /// clamped, [`CellBlend::clamped`]) under `sunlight` (already checked,
    /// [`CellSunlight::checked`]), lit by `lights` scattered with
    /// `response` (checked here) and by the sun in ground fog `fog_sun`
    /// under the clouds' shadow maps.
    pub(crate) fn new(
        scattering: Option<&CellScattering>,
        blend: f32,
        sunlight: Vec3,
        (lights, response): (&ReachingLights, LightResponse),
        fog_sun: Option<(&CellFogSunlight, [CloudShadowMapUniform; 2])>,
    ) -> Self {
        let mut uniform = scattering.map_or_else(Self::default, |scattering| Self {
            sun: scattering
                .sun_direction
                .normalize_or(Vec3::Y)
                .extend(scattering.asymmetry.clamp(-0.99, 0.99)),
            sun_colour: scattering.sun_colour.extend(0.0),
            ambient_colour: scattering.ambient_colour.extend(0.0),
            ..Self::default()
        });
        uniform.blend.x = blend;
        uniform.sunlight = sunlight.extend(0.0);
        uniform.lights = LocalLightsUniform::new(lights, response);
        uniform.fog_sun = fog_sun
            .map(|(sunlight, clouds)| FogSunUniform::new(sunlight, clouds))
            .unwrap_or_default();
        uniform
    }
}

/// The colour and strength of the sunlight a lit [`CellBatch`] is drawn
/// under, as a factor on its colours (linear RGB): the batch's transfer
/// function gives the colour under a white sun of the reference strength;
/// this tints and scales it. For single scattering
/// ([`CellBatch::scattering`]) it scales the sun's part only; otherwise
/// the whole colour, sky light included (one light field cannot tell them
/// apart). A volume plugin sets it from the scene's sun; the render system
/// writes it into a uniform each frame it changes, without an upload of the
/// cells. Without it a batch is drawn as if under `(1, 1, 1)`.
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct CellSunlight {
    /// The factor, linear RGB, each finite and ≥ 0 (others draw as 0).
    /// Default (1, 1, 1).
    pub colour: Vec3,
}

impl Default for CellSunlight {
    fn default() -> Self {
        Self { colour: Vec3::ONE }
    }
}

impl CellSunlight {
    /// The factor the render system draws with: each channel finite and
    /// ≥ 0, others as 0.
    pub fn checked(&self) -> Vec3 {
        finite_non_negative(self.colour)
    }
}

/// `colour` with each channel finite and ≥ 0, others as 0: a light's colour
/// as the render system draws it.
pub(crate) fn finite_non_negative(colour: Vec3) -> Vec3 {
    Vec3::from_array(
        colour
            .to_array()
            .map(|c| if c.is_finite() { c.max(0.0) } else { 0.0 }),
    )
}

/// How far a keyframe-blended [`CellBatch`] is drawn from the field at the
/// first blend of its span toward the field at its last
/// (`nebel_lod::Cells`'s keyframe blending, whose `mix_factor` gives it
/// for a keyframe blend): every vertex's scalar and modulator at `(1 − t) ·
/// current + t · next`. Changing it costs a 64-byte uniform write, not an
/// upload of the cells. Ignored for a batch that is not blended.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct CellBlend {
    /// The mix factor `t`, in [0, 1]: 0 draws the cells' own scalars, 1 their
    /// next ones. Clamped by the render system (NaN draws as 0). Default 0.
    pub factor: f32,
}

impl CellBlend {
    /// The factor the render system draws with: clamped to [0, 1], NaN as 0.
    pub fn clamped(&self) -> f32 {
        if self.factor.is_nan() {
            0.0
        } else {
            self.factor.clamp(0.0, 1.0)
        }
    }
}

/// Cells in world space with one transfer function and one optical mode.
///
/// The render system uploads the cells again whenever the component changed
/// (Bevy's change detection: any mutable access counts), so write it only
/// when the cells did change.
#[derive(Component, Clone, Debug, Default, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct CellBatch {
    /// Tetrahedra in world space, scalar in `w`, in draw order (back to front
    /// for [`OpticalMode::Sorted`], any order for the other modes), with
    /// their world bounds and, for a lit cloud, per cell the segment-length
    /// modulator `m ∈ [0, 1]` at its four vertices: every ray segment is then
    /// integrated over `l' = l · (m_f + m_b)/2` instead of `l` (Röttger and
    /// Ertl 2003, §5.1, Eq. 9; see [`nebel_lod::Cells`]). A modulator list
    /// whose length is neither 0 nor the cell count is refused by the render
    /// system (the batch is not drawn and an error is logged); so is a
    /// keyframe-blended batch whose next scalars (or, when modulated, next
    /// modulators) do not number the cells. The blend factor is the
    /// entity's [`CellBlend`]. A batch that is a whole grid
    /// (`nebel_lod::Cells::grid`) is ray cast through its tetrahedra
    /// instead; one whose values exceed the device's storage buffer binding
    /// is refused the same way. Shared with
    /// whatever built it (`nebel_lod::VolumeBatcher`). Default: no cells.
    #[reflect(ignore)]
    pub cells: Arc<Cells>,
    /// κ and ρ over the scalar; `None` draws nothing. Default: `None`.
    #[reflect(ignore)]
    pub transfer_function: Option<Arc<TransferFunction>>,
    /// How the cells' segments combine. Default: [`OpticalMode::Sorted`].
    pub mode: OpticalMode,
    /// Single scattering of the sun (Nes, "Physically Plausible Weather
    /// Visualization", 2008; only for [`OpticalMode::Sorted`]): the transfer
    /// function's colour is read as the light scattered from the sun at each
    /// point (its transmittance toward the sun, times an albedo), and every
    /// segment's colour becomes `ambient · α + sun · 4π p_HG(θ) · C`, with θ
    /// between the view ray and the sunlight. `None` draws the transfer
    /// function's colour as it is. Default: `None`.
    pub scattering: Option<CellScattering>,
    /// The cells are fog that a view's fog layers take over from where they
    /// begin (`FogLayers::start_distance` of `nebel_fog`, when above 0):
    /// their segments end at that distance from the eye, so the two never
    /// count the same fog twice. Ground fog sets it. Default false.
    pub ends_where_fog_layers_begin: bool,
    /// How a sorted batch scatters the point and spot lights that reach it
    /// ([`crate::local_lights`]): their phase's asymmetry and a factor on
    /// its colour; checked by the render system
    /// ([`LightResponse::checked`]). Default: isotropic, factor 1.
    pub light_response: LightResponse,
}

impl CellBatch {
    /// A batch of `cells` drawn with `transfer_function` in `mode`.
    pub fn new(
        cells: Arc<Cells>,
        transfer_function: Arc<TransferFunction>,
        mode: OpticalMode,
    ) -> Self {
        Self {
            cells,
            transfer_function: Some(transfer_function),
            mode,
            scattering: None,
            ends_where_fog_layers_begin: false,
            light_response: LightResponse::default(),
        }
    }

    /// Whether the render system has anything to draw for this batch.
    pub fn is_drawable(&self) -> bool {
        !self.cells.is_empty()
            && self
                .transfer_function
                .as_ref()
                .is_some_and(|tf| !tf.is_transparent(0.0, 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_phase_peaks_toward_the_sun_and_the_uniform_clamps_g() {
        let scattering = CellScattering {
            sun_direction: Vec3::Z,
            asymmetry: 1.5,
            ..default()
        };
        assert!(scattering.phase(Vec3::Z) > 100.0 * scattering.phase(Vec3::NEG_Z));
        let none = ReachingLights::default();
        let uniform =
            CellBatchUniform::new(Some(&scattering), 0.25, Vec3::ONE, (&none, default()), None);
        assert_eq!(uniform.sun, Vec4::new(0.0, 0.0, 1.0, 0.99));
        assert_eq!(uniform.blend.x, 0.25);
        assert_eq!(uniform.sunlight, Vec4::new(1.0, 1.0, 1.0, 0.0));
        assert_eq!(uniform.lights.response.truncate().truncate(), Vec2::ZERO);
        let nan = LightResponse {
            asymmetry: f32::NAN,
            strength: f32::NAN,
        };
        let unlit = CellBatchUniform::new(None, 0.5, Vec3::ONE, (&none, nan), None);
        assert_eq!(
            (
                unlit.sun,
                unlit.lights.response.x,
                unlit.lights.response.y,
                unlit.lights.response.w
            ),
            (Vec4::ZERO, 0.0, 0.0, 0.0)
        );
        let lights = ReachingLights {
            count: 2,
            ..default()
        };
        let response = LightResponse {
            asymmetry: -3.0,
            strength: 4.0,
        };
        let lit = CellBatchUniform::new(None, 0.5, Vec3::ONE, (&lights, response), None);
        assert_eq!(lit.lights.response, Vec4::new(2.0, -0.99, 1e-4, 4.0));
        let sunlight = CellSunlight {
            colour: Vec3::new(f32::NAN, -1.0, 2.5),
        };
        assert_eq!(sunlight.checked(), Vec3::new(0.0, 0.0, 2.5));
        for (factor, clamped) in [(f32::NAN, 0.0), (-1.0, 0.0), (0.3, 0.3), (7.0, 1.0)] {
            assert_eq!(CellBlend { factor }.clamped(), clamped);
        }
    }
}
