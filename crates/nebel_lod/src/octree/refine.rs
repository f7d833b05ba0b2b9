//! The per-frame, view-dependent refinement of a [`VolumeHierarchy`].
//!
//! After Röttger and Ertl 2003 §2.2 and §3 (§4 for the culling), [`refine`]
//! makes one top-down traversal of every root and decides which nodes are drawn
//! as leaves, in exact back-to-front order for the eye, with the error metric
//! `e` of each node. A node is refined while `e > 1`, and every visited node
//! gets the morph factor `e' = clamp(e − 1, 0, 1)` of Eq. 6.
//! [`RefinementSettings::criterion`] picks the metric:
//!
//! - [`LodCriterion::ScreenError`] (the default): the estimated colour error of
//!   the node in the pixels it covers, against a tolerance in colour units
//!   ([`super::screen_error`]); its `e'` is clamped to the parent's.
//! - [`LodCriterion::Distance`]: the paper's `e = s · C · max(c · Δ, 1) / d`
//!   (Eq. 1), `s` the node's longest edge in world units, `d` the distance of
//!   its centre from the eye, `C` = [`VolumeHierarchy::min_accuracy`], so the
//!   descent can stop at the first unrefined node (Eq. 2 to 5). Subtrees
//!   outside the view frustum are pruned.
//!
//! A node whose scalar range has zero opacity is never refined (§4.1): a
//! transparent root is skipped, any other such node is a leaf marked
//! [`NodeMorph::transparent`], kept so that a parent still morphing can carry
//! its coarse field into it. A hierarchy of two keyframes is refined for a span
//! of blends ([`RefinementSettings::blend_span`]) and carries `e'` at both ends
//! of the span ([`NodeMorph`]).
//!
//! The traversal runs front to back (what the screen error's occlusion needs)
//! and hands out the leaves reversed: the slab rule of the full-resolution
//! batch ([`crate::full_resolution`]) applied to the roots and, in every
//! refined node, to its eight children, a BSP order for any eye (inside the
//! volume and on a node plane included). The [`Refinement`] holds the leaves in
//! drawing order, every refined node with its `e'`, which the morphing reads,
//! and [`RefinementStats`].
//!
//! The decisions behind the distance metric (centre distance, longest edge, an
//! eye at a centre), the culling and the order are in `docs/octree-lod.md` in
//! the repository.

use glam::{DAffine3, DVec3};
use nebel_core::pacing::pace;
use nebel_core::transfer::TransferFunction;
use thiserror::Error;

use super::emit::CellScalars;
use super::keyframe::clamped_blend;
use super::screen_error::{Footprint, NodeOptics, ScreenTiles};
use super::{Node, VolumeHierarchy};
use crate::frustum::Frustum;
use crate::full_resolution::{axis_order, index_maps};
use crate::view::View;

/// The error metric of the refinement (module docs). It (de)serializes as
/// `ScreenError(image_error: 0.1)` or `Distance(accuracy: 16.0)` with the
/// `serde` feature.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "bevy_reflect", derive(bevy_reflect::Reflect))]
pub enum LodCriterion {
    /// The estimated colour error on the screen ([`super::screen_error`]):
    /// a node is refined while the RMSE over the image that its error alone
    /// would cause exceeds `image_error`, and it covers more than a pixel.
    /// Needs the view's projection ([`View::clip_from_world`]).
    ScreenError {
        /// The tolerated RMSE over the image of one node's error, linear RGB
        /// (premultiplied, the units of the HDR image before tonemapping),
        /// finite and above 0. Smaller values draw more cells. Measured on
        /// the cumulus layers of the examples, the image's RMSE against full
        /// resolution comes out at 0.02 to 3 times this value. Default
        /// [`LodCriterion::DEFAULT_IMAGE_ERROR`].
        image_error: f64,
    },
    /// The distance metric of Röttger and Ertl 2003 Eq. 1,
    /// `e = s · C · max(c · Δ, 1) / d`.
    Distance {
        /// The global accuracy `c` of Eq. 1, in units of 1/density (`c · Δ`
        /// is dimensionless, Δ in density units of [0, 1]): a node whose
        /// deviation Δ exceeds `1/c` is refined `c · Δ` times farther away
        /// than the minimum accuracy alone would refine it. Higher values
        /// give a finer mesh; 0 leaves only the distance term `s · C / d`.
        /// Must be ≥ 0 and not NaN; `+∞` refines every node with Δ > 0 (and
        /// every node closer than `s · C`) down to voxels. Default
        /// [`LodCriterion::DEFAULT_ACCURACY`].
        accuracy: f64,
    },
}

impl LodCriterion {
    /// The default tolerance of the screen error, 0.1: on the cumulus layers
    /// of the examples about as many cells as the distance criterion's
    /// default `c` = 16 draws, at a half to two thirds of its RMSE seen from
    /// outside the layer.
    pub const DEFAULT_IMAGE_ERROR: f64 = 0.1;

    /// The default global accuracy `c` of the distance criterion, 16:
    /// deviations above 1/16 of the density range extend the refinement
    /// distance.
    pub const DEFAULT_ACCURACY: f64 = 16.0;

    /// The distance criterion with accuracy `c`.
    pub fn distance(accuracy: f64) -> Self {
        Self::Distance { accuracy }
    }

    /// The screen-error criterion with the tolerance `image_error`.
    pub fn screen_error(image_error: f64) -> Self {
        Self::ScreenError { image_error }
    }

    /// The criterion refining as if its accuracy were `factor` times higher
    /// (a quality preset's factor): `c · factor`, or `image_error / factor`.
    pub fn scaled(self, factor: f64) -> Self {
        match self {
            Self::Distance { accuracy } => Self::Distance {
                accuracy: accuracy * factor,
            },
            Self::ScreenError { image_error } => Self::ScreenError {
                image_error: image_error / factor,
            },
        }
    }

    /// `Ok` when the criterion is usable: `accuracy` ≥ 0 and not NaN,
    /// `image_error` finite and > 0.
    pub fn validate(&self) -> Result<(), RefinementError> {
        match *self {
            Self::Distance { accuracy } if accuracy >= 0.0 => Ok(()),
            Self::Distance { accuracy } => {
                Err(RefinementError::InvalidAccuracy { value: accuracy })
            }
            Self::ScreenError { image_error } if image_error > 0.0 && image_error.is_finite() => {
                Ok(())
            }
            Self::ScreenError { image_error } => {
                Err(RefinementError::InvalidImageError { value: image_error })
            }
        }
    }
}

impl Default for LodCriterion {
    fn default() -> Self {
        Self::ScreenError {
            image_error: Self::DEFAULT_IMAGE_ERROR,
        }
    }
}

