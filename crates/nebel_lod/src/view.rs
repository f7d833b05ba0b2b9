//! The view of one volume for one frame: everything the batch builders of
//! this crate read of the camera.
//!
//! A [`View`] places the volume in the world (`world_from_local`: the
//! volume's own frame, grid coordinates for a density grid, cell coordinates
//! for a cell mesh, to world space) and holds the eye and the view frustum in
//! world space and the viewport's size in pixels. Every builder takes one:
//! [`full_resolution_batch`](crate::full_resolution_batch) and
//! [`order_key`](crate::order_key), the octree's
//! [`refine`](fn@crate::octree::refine) and
//! [`lod_batch`](crate::octree::lod_batch), [`sorted_batch`](crate::sorted_batch),
//! and [`VolumeBatcher`](crate::VolumeBatcher), which compares consecutive
//! views to rebuild only when the batch would change.
//!
//! # Viewport
//!
//! `viewport` is the size of the view's render target in physical pixels. A
//! view with no pixels (zero width or height: a minimised window, a
//! collapsed split screen) sees nothing: every builder still checks the view
//! (transform and eye) and then returns an empty batch, or an empty
//! refinement. The octree's screen-error criterion
//! ([`crate::octree::LodCriterion::ScreenError`]) measures nodes in pixels of
//! this viewport through the view's projection (`clip_from_world`); the
//! distance criterion of Röttger and Ertl 2003 Eq. 1 reads neither.
//!
//! # Projection
//!
//! `clip_from_world` is the camera's projection times the inverse of its
//! transform, Bevy's convention (clip `x, y` in [−1, 1] across the viewport,
//! `+y` up, `w > 0` in front of the eye). [`View::with_projection`] sets it
//! and the frustum from it at once.

use glam::{DAffine3, DMat4, DVec3, UVec2};
use nebel_core::cell::Tetrahedron;

use crate::frustum::Frustum;

/// The view of one volume for one frame (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// Maps the volume's local frame to world space: for a density grid its
    /// grid coordinates (point `(i, j, k)` at `origin + (i, j, k) · spacing`),
    /// for a cell mesh the cells' coordinates. Any finite invertible affine
    /// map (rotation, non-uniform scale, shear, mirror); the builders refuse
    /// others.
    pub world_from_local: DAffine3,
    /// The eye, world units.
    pub eye: DVec3,
    /// The view frustum in world space; `None` culls nothing.
    pub frustum: Option<Frustum>,
    /// Width and height of the render target, physical pixels. A zero width
    /// or height sees nothing (module docs).
    pub viewport: UVec2,
    /// World space to clip space (module docs); `None` when the builder is
    /// not told the projection, which only the screen-error criterion needs.
    pub clip_from_world: Option<DMat4>,
}

impl View {
    /// A view without culling: the volume placed by `world_from_local`, seen
    /// from `eye` (world units) on a render target of `viewport` pixels.
    pub fn new(world_from_local: DAffine3, eye: DVec3, viewport: UVec2) -> Self {
        Self {
            world_from_local,
            eye,
            frustum: None,
            viewport,
            clip_from_world: None,
        }
    }

    /// The view seen through the projection `clip_from_world` (module docs):
    /// the projection for criteria in pixels, and the frustum culled by,
    /// unless the matrix has no frustum (not finite or singular), which then
    /// culls nothing.
    pub fn with_projection(self, clip_from_world: DMat4) -> Self {
        Self {
            frustum: Frustum::from_view_projection(clip_from_world).ok(),
            clip_from_world: Some(clip_from_world),
            ..self
        }
    }

    /// The view culled by `frustum` (world space).
    pub fn with_frustum(self, frustum: Frustum) -> Self {
        Self {
            frustum: Some(frustum),
            ..self
        }
    }

    /// Whether the viewport has no pixels, so the view sees nothing.
    pub fn viewport_is_empty(&self) -> bool {
        self.viewport.x == 0 || self.viewport.y == 0
    }

    /// The inverse of `world_from_local`; `None` when that map is not finite
    /// or not invertible.
    pub fn local_from_world(&self) -> Option<DAffine3> {
        let determinant = self.world_from_local.matrix3.determinant();
        let inverse = self.world_from_local.inverse();
        (self.world_from_local.is_finite()
            && determinant != 0.0
            && determinant.is_finite()
            && inverse.is_finite())
        .then_some(inverse)
    }

    /// `tetrahedron` (local frame) in world space, scalars unchanged.
    pub(crate) fn to_world(&self, tetrahedron: &Tetrahedron) -> Tetrahedron {
        Tetrahedron {
            positions: tetrahedron
                .positions
                .map(|p| self.world_from_local.transform_point3(p)),
            scalars: tetrahedron.scalars,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_empty_viewport_and_a_singular_transform_are_recognised() {
        let view = View::new(
            DAffine3::from_translation(DVec3::X),
            DVec3::ZERO,
            UVec2::new(4, 3),
        );
        assert!(!view.viewport_is_empty());
        assert!(
            View {
                viewport: UVec2::new(0, 3),
                ..view.clone()
            }
            .viewport_is_empty()
        );
        assert!(
            View {
                viewport: UVec2::new(4, 0),
                ..view.clone()
            }
            .viewport_is_empty()
        );
        assert_eq!(
            view.local_from_world().unwrap().transform_point3(DVec3::X),
            DVec3::ZERO
        );
        for singular in [
            DAffine3::from_scale(DVec3::new(1.0, 0.0, 1.0)),
            DAffine3::from_translation(DVec3::NAN),
            DAffine3::from_scale(DVec3::splat(1e300)),
        ] {
            let view = View {
                world_from_local: singular,
                ..view.clone()
            };
            assert_eq!(view.local_from_world(), None, "{singular}");
        }
        let frustum = Frustum::from_planes([(DVec3::X, 0.0)]).unwrap();
        assert_eq!(view.with_frustum(frustum.clone()).frustum, Some(frustum));
    }
}
