//! View frusta and the conservative box test of frustum culling (Röttger and
//! Ertl 2003 §3: frustum culling and the zero-opacity test prune nodes).
//!
//! A [`Frustum`] is an intersection of half-spaces `normal · p + d ≥ 0`
//! (Bevy's `HalfSpace` convention: the inside is the positive side), normals of
//! unit length. [`Frustum::from_view_projection`] extracts the planes from a
//! clip-from-world matrix (Gribb and Hartmann): left, right, bottom, top and
//! near. There is no far plane: Bevy's cameras use an infinite reversed-Z
//! perspective, and a finite far plane of any other projection is ignored, so
//! culling never removes what a camera with a longer far distance would draw.
//!
//! [`Frustum::intersects_aabb`] is the usual "positive vertex" test: a box is
//! rejected only if it lies entirely on the outer side of one plane. That is
//! conservative: it never rejects a box that meets the frustum, and it keeps a
//! few boxes near the frustum's edges that miss it.

use glam::{DAffine3, DMat4, DVec3, DVec4};
use thiserror::Error;

/// Why a frustum could not be built.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum FrustumError {
    /// A plane has a NaN or infinite component.
    #[error("frustum plane {index} (normal {normal}, d = {d}) is not finite")]
    NonFinitePlane {
        /// Index of the plane in the input.
        index: usize,
        /// Its normal as given.
        normal: DVec3,
        /// Its offset as given.
        d: f64,
    },
    /// A plane's normal has zero length, so it has no inside.
    #[error("frustum plane {index} has a zero normal")]
    ZeroNormal {
        /// Index of the plane in the input.
        index: usize,
    },
    /// The view-projection matrix has a NaN or infinite element.
    #[error("the view-projection matrix is not finite")]
    NonFiniteMatrix,
    /// The view-projection matrix is singular along a side of the view
    /// (for example a zero field of view or aspect ratio).
    #[error("the view-projection matrix has no {side} plane (is it singular?)")]
    DegenerateMatrix {
        /// Which plane is missing: `left`, `right`, `bottom`, `top` or `near`.
        side: &'static str,
    },
}

/// A convex region bounded by planes: the intersection of the half-spaces
/// `normal · p + d ≥ 0`. With no planes it is the whole space.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Frustum {
    /// `(normal.x, normal.y, normal.z, d)` per plane, normal of unit length.
    planes: Vec<DVec4>,
}

impl Frustum {
    /// The frustum bounded by `planes`, each `(normal, d)` with the inside at
    /// `normal · p + d ≥ 0` (world units; any non-zero normal length, it is
    /// normalised here). Usually six planes, but any number works.
    pub fn from_planes(
        planes: impl IntoIterator<Item = (DVec3, f64)>,
    ) -> Result<Self, FrustumError> {
        let planes = planes
            .into_iter()
            .enumerate()
            .map(|(index, (normal, d))| {
                if !normal.is_finite() || !d.is_finite() {
                    return Err(FrustumError::NonFinitePlane { index, normal, d });
                }
                normalized(normal.extend(d)).ok_or(FrustumError::ZeroNormal { index })
            })
            .collect::<Result<_, _>>()?;
        Ok(Self { planes })
    }

    /// The frustum of a camera from its `clip_from_world` matrix (projection ×
    /// view, wgpu clip space: x and y in [−w, w], depth z in [0, w]).
    ///
    /// Extracts the left, right, bottom and top planes and the near plane, for
    /// standard depth (near at z = 0) and reversed depth (near at z = w, Bevy's
    /// default) alike: under perspective the near plane is the depth plane
    /// that faces the view direction. The far plane is dropped (see the module
    /// docs). Under an orthographic projection (no view direction in `w`) both
    /// depth planes are kept, since nothing tells them apart and both are
    /// finite.
    pub fn from_view_projection(clip_from_world: DMat4) -> Result<Self, FrustumError> {
        if !clip_from_world.is_finite() {
            return Err(FrustumError::NonFiniteMatrix);
        }
        let row = |i: usize| clip_from_world.row(i);
        let (x, y, z, w) = (row(0), row(1), row(2), row(3));
        let mut planes = Vec::with_capacity(6);
        for (side, plane) in [
            ("left", w + x),
            ("right", w - x),
            ("bottom", w + y),
            ("top", w - y),
        ] {
            planes.push(normalized(plane).ok_or(FrustumError::DegenerateMatrix { side })?);
        }
        // Depth candidates: z ≥ 0 and z ≤ w, one of them the near plane.
        let depth = [normalized(z), normalized(w - z)];
        let view_direction = w.truncate();
        let scale = w.abs().max_element().max(f64::MIN_POSITIVE);
        let before = planes.len();
        if view_direction.length() > 1e-12 * scale {
            planes.extend(
                depth
                    .into_iter()
                    .flatten()
                    .filter(|plane| plane.truncate().dot(view_direction) > 0.0),
            );
        } else {
            planes.extend(depth.into_iter().flatten());
        }
        if planes.len() == before {
            return Err(FrustumError::DegenerateMatrix { side: "near" });
        }
        Ok(Self { planes })
    }