/// The user's controls of the refinement.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RefinementSettings {
    /// The error metric and its tolerance. Default
    /// [`LodCriterion::ScreenError`] at 0.1.
    pub criterion: LodCriterion,
    /// What the cells will draw (the emission's [`CellScalars`]): which
    /// field sets the opacity for the zero-opacity test and how the transfer
    /// function turns deviations into colour for the screen error. Default
    /// the density alone.
    pub scalars: CellScalars,
    /// For a hierarchy of two keyframes, the blend factor β toward the
    /// second that the cells are refined for: each node's Δ and scalar
    /// range are interpolated between the two keyframes' (bounds of the
    /// blend's own, see [`super::keyframe`]). Clamped to [0, 1], NaN as 0;
    /// ignored for a single keyframe. Default 0.
    pub blend: f32,
    /// How far the blend may advance past [`RefinementSettings::blend`]
    /// while the cells are drawn: they are refined for every blend from
    /// `blend` to `blend + blend_span` (each node's largest Δ and the hull
    /// of its scalar ranges over them, see [`super::keyframe`]), so none of
    /// them is refined too coarsely or culled. Blends beyond 1 count as 1;
    /// a negative or NaN span is 0; ignored for a single keyframe. Default
    /// 0: the cells are drawn at `blend` alone.
    pub blend_span: f32,
}

impl RefinementSettings {
    /// Density cells refined by `criterion`.
    pub fn new(criterion: LodCriterion) -> Self {
        Self {
            criterion,
            scalars: CellScalars::Density,
            blend: 0.0,
            blend_span: 0.0,
        }
    }

    /// `Ok` when the settings are usable ([`LodCriterion::validate`]).
    pub fn validate(&self) -> Result<(), RefinementError> {
        self.criterion.validate()
    }
}

/// Why [`refine`] could not run.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum RefinementError {
    /// A lit batch was asked of a hierarchy built without a light field.
    #[error(
        "the cells were asked to carry the light field, but the hierarchy has none (build it with VolumeHierarchy::with_light)"
    )]
    MissingLightField,
    /// The global accuracy `c` is NaN or negative.
    #[error(
        "the global accuracy c must be a number ≥ 0 (Röttger and Ertl 2003 Eq. 1), got {value}"
    )]
    InvalidAccuracy {
        /// The value given.
        value: f64,
    },
    /// The screen-error tolerance is not a finite number above 0.
    #[error("the tolerated image error (RMSE) must be finite and above 0, got {value}")]
    InvalidImageError {
        /// The value given.
        value: f64,
    },
    /// The screen-error criterion was asked of a view without its projection.
    #[error(
        "the screen-error criterion measures nodes in pixels and needs the view's projection (View::with_projection)"
    )]
    MissingProjection,
    /// The view's `world_from_local` (with the grid's origin and spacing) is
    /// not finite or not invertible.
    #[error("world_from_local must be finite and invertible (determinant {determinant})")]
    SingularTransform {
        /// Determinant of the linear part of the grid-index-to-world map.
        determinant: f64,
    },
    /// The eye is NaN or infinite, so neither distances nor an order exist.
    #[error("the eye position {eye} is not finite")]
    NonFiniteEye {
        /// The eye position given, world units.
        eye: DVec3,
    },
    /// A refinement given to the emission is not a tree as [`refine()`]
    /// makes it: a node below the roots' level whose parent is not refined,
    /// or a refined voxel.
    #[error("node {node:?} of the refinement is a refined voxel or lies below no refined parent")]
    MalformedRefinement {
        /// The node.
        node: Node,
    },
}

/// A node with its morph factor `e' = clamp(e − 1, 0, 1)` (Röttger and Ertl 2003 Eq. 6).
///
/// For a hierarchy of two keyframes refined for a span of blends
/// ([`Refinement::blends`]) the node is refined when `e > 1` for some blend
/// of the span, and carries `e'` at the span's two ends, where its batch
/// draws the field ([`super::emit`]): a node refined for another blend of the
/// span may have `e ≤ 1`, so `e' = 0`, at an end, and then draws its coarse
/// field there. For a single keyframe or an empty span both are its `e'`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NodeMorph {
    /// The node.
    pub node: Node,
    /// `e'` in [0, 1] at the span's first blend: 0 for every leaf above
    /// level 0 (a leaf has `e ≤ 1`; a leaf of a span takes the span's `e'`
    /// at both ends); above 0 for every refined node of a single keyframe.
    pub morph: f32,
    /// `e'` in [0, 1] at the span's last blend, as [`NodeMorph::morph`].
    pub end_morph: f32,
    /// Whether the node's scalar range at the span's first (`[0]`) and last
    /// (`[1]`) blend has zero opacity. At such an end the node takes no
    /// part in the morph: it does not constrain the points it shares, and
    /// the leaves in it draw its own piecewise-linear field (see
    /// [`super::emit`]), exactly as where a refinement for another span
    /// draws it as a leaf. For a single keyframe both are whether its range
    /// is transparent, which only a leaf's can be.
    pub transparent: [bool; 2],
}

/// Counters of one refinement.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RefinementStats {
    /// Nodes the traversal reached, pruned ones included.
    pub nodes_visited: usize,
    /// Leaves to draw (six tetrahedra each).
    pub leaves: usize,
    /// Leaves that are voxels (level 0), drawn at full resolution.
    pub full_resolution_leaves: usize,
    /// Nodes skipped with their subtree because their box misses the frustum.
    pub culled_by_frustum: usize,
    /// Roots skipped because their scalar range has zero opacity under the
    /// transfer function (a transparent node below a drawn parent is a leaf
    /// instead, see [`NodeMorph::transparent`]).
    pub culled_transparent: usize,
    /// Leaves whose scalar range has zero opacity, below drawn parents.
    pub transparent_leaves: usize,
}

/// The outcome of one refinement.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Refinement {
    /// The leaves to draw, back to front for the eye.
    pub leaves: Vec<NodeMorph>,
    /// Every refined node (`e > 1`, not a voxel), parents before children.
    pub refined: Vec<NodeMorph>,
    /// For a hierarchy of two keyframes, the first and last blend
    /// ([`RefinementSettings::blend`], [`RefinementSettings::blend_span`],
    /// clamped to [0, 1]) the refinement serves and its morph factors are
    /// taken at ([`NodeMorph`]); `[0, 0]` for a single keyframe.
    pub blends: [f32; 2],
    /// Counters.
    pub stats: RefinementStats,
}

impl Refinement {}

/// The map from the hierarchy's index space (point `(i, j, k)` at
/// `(i, j, k)`) to world space, and the eye in index space, for `view`;
/// refinement and emission share it.
pub(crate) fn index_frame(
    hierarchy: &VolumeHierarchy,
    view: &View,
) -> Result<(DAffine3, DVec3), RefinementError> {
    let (world_from_index, index_from_world) = index_maps(
        hierarchy.origin(),
        hierarchy.spacing(),
        view.world_from_local,
    )
    .ok_or(RefinementError::SingularTransform {
        determinant: view.world_from_local.matrix3.determinant(),
    })?;
    let eye_index = index_from_world.transform_point3(view.eye);
    if !(view.eye.is_finite() && eye_index.is_finite()) {
        return Err(RefinementError::NonFiniteEye { eye: view.eye });
    }
    Ok((world_from_index, eye_index))
}

