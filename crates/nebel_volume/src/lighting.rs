//! Lit clouds: a light field γ per grid point and a segment length modulated
//! by a second field (Röttger and Ertl 2003 §5).
//!
//! Add [`VolumeLighting`] to a grid [`Volume`](crate::Volume). Without
//! [`VolumeLod`](crate::VolumeLod) the grid is ray cast whole at full
//! resolution, with the light field at its points (`nebel_lod::CellGrid`);
//! with it, drawn through the octree, which carries both fields. Projected
//! cells at full resolution carry no light field:
//! [`ProjectedCells`](crate::ProjectedCells) on a lit volume needs
//! [`VolumeLod`](crate::VolumeLod) (the batch's error says so otherwise).
//! The volume system then
//!
//! 1. computes γ at every grid point with `nebel_core::field::light_field`:
//!    `γ = ambient · T_sky + diffuse · T_sun · lambert`, the "standard
//!    ambient and diffuse lighting" of §5.2 on the density gradient,
//!    optionally shadowed by the transmittance toward the sun (Nes 2008;
//!    with [`VolumeLighting::scattering_octaves`], multiple scattering) and
//!    the sky dimmed by the cloud above ([`VolumeLighting::sky_occlusion`]), with the sun taken
//!    from the first [`DirectionalLight`] (straight up in the volume's frame
//!    when there is none), and again whenever the volume or its rotation
//!    changes or the sun comes to rest somewhere new; while the sun moves,
//!    from keyframes of the light field blended on the GPU
//!    (`nebel_lod::VolumeBatching`); the light's colour and illuminance scale the
//!    colours drawn (`nebel_render::CellSunlight`);
//! 2. with the octree, builds the hierarchy over both fields
//!    (`VolumeHierarchy::with_light`), so refinement follows the larger
//!    deviation of density and light (§5.1);
//! 3. draws one field as the transfer function's scalar and the other as a
//!    segment-length modulator, per [`CloudLightModel`].
//!
//! The sky's colour (`GlobalAmbientLight`'s) tints the ambient term of the
//! scattering model only, whose colour is `ambient · α + sun · C`; in the
//! paper's two models γ is one scalar of sky and sun together, and the
//! transfer function's colour over it is the palette, sky tint included.
//!
//! The render system draws the modulator exactly per pixel (the mean of the
//! linear modulator over each segment), so the model costs one extra storage
//! read per fragment and one byte per grid point.

use bevy::math::Affine3A;
use bevy::prelude::*;
use nebel_core::field::CloudLighting;
use nebel_lod::octree::CellScalars;
use nebel_render::CellScattering;

/// Which field gives the colour and which the opacity (Röttger and Ertl 2003 §5).
#[derive(Clone, Copy, Debug, Default, PartialEq, Reflect)]
#[reflect(Default, Clone)]
pub enum CloudLightModel {
    /// §5.1: the transfer function is over the light γ (colour `κ(γ)`, use
    /// `TransferPreset::CloudLight`, constant ρ = `ρ_max`), and the density
    /// `f` scales the segment length, `l' = l · f / f_max` (Eq. 9), so the
    /// opacity follows the density exactly and the colour the light. The
    /// default.
    #[default]
    Isotropic,
    /// §5.2 (non-physical): the transfer function is over the density (the
    /// paper's inverse colour ramp and linear ρ above a cut-off,
    /// `TransferPreset::Cloud`), and γ scales the segment length: the sunny
    /// side is opaque and bright, the far side translucent.
    NonPhysical,
    /// Single scattering of the sun (Nes 2008, beyond Röttger and Ertl 2003): γ is the
    /// plain transmittance toward the sun (no Lambert term; `ambient` and
    /// `diffuse` become the sky's and the sun's strength), the transfer
    /// function is over γ (use `TransferPreset::Transmittance`, or scale its
    /// κ by an albedo colour), the density scales the segment length as in
    /// `Isotropic`, and every pixel weighs the sunlit part by the
    /// Henyey-Greenstein phase of its view ray: a cloud between the eye and
    /// the sun gets a bright rim (`nebel_render::CellScattering`). A sun
    /// that casts shadows is hidden from the cloud by opaque meshes too,
    /// through Bevy's shadow map of it (the sky's light stays).
    Scattering {
        /// Henyey-Greenstein asymmetry `g` in (−1, 1); > 0 scatters forward.
        /// Clouds: about 0.6 to 0.85.
        asymmetry: f32,
    },
}

impl CloudLightModel {
    /// The cells' scalar and modulator for this model.
    pub fn cell_scalars(self) -> CellScalars {
        match self {
            Self::Isotropic | Self::Scattering { .. } => CellScalars::LightModulatedByDensity,
            Self::NonPhysical => CellScalars::DensityModulatedByLight,
        }
    }
}