    /// The planes as `(normal.x, normal.y, normal.z, d)`, unit normals, inside
    /// where `normal · p + d ≥ 0`.
    pub fn planes(&self) -> &[DVec4] {
        &self.planes
    }

    /// Whether `point` lies inside or on the frustum. A NaN point is outside
    /// unless there are no planes.
    pub fn contains_point(&self, point: DVec3) -> bool {
        self.planes
            .iter()
            .all(|p| p.truncate().dot(point) + p.w >= 0.0)
    }

    /// Whether the axis-aligned box from `min` to `max` may meet the frustum:
    /// `false` only if the box lies entirely outside one plane (conservative,
    /// see the module docs). Corners may come in either order; a NaN corner
    /// component counts as unbounded, so such a box is kept.
    pub fn intersects_aabb(&self, min: DVec3, max: DVec3) -> bool {
        let (lo, hi) = (min.min(max), min.max(max));
        self.planes.iter().all(|plane| {
            let normal = plane.truncate();
            // The corner farthest along the normal ("positive vertex").
            let corner = DVec3::select(normal.cmpge(DVec3::ZERO), hi, lo);
            // NaN compares false, so a NaN corner keeps the box.
            (normal.dot(corner) + plane.w).partial_cmp(&0.0) != Some(std::cmp::Ordering::Less)
        })
    }

    /// This frustum of a perspective camera at `eye` (four side planes, then
    /// the near plane facing the view direction, as
    /// [`Frustum::from_view_projection`] gives it) widened so that it holds
    /// everything the camera sees after the eye moved by less than
    /// `distance` and the camera turned by less than `angle` (radians), with
    /// no near plane. Each side plane is pushed out by `distance` (a move
    /// shifts every plane by less than that) and turned outward about the
    /// eye, towards the view direction, by `atan(tan(angle) / cos φ)`, `φ`
    /// the angle between the middle of its face and the face's edges: a turn
    /// by less than `angle` takes an edge direction at most `angle` out of
    /// the plane, and an edge at `φ` from the middle needs that much. The turn
    /// is at most π/4 (only very wide views and turns reach it; then views
    /// near the limit may leave the frustum, which [`Frustum::holds_view`]
    /// tells). `None` for another frustum (an orthographic camera's, whose
    /// side planes are parallel to the view).
    pub fn widened(&self, eye: DVec3, distance: f64, angle: f64) -> Option<Frustum> {
        let [left, right, bottom, top, near] = self.planes.as_slice() else {
            return None;
        };
        let forward = near.truncate();
        let tan = angle.clamp(0.0, std::f64::consts::FRAC_PI_4).tan();
        let sides = [
            (left, [bottom, top]),
            (right, [bottom, top]),
            (bottom, [left, right]),
            (top, [left, right]),
        ];
        let widened = sides.map(|(plane, neighbours)| {
            let normal = plane.truncate();
            let offset = normal.dot(eye) + plane.w;
            let middle = (forward - forward.dot(normal) * normal).normalize_or_zero();
            let cos_edge = neighbours
                .map(|other| edge(normal, other.truncate(), forward).dot(middle))
                .into_iter()
                .fold(1.0, f64::min);
            let turn = tan
                .atan2(cos_edge.max(0.0))
                .min(std::f64::consts::FRAC_PI_4);
            let (sin, cos) = turn.sin_cos();
            let turned = (cos * normal + sin * middle).normalize_or(normal);
            (turned, -turned.dot(eye) + offset + distance.max(0.0))
        });
        Frustum::from_planes(widened).ok()
    }

    /// Whether this frustum holds everything the perspective frustum `view`
    /// of a camera at `eye` sees ([`Frustum::widened`]'s shape): the eye and
    /// the four edges of its view cone, the near plane ignored. `false` for
    /// another `view`.
    pub fn holds_view(&self, view: &Frustum, eye: DVec3) -> bool {
        let [left, right, bottom, top, near] = view.planes.as_slice() else {
            return false;
        };
        let forward = near.truncate();
        let edges = [(left, bottom), (bottom, right), (right, top), (top, left)]
            .map(|(a, b)| edge(a.truncate(), b.truncate(), forward));
        self.contains_point(eye)
            && self
                .planes
                .iter()
                .all(|plane| edges.iter().all(|edge| plane.truncate().dot(*edge) >= 0.0))
    }

