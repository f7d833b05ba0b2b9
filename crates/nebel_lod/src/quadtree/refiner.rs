//! One terrain's level of detail frame after frame: [`TerrainRefiner`]
//! refines a [`TerrainHierarchy`] for a camera only when the view changed
//! enough, and culls with a frustum widened so that the mesh stays valid
//! until the next refinement.
//!
//! # When the mesh is refined again
//!
//! [`TerrainRefiner::update`] refines (into the same [`TerrainMesh`]) on the
//! first call, when asked to (`settings_changed`: the terrain's quadtree or
//! map changed), when its [`LodSettings`] differ from the last
//! refinement's (an accuracy derived from a pixel tolerance changes with the
//! viewport, say), and when
//!
//! - the eye moved more than `update_distance` (terrain units) since the
//!   last refinement;
//! - the camera turned by more than `view_margin` (radians);
//! - the camera's projection or the terrain's placement changed.
//!
//! A still camera costs nothing. Why `δ = update_distance` is small enough:
//! in the morph zone (`1/4 < f < 1`) a node of size `d` has `l ≤ d·M`
//! (`M = max(c·d2, C)`), so moving the eye by `δ` changes `f = l²/(d²M²)` by
//! at most `2δ/(dM)` and the morph weight `t = (1 − f)/(3/4)` by at most
//! `8δ/(3dM)`; the blend of the node's new vertices, `t · (h − (a + b)/2)`
//! with `|h − (a + b)/2| ≤ d2 · d/2`, moves by at most `4δ·d2/(3M) ≤ 4δ/(3c)`
//! (their coarse endpoints, when their own nodes morph too, add terms of the
//! same kind one level up). With 10 m spacing, `δ` = 2.5 m and `c` = 300 that
//! is 1.1 cm per level, and the level of detail is the one of an eye at most
//! `δ` away.
//!
//! # Culling
//!
//! The frustum is the camera's four side planes widened so that the culled
//! mesh stays valid until the next refinement: each plane is turned outward
//! by `view_margin` about the eye (any rotation by less than that moves every
//! view direction by less than that) and pushed out by `update_distance`
//! (any move by less than that shifts every plane by less than that), and
//! by [`RefinerSettings::latency`] more when the mesh is drawn later than
//! the view it was refined for. The
//! near plane is dropped (the side planes already bound the view to a cone in
//! front of the eye). An orthographic camera culls nothing.

use std::sync::Arc;

use glam::{DAffine3, DMat4, DQuat, DVec3};

use super::{LodSettings, LodStats, TerrainError, TerrainHierarchy, TerrainMap, TerrainMesh};
use crate::frustum::Frustum;

/// A camera seen from one terrain.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TerrainView {
    /// The camera's world transform (its eye and orientation).
    pub world_from_view: DAffine3,
    /// The camera's projection: view space to clip space.
    pub clip_from_view: DMat4,
    /// Where the terrain is: its frame (the hierarchy's) to world space.
    pub world_from_terrain: DAffine3,
}

impl TerrainView {
    /// The eye in the terrain's frame.
    pub fn eye(&self) -> DVec3 {
        self.world_from_terrain
            .inverse()
            .transform_point3(self.world_from_view.translation)
    }

    /// The camera's orientation in the world.
    fn rotation(&self) -> DQuat {
        DQuat::from_mat3(&self.world_from_view.matrix3)
    }

    /// The camera's side planes, each turned outward by `angle` (radians,
    /// at most π/4) about the eye and pushed out by `distance` (terrain
    /// units), in the terrain's frame: a frustum that still holds everything
    /// the camera sees after the eye moved by less than `distance` and the
    /// camera turned by less than `angle` (see the module docs). `None` (cull
    /// nothing) for an orthographic or degenerate camera.
    pub fn culling_frustum(&self, distance: f64, angle: f64) -> Option<Frustum> {
        // Terrain units to world units: at most the longest axis.
        let margin = distance
            * self
                .world_from_terrain
                .matrix3
                .to_cols_array_2d()
                .iter()
                .map(|column| DVec3::from(*column).length())
                .fold(0.0, f64::max);
        let clip_from_world = self.clip_from_view * DMat4::from(self.world_from_view.inverse());
        let frustum = Frustum::from_view_projection(clip_from_world)
            .ok()?
            .widened(self.world_from_view.translation, margin, angle)?;
        Some(frustum.in_local_frame(&self.world_from_terrain))
    }