/// Lights a grid [`Volume`](crate::Volume) with ambient and diffuse sunlight
/// (see the module docs).
#[derive(Component, Clone, Copy, Debug, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct VolumeLighting {
    /// Light every point receives, as a fraction of full light, in [0, 1]
    /// (the sky's strength for [`CloudLightModel::Scattering`], tinted by
    /// the colour of Bevy's `GlobalAmbientLight`). Default 0.3.
    pub ambient: f32,
    /// Strength of the sunlight (Lambert on the density gradient, times the
    /// shadow transmittance), as a fraction of full light, in [0, 1]; `γ` is
    /// clamped to 1 (the sun's strength for [`CloudLightModel::Scattering`]).
    /// Default 0.7.
    pub diffuse: f32,
    /// Optical density per world unit of the volume's local frame at density
    /// 1, for the transmittance toward the sun (Nes 2008's shadow volume),
    /// ≥ 0; 0 casts no shadow. Default 0.
    pub shadow_extinction: f32,
    /// Which field gives the colour and which the opacity. Default
    /// [`CloudLightModel::Isotropic`].
    pub model: CloudLightModel,
    /// Seconds between the keyframes of the light field while the sun moves
    /// (`nebel_lod::VolumeBatching`; a windy cloud uses its own
    /// [`CloudVolume::keyframe_interval`](crate::CloudVolume::keyframe_interval)),
    /// finite (below 1 ms, and NaN, count as 1 ms). Shorter follows the sun
    /// more closely at a proportional CPU cost. Default 2.
    pub keyframe_interval: f32,
    /// Octaves of multiple scattering of the sunlight (Wrenninge et al.
    /// 2013; `nebel_core::field::CloudLighting::scattering_octaves`), 1 to
    /// 8: more light reaches a cloud's interior. Default 1 (single
    /// scattering).
    pub scattering_octaves: u32,
    /// Whether the cloud above a point dims its ambient sky light, so the
    /// bases of thick clouds darken (`nebel_core::field::CloudLighting::sky_occlusion`);
    /// needs a shadow. Not for [`CloudLightModel::Scattering`], whose sky
    /// light the renderer adds per pixel. Default false.
    pub sky_occlusion: bool,
}

impl Default for VolumeLighting {
    fn default() -> Self {
        Self {
            ambient: CloudLighting::DEFAULT_AMBIENT,
            diffuse: CloudLighting::DEFAULT_DIFFUSE,
            shadow_extinction: 0.0,
            model: CloudLightModel::Isotropic,
            keyframe_interval: 2.0,
            scattering_octaves: 1,
            sky_occlusion: false,
        }
    }
}

impl VolumeLighting {
    /// The light-field settings for a sun in direction `sun_local` (toward the
    /// sun, in the volume's local frame): ambient and Lambert-shaded diffuse
    /// light, or for [`CloudLightModel::Scattering`] the transmittance alone.
    pub fn light_field_settings(&self, sun_local: Vec3, zenith_local: Vec3) -> CloudLighting {
        let (sun, extinction) = (sun_local.as_dvec3(), self.shadow_extinction);
        let light = match self.model {
            CloudLightModel::Scattering { .. } => CloudLighting::transmittance(sun, extinction),
            CloudLightModel::Isotropic | CloudLightModel::NonPhysical => {
                CloudLighting::shaded(self.ambient, self.diffuse, sun, extinction)
            }
        };
        CloudLighting {
            scattering_octaves: self.scattering_octaves,
            sky_occlusion: self.sky_occlusion,
            sky_direction: zenith_local.as_dvec3(),
            ..light
        }
    }

    /// The render system's sun and sky for [`CloudLightModel::Scattering`]
    /// (`sun_world`: toward the sun, world space; `sky`: the sky's linear
    /// colour, Bevy's `GlobalAmbientLight` colour); `None` for the other
    /// models. The sun is white of strength `diffuse` (its own colour comes
    /// with `nebel_render::CellSunlight`), the sky `ambient` times its
    /// colour; a sun that casts shadows (`shadows`) is hidden by opaque
    /// meshes through Bevy's shadow map of it.
    pub fn cell_scattering(
        &self,
        sun_world: Vec3,
        sky: Vec3,
        shadows: bool,
    ) -> Option<CellScattering> {
        match self.model {
            CloudLightModel::Scattering { asymmetry } => Some(CellScattering {
                sun_direction: sun_world.normalize_or(Vec3::Y),
                sun_colour: Vec3::splat(self.diffuse),
                ambient_colour: self.ambient * sky,
                asymmetry,
                shadows,
            }),
            _ => None,
        }
    }
}

/// A world direction (toward the sun: the first directional light's `+Z`,
/// as it shines along `−Z`; or toward the zenith) in a volume's local frame,
/// mapped by the inverse of the volume's linear part; `+Y` without one or
/// when the map is singular.
pub(crate) fn in_local_frame(world: Option<Vec3>, world_from_local: &Affine3A) -> Vec3 {
    let Some(sun) = world else {
        return Vec3::Y;
    };
    let linear = Mat3::from(world_from_local.matrix3);
    if linear.determinant().abs() <= f32::EPSILON {
        return Vec3::Y;
    }
    (linear.inverse() * sun).try_normalize().unwrap_or(Vec3::Y)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sun_is_mapped_into_the_volume_frame() {
        let turned = Affine3A::from_rotation_y(std::f32::consts::FRAC_PI_2);
        let sun = in_local_frame(Some(Vec3::X), &turned);
        assert!(sun.distance(Vec3::Z) < 1e-6, "{sun}");
        let stretched = Affine3A::from_scale(Vec3::new(4.0, 1.0, 1.0));
        let sun = in_local_frame(Some(Vec3::new(1.0, 1.0, 0.0).normalize()), &stretched);
        assert!(sun.distance(Vec3::new(0.25, 1.0, 0.0).normalize()) < 1e-6);
        assert_eq!(in_local_frame(None, &turned), Vec3::Y);
        assert_eq!(
            in_local_frame(Some(Vec3::X), &Affine3A::from_scale(Vec3::ZERO)),
            Vec3::Y
        );
    }
}
