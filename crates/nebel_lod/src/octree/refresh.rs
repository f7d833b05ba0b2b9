//! When an octree's batch is refined again for a moving camera: not on every
//! move, but once the eye moved [`REFRESH_DISTANCE`] voxels or the view left
//! the frustum the batch was culled with, as the terrain waits for a
//! distance and a turn.
//!
//! A refinement culls with the camera's side planes widened as
//! [`Frustum::widened`] widens them: turned out by [`REFRESH_ANGLE`] and
//! pushed out by as far as a move of [`REFRESH_DISTANCE`] voxels reaches in
//! the world, each plus a [`Latency`] when the batch is drawn later than its
//! view (made on a worker: twice how far the view changed while the last one
//! was made). Its batch serves every later view of the same volume,
//! criterion and transfer function while
//!
//! - the eye is within [`REFRESH_DISTANCE`] voxels (index units of the grid)
//!   of the eye it was refined for;
//! - that widened frustum holds the new view's cone ([`Frustum::holds_view`]:
//!   a turn or a move that stays inside it, or a zoom in), and the projection
//!   is the same up to a rotation (the side planes' angles to each other);
//! - for the screen error, the viewport is the same.
//!
//! An orthographic or degenerate camera culls with its exact frustum, and any
//! change of it refines again. Drawn from an eye up to half a voxel away
//! (plus a frame or two of latency), a batch composites rays across the faces
//! whose planes the eye crossed out of order and carries the morph of a
//! slightly different distance: the octree tests bound both together against
//! a batch refined for the new eye.

use glam::DAffine3;

use super::VolumeHierarchy;
use crate::frustum::Frustum;
use crate::full_resolution::index_maps;
use crate::octree::LodCriterion;
use crate::view::View;

/// How far the eye may move, in voxels (the grid's index units), before an
/// octree's batch is refined again.
pub const REFRESH_DISTANCE: f64 = 0.5;

/// How far the camera may turn, radians (3°), before an octree's batch is
/// refined again.
pub const REFRESH_ANGLE: f64 = 3.0 * std::f64::consts::PI / 180.0;

/// How much more a refinement's culling allows for the view's change until
/// its batch is drawn, as when it is made on a worker (module docs): the
/// eye's move in voxels and the camera's turn in radians, besides the
/// thresholds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Latency {
    /// The eye's move, voxels (index units).
    pub distance: f64,
    /// The camera's turn, radians.
    pub angle: f64,
}

impl Latency {
    /// How far the view changed from `from` to `to` for `hierarchy`: the
    /// eye's move in index units, and the largest angle any plane of the
    /// frustum turned (0 without both frusta). Zero for a singular placement
    /// or a non-finite eye.
    pub fn between(hierarchy: &VolumeHierarchy, from: &View, to: &View) -> Self {
        let Some((_, index_from_world)) = maps(hierarchy, to) else {
            return Self::default();
        };
        let distance = index_from_world
            .transform_point3(from.eye)
            .distance(index_from_world.transform_point3(to.eye));
        let angle = match (&from.frustum, &to.frustum) {
            (Some(a), Some(b)) if a.planes().len() == b.planes().len() => a
                .planes()
                .iter()
                .zip(b.planes())
                .map(|(a, b)| a.truncate().angle_between(b.truncate()))
                .fold(0.0, f64::max),
            _ => 0.0,
        };
        let finite = |x: f64| if x.is_finite() { x } else { 0.0 };
        Self {
            distance: finite(distance),
            angle: finite(angle),
        }
    }
}

/// The frustum a refinement for `view` culls with (module docs): widened by
/// the thresholds and `latency`, or the view's own for a camera that cannot
/// be widened.
pub fn culling(hierarchy: &VolumeHierarchy, view: &View, latency: Latency) -> Option<Frustum> {
    let widened = view.frustum.as_ref().and_then(|frustum| {
        let (world_from_index, _) = maps(hierarchy, view)?;
        let m = world_from_index.matrix3;
        let norm =
            (m.x_axis.length_squared() + m.y_axis.length_squared() + m.z_axis.length_squared())
                .sqrt();
        let distance = (REFRESH_DISTANCE + latency.distance) * norm;
        frustum.widened(view.eye, distance, REFRESH_ANGLE + latency.angle)
    });
    widened.or_else(|| view.frustum.clone())
}