    /// How far the eye moved (in the terrain's frame) and the camera turned
    /// (radians) since `earlier`.
    pub fn change_since(&self, earlier: &TerrainView) -> (f64, f64) {
        (
            earlier.eye().distance(self.eye()),
            earlier.rotation().angle_between(self.rotation()),
        )
    }
}

/// How far the view may change before the mesh is refined again (see the
/// module docs), and the refinement's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefinerSettings {
    /// The refinement's settings.
    pub lod: LodSettings,
    /// How far the eye may move, terrain units, before the mesh is refined
    /// again; the culling frustum is pushed out by as much (scaled to world
    /// units). Negative counts as 0.
    pub update_distance: f64,
    /// How far the camera may turn, radians, before the mesh is refined
    /// again; the culling frustum is turned out by as much. Clamped to
    /// [0, π/4].
    pub view_margin: f64,
    /// How far the eye may move (terrain units) and the camera turn
    /// (radians) between the view a mesh is refined for and the first view
    /// it is drawn for, as when refinements run on another thread: the
    /// culling frustum is widened by as much more (the turn in all at most
    /// π/4). Zero when a mesh is drawn for the view it was refined for.
    pub latency: (f64, f64),
}

/// One terrain's level of detail frame after frame (see the module docs).
#[derive(Clone, Debug, Default)]
pub struct TerrainRefiner {
    /// Shared with whoever still reads an earlier refinement (a refinement
    /// running on another thread, an effect built on the mesh): the next
    /// refinement writes into a new mesh then, into this one otherwise.
    mesh: Arc<TerrainMesh>,
    /// The view and settings the mesh was refined for.
    refined_for: Option<(TerrainView, LodSettings)>,
}

impl TerrainRefiner {
    /// A refiner with an empty mesh.
    pub fn new() -> Self {
        Self::default()
    }

    /// Refines `hierarchy` for `view` if the view changed enough since the
    /// last refinement or `settings_changed` (see the module docs), carrying
    /// `map` into the mesh when given
    /// ([`TerrainHierarchy::update_with_map`]); returns the refinement's
    /// counters, or `None` when the mesh stays as it is. After an error the
    /// next call refines again.
    pub fn update(
        &mut self,
        hierarchy: &TerrainHierarchy,
        map: Option<&TerrainMap>,
        view: &TerrainView,
        settings: &RefinerSettings,
        settings_changed: bool,
    ) -> Result<Option<LodStats>, TerrainError> {
        if self.is_current(view, settings) && !settings_changed {
            return Ok(None);
        }
        self.refined_for = None;
        let (moved, turned) = settings.latency;
        let distance = settings.update_distance.max(0.0) + moved.max(0.0);
        let margin = settings.view_margin.max(0.0) + turned.max(0.0);
        let frustum = view.culling_frustum(distance, margin);
        if Arc::get_mut(&mut self.mesh).is_none() {
            self.mesh = Arc::default();
        }
        let mesh = Arc::get_mut(&mut self.mesh).expect("a mesh of its own");
        let stats =
            hierarchy.update_with_map(view.eye(), frustum.as_ref(), &settings.lod, map, mesh)?;
        self.refined_for = Some((*view, settings.lod));
        Ok(Some(stats))
    }

    /// Whether the last refinement still serves `view` with `settings`: the
    /// view has not changed enough since (see the module docs).
    pub fn is_current(&self, view: &TerrainView, settings: &RefinerSettings) -> bool {
        let distance = settings.update_distance.max(0.0);
        let margin = settings.view_margin.clamp(0.0, std::f64::consts::FRAC_PI_4);
        self.refined_for.is_some_and(|(last, lod)| {
            let (moved, turned) = view.change_since(&last);
            lod == settings.lod
                && last.clip_from_view == view.clip_from_view
                && last.world_from_terrain == view.world_from_terrain
                && moved <= distance
                && turned <= margin
        })
    }