/// Refines `hierarchy` for one frame (see the module docs).
///
/// - `view`: its `world_from_local` maps the grid's own coordinates (point
///   `(i, j, k)` at `origin + (i, j, k) · spacing`) to world space, as for
///   [`crate::full_resolution_batch`]; the eye sets distances and order; the
///   frustum prunes nodes (distance criterion); the projection and viewport measure nodes in
///   pixels for the screen-error criterion; an empty viewport gives an empty
///   refinement (after the checks below).
/// - `transfer`: the volume's transfer function, as the cells will be drawn
///   with it ([`RefinementSettings::scalars`] says over which field).
/// - `settings`: the criterion and what the cells draw.
///
/// Errors: [`RefinementError`].
pub fn refine(
    hierarchy: &VolumeHierarchy,
    view: &View,
    transfer: &TransferFunction,
    settings: &RefinementSettings,
) -> Result<Refinement, RefinementError> {
    settings.validate()?;
    let (world_from_index, eye_index) = index_frame(hierarchy, view)?;
    let metric = match settings.criterion {
        LodCriterion::Distance { accuracy } => Metric::Distance { accuracy },
        LodCriterion::ScreenError { image_error } => {
            let clip_from_world = view
                .clip_from_world
                .ok_or(RefinementError::MissingProjection)?;
            let tiles =
                ScreenTiles::new(clip_from_world, world_from_index, view.viewport.to_array());
            let blends = blend_interval(settings.blend, settings.blend_span);
            let spanned = hierarchy.has_next_keyframe() && blends[0] != blends[1];
            Metric::ScreenError {
                image_error,
                optics: Box::new(NodeOptics::new(transfer, settings.scalars)),
                end_tiles: if spanned {
                    vec![tiles.clone(), tiles.clone()]
                } else {
                    Vec::new()
                },
                tiles: Box::new(tiles),
            }
        }
    };
    if view.viewport_is_empty() {
        return Ok(Refinement::default());
    }
    let m = world_from_index.matrix3;
    let edges = [m.x_axis.length(), m.y_axis.length(), m.z_axis.length()];
    let mut traversal = Traversal {
        hierarchy,
        world_from_index,
        eye_world: view.eye,
        eye_index,
        // The screen error gives nodes off the screen no error instead.
        frustum: view
            .frustum
            .as_ref()
            .filter(|_| matches!(settings.criterion, LodCriterion::Distance { .. }))
            .map(|f| f.in_local_frame(&world_from_index)),
        transfer,
        density_is_opacity: settings.scalars == CellScalars::LightModulatedByDensity,
        blends: blend_interval(settings.blend, settings.blend_span),
        metric,
        voxel_edge: edges[0].max(edges[1]).max(edges[2]),
        shortest_voxel_edge: edges[0].min(edges[1]).min(edges[2]),
        result: Refinement::default(),
    };

    let root_size = (1u64 << hierarchy.root_level()) as f64;
    let root_order: [Vec<usize>; 3] = std::array::from_fn(|axis| {
        // ±2⁶² keeps axis_order's i64 arithmetic far from overflow.
        let slab = (eye_index[axis] / root_size)
            .floor()
            .clamp(-(2f64.powi(62)), 2f64.powi(62)) as i64;
        let mut order = Vec::with_capacity(hierarchy.root_counts()[axis]);
        axis_order(0, hierarchy.root_counts()[axis], Some(slab), &mut order);
        // Front to back.
        order.reverse();
        order
    });
    let size = 1 << hierarchy.root_level();
    for &z in &root_order[2] {
        for &y in &root_order[1] {
            for &x in &root_order[0] {
                let root = Node {
                    level: hierarchy.root_level(),
                    origin: [x * size, y * size, z * size],
                };
                traversal.visit(root, None);
            }
        }
    }
    let blends = traversal.blends;
    let mut result = traversal.result;
    if hierarchy.has_next_keyframe() {
        result.blends = blends;
    }
    result.leaves.reverse();
    result.stats.leaves = result.leaves.len();
    Ok(result)
}

/// The first and last blend of [`RefinementSettings::blend`] and
/// [`RefinementSettings::blend_span`]: NaN read as 0, both clamped to
/// [0, 1].
fn blend_interval(blend: f32, span: f32) -> [f32; 2] {
    let start = clamped_blend(blend);
    let span = if span.is_nan() { 0.0 } else { span.max(0.0) };
    [start, clamped_blend(start + span)]
}

/// The error metric of one refinement, with what it keeps while it runs.
enum Metric {
    /// Röttger and Ertl 2003 Eq. 1 with the global accuracy `c`.
    Distance { accuracy: f64 },
    /// The screen error ([`super::screen_error`]).
    ScreenError {
        image_error: f64,
        optics: Box<NodeOptics>,
        tiles: Box<ScreenTiles>,
        /// For a span of blends of two keyframes, the occlusion at its first
        /// and at its last blend, from the nodes in front with their `e'`
        /// and ranges there; empty otherwise.
        end_tiles: Vec<ScreenTiles>,
    },
}

/// The parts of a node's error metric that do not depend on the keyframe
/// blend ([`Traversal::error_terms`]).
struct ErrorTerms {
    /// The world-space image of the node's longest edge.
    size: f64,
    /// The eye's distance from the node's centre, world units.
    eye_distance: f64,
    /// Screen error: the node's footprint, `None` wholly behind the eye.
    footprint: Option<Footprint>,
    /// Screen error: the share of the footprint on the screen.
    share: f64,
    /// Screen error: the transmittance in front of the footprint.
    transmittance: f64,
    /// Screen error: the same at the span's first and last blend.
    end_transmittance: [f64; 2],
}

/// The state of one top-down traversal.
struct Traversal<'a> {
    /// The hierarchy being refined.
    hierarchy: &'a VolumeHierarchy,
    /// Grid index coordinates to world space.
    world_from_index: DAffine3,
    /// The eye, world units.
    eye_world: DVec3,
    /// The eye in grid index coordinates, for the order.
    eye_index: DVec3,
    /// The frustum in grid index coordinates.
    frustum: Option<Frustum>,
    /// The transfer function of the zero-opacity test.
    transfer: &'a TransferFunction,
    /// The density itself is the opacity (only density 0 is empty).
    density_is_opacity: bool,
    /// The keyframe blends refined for, the first and the last, in [0, 1].
    blends: [f32; 2],
    /// The error metric.
    metric: Metric,
    /// The longest world-space image of one voxel edge.
    voxel_edge: f64,
    /// The shortest world-space image of one voxel edge.
    shortest_voxel_edge: f64,
    /// What has been found so far.
    result: Refinement,
}