/// Whether a batch refined for `refined` under `criterion`, culled with
/// `culling` ([`culling`]), serves `view` (module docs).
pub(crate) fn serves(
    hierarchy: &VolumeHierarchy,
    refined: &View,
    culling: Option<&Frustum>,
    view: &View,
    criterion: LodCriterion,
) -> bool {
    let measures_pixels = matches!(criterion, LodCriterion::ScreenError { .. });
    if refined.world_from_local != view.world_from_local
        || refined.viewport_is_empty() != view.viewport_is_empty()
        || refined.clip_from_world.is_some() != view.clip_from_world.is_some()
        || (measures_pixels && refined.viewport != view.viewport)
    {
        return false;
    }
    let Some((_, index_from_world)) = maps(hierarchy, view) else {
        return false;
    };
    let moved = index_from_world
        .transform_point3(refined.eye)
        .distance(index_from_world.transform_point3(view.eye));
    // A NaN distance refines again (and the refinement reports the eye).
    if moved.is_nan() || moved > REFRESH_DISTANCE {
        return false;
    }
    match (&refined.frustum, &view.frustum) {
        // No frustum to widen (a projection that has none): the screen
        // error, which measures through the projection, refines for any
        // other.
        (None, None) => !measures_pixels || refined.clip_from_world == view.clip_from_world,
        (Some(was), Some(is)) if culling != Some(was) => {
            culling.is_some_and(|culling| same_shape(was, is) && culling.holds_view(is, view.eye))
        }
        (was, is) => was == is,
    }
}

/// The hierarchy's world-from-index and index-from-world maps for `view`.
fn maps(hierarchy: &VolumeHierarchy, view: &View) -> Option<(DAffine3, DAffine3)> {
    index_maps(
        hierarchy.origin(),
        hierarchy.spacing(),
        view.world_from_local,
    )
}

/// Whether two frusta have the same angles between their planes (the same
/// projection, turned): their normals' dot products agree to 1e-6, about
/// what a single-precision camera transform keeps.
fn same_shape(a: &Frustum, b: &Frustum) -> bool {
    let (a, b) = (a.planes(), b.planes());
    a.len() == b.len()
        && (0..a.len()).all(|i| {
            (i + 1..a.len()).all(|j| {
                let dot = |planes: &[glam::DVec4]| planes[i].truncate().dot(planes[j].truncate());
                (dot(a) - dot(b)).abs() <= 1e-6
            })
        })
}

#[cfg(test)]
mod tests {
    use glam::{DMat4, DVec3, UVec2};
    use nebel_core::field::DensityGrid;

    use super::*;

    /// A view from `eye` through `clip_from_world` without a frustum, as a
    /// projection that has none leaves it.
    fn unculled(eye: DVec3, clip_from_world: DMat4) -> View {
        View {
            clip_from_world: Some(clip_from_world),
            ..View::new(DAffine3::IDENTITY, eye, UVec2::new(64, 48))
        }
    }

    #[test]
    fn without_a_frustum_the_screen_error_refines_for_another_projection() {
        let grid = DensityGrid::new([5; 3], DVec3::ONE, DVec3::ZERO, vec![0.5; 125]).unwrap();
        let hierarchy = VolumeHierarchy::new(&grid, 4.0).unwrap();
        let eye = DVec3::new(2.0, 2.0, -6.0);
        let looking = |target: DVec3| {
            DMat4::perspective_infinite_reverse_rh(1.0, 4.0 / 3.0, 0.1)
                * DMat4::look_at_rh(eye, target, DVec3::Y)
        };
        let refined = unculled(eye, looking(DVec3::splat(2.0)));
        let turned = unculled(eye, looking(DVec3::new(2.5, 2.0, 2.0)));
        let screen = LodCriterion::default();
        let distance = LodCriterion::distance(8.0);
        assert!(serves(&hierarchy, &refined, None, &refined, screen));
        assert!(!serves(&hierarchy, &refined, None, &turned, screen));
        assert!(serves(&hierarchy, &refined, None, &turned, distance));
        let moved = View {
            eye: eye + DVec3::X,
            ..refined.clone()
        };
        assert!(!serves(&hierarchy, &refined, None, &moved, distance));
    }
}