    /// The mesh of the last refinement, in the hierarchy's frame.
    pub fn mesh(&self) -> &Arc<TerrainMesh> {
        &self.mesh
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::quadtree::TriangleOrder;
    use glam::DVec2;
    use nebel_core::field::{HeightField, ValueNoise};

    fn hierarchy() -> TerrainHierarchy {
        let noise = ValueNoise {
            seed: 7,
            ..ValueNoise::default()
        };
        let field =
            HeightField::value_noise([65, 65], DVec2::splat(10.0), DVec2::ZERO, &noise, 200.0)
                .unwrap();
        TerrainHierarchy::new(field, 2.0).unwrap()
    }

    fn view(eye: DVec3, yaw: f64) -> TerrainView {
        let rotation = DQuat::from_rotation_y(yaw) * DQuat::from_rotation_x(-0.5);
        TerrainView {
            world_from_view: DAffine3::from_rotation_translation(rotation, eye),
            clip_from_view: DMat4::perspective_infinite_reverse_rh(1.0, 1.0, 0.1),
            world_from_terrain: DAffine3::IDENTITY,
        }
    }

    fn settings() -> RefinerSettings {
        RefinerSettings {
            lod: LodSettings {
                accuracy: 40.0,
                order: TriangleOrder::FrontToBack,
                ..LodSettings::default()
            },
            update_distance: 2.5,
            view_margin: 3f64.to_radians(),
            latency: (0.0, 0.0),
        }
    }

    #[test]
    fn it_refines_only_when_the_view_changed_enough() {
        let hierarchy = hierarchy();
        let mut refiner = TerrainRefiner::new();
        let start = DVec3::new(320.0, 400.0, 900.0);
        let first = refiner.update(&hierarchy, None, &view(start, 0.0), &settings(), false);
        assert!(first.unwrap().is_some_and(|stats| stats.triangles > 0));
        let mut expected = TerrainMesh::new();
        let eye = start;
        let frustum = view(start, 0.0).culling_frustum(2.5, 3f64.to_radians());
        hierarchy
            .update(eye, frustum.as_ref(), &settings().lod, &mut expected)
            .unwrap();
        assert_eq!(refiner.mesh().positions, expected.positions, "the mesh");

        let moved = |x: f64, yaw: f64| view(start + DVec3::new(x, 0.0, 0.0), yaw);
        let update = |refiner: &mut TerrainRefiner, view: TerrainView, changed: bool| {
            let current = refiner.is_current(&view, &settings());
            let refined = refiner
                .update(&hierarchy, None, &view, &settings(), changed)
                .unwrap()
                .is_some();
            assert_eq!(refined, !current || changed, "is_current agrees");
            refined
        };
        assert!(!update(&mut refiner, moved(2.0, 0.0), false), "2 m < δ");
        assert!(update(&mut refiner, moved(3.0, 0.0), false), "3 m > δ");
        assert!(
            !update(&mut refiner, moved(3.0, 2f64.to_radians()), false),
            "2° < 3°"
        );
        assert!(
            update(&mut refiner, moved(3.0, 4f64.to_radians()), false),
            "4° > 3°"
        );
        assert!(
            update(&mut refiner, moved(3.0, 4f64.to_radians()), true),
            "settings"
        );
        let mut placed = moved(3.0, 4f64.to_radians());
        placed.world_from_terrain = DAffine3::from_translation(DVec3::X);
        assert!(update(&mut refiner, placed, false), "the terrain moved");
        assert!(!update(&mut refiner, placed, false), "unchanged");
        let mut finer = settings();
        finer.lod.accuracy *= 1.5;
        let refined = refiner.update(&hierarchy, None, &placed, &finer, false);
        assert!(refined.unwrap().is_some(), "a new accuracy");
    }

    #[test]
    fn the_latency_widens_the_culling_and_not_the_update_distance() {
        let hierarchy = hierarchy();
        let start = view(DVec3::new(-200.0, 300.0, 320.0), -1.2);
        let late = RefinerSettings {
            latency: (47.5, 7f64.to_radians()),
            ..settings()
        };
        let mut refiner = TerrainRefiner::new();
        let stats = refiner
            .update(&hierarchy, None, &start, &late, false)
            .unwrap()
            .unwrap();
        let frustum = start.culling_frustum(50.0, 10f64.to_radians());
        let mut expected = TerrainMesh::new();
        let expected_stats = hierarchy
            .update(start.eye(), frustum.as_ref(), &late.lod, &mut expected)
            .unwrap();
        assert_eq!(refiner.mesh().positions, expected.positions);
        let mut on_time = TerrainRefiner::new();
        let on_time_stats = on_time
            .update(&hierarchy, None, &start, &settings(), false)
            .unwrap()
            .unwrap();
        assert_eq!(stats.culled, expected_stats.culled);
        assert!(
            stats.culled < on_time_stats.culled && stats.triangles > on_time_stats.triangles,
            "culls less: {stats:?} {on_time_stats:?}"
        );
        // The mesh is still current as far as δ and α go, no farther.
        let moved = view(DVec3::new(-197.0, 300.0, 320.0), -1.2);
        assert!(!refiner.is_current(&moved, &late), "3 m > δ");
    }

    #[test]
    fn a_mesh_still_read_elsewhere_is_not_overwritten() {
        let hierarchy = hierarchy();
        let mut refiner = TerrainRefiner::new();
        let near = view(DVec3::new(320.0, 150.0, 330.0), 0.0);
        let far = view(DVec3::new(320.0, 900.0, 1500.0), 0.0);
        refiner
            .update(&hierarchy, None, &near, &settings(), false)
            .unwrap();
        // Another thread still draws the near mesh.
        let drawn = refiner.mesh().clone();
        let near_positions = drawn.positions.clone();
        refiner
            .update(&hierarchy, None, &far, &settings(), false)
            .unwrap();
        assert_eq!(drawn.positions, near_positions, "the shared mesh kept");
        assert!(!Arc::ptr_eq(&drawn, refiner.mesh()));
        assert_ne!(refiner.mesh().positions, near_positions, "a new mesh");
        // Unshared again: refined in place.
        drop(drawn);
        let buffer = Arc::as_ptr(refiner.mesh());
        refiner
            .update(&hierarchy, None, &near, &settings(), false)
            .unwrap();
        assert_eq!(Arc::as_ptr(refiner.mesh()), buffer, "the buffers reused");
        assert_eq!(refiner.mesh().positions, near_positions);
    }

    #[test]
    fn the_widened_frustum_keeps_every_node_seen_from_any_view_within_the_margins() {
        // Culled from one view, refined from another within δ and α: every
        // triangle the exact frustum of the second view would draw is kept.
        let hierarchy = hierarchy();
        let start = DVec3::new(-200.0, 300.0, 320.0);
        let (delta, alpha) = (2.5, 3f64.to_radians());
        let widened = view(start, -1.2).culling_frustum(delta, alpha).unwrap();
        let origin = hierarchy.origin();
        for (dx, dyaw) in [
            (2.4, 0.0),
            (-1.7, 2.9f64.to_radians()),
            (0.0, -2.9f64.to_radians()),
        ] {
            let other = view(start + DVec3::new(dx, 0.0, 0.0), -1.2 + dyaw);
            let exact = other.culling_frustum(0.0, 0.0).unwrap();
            let mut culled = TerrainMesh::new();
            let mut seen = TerrainMesh::new();
            let lod = settings().lod;
            hierarchy
                .update(start, Some(&widened), &lod, &mut culled)
                .unwrap();
            hierarchy
                .update(start, Some(&exact), &lod, &mut seen)
                .unwrap();
            let kept: std::collections::HashSet<[u32; 3]> = culled
                .positions
                .iter()
                .map(|p| p.map(f32::to_bits))
                .collect();
            // Every vertex inside the other view's frustum is kept (its
            // node's box meets the widened frustum).
            let inside = seen
                .positions
                .iter()
                .filter(|p| exact.contains_point(origin + DVec3::from(p.map(f64::from))));
            let mut count = 0;
            for position in inside {
                count += 1;
                assert!(
                    kept.contains(&position.map(f32::to_bits)),
                    "a seen vertex was culled"
                );
            }
            assert!(count > 0, "the view sees the terrain");
        }
    }

    #[test]
    fn an_orthographic_camera_culls_nothing_and_bad_accuracy_is_an_error() {
        let hierarchy = hierarchy();
        let mut orthographic = view(DVec3::new(0.0, 500.0, 0.0), 0.0);
        orthographic.clip_from_view = DMat4::orthographic_rh(-10.0, 10.0, -10.0, 10.0, 0.1, 100.0);
        assert!(orthographic.culling_frustum(1.0, 0.1).is_none());
        let mut refiner = TerrainRefiner::new();
        let mut bad = settings();
        bad.lod.accuracy = f32::NAN;
        assert!(
            refiner
                .update(&hierarchy, None, &orthographic, &bad, false)
                .is_err()
        );
        // After an error the next call refines.
        let ok = refiner.update(&hierarchy, None, &orthographic, &settings(), false);
        assert!(ok.unwrap().is_some());
    }
}