impl Traversal<'_> {
    /// Visits `node` and, when it is refined, its children front to back;
    /// `parent` is the parent's `e'` and occlusion weight, each for the span,
    /// at its first and at its last blend (`None` for a root).
    fn visit(&mut self, node: Node, parent: Option<([f32; 3], [f64; 3])>) {
        pace();
        let stats = &mut self.result.stats;
        stats.nodes_visited += 1;
        let size = node.size() as f64;
        let lo = DVec3::from(node.origin.map(|o| o as f64));
        if self
            .frustum
            .as_ref()
            .is_some_and(|f| !f.intersects_aabb(lo, lo + size))
        {
            stats.culled_by_frustum += 1;
            return;
        }
        let range = self.hierarchy.scalar_range_over(node, self.blends);
        if self.is_transparent(range) {
            if parent.is_none() {
                self.result.stats.culled_transparent += 1;
            } else {
                // Below a drawn parent a transparent node is a leaf: its
                // parent's coarse field reaches into it while the parent
                // morphs (see `super::emit`). It occludes nothing.
                self.result.stats.transparent_leaves += 1;
                self.result.leaves.push(NodeMorph {
                    node,
                    morph: 0.0,
                    end_morph: 0.0,
                    transparent: [true; 2],
                });
            }
            return;
        }

        let centre = lo + 0.5 * size;
        let delta = self.hierarchy.deviation_over(node, self.blends);
        let terms = self.error_terms(node, centre, lo);
        let e = self.error(&terms, range, delta, terms.transmittance);
        // e for the span (the refinement's and the occlusion's), then at its
        // two ends, each with the occlusion there.
        let mut errors = [e; 3];
        let mut transparent = [false; 2];
        let mut end_ranges = [range; 2];
        if self.blends[0] != self.blends[1] && self.hierarchy.has_next_keyframe() {
            for (end, &blend) in self.blends.iter().enumerate() {
                // A node transparent at an end takes no part in the morph
                // there (`NodeMorph::transparent`).
                end_ranges[end] = self.hierarchy.scalar_range_at(node, blend);
                transparent[end] = self.is_transparent(end_ranges[end]);
                errors[1 + end] = if transparent[end] {
                    0.0
                } else {
                    let delta = self.hierarchy.deviation_at(node, blend);
                    self.error(&terms, end_ranges[end], delta, terms.end_transmittance[end])
                };
            }
        }
        // Refined when any of them asks for it, so a refinement for the next
        // span refines no node this one would draw coarser at their shared
        // blend.
        let refine = errors.iter().any(|&e| e > 1.0);
        let mut morphs = errors.map(|e| (e - 1.0).clamp(0.0, 1.0) as f32);
        // The screen error: e' at most the parent's, and the weights of this
        // node's occlusion for the span and at its ends (see `screen_error`).
        let mut weights = [1.0; 3];
        if let (Metric::ScreenError { .. }, Some((parent_morphs, parent_weights))) =
            (&self.metric, parent)
        {
            for (morph, parent_morph) in morphs.iter_mut().zip(parent_morphs) {
                *morph = morph.min(parent_morph);
            }
            weights =
                std::array::from_fn(|set| parent_weights[set] * f64::from(parent_morphs[set]));
        }
        let footprint = terms.footprint;
        let morph = NodeMorph {
            node,
            morph: morphs[1],
            end_morph: morphs[2],
            transparent,
        };
        let ranges = [range, end_ranges[0], end_ranges[1]];
        match node.children() {
            Some(children) if refine => {
                self.result.refined.push(morph);
                // Per axis the child bit on the eye's side first; an eye on
                // the split plane counts as on the upper side.
                let bits = |axis: usize| {
                    if self.eye_index[axis] < centre[axis] {
                        [0, 1]
                    } else {
                        [1, 0]
                    }
                };
                let (bx, by, bz) = (bits(0), bits(1), bits(2));
                for z in bz {
                    for y in by {
                        for x in bx {
                            let child = children[x + 2 * y + 4 * z];
                            self.visit(child, Some((morphs, weights)));
                        }
                    }
                }
                let unmorphed =
                    std::array::from_fn(|set| weights[set] * f64::from(1.0 - morphs[set]));
                self.occlude(footprint, ranges, size, unmorphed);
            }
            _ => {
                if node.level == 0 {
                    self.result.stats.full_resolution_leaves += 1;
                }
                self.occlude(footprint, ranges, size, weights);
                self.result.leaves.push(morph);
            }
        }
    }

    /// Whether the scalar range `range` (units of 1/255) has zero opacity
    /// for what the cells draw.
    fn is_transparent(&self, range: [u8; 2]) -> bool {
        if self.density_is_opacity {
            range[1] == 0
        } else {
            let [s_min, s_max] = range.map(|q| f64::from(q) / 255.0);
            self.transfer.is_transparent(s_min, s_max)
        }
    }

    /// The screen error's occlusion by a node of this footprint and size
    /// (voxels), for the span and at its two ends with the node's scalar
    /// range and `weights` of its own depth there (see `screen_error`).
    fn occlude(
        &mut self,
        footprint: Option<Footprint>,
        ranges: [[u8; 2]; 3],
        size: f64,
        weights: [f64; 3],
    ) {
        let depth = self.shortest_voxel_edge * size / 2.0;
        if let (
            Some(footprint),
            Metric::ScreenError {
                optics,
                tiles,
                end_tiles,
                ..
            },
        ) = (footprint, &mut self.metric)
        {
            let sets = std::iter::once(&mut **tiles).chain(end_tiles.iter_mut());
            for ((tiles, range), weight) in sets.zip(ranges).zip(weights) {
                if weight > 0.0 {
                    tiles.occlude(footprint, weight * optics.min_extinction(range) * depth);
                }
            }
        }
    }

    /// What the error metric of `node` (box at `lo`, centre at `centre`,
    /// grid index coordinates) needs besides its deviation and scalar range:
    /// its size, its distance term and, for the screen error, its footprint,
    /// visible share and transmittance.
    fn error_terms(&self, node: Node, centre: DVec3, lo: DVec3) -> ErrorTerms {
        let size = self.voxel_edge * node.size() as f64;
        let eye_distance = self
            .world_from_index
            .transform_point3(centre)
            .distance(self.eye_world);
        match &self.metric {
            Metric::Distance { .. } => ErrorTerms {
                size,
                eye_distance,
                footprint: None,
                share: 0.0,
                transmittance: 0.0,
                end_transmittance: [0.0; 2],
            },
            Metric::ScreenError {
                tiles, end_tiles, ..
            } => {
                let footprint = tiles.footprint(lo, node.size() as f64);
                let transmittance = footprint.map_or(0.0, |f| tiles.transmittance(f));
                let end_transmittance = std::array::from_fn(|end| {
                    end_tiles
                        .get(end)
                        .zip(footprint)
                        .map_or(transmittance, |(tiles, f)| tiles.transmittance(f))
                });
                ErrorTerms {
                    size,
                    eye_distance,
                    footprint,
                    share: footprint.map_or(0.0, |f| tiles.visible_share(f)),
                    transmittance,
                    end_transmittance,
                }
            }
        }
    }

    /// The error metric `e` of a node with the terms `terms`, scalar range
    /// `range`, deviation `delta` and, for the screen error, the
    /// transmittance `transmittance` in front of it. The distance metric
    /// (Eq. 1) is `∞` when the eye is at the centre; the screen error is 0
    /// for a node wholly behind the eye.
    fn error(&self, terms: &ErrorTerms, range: [u8; 2], delta: f32, transmittance: f64) -> f64 {
        let delta = f64::from(delta);
        match &self.metric {
            Metric::Distance { accuracy } => {
                // `max` ignores the NaN of ∞ · 0 (c = ∞ with Δ = 0).
                let numerator =
                    terms.size * self.hierarchy.min_accuracy() * (accuracy * delta).max(1.0);
                over_distance(numerator, terms.eye_distance)
            }
            Metric::ScreenError {
                image_error,
                optics,
                ..
            } => {
                let Some(footprint) = terms.footprint else {
                    return 0.0;
                };
                let share = terms.share;
                let error = if delta > 0.0 && share > 0.0 && transmittance > 0.0 {
                    transmittance * optics.error(range, delta, terms.size)
                } else {
                    0.0
                };
                // Nodes with detail around the eye are refined (see
                // `screen_error`).
                let near = if delta > 0.0 {
                    over_distance(terms.size * 3f64.sqrt(), terms.eye_distance)
                } else {
                    0.0
                };
                (error * share / image_error)
                    .min(footprint.pixels())
                    .max(near)
            }
        }
    }
}