    /// The same frustum in the local frame of an object placed by
    /// `world_from_local` (planes pulled back through the affine map), so that
    /// boxes in the object's own coordinates can be tested exactly as boxes.
    /// A plane whose normal vanishes under a singular map keeps a zero normal
    /// (it then keeps everything or nothing, by the sign of `d`).
    pub fn in_local_frame(&self, world_from_local: &DAffine3) -> Self {
        let linear_transposed = world_from_local.matrix3.transpose();
        let planes = self
            .planes
            .iter()
            .map(|plane| {
                let normal = linear_transposed * plane.truncate();
                let local =
                    normal.extend(plane.truncate().dot(world_from_local.translation) + plane.w);
                normalized(local).unwrap_or(local)
            })
            .collect();
        Self { planes }
    }
}

/// The unit direction of the line where the planes with normals `a` and `b`
/// meet, the one along `forward`.
fn edge(a: DVec3, b: DVec3, forward: DVec3) -> DVec3 {
    let edge = a.cross(b).normalize_or_zero();
    if edge.dot(forward) < 0.0 { -edge } else { edge }
}

/// `plane` scaled so its normal has unit length; `None` for a zero or
/// non-finite normal.
fn normalized(plane: DVec4) -> Option<DVec4> {
    let length = plane.truncate().length();
    (length.is_finite() && length > 0.0).then(|| plane / length)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box() -> Frustum {
        Frustum::from_planes([
            (DVec3::X, 1.0),
            (-DVec3::X, 1.0),
            (DVec3::Y, 1.0),
            (-DVec3::Y, 1.0),
            (DVec3::Z * 3.0, 3.0),
            (-DVec3::Z, 1.0),
        ])
        .unwrap()
    }

    #[test]
    fn box_test_is_conservative_and_rejects_boxes_outside_a_plane() {
        let f = unit_box();
        assert!(f.intersects_aabb(DVec3::splat(-0.1), DVec3::splat(0.1)));
        assert!(f.intersects_aabb(DVec3::splat(-5.0), DVec3::splat(5.0)));
        assert!(f.intersects_aabb(DVec3::new(1.0, 0.0, 0.0), DVec3::new(2.0, 0.5, 0.5)));
        assert!(!f.intersects_aabb(DVec3::new(1.01, 0.0, 0.0), DVec3::new(2.0, 0.5, 0.5)));
        assert!(!f.intersects_aabb(DVec3::new(2.0, 0.5, 0.5), DVec3::new(1.01, 0.0, 0.0)));
        assert!(f.intersects_aabb(DVec3::NAN, DVec3::ONE));
        assert!(f.contains_point(DVec3::ZERO));
        assert!(!f.contains_point(DVec3::NAN));
        // The plane with a scaled normal was normalised.
        assert_eq!(f.planes()[4], DVec4::new(0.0, 0.0, 1.0, 1.0));
    }

    #[test]
    fn bad_planes_are_refused() {
        let err = Frustum::from_planes([(DVec3::X, 0.0), (DVec3::ZERO, 1.0)]).unwrap_err();
        assert_eq!(err, FrustumError::ZeroNormal { index: 1 });
        let err = Frustum::from_planes([(DVec3::new(f64::NAN, 0.0, 1.0), 0.0)]).unwrap_err();
        assert!(err.to_string().contains("plane 0"), "{err}");
        assert!(Frustum::from_view_projection(DMat4::NAN).is_err());
        assert!(Frustum::from_view_projection(DMat4::ZERO).is_err());
    }

    /// A camera at (1, 2, 3) looking along −z rotated a little.
    fn view() -> DMat4 {
        DMat4::look_to_rh(
            DVec3::new(1.0, 2.0, 3.0),
            DVec3::new(0.2, -0.1, -1.0).normalize(),
            DVec3::Y,
        )
    }

    #[test]
    fn view_projection_planes_for_standard_reversed_and_orthographic_depth() {
        let eye = DVec3::new(1.0, 2.0, 3.0);
        let forward = DVec3::new(0.2, -0.1, -1.0).normalize();
        let fov = 1.0;
        let projections = [
            DMat4::perspective_infinite_reverse_rh(fov, 1.5, 0.1),
            DMat4::perspective_rh(fov, 1.5, 0.1, 50.0),
            DMat4::perspective_infinite_rh(fov, 1.5, 0.1),
        ];
        for projection in projections {
            let f = Frustum::from_view_projection(projection * view()).unwrap();
            assert_eq!(f.planes().len(), 5, "no far plane");
            assert!(f.contains_point(eye + forward));
            assert!(
                f.contains_point(eye + forward * 1e4),
                "beyond any far plane"
            );
            assert!(
                !f.contains_point(eye + forward * 0.05),
                "before the near plane"
            );
            assert!(!f.contains_point(eye - forward));
            let right = forward.cross(DVec3::Y).normalize();
            assert!(!f.contains_point(eye + forward + right * 3.0));
            // The near plane's distance from the eye is the near distance.
            let near = f.planes()[4];
            let distance = near.truncate().dot(eye) + near.w;
            assert!((distance + 0.1).abs() < 1e-9, "{distance} {projection}");
        }
        let ortho = DMat4::orthographic_rh(-1.0, 1.0, -1.0, 1.0, 0.5, 10.0);
        let f = Frustum::from_view_projection(ortho * view()).unwrap();
        assert_eq!(f.planes().len(), 6);
        assert!(f.contains_point(eye + forward));
        assert!(!f.contains_point(eye + forward * 0.2));
        assert!(!f.contains_point(eye + forward * 11.0));
    }

    #[test]
    fn a_widened_frustum_holds_every_view_within_its_move_and_turn() {
        let projection = DMat4::perspective_infinite_reverse_rh(0.9, 1.6, 0.1);
        let eye = DVec3::new(1.0, 2.0, 3.0);
        let exact = Frustum::from_view_projection(projection * view()).unwrap();
        let (distance, angle) = (0.5, 3f64.to_radians());
        let widened = exact.widened(eye, distance, angle).unwrap();
        assert_eq!(widened.planes().len(), 4, "no near plane");
        assert!(widened.holds_view(&exact, eye));
        let mut state = 0x9e37_u64;
        let mut random = move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for _ in 0..500 {
            let axis = DVec3::new(random(), random(), random()).normalize();
            let direction = DVec3::new(random(), random(), random()).normalize();
            // Any view moved and turned by less than the margins.
            let (moved, turned) = (0.99 * distance * random().abs(), 0.99 * angle * random());
            let other = eye + direction * moved;
            let camera = DMat4::from(DAffine3::from_rotation_translation(
                glam::DQuat::from_axis_angle(axis, turned),
                DVec3::ZERO,
            ));
            let world_from_view = DMat4::from_translation(other)
                * camera
                * DMat4::from_translation(-eye)
                * view().inverse();
            let seen = Frustum::from_view_projection(projection * world_from_view.inverse());
            assert!(
                widened.holds_view(&seen.unwrap(), other),
                "{moved} {turned}"
            );
        }
        // A turn of twice the margin, or a wider view, leaves it.
        let yaw = DMat4::from_rotation_y(2.0 * angle);
        let turned = Frustum::from_view_projection(projection * view() * yaw).unwrap();
        assert!(!widened.holds_view(&turned, eye));
        let wider = DMat4::perspective_infinite_reverse_rh(1.1, 1.6, 0.1);
        let wider = Frustum::from_view_projection(wider * view()).unwrap();
        assert!(!widened.holds_view(&wider, eye));
        let right = DVec3::new(0.2, -0.1, -1.0).cross(DVec3::Y).normalize();
        assert!(!widened.holds_view(&exact, eye + right * 2.0 * distance));
        // An orthographic frustum is not widened or held.
        let ortho = DMat4::orthographic_rh(-1.0, 1.0, -1.0, 1.0, 0.5, 10.0);
        let ortho = Frustum::from_view_projection(ortho * view()).unwrap();
        assert!(ortho.widened(eye, distance, angle).is_none());
        assert!(!widened.holds_view(&ortho, eye));
    }

    #[test]
    fn local_frame_agrees_with_world_tests() {
        let f = Frustum::from_view_projection(
            DMat4::perspective_infinite_reverse_rh(0.8, 1.0, 0.1) * view(),
        )
        .unwrap();
        let world_from_local = DAffine3::from_scale_rotation_translation(
            DVec3::new(2.0, 0.5, 1.5),
            glam::DQuat::from_rotation_y(0.7),
            DVec3::new(-1.0, 0.0, -4.0),
        );
        let local = f.in_local_frame(&world_from_local);
        for i in 0..1000 {
            let p = DVec3::new(
                (i % 10) as f64 - 4.5,
                ((i / 10) % 10) as f64 - 4.5,
                (i / 100) as f64 - 4.5,
            ) * 0.7;
            assert_eq!(
                local.contains_point(p),
                f.contains_point(world_from_local.transform_point3(p)),
                "{p}"
            );
        }
    }
}