/// `numerator / d` for the eye distance `d`; `∞` at the eye.
fn over_distance(numerator: f64, d: f64) -> f64 {
    if d > 0.0 {
        numerator / d
    } else {
        f64::INFINITY
    }
}

#[cfg(test)]
mod tests {
    use glam::{DMat4, DQuat};
    use nebel_core::field::DensityGrid;
    use nebel_core::transfer::{ControlPoint, TransferPreset};
    use proptest::prelude::*;

    use super::*;
    use crate::full_resolution::{BrickTable, CellOrder, full_resolution_batch};

    /// The smallest minimum accuracy the tests use (`K_max` close to 1).
    const C_MIN: f64 = 1.75;

    /// ρ > 0 for every s > 0.
    fn fog() -> TransferFunction {
        TransferFunction::preset(TransferPreset::GroundFog)
    }

    /// A rough field in (0, 1) with a hole of density 0.02 in one corner
    /// (transparent for the cloud preset, not for fog).
    fn field(dims: [usize; 3], seed: u64) -> DensityGrid {
        let [nx, ny, nz] = dims;
        let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        let mut values = Vec::with_capacity(nx * ny * nz);
        for _ in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    let hole = i < nx / 3 && j < ny / 3;
                    let noise = (state >> 40) as f32 / (1u64 << 24) as f32;
                    values.push(if hole { 0.02 } else { 0.05 + 0.9 * noise });
                }
            }
        }
        DensityGrid::new(
            dims,
            DVec3::new(0.5, 0.5, 0.5),
            DVec3::new(-2.0, 1.0, 0.5),
            values,
        )
        .expect("valid grid")
    }

    fn hierarchy(dims: [usize; 3], seed: u64, min_accuracy: f64) -> VolumeHierarchy {
        VolumeHierarchy::new(&field(dims, seed), min_accuracy).expect("2^n+1 grid")
    }

    fn settings(accuracy: f64) -> RefinementSettings {
        RefinementSettings::new(LodCriterion::distance(accuracy))
    }

    fn screen(image_error: f64) -> RefinementSettings {
        RefinementSettings::new(LodCriterion::screen_error(image_error))
    }

    /// [`view`] through a 60° perspective looking from `eye` at `target`
    /// (world units), culled by its frustum.
    fn projected_view(eye: DVec3, target: DVec3, viewport: glam::UVec2) -> View {
        let up = if (target - eye).cross(DVec3::Y).length() > 1e-9 {
            DVec3::Y
        } else {
            DVec3::X
        };
        let aspect = f64::from(viewport.x) / f64::from(viewport.y);
        let clip_from_world =
            DMat4::perspective_infinite_reverse_rh(60f64.to_radians(), aspect, 0.01)
                * DMat4::look_at_rh(eye, target, up);
        View::new(world_from_grid(), eye, viewport).with_projection(clip_from_world)
    }

    fn world_from_grid() -> DAffine3 {
        DAffine3::from_rotation_translation(
            DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.7, 0.2),
            DVec3::new(1.0, 2.0, -3.0),
        )
    }

    /// The view of the grid placed by [`world_from_grid`] from `eye` (world
    /// units), culled by `frustum`, on a 640 × 480 viewport.
    fn view(eye: DVec3, frustum: Option<&Frustum>) -> View {
        View {
            frustum: frustum.cloned(),
            ..View::new(world_from_grid(), eye, glam::UVec2::new(640, 480))
        }
    }

    /// The eye in world space for a point in grid index coordinates.
    fn eye_at_index(h: &VolumeHierarchy, index: DVec3) -> DVec3 {
        world_from_grid().transform_point3(h.origin() + index * h.spacing())
    }

    fn run(
        h: &VolumeHierarchy,
        eye: DVec3,
        frustum: Option<&Frustum>,
        transfer: &TransferFunction,
        accuracy: f64,
    ) -> Refinement {
        refine(h, &view(eye, frustum), transfer, &settings(accuracy)).unwrap()
    }

    /// Whether `node` covers the voxel with minimum corner `voxel`.
    fn holds_voxel(node: Node, voxel: [usize; 3]) -> bool {
        (0..3).all(|a| voxel[a].wrapping_sub(node.origin[a]) < node.size())
    }

    /// Boxes `[min, max]` of the leaves in grid index coordinates.
    fn boxes(r: &Refinement) -> Vec<(DVec3, DVec3)> {
        r.leaves
            .iter()
            .map(|l| {
                let lo = DVec3::from(l.node.origin.map(|o| o as f64));
                (lo, lo + l.node.size() as f64)
            })
            .collect()
    }

    /// Every voxel covered by exactly as many leaves as `expected(voxel)`
    /// says (0 or 1).
    fn assert_tiling(h: &VolumeHierarchy, r: &Refinement, expected: impl Fn([usize; 3]) -> usize) {
        let v = h.dims().map(|n| n - 1);
        let mut cover = vec![0usize; v[0] * v[1] * v[2]];
        for leaf in &r.leaves {
            let (o, s) = (leaf.node.origin, leaf.node.size());
            for k in o[2]..o[2] + s {
                for j in o[1]..o[1] + s {
                    for i in o[0]..o[0] + s {
                        cover[i + v[0] * (j + v[1] * k)] += 1;
                    }
                }
            }
        }
        for k in 0..v[2] {
            for j in 0..v[1] {
                for i in 0..v[0] {
                    assert_eq!(cover[i + v[0] * (j + v[1] * k)], expected([i, j, k]));
                }
            }
        }
    }

    /// Along rays from `eye` (grid index coordinates) through the leaves'
    /// boxes, the farther box comes first in the list.
    fn assert_back_to_front(r: &Refinement, eye: DVec3, directions: &[DVec3]) -> usize {
        let boxes = boxes(r);
        let mut pairs = 0;
        for &dir in directions {
            let mut hits: Vec<(f64, f64, usize)> = boxes
                .iter()
                .enumerate()
                .filter_map(|(index, &(lo, hi))| {
                    let (t0, t1) = ((lo - eye) / dir, (hi - eye) / dir);
                    let entry = t0.min(t1).max_element().max(0.0);
                    let exit = t0.max(t1).min_element();
                    (exit - entry > 1e-9).then_some((entry, exit, index))
                })
                .collect();
            hits.sort_by(|a, b| (a.0 + a.1).total_cmp(&(b.0 + b.1)));
            for pair in hits.windows(2) {
                let (near, far) = (pair[0], pair[1]);
                assert!(near.1 <= far.0 + 1e-9, "leaves overlap: {near:?} {far:?}");
                assert!(
                    far.2 < near.2,
                    "eye {eye}, direction {dir}: leaf {:?} is behind leaf {:?} but drawn after it",
                    r.leaves[far.2].node,
                    r.leaves[near.2].node
                );
                pairs += 1;
            }
        }
        pairs
    }

    fn directions(seed: u64, count: usize) -> Vec<DVec3> {
        let mut state = seed | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        (0..count)
            .map(|_| DVec3::new(next(), next(), next()).normalize_or(DVec3::X))
            .collect()
    }

    #[test]
    fn settings_reject_nan_and_negative_accuracy() {
        assert_eq!(
            RefinementSettings::default().criterion,
            LodCriterion::screen_error(0.1)
        );
        assert_eq!(
            LodCriterion::distance(4.0).scaled(0.5),
            LodCriterion::distance(2.0)
        );
        assert_eq!(
            LodCriterion::screen_error(0.01).scaled(0.5),
            LodCriterion::screen_error(0.02)
        );
        assert!(settings(0.0).validate().is_ok());
        assert!(settings(f64::INFINITY).validate().is_ok());
        for bad in [f64::NAN, -1.0, -0.5, f64::NEG_INFINITY] {
            let err = settings(bad).validate().unwrap_err();
            assert!(matches!(err, RefinementError::InvalidAccuracy { .. }));
            assert!(err.to_string().contains("c must be a number ≥ 0"));
        }
        let h = hierarchy([5, 5, 5], 1, 2.0);
        let eye = DVec3::ZERO;
        let t = fog();
        let r = refine(&h, &view(eye, None), &t, &settings(f64::NAN));
        assert!(matches!(r, Err(RefinementError::InvalidAccuracy { .. })));
        let singular = View {
            world_from_local: DAffine3::from_scale(DVec3::new(1.0, 0.0, 1.0)),
            ..view(eye, None)
        };
        let r = refine(&h, &singular, &t, &settings(1.0));
        assert!(matches!(r, Err(RefinementError::SingularTransform { .. })));
        let r = refine(
            &h,
            &view(DVec3::new(0.0, f64::NAN, 0.0), None),
            &t,
            &settings(1.0),
        );
        assert!(matches!(r, Err(RefinementError::NonFiniteEye { .. })));
        // An empty viewport is checked like any view, then sees nothing.
        let mut hidden = view(eye, None);
        hidden.viewport.y = 0;
        assert_eq!(
            refine(&h, &hidden, &t, &settings(1e9)),
            Ok(Refinement::default())
        );
        hidden.eye.x = f64::INFINITY;
        let r = refine(&h, &hidden, &t, &settings(1.0));
        assert!(matches!(r, Err(RefinementError::NonFiniteEye { .. })));
    }

    #[test]
    fn screen_error_rejects_bad_tolerances_and_views_without_projection() {
        let h = hierarchy([9, 9, 9], 1, 2.0);
        let t = fog();
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let err = refine(&h, &view(DVec3::ZERO, None), &t, &screen(bad)).unwrap_err();
            assert!(
                matches!(err, RefinementError::InvalidImageError { .. }),
                "{bad}"
            );
            assert!(err.to_string().contains("above 0"));
        }
        let err = refine(&h, &view(DVec3::ZERO, None), &t, &screen(0.01)).unwrap_err();
        assert_eq!(err, RefinementError::MissingProjection);
        // A projection that is not finite: every footprint is "everywhere",
        // nothing is NaN.
        let mut broken = view(DVec3::splat(30.0), None);
        broken.clip_from_world = Some(DMat4::from_cols_array(&[f64::NAN; 16]));
        let r = refine(&h, &broken, &t, &screen(0.01)).unwrap();
        assert!(
            r.leaves
                .iter()
                .chain(&r.refined)
                .all(|n| (0.0..=1.0).contains(&n.morph))
        );
    }

    /// Far away the whole volume is a few pixels: only nodes larger than a
    /// pixel are refined, however small the tolerance; close up a small
    /// tolerance refines to voxels, and a larger one draws fewer leaves.
    #[test]
    fn screen_error_refines_by_pixels_and_tolerance() {
        let h = hierarchy([17, 17, 9], 3, 2.0);
        let t = fog();
        let target = eye_at_index(&h, DVec3::new(8.0, 8.0, 4.0));
        let viewport = glam::UVec2::new(320, 200);
        let far = projected_view(
            eye_at_index(&h, DVec3::new(8.0, 8.0, 4.0e4)),
            target,
            viewport,
        );
        let r = refine(&h, &far, &t, &screen(1e-9)).unwrap();
        assert!(r.refined.is_empty() && r.leaves.len() == 4, "{:?}", r.stats);
        let near = projected_view(
            eye_at_index(&h, DVec3::new(8.0, 8.0, 24.0)),
            target,
            viewport,
        );
        let fine = refine(&h, &near, &t, &screen(1e-9)).unwrap();
        assert!(fine.stats.full_resolution_leaves > 0);
        let mut last = fine.leaves.len();
        for tolerance in [1e-3, 1e-2, 1e-1, 1.0] {
            let r = refine(&h, &near, &t, &screen(tolerance)).unwrap();
            assert!(
                r.leaves.len() <= last,
                "{tolerance}: {} > {last}",
                r.leaves.len()
            );
            last = r.leaves.len();
        }
        assert!(last < fine.leaves.len());
        // A refined node's e' never exceeds its parent's.
        let mut morphs = std::collections::HashMap::new();
        for n in &fine.refined {
            morphs.insert(n.node, n.morph);
        }
        let mut checked = 0;
        for n in fine.refined.iter().chain(&fine.leaves) {
            if let Some(&parent_morph) = morphs.get(&n.node.parent()) {
                assert!(
                    n.morph <= parent_morph,
                    "{:?}: {} > {parent_morph}",
                    n.node,
                    n.morph
                );
                checked += 1;
            }
        }
        assert!(checked > 0);
    }

    /// A dense slab in front of a rough field hides it: the screen error
    /// draws fewer leaves behind it than behind the same slab made clear,
    /// and never more than the distance criterion needs for the same view
    /// at a huge accuracy.
    #[test]
    fn screen_error_needs_less_detail_behind_dense_volume() {
        let dims = [33, 33, 17];
        let rough = |wall: f32| {
            let base = field(dims, 9);
            let values = base
                .values()
                .iter()
                .enumerate()
                .map(|(index, &v)| if index / (33 * 33) >= 13 { wall } else { v })
                .collect();
            DensityGrid::new(dims, base.spacing(), base.origin(), values).unwrap()
        };
        // ρ = 0.5 per world unit from density 0.04 to 0.95, rising to 8 at
        // density 1: the wall (density 1) is opaque, density 0.3 lets light through.
        let white = |s: f32, rho: f32| ControlPoint {
            s,
            kappa: [1.0; 3],
            rho,
        };
        let transfer = TransferFunction::new([
            white(0.0, 0.0),
            white(0.04, 0.5),
            white(0.95, 0.5),
            white(1.0, 8.0),
        ])
        .unwrap();
        let viewport = glam::UVec2::new(320, 200);
        let leaves_behind = |wall: f32| {
            let h = VolumeHierarchy::new(&rough(wall), 2.0).unwrap();
            let eye = eye_at_index(&h, DVec3::new(16.0, 16.0, 40.0));
            let target = eye_at_index(&h, DVec3::new(16.0, 16.0, 0.0));
            let r = refine(
                &h,
                &projected_view(eye, target, viewport),
                &transfer,
                &screen(1e-3),
            )
            .unwrap();
            // Behind the voxels at the wall's back face (which the steep
            // transfer function there refines either way).
            r.leaves
                .iter()
                .filter(|l| l.node.origin[2] + l.node.size() <= 12)
                .count()
        };
        let (hidden, visible) = (leaves_behind(1.0), leaves_behind(0.3));
        eprintln!("leaves behind an opaque wall {hidden}, behind a clear one {visible}");
        assert!(4 * hidden < visible, "{hidden} vs {visible}");
    }

    #[test]
    fn huge_accuracy_gives_the_full_resolution_cells() {
        let h = hierarchy([17, 17, 9], 3, C_MIN);
        let grid = h.quantised_grid();
        let bricks = BrickTable::new(&grid, 1);
        let transfer = TransferFunction::preset(TransferPreset::Cloud);
        let eye = eye_at_index(&h, DVec3::new(-6.0, 30.0, 4.0));
        let target = eye_at_index(&h, DVec3::new(8.0, 8.0, 4.0));
        let camera = DMat4::look_at_rh(eye, target, DVec3::Y);
        let frustum = Frustum::from_view_projection(
            DMat4::perspective_infinite_reverse_rh(0.5, 1.2, 0.1) * camera,
        )
        .unwrap();
        for frustum in [None, Some(&frustum)] {
            let r = run(&h, eye, frustum, &transfer, 1e9);
            let full = full_resolution_batch(
                &grid,
                &bricks,
                &view(eye, frustum),
                &transfer,
                CellOrder::BackToFront,
            )
            .unwrap();
            // Every leaf with something to show is a voxel, and they are the
            // voxels the full-resolution batch keeps; the transparent nodes
            // below drawn parents are leaves of their own.
            let shown: Vec<&NodeMorph> = r.leaves.iter().filter(|l| !l.transparent[0]).collect();
            assert!(shown.iter().all(|l| l.node.level == 0));
            assert_eq!(6 * shown.len(), full.tetrahedra.len());
            assert!(r.stats.transparent_leaves > 0);
            assert_eq!(r.stats.leaves, shown.len() + r.stats.transparent_leaves);
            assert_eq!(r.stats.culled_by_frustum > 0, frustum.is_some());
            assert!(full.tetrahedra.len() < 6 * 16 * 16 * 8);
        }
    }

    #[test]
    fn far_eye_with_zero_accuracy_keeps_only_the_roots() {
        let h = hierarchy([17, 17, 9], 4, 2.0);
        let r = run(&h, DVec3::new(1e4, -3e3, 2e3), None, &fog(), 0.0);
        let roots: Vec<Node> = r.leaves.iter().map(|l| l.node).collect();
        assert_eq!(roots.len(), 4);
        assert!(roots.iter().all(|n| n.level == h.root_level()));
        assert!(r.refined.is_empty());
        assert_eq!(r.stats.nodes_visited, 4);
        assert!(r.leaves.iter().all(|l| l.morph == 0.0));
    }

    #[test]
    fn transparent_transfer_gives_no_leaves() {
        let clear = TransferFunction::new([ControlPoint {
            s: 0.5,
            kappa: [1.0; 3],
            rho: 0.0,
        }])
        .unwrap();
        let h = hierarchy([9, 9, 9], 5, 2.0);
        let r = run(&h, eye_at_index(&h, DVec3::splat(4.0)), None, &clear, 1e9);
        assert!(r.leaves.is_empty() && r.refined.is_empty());
        assert_eq!(r.stats.culled_transparent, 1);
        assert_eq!(r.stats.nodes_visited, 1);
    }

    #[test]
    fn eye_at_node_centres_and_on_planes_refines_without_nan() {
        let h = hierarchy([17, 17, 17], 6, 2.0);
        for eye in [
            [8.0, 8.0, 8.0],
            [4.0, 4.0, 4.0],
            [1.0, 1.0, 1.0],
            [0.5, 0.5, 0.5],
            [8.0, 3.0, 0.0],
            [16.0, 16.0, 16.0],
        ] {
            let eye_index = DVec3::from(eye);
            let r = run(&h, eye_at_index(&h, eye_index), None, &fog(), 4.0);
            // The node whose centre is the eye is refined with e = ∞.
            let at_centre = r.refined.iter().filter(|n| {
                let c = n.node.centre().unwrap();
                DVec3::from(c.map(|v| v as f64)) == eye_index
            });
            for n in at_centre {
                assert_eq!(n.morph, 1.0);
            }
            assert!(
                r.leaves
                    .iter()
                    .chain(&r.refined)
                    .all(|n| (0.0..=1.0).contains(&n.morph))
            );
            assert_tiling(&h, &r, |_| 1);
            assert_back_to_front(&r, eye_index, &directions(7, 64));
            // The voxel around the eye is drawn at full resolution.
            let near = r.leaves.iter().find(|l| {
                (0..3).all(|a| {
                    let o = l.node.origin[a] as f64;
                    (o..=o + l.node.size() as f64).contains(&eye_index[a])
                })
            });
            assert_eq!(near.unwrap().node.level, 0);
        }
    }

    #[test]
    fn infinite_accuracy_refines_to_voxels_without_nan() {
        let h = hierarchy([9, 9, 9], 8, 2.0);
        let r = run(&h, DVec3::splat(1e6), None, &fog(), f64::INFINITY);
        // Only the flat hole (Δ = 0) stays coarse from far away.
        assert!(
            r.leaves
                .iter()
                .all(|l| l.node.level == 0 || h.deviation(l.node) == 0.0)
        );
        assert!(r.leaves.iter().any(|l| l.node.level == 0));
        assert!(r.refined.iter().all(|n| n.morph == 1.0));
    }

    /// Cells refined for a span of keyframe blends serve every blend in it:
    /// each voxel that a blend in the span makes visible (its corners' exact
    /// blended densities) is drawn exactly once, and every node that the
    /// blend's own refinement refines is refined. The second keyframe has
    /// its transparent hole at the other end, so blends make voxels appear
    /// that the span's start culls, and the span refines more than its
    /// start alone (both counted: the test can fail).
    #[test]
    fn a_span_of_blends_is_refined_for_every_blend_in_it() {
        let dims = [17, 17, 9];
        let cloud = TransferFunction::preset(TransferPreset::Cloud);
        let (mut appearing, mut finer) = (0usize, 0usize);
        for case in 0..24u64 {
            let first = field(dims, case);
            let other = field(dims, case + 1000);
            let nx = dims[0];
            let mirrored = (0..other.values().len())
                .map(|n| other.values()[n - n % nx + nx - 1 - n % nx])
                .collect();
            let second = DensityGrid::new(dims, other.spacing(), other.origin(), mirrored).unwrap();
            let pair = VolumeHierarchy::new(&first, 2.0)
                .unwrap()
                .with_next_keyframe(&VolumeHierarchy::new(&second, 2.0).unwrap())
                .unwrap();
            let eye = eye_at_index(&pair, 8.0 + 20.0 * directions(case, 1)[0]);
            let start = (case % 9) as f32 / 8.0;
            let span = [0.05, 0.2, 0.6][(case % 3) as usize];
            let refined_for = |blend: f32, blend_span: f32| {
                let settings = RefinementSettings {
                    blend,
                    blend_span,
                    ..settings(4.0)
                };
                refine(&pair, &view(eye, None), &cloud, &settings).unwrap()
            };
            let spanned = refined_for(start, span);
            let refined: Vec<Node> = spanned.refined.iter().map(|n| n.node).collect();
            let at_start = refined_for(start, 0.0);
            finer += usize::from(refined.len() > at_start.refined.len());
            for beta in [start, start + span / 3.0, start + span].map(|b| b.min(1.0)) {
                let own = refined_for(beta, 0.0);
                assert!(
                    own.refined.iter().all(|n| refined.contains(&n.node)),
                    "case {case}: β = {beta} refines a node the span {start} + {span} does not"
                );
                let visible = |blend: f32, voxel: Node| {
                    let densities: [f32; 8] = std::array::from_fn(|v| {
                        let p = voxel.corner(v);
                        (1.0 - blend) * pair.density(p) + blend * pair.next_density(p).unwrap()
                    });
                    let low = densities.into_iter().fold(f32::INFINITY, f32::min);
                    let high = densities.into_iter().fold(0.0, f32::max);
                    !cloud.is_transparent(f64::from(low), f64::from(high))
                };
                let voxel = |origin| Node { level: 0, origin };
                assert_tiling(&pair, &spanned, |origin| {
                    let covered = spanned.leaves.iter().any(|l| holds_voxel(l.node, origin));
                    if visible(beta, voxel(origin)) {
                        1
                    } else {
                        usize::from(covered)
                    }
                });
                let [nx, ny, nz] = dims.map(|n| n - 1);
                appearing += (0..nx * ny * nz)
                    .map(|n| voxel([n % nx, n / nx % ny, n / (nx * ny)]))
                    .filter(|&v| visible(beta, v) && !visible(start, v))
                    .count();
            }
        }
        assert!(appearing > 0, "no blend made a voxel appear");
        assert!(finer > 0, "no span refined more than its start");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// Leaves tile the volume once (or skip exactly the transparent
        /// voxels), come back to front along rays and carry e' in [0, 1];
        /// refined nodes have e' > 0.
        #[test]
        fn leaves_tile_once_in_back_to_front_order(
            seed in 0u64..1000,
            eye in prop::array::uniform3(-12.0..30.0f64),
            accuracy in 0.0..64.0f64,
            cloud in any::<bool>(),
            screen_error in any::<bool>(),
        ) {
            let h = hierarchy([17, 17, 9], seed, 2.0);
            let transfer = if cloud { TransferFunction::preset(TransferPreset::Cloud) } else { fog() };
            let eye_index = DVec3::from(eye);
            let eye_world = eye_at_index(&h, eye_index);
            let r = if screen_error {
                // Looking at the middle of the field from anywhere, the
                // frustum culling nothing.
                let target = eye_at_index(&h, DVec3::new(8.0, 8.0, 4.0)) + DVec3::splat(1e-3);
                let mut v = projected_view(eye_world, target, glam::UVec2::new(160, 100));
                v.frustum = None;
                refine(&h, &v, &transfer, &screen(accuracy.max(0.01) * 1e-3)).unwrap()
            } else {
                run(&h, eye_world, None, &transfer, accuracy)
            };
            prop_assert_eq!(r.stats.leaves, r.leaves.len());
            prop_assert!(r.leaves.iter().all(|l| (0.0..=1.0).contains(&l.morph)));
            prop_assert!(r.leaves.iter().all(|l| l.node.level == 0 || l.morph == 0.0));
            if screen_error {
                // e' is clamped to the parent's, so a refined node may have 0.
                prop_assert!(r.refined.iter().all(|n| (0.0..=1.0).contains(&n.morph)));
            } else {
                prop_assert!(r.refined.iter().all(|n| n.morph > 0.0 && n.morph <= 1.0));
            }
            if cloud {
                // Every voxel is covered at most once, and every voxel with
                // some opacity exactly once.
                assert_tiling(&h, &r, |[i, j, k]| {
                    let voxel = Node { level: 0, origin: [i, j, k] };
                    let [lo, hi] = h.scalar_range(voxel);
                    let opaque = !transfer.is_transparent(f64::from(lo), f64::from(hi));
                    let covered = r.leaves.iter().any(|l| holds_voxel(l.node, [i, j, k]));
                    if opaque { 1 } else { usize::from(covered) }
                });
            } else {
                let volume: usize = r.leaves.iter().map(|l| l.node.size().pow(3)).sum();
                prop_assert_eq!(volume, 16 * 16 * 8);
                assert_tiling(&h, &r, |_| 1);
            }
            assert_back_to_front(&r, eye_index, &directions(seed, 48));
        }

        /// More accuracy refines a superset of nodes; without culling the
        /// leaf count grows monotonically.
        #[test]
        fn leaves_grow_with_accuracy(
            seed in 0u64..1000,
            eye in prop::array::uniform3(-20.0..40.0f64),
        ) {
            let h = hierarchy([17, 17, 9], seed, 2.0);
            let eye = eye_at_index(&h, DVec3::from(eye));
            let cloud = TransferFunction::preset(TransferPreset::Cloud);
            let (mut last_leaves, mut last_refined) = (0, Vec::new());
            for accuracy in [0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 64.0, 256.0, 1e4] {
                let r = run(&h, eye, None, &fog(), accuracy);
                prop_assert!(r.leaves.len() >= last_leaves);
                last_leaves = r.leaves.len();
                let refined: Vec<Node> = run(&h, eye, None, &cloud, accuracy)
                    .refined.iter().map(|n| n.node).collect();
                prop_assert!(last_refined.iter().all(|n| refined.contains(n)));
                last_refined = refined;
            }
        }
    }
}
