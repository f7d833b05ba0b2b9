//! The per-frame emission of a [`Refinement`] as a morphed [`Cells`].
//!
//! Kuhn's six tetrahedra per leaf with morphed scalars (Röttger and Ertl 2003
//! §3, volumetric morphing, Eq. 7 and Eq. 8), in exact back-to-front order.
//!
//! Every grid point `p` that is not a root corner is born at the level `L`
//! where it first is a non-corner point (an edge midpoint, a face centre or a
//! node centre). The batch gives it
//!
//! `v(p) = w · own(p) + (1 − w) · coarse(p)`,
//!
//! with `w` the minimum `e'` of all level-`L` nodes that share `p` (Eq. 7;
//! `e' = 0` for a drawn node that is not refined) and `coarse(p)` the mean of
//! the morphed values at the two ends of the Kuhn edge through `p`, the coarse
//! value Δ is measured against (see [`super`]). Eq. 8 as printed weighs the two
//! the other way round; this direction makes a node just refined (`e' = 0`)
//! look like its unrefined self and one with `e' = 1` show its own values, so
//! with every `e' = 1` the batch is the full-resolution one.
//!
//! Because `v` depends on the grid point alone, every cell that uses a point
//! gets the same value, T-vertices lie on their coarser neighbour's field and,
//! Kuhn's decomposition being nested, the field is continuous across faces
//! between leaves of any levels: a refinement at `e' = 0` changes no pixel. A
//! node with zero opacity ([`NodeMorph::transparent`]) does not constrain the
//! points it shares, as if culled (§4.1), but its leaves draw the field of the
//! largest transparent node holding them where a morphing parent carries
//! something visible into it. A hierarchy of two keyframes is emitted with the
//! blended field at both ends of the refinement's span of blends
//! ([`Cells::next_scalars`], [`Cells::mix_factor`]).
//!
//! Leaves come in the order of [`Refinement::leaves`], the six tetrahedra of
//! each in the in-voxel MPVO order of [`crate::full_resolution`]; positions are
//! rounded to f32 once per grid point, so shared points coincide. Values are
//! evaluated level by level from the roots over each refined node's 3 × 3 × 3
//! lattice, without recursion; the refinement must be a tree as
//! [`super::refine()`] makes it.
//!
//! The morph rule in full, its proof of continuity at T-vertices, the rule for
//! transparent nodes and the direction of Eq. 8 are in `docs/octree-lod.md` in
//! the repository.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use glam::{DVec3, Vec4};
use nebel_core::cell::KUHN_TETRAHEDRA;
use nebel_core::pacing::pace;

use super::build::BORN_POINTS;
use super::keyframe::clamped_blend;
use super::refine::index_frame;
use super::{Node, NodeMorph, Refinement, RefinementError, VolumeHierarchy};
use crate::batch::{Cells, GpuCell};
use crate::full_resolution::{EyeSides, kuhn_back_to_front};
use crate::view::View;

/// Builds the world-space batch of `refinement` (from [`super::refine()`] of
/// `hierarchy`, or built by hand) with morphed scalars, in back-to-front order
/// for the view's eye (see the module docs for the morph rule and the order).
///
/// `view`: its `world_from_local` maps the grid's own coordinates (point
/// `(i, j, k)` at `origin + (i, j, k) · spacing`) to world space, as for
/// [`super::refine()`]; pass the view the refinement was made for. The eye
/// orders the cells inside each leaf; the frustum is not read (the
/// refinement culled); an empty viewport gives an empty batch (after the
/// checks below).
///
/// Errors: [`RefinementError::SingularTransform`] and
/// [`RefinementError::NonFiniteEye`], as [`super::refine()`];
/// [`RefinementError::MalformedRefinement`] for a refinement that is not a
/// tree as [`super::refine()`] makes it. Panics when a node of `refinement`
/// is not a node of `hierarchy`.
pub fn lod_batch(
    hierarchy: &VolumeHierarchy,
    refinement: &Refinement,
    view: &View,
) -> Result<Cells, RefinementError> {
    lod_batch_with(hierarchy, refinement, view, CellScalars::Density)
}

/// Which of a lit cloud's two fields the cells carry as their scalar and
/// which as the segment-length modulator ([`Cells`] type docs; Röttger and Ertl 2003
/// §5). Both fields are morphed by the same rule with the same weights.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum CellScalars {
    /// The density alone, no modulator (an unlit volume). The default.
    #[default]
    Density,
    /// Paper Röttger and Ertl 2003 §5.1: the light γ indexes the transfer function (colour
    /// `κ(γ)`, constant `ρ = ρ_max`) and the density `f` modulates the segment
    /// length, `l' = l · f / f_max` with `f_max = 1` (Eq. 9).
    LightModulatedByDensity,
    /// Paper Röttger and Ertl 2003 §5.2 (non-physical lighting): the density indexes the
    /// transfer function (`κ(f)` an inverse colour ramp, `ρ(f)` linear above
    /// a cut-off) and γ modulates the segment length, so the lit side is
    /// opaque and the far side translucent.
    DensityModulatedByLight,
}

/// [`lod_batch`] with a choice of scalar and modulator for a lit hierarchy
/// ([`VolumeHierarchy::with_light`]). Errors as [`lod_batch`], and
/// [`RefinementError::MissingLightField`] when `scalars` needs the light field
/// and the hierarchy has none.
pub fn lod_batch_with(
    hierarchy: &VolumeHierarchy,
    refinement: &Refinement,
    view: &View,
    scalars: CellScalars,
) -> Result<Cells, RefinementError> {
    if scalars != CellScalars::Density && !hierarchy.has_light() {
        return Err(RefinementError::MissingLightField);
    }
    let (world_from_index, eye) = index_frame(hierarchy, view)?;
    // u_a − u_b of the eye per axis pair, the same values the
    // full-resolution batch compares.
    let differences = EyeSides::new(eye)
        .ok_or(RefinementError::NonFiniteEye { eye: view.eye })?
        .differences;
    if view.viewport_is_empty() {
        return Ok(Cells::default());
    }

    let morpher = Morpher::new(hierarchy, refinement)?;
    let mut cells = Vec::with_capacity(6 * refinement.leaves.len());
    let modulated = scalars != CellScalars::Density;
    let blended = hierarchy.has_next_keyframe();
    let reserve = |wanted: bool| Vec::with_capacity(if wanted { cells.capacity() } else { 0 });
    let mut modulators = reserve(modulated);
    let mut next_scalars = reserve(blended);
    let mut next_modulators = reserve(blended && modulated);
    let blends = refinement.blends.map(clamped_blend);
    // A morphed (density, light) as the cells' (scalar, modulator).
    let carried = |[density, light]: [f32; 2]| match scalars {
        CellScalars::Density => (density, 0.0),
        CellScalars::LightModulatedByDensity => (light, density),
        CellScalars::DensityModulatedByLight => (density, light),
    };
    for leaf in &refinement.leaves {
        pace();
        let node = leaf.node;
        let mut corner_modulators = [0.0f32; 8];
        let mut corner_next = [(0.0f32, 0.0f32); 8];
        let values = morpher.leaf_values(leaf)?;
        // A transparent leaf whose field stays inside its transparent range
        // at both ends shows nothing.
        if leaf.transparent == [true; 2] {
            let range = hierarchy.scalar_range_over(node, blends);
            if values.iter().all(|&[start, end]| {
                density_within(start, blends[0], range) && density_within(end, blends[1], range)
            }) {
                continue;
            }
        }
        let vertices: [[f32; 4]; 8] = std::array::from_fn(|v| {
            let p = node.corner(v);
            let position = world_from_index
                .transform_point3(DVec3::from(p.map(|c| c as f64)))
                .as_vec3();
            // A pair: the blended field at each end of the span; a single
            // keyframe: its field.
            let [start, end] = values[v];
            let (scalar, modulator) = if blended {
                let [density, light] = at_blend(start, blends[0]);
                corner_next[v] = carried(at_blend(end, blends[1]));
                carried([density, light])
            } else {
                carried([start.x, start.y])
            };
            corner_modulators[v] = modulator;
            [position.x, position.y, position.z, scalar]
        });
        let mut cell = |t: &[usize; 4]| {
            if modulated {
                modulators.push(t.map(|v| corner_modulators[v]));
            }
            if blended {
                next_scalars.push(t.map(|v| corner_next[v].0));
                if modulated {
                    next_modulators.push(t.map(|v| corner_next[v].1));
                }
            }
            GpuCell {
                vertices: t.map(|v| vertices[v]),
            }
        };
        let origin = node.origin.map(|o| o as f64);
        for t in kuhn_back_to_front(&differences, origin) {
            cells.push(cell(&KUHN_TETRAHEDRA[t]));
        }
    }
    let mut batch = Cells::with_bounds(cells);
    batch.modulators = modulators;
    batch.next_scalars = next_scalars;
    batch.next_modulators = next_modulators;
    if blended {
        batch.blends = blends;
    }
    Ok(batch)
}

/// A hasher for flat grid indices: one multiply and a fold, enough to spread
/// the regular index patterns of nodes and points over the table.
#[derive(Default)]
struct IndexHasher(u64);

impl Hasher for IndexHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_usize(usize::from(b));
        }
    }

    fn write_usize(&mut self, n: usize) {
        let x = (n as u64 ^ self.0.rotate_left(5)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        self.0 = x ^ (x >> 29);
    }
}

/// A map keyed by flat grid index.
type IndexMap<V> = HashMap<usize, V, BuildHasherDefault<IndexHasher>>;

/// The piecewise-linear field of `node` over Kuhn's six tetrahedra
/// ([`KUHN_TETRAHEDRA`]) with the values `corners` ([`Node::corner`] order)
/// at grid point `p` of its closed box: with the local coordinates sorted,
/// `u_a ≥ u_b ≥ u_c`, the weights of corners `0, a, a + b, 7` are `1 − u_a,
/// u_a − u_b, u_b − u_c, u_c`.
fn kuhn_field(node: Node, corners: &[Vec4; 8], p: [usize; 3]) -> Vec4 {
    let size = node.size() as f32;
    let u: [f32; 3] = std::array::from_fn(|a| (p[a] - node.origin[a]) as f32 / size);
    let mut axes = [0, 1, 2];
    axes.sort_by(|&i, &j| u[j].total_cmp(&u[i]));
    let [a, b, c] = axes;
    (1.0 - u[a]) * corners[0]
        + (u[a] - u[b]) * corners[1 << a]
        + (u[b] - u[c]) * corners[(1 << a) | (1 << b)]
        + u[c] * corners[7]
}

/// The (density, light) of a morphed value ([`Morphed`]) at keyframe
/// blend `beta`: `(1 − β) · first + β · next`.
fn at_blend(value: Vec4, beta: f32) -> [f32; 2] {
    [
        (1.0 - beta) * value.x + beta * value.z,
        (1.0 - beta) * value.y + beta * value.w,
    ]
}

/// Whether the blended density of `value` at `beta` lies in the scalar range
/// `range` (units of 1/255), give or take f32 rounding.
fn density_within(value: Vec4, beta: f32, range: [u8; 2]) -> bool {
    let [low, high] = range.map(|q| f32::from(q) / 255.0);
    let density = at_blend(value, beta)[0];
    density >= low - 1e-6 && density <= high + 1e-6
}

/// A point's morphed (density, light, next density, next light) at the
/// first and at the last blend of the refinement's span, with the morph
/// factors there ([`NodeMorph::morph`], [`NodeMorph::end_morph`]); a single
/// keyframe's are both at its `e'`.
type Morphed = [Vec4; 2];

/// Evaluates the morph rule of the module docs over the refinement's tree,
/// parents first, at both ends of its span at once. A refined node's
/// **lattice** is its 3 × 3 × 3 grid points half its edge apart (the
/// corners of its children): its eight corners are points of its parent's
/// lattice (a root's are its own values), and the other nineteen are born
/// at its level, so their coarse values average its corners. So every value
/// is read from a lattice made before it, with no lookup per point, and a
/// leaf's corners are its parent's lattice.
struct Morpher<'a> {
    /// The hierarchy read.
    hierarchy: &'a VolumeHierarchy,
    /// `e'` and transparency at both ends ([`NodeMorph`]) and lattice slot
    /// of every refined node, keyed by the flat index of its centre.
    refined: IndexMap<([f32; 2], [bool; 2], usize)>,
    /// Drawn leaves above level 0, by centre index, and their transparency
    /// at both ends.
    drawn: IndexMap<[bool; 2]>,
    /// The morphed values of each refined node's lattice, in the order of
    /// [`Refinement::refined`]: point `origin + (a, b, c) · size / 2` at
    /// `a + 3b + 9c`.
    lattices: Vec<[Morphed; 27]>,
    /// Whether each lattice is made yet.
    made: Vec<bool>,
    /// The refinement's blends at the span's two ends, clamped.
    blends: [f32; 2],
}

/// The index in a lattice of the point `(a, b, c)` half edges from the
/// node's origin.
fn lattice_index([a, b, c]: [usize; 3]) -> usize {
    a + 3 * b + 9 * c
}

/// A stored `e'` clamped to [0, 1], NaN as 0.
fn clamped_morph(e: f32) -> f32 {
    if e.is_nan() { 0.0 } else { e.clamp(0.0, 1.0) }
}

impl<'a> Morpher<'a> {
    /// The lattices of every refined node of `refinement`. Errors with
    /// [`RefinementError::MalformedRefinement`] for a refined voxel or a
    /// refined node below the roots' level whose parent is not refined
    /// before it.
    fn new(
        hierarchy: &'a VolumeHierarchy,
        refinement: &Refinement,
    ) -> Result<Self, RefinementError> {
        let mut refined = IndexMap::default();
        refined.reserve(refinement.refined.len());
        for (slot, node_morph) in refinement.refined.iter().enumerate() {
            let centre = node_morph
                .node
                .centre()
                .ok_or(RefinementError::MalformedRefinement {
                    node: node_morph.node,
                })?;
            let morphs = [node_morph.morph, node_morph.end_morph].map(clamped_morph);
            refined.insert(
                hierarchy.index(centre),
                (morphs, node_morph.transparent, slot),
            );
        }
        let drawn = refinement
            .leaves
            .iter()
            .filter_map(|leaf| Some((hierarchy.index(leaf.node.centre()?), leaf.transparent)))
            .collect();
        let mut morpher = Self {
            hierarchy,
            refined,
            drawn,
            lattices: vec![[[Vec4::ZERO; 2]; 27]; refinement.refined.len()],
            made: vec![false; refinement.refined.len()],
            blends: refinement.blends.map(clamped_blend),
        };
        // Coarse levels first (parents before children within each): a
        // point's sharers may lie under transparent nodes of any coarser
        // level, whose fields read their parents' lattices.
        let mut order: Vec<usize> = (0..refinement.refined.len()).collect();
        order.sort_by_key(|&slot| std::cmp::Reverse(refinement.refined[slot].node.level));
        for slot in order {
            let node = refinement.refined[slot].node;
            let corners = morpher.corner_values(node)?;
            let lattice = morpher.lattice(node, corners)?;
            morpher.lattices[slot] = lattice;
            morpher.made[slot] = true;
            pace();
        }
        Ok(morpher)
    }

    /// The morphed values of `node`'s corners ([`Node::corner`] order): a
    /// root's own, otherwise points of its parent's lattice. Errors with
    /// [`RefinementError::MalformedRefinement`] when the parent has no
    /// lattice yet (its parent is not refined).
    fn corner_values(&self, node: Node) -> Result<[Morphed; 8], RefinementError> {
        let h = self.hierarchy;
        if node.level >= h.root_level() {
            return Ok(std::array::from_fn(|v| [self.own(node.corner(v)); 2]));
        }
        let parent = node.parent();
        let lattice = parent
            .centre()
            .and_then(|centre| self.refined.get(&h.index(centre)))
            .filter(|&&(_, _, slot)| self.made[slot])
            .map(|&(_, _, slot)| &self.lattices[slot])
            .ok_or(RefinementError::MalformedRefinement { node })?;
        let offset: [usize; 3] =
            std::array::from_fn(|a| (node.origin[a] - parent.origin[a]) >> node.level);
        Ok(std::array::from_fn(|v| {
            lattice[lattice_index(std::array::from_fn(|a| offset[a] + ((v >> a) & 1)))]
        }))
    }

    /// The lattice of the refined `node` with the morphed values `corners`
    /// of its corners.
    fn lattice(&self, node: Node, corners: [Morphed; 8]) -> Result<[Morphed; 27], RefinementError> {
        let mut lattice = [[Vec4::ZERO; 2]; 27];
        for (v, &value) in corners.iter().enumerate() {
            lattice[lattice_index(std::array::from_fn(|a| 2 * ((v >> a) & 1)))] = value;
        }
        for (steps, ends) in BORN_POINTS {
            lattice[lattice_index(steps)] = self.born_value(node, &lattice, steps, ends)?;
        }
        Ok(lattice)
    }

    /// `e'` and transparency of `node` at both ends; `None` unless it is
    /// refined.
    fn morph_factors(&self, node: Node) -> Option<([f32; 2], [bool; 2])> {
        let centre = node.centre()?;
        self.refined
            .get(&self.hierarchy.index(centre))
            .map(|&(e, transparent, _)| (e, transparent))
    }

    /// The values the leaf draws at its corners at both ends: their morphed
    /// values, but at an end where the leaf is transparent, the
    /// piecewise-linear field of its largest transparent ancestor there (the
    /// leaf that a refinement for that blend alone draws).
    fn leaf_values(&self, leaf: &NodeMorph) -> Result<[Morphed; 8], RefinementError> {
        let node = leaf.node;
        let mut values = self.corner_values(node)?;
        for end in (0..2).filter(|&end| leaf.transparent[end]) {
            let ancestor = self.topmost_transparent(node, end);
            if ancestor == node {
                continue;
            }
            let corners = self.corner_values(ancestor)?.map(|value| value[end]);
            for (v, value) in values.iter_mut().enumerate() {
                value[end] = kuhn_field(ancestor, &corners, node.corner(v));
            }
        }
        Ok(values)
    }

    /// The largest node transparent at `end` that holds `node` (itself
    /// when its parent is not transparent there): the leaf a refinement for
    /// that blend alone draws over it.
    fn topmost_transparent(&self, mut node: Node, end: usize) -> Node {
        while node.level < self.hierarchy.root_level() {
            let parent = node.parent();
            match self.morph_factors(parent) {
                Some((_, transparent)) if transparent[end] => node = parent,
                _ => break,
            }
        }
        node
    }

    /// Whether the transparent `node` (the largest transparent one there,
    /// [`Morpher::topmost_transparent`]) shows anything at `end`: its field,
    /// the piecewise-linear one of its corners' morphed values, leaves its
    /// transparent range there somewhere (the morph carries coarser values
    /// into it). Only then does it constrain the points it shares.
    fn shows(&self, node: Node, end: usize) -> Result<bool, RefinementError> {
        let (beta, range) = (
            self.blends[end],
            self.hierarchy.scalar_range_at(node, self.blends[end]),
        );
        Ok(self
            .corner_values(node)?
            .iter()
            .any(|value| !density_within(value[end], beta, range)))
    }

    /// The leaf drawn over `node` when `node` is not refined: its highest
    /// ancestor (or itself) below a refined node or at the roots' level.
    fn leaf_above(&self, mut node: Node) -> Node {
        while node.level < self.hierarchy.root_level() {
            let parent = node.parent();
            if self.morph_factors(parent).is_some() {
                break;
            }
            node = parent;
        }
        node
    }

    /// The own (quantised) density and light of grid point `p`, then the
    /// next keyframe's; 0 for what the hierarchy lacks.
    fn own(&self, p: [usize; 3]) -> Vec4 {
        let h = self.hierarchy;
        Vec4::new(
            h.density(p),
            h.light(p).unwrap_or(0.0),
            h.next_density(p).unwrap_or(0.0),
            h.next_light(p).unwrap_or(0.0),
        )
    }

    /// The morphed value of the point `steps` half edges from the refined
    /// `node`'s origin, other than its corners (so born at `node`'s level),
    /// from the values in `lattice` of its corners `ends` at the ends of the
    /// Kuhn edge through it ([`BORN_POINTS`]; module docs).
    fn born_value(
        &self,
        node: Node,
        lattice: &[Morphed; 27],
        steps: [usize; 3],
        ends: [usize; 2],
    ) -> Result<Morphed, RefinementError> {
        let h = self.hierarchy;
        let (half, size) = (node.size() / 2, node.size());
        let p: [usize; 3] = std::array::from_fn(|a| node.origin[a] + half * steps[a]);
        let odd = steps.map(|s| s == 1);
        // The level-L nodes sharing p: per axis the one origin an odd
        // coordinate allows, or both sides of an even one that the grid has.
        let dims = h.dims();
        let candidates: [[Option<usize>; 2]; 3] = std::array::from_fn(|a| {
            if odd[a] {
                [Some(p[a] - half), None]
            } else {
                [
                    p[a].checked_sub(size),
                    (p[a] + size < dims[a]).then_some(p[a]),
                ]
            }
        });
        // Per end of the span: the smallest e' of the sharers.
        let mut w = [1.0f32; 2];
        for oz in candidates[2].iter().flatten() {
            for oy in candidates[1].iter().flatten() {
                for ox in candidates[0].iter().flatten() {
                    let sharer = Node {
                        level: node.level,
                        origin: [*ox, *oy, *oz],
                    };
                    // The sharer itself when refined, else the leaf drawn
                    // over it; one under a pruned (culled) node draws nothing
                    // and does not constrain p.
                    let (holder, morphs, transparent) = match self.morph_factors(sharer) {
                        Some((e, transparent)) => (sharer, e, transparent),
                        None => {
                            let leaf = self.leaf_above(sharer);
                            match leaf.centre().and_then(|c| self.drawn.get(&h.index(c))) {
                                Some(&transparent) => (leaf, [0.0; 2], transparent),
                                None => continue,
                            }
                        }
                    };
                    for end in 0..2 {
                        if !transparent[end] {
                            w[end] = w[end].min(morphs[end]);
                        } else if self.shows(self.topmost_transparent(holder, end), end)? {
                            // A transparent leaf that shows its coarser
                            // field is drawn: p takes that field.
                            w[end] = 0.0;
                        }
                    }
                }
            }
        }
        let own = self.own(p);
        // The ends p ∓ h·1_S of the Kuhn edge through p, corners of `node`.
        let [low, high] =
            ends.map(|v| lattice[lattice_index(std::array::from_fn(|a| 2 * ((v >> a) & 1)))]);
        Ok(std::array::from_fn(|end| {
            let w = w[end];
            if w >= 1.0 {
                return own;
            }
            let coarse = 0.5 * (low[end] + high[end]);
            (w * own + (1.0 - w) * coarse).clamp(Vec4::ZERO, Vec4::ONE)
        }))
    }
}

#[cfg(test)]
mod tests {
    use glam::{DAffine3, DQuat};
    use nebel_core::cell::{Hexahedron, Tetrahedron};
    use nebel_core::field::DensityGrid;
    use nebel_core::transfer::{TransferFunction, TransferPreset};
    use proptest::prelude::*;

    use super::*;
    use crate::full_resolution::{BrickTable, CellOrder, full_resolution_batch};
    use crate::octree::{HierarchyError, LodCriterion, NodeMorph, RefinementSettings, refine};

    /// ρ > 0 for every s > 0: nothing of a field in (0, 1] is culled.
    fn fog() -> TransferFunction {
        TransferFunction::preset(TransferPreset::GroundFog)
    }

    /// A rough field in [0.05, 0.95], spacing 1/2, origin off zero.
    fn field(dims: [usize; 3], seed: u64) -> DensityGrid {
        let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        let values = (0..dims.iter().product::<usize>())
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                0.05 + 0.9 * ((state >> 40) as f32 / (1u64 << 24) as f32)
            })
            .collect();
        DensityGrid::new(dims, DVec3::splat(0.5), DVec3::new(-2.0, 1.0, 0.5), values)
            .expect("valid grid")
    }

    fn hierarchy(dims: [usize; 3], seed: u64) -> VolumeHierarchy {
        VolumeHierarchy::new(&field(dims, seed), 2.0).expect("2^n+1 grid")
    }

    fn world_from_grid() -> DAffine3 {
        DAffine3::from_rotation_translation(
            DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.7, 0.2),
            DVec3::new(1.0, 2.0, -3.0),
        )
    }

    /// The view of a grid placed by `world_from_grid` from `eye` (world
    /// units), without culling, on a 640 × 480 viewport.
    fn view(world_from_grid: DAffine3, eye: DVec3) -> View {
        View::new(world_from_grid, eye, glam::UVec2::new(640, 480))
    }

    /// The eye in world space for a point in grid index coordinates.
    fn eye_at_index(h: &VolumeHierarchy, index: DVec3) -> DVec3 {
        world_from_grid().transform_point3(h.origin() + index * h.spacing())
    }

    fn refined(h: &VolumeHierarchy, eye: DVec3, accuracy: f64) -> Refinement {
        refine(
            h,
            &view(world_from_grid(), eye),
            &fog(),
            &RefinementSettings::new(LodCriterion::distance(accuracy)),
        )
        .unwrap()
    }

    /// `r` with its morph factors at the end of its span as its own (as a
    /// single keyframe's refinement reads them).
    fn at_end(r: &Refinement) -> Refinement {
        let mut end = r.clone();
        for node in end.refined.iter_mut().chain(&mut end.leaves) {
            node.morph = node.end_morph;
        }
        end
    }

    /// A refinement built by hand: below every root, each node is refined
    /// while `split(node)` says so, with `e' = morph(node)`; leaves in
    /// storage order (the order does not matter for the values).
    fn by_hand(
        h: &VolumeHierarchy,
        split: &mut impl FnMut(Node) -> bool,
        morph: &mut impl FnMut(Node) -> f32,
    ) -> Refinement {
        fn visit(
            node: Node,
            split: &mut impl FnMut(Node) -> bool,
            morph: &mut impl FnMut(Node) -> f32,
            r: &mut Refinement,
        ) {
            match node.children() {
                Some(children) if split(node) => {
                    let e = morph(node);
                    r.refined.push(NodeMorph {
                        node,
                        morph: e,
                        end_morph: e,
                        transparent: [false; 2],
                    });
                    for child in children {
                        visit(child, split, morph, r);
                    }
                }
                _ => r.leaves.push(NodeMorph {
                    node,
                    morph: 0.0,
                    end_morph: 0.0,
                    transparent: [false; 2],
                }),
            }
        }
        let mut r = Refinement::default();
        for root in h.roots() {
            visit(root, split, morph, &mut r);
        }
        r
    }

    /// A small xorshift generator for the hand-built refinements.
    fn rng(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed.wrapping_mul(0x2545_f491_4f6c_dd1d) | 1;
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// Bits of a cell, for exact comparisons and sorting.
    fn bits(cells: &[GpuCell]) -> Vec<[u32; 16]> {
        cells
            .iter()
            .map(|c| {
                let flat: Vec<u32> = c.vertices.iter().flatten().map(|v| v.to_bits()).collect();
                std::array::from_fn(|i| flat[i])
            })
            .collect()
    }

    /// Panics unless every vertex position has one scalar in every cell and
    /// every scalar is in [0, 1].
    fn assert_one_value_per_point(batch: &Cells) {
        let mut seen = HashMap::new();
        for vertex in batch.tetrahedra.iter().flat_map(|c| c.vertices) {
            let [x, y, z, s] = vertex;
            assert!((0.0..=1.0).contains(&s), "scalar {s} outside [0, 1]");
            let key = [x, y, z].map(f32::to_bits);
            let first = *seen.entry(key).or_insert(s.to_bits());
            assert_eq!(first, s.to_bits(), "two values at {:?}", [x, y, z]);
        }
    }

    /// Barycentric coordinates of `p` in `t`.
    fn barycentric(t: &Tetrahedron, p: DVec3) -> [f64; 4] {
        let [a, b, c, d] = t.positions;
        let volume =
            |p0: DVec3, p1: DVec3, p2: DVec3, p3: DVec3| (p1 - p0).dot((p2 - p0).cross(p3 - p0));
        let total = volume(a, b, c, d);
        [
            volume(p, b, c, d) / total,
            volume(a, p, c, d) / total,
            volume(a, b, p, d) / total,
            volume(a, b, c, p) / total,
        ]
    }

    /// The linear interpolation of `t`'s scalars at `p`, if `p` is in `t`.
    fn interpolate(t: &Tetrahedron, p: DVec3) -> Option<f64> {
        let w = barycentric(t, p);
        w.iter()
            .all(|&w| w > -1e-9)
            .then(|| (0..4).map(|v| w[v] * t.scalars[v]).sum())
    }

    #[test]
    fn infinite_accuracy_gives_the_full_resolution_cells_voxel_by_voxel() {
        let h = hierarchy([17, 17, 9], 3);
        let grid = h.quantised_grid();
        let bricks = BrickTable::new(&grid, 1);
        let eyes = [
            DVec3::new(-6.0, 30.0, 4.0),
            DVec3::new(8.3, 5.6, 3.1),
            DVec3::new(8.0, 8.0, 4.0),
            DVec3::new(4.0, 12.0, 2.0),
            DVec3::new(12.0, 4.0, 4.0),
            DVec3::new(40.0, -9.0, -20.0),
        ];
        for eye in eyes.map(|e| eye_at_index(&h, e)) {
            let r = refined(&h, eye, f64::INFINITY);
            assert!(r.leaves.iter().all(|l| l.node.level == 0));
            assert!(r.refined.iter().all(|n| n.morph == 1.0));
            let lod = lod_batch(&h, &r, &view(world_from_grid(), eye)).unwrap();
            let full = full_resolution_batch(
                &grid,
                &bricks,
                &view(world_from_grid(), eye),
                &fog(),
                CellOrder::BackToFront,
            )
            .unwrap();
            assert_eq!(lod.len(), 6 * 16 * 16 * 8);
            assert_eq!(
                (lod.bounds_min, lod.bounds_max),
                (full.bounds_min, full.bounds_max)
            );
            // The octree's nested order of the voxels differs from the
            // full-resolution batch's flat slab order (both back to front),
            // so compare voxel by voxel: each run of six cells with its
            // in-voxel order, as a multiset of voxels.
            let voxels = |b: &Cells| {
                let mut v: Vec<Vec<[u32; 16]>> = bits(&b.tetrahedra)
                    .chunks(6)
                    .map(<[[u32; 16]]>::to_vec)
                    .collect();
                v.sort();
                v
            };
            assert_eq!(voxels(&lod), voxels(&full));
        }
    }

    /// Panics unless the cells of `batch` inside `node`'s closed box (grid
    /// index coordinates: identity transform, origin 0, spacing 1) each lie
    /// in one of `node`'s six tetrahedra and carry `node`'s own
    /// piecewise-linear field (over its quantised corner densities) at every
    /// vertex and inside. Returns the cells checked.
    fn assert_reproduces(h: &VolumeHierarchy, batch: &Cells, node: Node) -> usize {
        let lo = DVec3::from(node.origin.map(|o| o as f64));
        let hi = lo + node.size() as f64;
        let coarse = Hexahedron::axis_aligned(
            lo,
            DVec3::splat(node.size() as f64),
            std::array::from_fn(|v| f64::from(h.density(node.corner(v)))),
        )
        .kuhn_tetrahedra();
        let mut checked = 0;
        for cell in &batch.tetrahedra {
            let t = cell.to_tetrahedron();
            if !t
                .positions
                .iter()
                .all(|p| p.cmpge(lo).all() && p.cmple(hi).all())
            {
                continue;
            }
            checked += 1;
            for (&p, &s) in t.positions.iter().zip(&t.scalars) {
                let value = coarse.iter().find_map(|c| interpolate(c, p)).unwrap();
                assert!((value - s).abs() < 1e-6, "{s} vs {value} at {p}");
            }
            // The decompositions of a node and its children nest: the fine
            // cell lies in one coarse cell, and the field agrees inside.
            assert!(
                coarse
                    .iter()
                    .any(|c| t.positions.iter().all(|&p| interpolate(c, p).is_some())),
                "{t:?} crosses the node's tetrahedra"
            );
            for weights in [[0.25; 4], [0.7, 0.1, 0.1, 0.1], [0.05, 0.15, 0.3, 0.5]] {
                let p: DVec3 = (0..4).map(|v| weights[v] * t.positions[v]).sum();
                let fine: f64 = (0..4).map(|v| weights[v] * t.scalars[v]).sum();
                let value = coarse.iter().find_map(|c| interpolate(c, p)).unwrap();
                assert!((fine - value).abs() < 1e-6, "{fine} vs {value} at {p}");
            }
        }
        checked
    }

    #[test]
    fn a_node_just_refined_shows_its_coarse_field() {
        let grid = field([9, 9, 9], 7);
        let grid =
            DensityGrid::new(grid.dims(), DVec3::ONE, DVec3::ZERO, grid.values().to_vec()).unwrap();
        let h = VolumeHierarchy::new(&grid, 2.0).unwrap();
        let root = h.roots().next().unwrap();
        let child = Node {
            level: 2,
            origin: [4, 0, 4],
        };
        // The root just refined (e' = 0), its children leaves.
        let r = by_hand(&h, &mut |n| n == root, &mut |_| 0.0);
        let batch = lod_batch(&h, &r, &view(DAffine3::IDENTITY, DVec3::splat(-5.0))).unwrap();
        assert_eq!(assert_reproduces(&h, &batch, root), 48);
        // The root fully morphed (e' = 1), one child just refined: the
        // child's region shows the child's field, whose corners are the
        // root's own values.
        let r = by_hand(&h, &mut |n| n == root || n == child, &mut |n| {
            if n == root { 1.0 } else { 0.0 }
        });
        let batch = lod_batch(
            &h,
            &r,
            &view(DAffine3::IDENTITY, DVec3::new(3.0, 7.0, 20.0)),
        )
        .unwrap();
        assert_eq!(assert_reproduces(&h, &batch, child), 48);
        // Morphing halfway moves the child's new points halfway to their own
        // values.
        let half = by_hand(&h, &mut |n| n == root || n == child, &mut |n| {
            if n == root { 1.0 } else { 0.5 }
        });
        let batch_half = lod_batch(&h, &half, &view(DAffine3::IDENTITY, DVec3::ZERO)).unwrap();
        let centre = [6.0f32, 2.0, 6.0];
        let at_centre = |b: &Cells| {
            b.tetrahedra
                .iter()
                .flat_map(|c| c.vertices)
                .find(|v| v[..3] == centre)
                .unwrap()[3]
        };
        let own = h.density([6, 2, 6]);
        let coarse = at_centre(&batch);
        assert!((at_centre(&batch_half) - 0.5 * (own + coarse)).abs() < 1e-6);
    }

    #[test]
    fn t_vertices_lie_on_the_coarser_neighbours_field() {
        // Random refinements with random e' and neighbours several levels
        // apart: every vertex that lies in another cell (on its face or
        // edge, not one of its vertices) has the value that cell
        // interpolates there.
        let h = hierarchy([17, 9, 9], 5);
        let identity = DAffine3::IDENTITY;
        for seed in 0..4 {
            let mut random = rng(seed);
            let mut split_random = rng(seed + 100);
            let r = by_hand(
                &h,
                &mut |n| n.level == 3 || split_random() < 0.45,
                &mut |_| random() as f32,
            );
            // Some leaves meet a face neighbour two or more levels apart.
            let boxes: Vec<(DVec3, DVec3, u32)> = r
                .leaves
                .iter()
                .map(|l| {
                    let lo = DVec3::from(l.node.origin.map(|o| o as f64));
                    (lo, lo + l.node.size() as f64, l.node.level)
                })
                .collect();
            let far_apart = boxes.iter().any(|a| {
                boxes.iter().any(|b| {
                    let overlap = (a.1.min(b.1) - a.0.max(b.0)).to_array();
                    a.2 >= b.2 + 2
                        && overlap.iter().filter(|&&o| o == 0.0).count() == 1
                        && overlap.iter().all(|&o| o >= 0.0)
                })
            });
            assert!(far_apart, "seed {seed}");
            let batch = lod_batch(&h, &r, &view(identity, DVec3::new(3.0, -2.0, 7.0))).unwrap();
            assert_one_value_per_point(&batch);
            let cells: Vec<Tetrahedron> = batch
                .tetrahedra
                .iter()
                .map(GpuCell::to_tetrahedron)
                .collect();
            let mut t_vertices = 0;
            for cell in &cells {
                for (&p, &s) in cell.positions.iter().zip(&cell.scalars) {
                    for other in &cells {
                        if other.positions.contains(&p) {
                            continue;
                        }
                        if let Some(value) = interpolate(other, p) {
                            assert!((value - s).abs() < 1e-5, "{value} vs {s} at {p}");
                            t_vertices += 1;
                        }
                    }
                }
            }
            assert!(t_vertices > 0, "seed {seed} has no T-vertex");
        }
    }

    #[test]
    fn bad_transform_and_eye_are_errors() {
        let h = hierarchy([5, 5, 5], 1);
        let r = refined(&h, DVec3::splat(10.0), 4.0);
        assert!(matches!(
            lod_batch(&h, &r, &view(DAffine3::ZERO, DVec3::ZERO)),
            Err(RefinementError::SingularTransform { .. })
        ));
        assert!(matches!(
            lod_batch(
                &h,
                &r,
                &view(world_from_grid(), DVec3::new(f64::NAN, 0.0, 0.0))
            ),
            Err(RefinementError::NonFiniteEye { .. })
        ));
        let empty = lod_batch(
            &h,
            &Refinement::default(),
            &view(world_from_grid(), DVec3::ZERO),
        )
        .unwrap();
        assert!(empty.is_empty());
        // An empty viewport is checked like any view, then sees nothing.
        let mut hidden = view(world_from_grid(), DVec3::splat(10.0));
        hidden.viewport.x = 0;
        assert!(lod_batch(&h, &r, &hidden).unwrap().is_empty());
        assert!(
            !lod_batch(&h, &r, &view(world_from_grid(), DVec3::splat(10.0)))
                .unwrap()
                .is_empty()
        );
        hidden.eye.z = f64::NAN;
        assert!(matches!(
            lod_batch(&h, &r, &hidden),
            Err(RefinementError::NonFiniteEye { .. })
        ));
    }

    /// A refinement that is not a tree as `refine` makes it is an error
    /// naming the node: a leaf below an unrefined parent, a refined voxel.
    /// The order of the refined nodes does not matter.
    #[test]
    fn a_malformed_refinement_is_an_error() {
        let h = hierarchy([9, 9, 9], 3);
        let v = view(world_from_grid(), DVec3::splat(30.0));
        let mut split = |node: Node| node.level >= 2;
        let r = by_hand(&h, &mut split, &mut |_| 0.5);
        assert!(lod_batch(&h, &r, &v).is_ok());
        let malformed = |r: &Refinement| match lod_batch(&h, r, &v) {
            Err(RefinementError::MalformedRefinement { node }) => Some(node),
            _ => None,
        };
        // The first refined node below the root lost: its children's
        // parent is missing.
        let mut orphans = r.clone();
        let lost = orphans.refined.remove(1).node;
        let orphan = malformed(&orphans).expect("an error");
        assert_eq!(orphan.level, lost.level - 1);
        // Children before their parent: the same batch.
        let mut reversed = r.clone();
        reversed.refined.reverse();
        assert_eq!(lod_batch(&h, &reversed, &v), lod_batch(&h, &r, &v));
        // A voxel refined.
        let mut refined_voxel = r.clone();
        let voxel = Node {
            level: 0,
            origin: [1, 2, 3],
        };
        refined_voxel.refined.push(NodeMorph {
            node: voxel,
            morph: 1.0,
            end_morph: 1.0,
            transparent: [false; 2],
        });
        assert_eq!(malformed(&refined_voxel), Some(voxel));
    }

    /// The field a batch draws at `blend` at `p` (world space), `None`
    /// where no cell covers `p`.
    fn field_at(batch: &Cells, blend: f32, p: DVec3) -> Option<f64> {
        let drawn = batch.blended(blend);
        drawn
            .tetrahedra
            .iter()
            .find_map(|cell| interpolate(&cell.to_tetrahedron(), p))
    }

    /// Refinements for consecutive spans of blends, and the last span of one
    /// pair against the first of the next, draw the same field where they
    /// meet, whatever each refines or culls: a node refined by one and not
    /// the other has `e' = 0` there and Kuhn's tetrahedra nest, a node
    /// transparent for one span is a leaf below a drawn parent (not cut out
    /// of the parent's coarse field), and one transparent at the shared blend
    /// has `e' = 0` there; under the screen error each refinement takes the
    /// occlusion at the span's ends from the nodes in front with their `e'`
    /// there. Random points over rough keyframes with holes that open and
    /// close between them, from eyes inside and outside, under both
    /// criteria.
    #[test]
    fn consecutive_spans_draw_the_same_field_where_they_meet() {
        let dims = [17, 9, 17];
        let cloud = TransferFunction::preset(TransferPreset::Cloud);
        let holed = |seed: u64, hole: [usize; 2]| {
            let grid = field(dims, seed);
            let values = grid.values().iter().enumerate();
            let values = values.map(|(n, &v)| {
                let i = n % dims[0];
                if (hole[0]..hole[1]).contains(&i) {
                    0.0
                } else {
                    v
                }
            });
            let grid = DensityGrid::new(dims, grid.spacing(), grid.origin(), values.collect());
            VolumeHierarchy::new(&grid.unwrap(), 2.0).unwrap()
        };
        let keyframes = [holed(3, [0, 6]), holed(4, [9, 17]), holed(5, [3, 12])];
        let pairs = [0, 1].map(|k| keyframes[k].with_next_keyframe(&keyframes[k + 1]).unwrap());
        let spans = 8;
        let span = 1.0 / spans as f32;
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut random = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut compared, mut changed) = (0, 0usize);
        for index in [DVec3::new(8.3, 4.1, 30.0), DVec3::new(6.2, 3.7, 5.1)] {
            for criterion in [
                LodCriterion::distance(2.0),
                LodCriterion::distance(8.0),
                LodCriterion::screen_error(0.02),
            ] {
                let eye = eye_at_index(&pairs[0], index);
                let centre = eye_at_index(&pairs[0], DVec3::new(8.0, 4.0, 8.0));
                let clip_from_world = glam::DMat4::perspective_infinite_reverse_rh(1.0, 1.5, 0.01)
                    * glam::DMat4::look_at_rh(eye, centre, DVec3::Y);
                // The screen error reads the projection; the distance
                // criterion would cull by its frustum what no pixel shows.
                let v = match criterion {
                    LodCriterion::ScreenError { .. } => {
                        View::new(world_from_grid(), eye, glam::UVec2::new(240, 160))
                            .with_projection(clip_from_world)
                    }
                    LodCriterion::Distance { .. } => view(world_from_grid(), eye),
                };
                let batch = |pair: &VolumeHierarchy, step: usize| {
                    let settings = RefinementSettings {
                        blend: step as f32 * span,
                        blend_span: span,
                        ..RefinementSettings::new(criterion)
                    };
                    let r = refine(pair, &v, &cloud, &settings).unwrap();
                    (lod_batch(pair, &r, &v).unwrap(), r.leaves.len())
                };
                // (earlier batch, later batch, the blend of each where they meet)
                let mut meetings = Vec::new();
                for step in 0..spans - 1 {
                    let (a, b) = (batch(&pairs[0], step), batch(&pairs[0], step + 1));
                    let beta = (step + 1) as f32 * span;
                    changed += usize::from(a.1 != b.1);
                    meetings.push((a.0, beta, b.0, beta));
                }
                let (last, first) = (batch(&pairs[0], spans - 1), batch(&pairs[1], 0));
                meetings.push((last.0, 1.0, first.0, 0.0));
                for (a, blend_a, b, blend_b) in &meetings {
                    for _ in 0..40 {
                        let local = DVec3::new(random(), random(), random())
                            * DVec3::from(dims.map(|n| (n - 1) as f64));
                        let p = world_from_grid()
                            .transform_point3(pairs[0].origin() + local * pairs[0].spacing());
                        let (x, y) = (field_at(a, *blend_a, p), field_at(b, *blend_b, p));
                        match (x, y) {
                            (Some(x), Some(y)) => {
                                compared += 1;
                                assert!((x - y).abs() < 1e-5, "{x} vs {y} at {local}, β {blend_a}");
                            }
                            // Where one batch draws nothing the other's field
                            // shows nothing either.
                            (Some(s), None) | (None, Some(s)) => {
                                assert!(cloud.is_transparent(s, s), "{s} at {local}, β {blend_a}");
                            }
                            (None, None) => {}
                        }
                    }
                }
            }
        }
        assert!(compared > 1000, "{compared}");
        assert!(changed > 4, "the refinements hardly changed: {changed}");
    }

    #[test]
    fn a_keyframe_pair_carries_both_keyframes_morphed_over_the_same_cells() {
        let dims = [17, 9, 9];
        let (density, light) = (field(dims, 5), field(dims, 6));
        let (next_density, next_light) = (field(dims, 7), field(dims, 8));
        let first = VolumeHierarchy::with_light(&density, &light, 2.0).unwrap();
        let second = VolumeHierarchy::with_light(&next_density, &next_light, 2.0).unwrap();
        let pair = first.with_next_keyframe(&second).unwrap();
        let eye = eye_at_index(&pair, DVec3::new(3.3, 4.1, 2.7));
        // Δ is the larger of both: the pair refined for the whole interval
        // refines at least as finely as either keyframe alone.
        let settings = RefinementSettings {
            blend_span: 1.0,
            ..RefinementSettings::new(LodCriterion::distance(8.0))
        };
        let r = refine(&pair, &view(world_from_grid(), eye), &fog(), &settings).unwrap();
        assert_eq!(r.blends, [0.0, 1.0]);
        for alone in [&first, &second] {
            assert!(r.leaves.len() >= refined(alone, eye, 8.0).leaves.len());
        }
        for scalars in [
            CellScalars::LightModulatedByDensity,
            CellScalars::DensityModulatedByLight,
        ] {
            let batch = |h: &VolumeHierarchy, r: &Refinement| {
                lod_batch_with(h, r, &view(world_from_grid(), eye), scalars).unwrap()
            };
            let (blended, current, next) = (
                batch(&pair, &r),
                batch(&first, &r),
                batch(&second, &at_end(&r)),
            );
            assert!(blended.is_blended() && !current.is_blended());
            assert_eq!(blended.blends, [0.0, 1.0]);
            // The first keyframe exactly as alone, the second's values beside
            // it: the morph of each keyframe over the pair's cells, with the
            // morph factors at either end.
            assert_eq!(blended.tetrahedra, current.tetrahedra);
            assert_eq!(blended.modulators, current.modulators);
            let next_scalars: Vec<[f32; 4]> = next
                .tetrahedra
                .iter()
                .map(|cell| cell.vertices.map(|v| v[3]))
                .collect();
            assert_eq!(blended.next_scalars, next_scalars);
            assert_eq!(blended.next_modulators, next.modulators);
        }
        // Unlit keyframes blend the density alone.
        let unlit = VolumeHierarchy::new(&density, 2.0)
            .unwrap()
            .with_next_keyframe(&VolumeHierarchy::new(&next_density, 2.0).unwrap())
            .unwrap();
        let r = refined(&unlit, eye, 8.0);
        let batch = lod_batch(&unlit, &r, &view(world_from_grid(), eye)).unwrap();
        assert_eq!(batch.next_scalars.len(), batch.len());
        assert!(batch.next_modulators.is_empty() && !batch.is_modulated());
    }

    /// The refinement follows the blend continuously, and at the hand-over
    /// the next pair starts exactly where the last one ends: the same cells
    /// with the same values.
    #[test]
    fn the_next_pair_starts_where_the_last_one_ends() {
        let dims = [17, 9, 9];
        // Ever rougher keyframes: the second pair refines more than the first.
        let keyframes: Vec<VolumeHierarchy> = [0.02f32, 0.2, 0.9]
            .iter()
            .enumerate()
            .map(|(k, &roughness)| {
                let noise = field(dims, 20 + k as u64);
                let values = noise.values().iter().map(|v| 0.5 + roughness * (v - 0.5));
                let grid =
                    DensityGrid::new(dims, noise.spacing(), noise.origin(), values.collect())
                        .unwrap();
                VolumeHierarchy::new(&grid, 2.0).unwrap()
            })
            .collect();
        let pairs = [0, 1].map(|k| keyframes[k].with_next_keyframe(&keyframes[k + 1]).unwrap());
        for index in [DVec3::new(3.3, 4.1, 2.7), DVec3::new(-9.0, 3.0, 12.0)] {
            let eye = eye_at_index(&pairs[0], index);
            let batch = |pair: &VolumeHierarchy, blend: f32| {
                let settings = RefinementSettings {
                    blend,
                    ..RefinementSettings::new(LodCriterion::distance(4.0))
                };
                let view = view(world_from_grid(), eye);
                let r = refine(pair, &view, &fog(), &settings).unwrap();
                lod_batch(pair, &r, &view).unwrap()
            };
            let ending = batch(&pairs[0], 1.0);
            let starting = batch(&pairs[1], 0.0);
            assert_eq!(ending.blended(1.0), starting.blended(0.0));
            // Refined for the blend: the cells change within a pair.
            let sizes = [0.0, 0.5, 1.0].map(|blend| batch(&pairs[1], blend).len());
            assert!(sizes[0] < sizes[1] && sizes[1] < sizes[2], "{sizes:?}");
        }
    }

    #[test]
    fn a_lit_batch_morphs_both_fields_with_one_rule() {
        let dims = [17, 9, 9];
        let density = field(dims, 5);
        let light = field(dims, 6);
        let lit = VolumeHierarchy::with_light(&density, &light, 2.0).unwrap();
        let unlit = VolumeHierarchy::new(&density, 2.0).unwrap();
        let eye = eye_at_index(&lit, DVec3::new(3.3, 4.1, 2.7));
        // Δ covers the light too: the lit refinement is at least as fine.
        let r = refined(&lit, eye, 8.0);
        assert!(r.leaves.len() >= refined(&unlit, eye, 8.0).leaves.len());
        assert!((lit.bytes_per_point() - 5.0).abs() < 1e-12);

        let plain = lod_batch_with(
            &unlit,
            &r,
            &view(world_from_grid(), eye),
            CellScalars::Density,
        )
        .unwrap();
        assert!(!plain.is_modulated());
        let by_density = lod_batch_with(
            &lit,
            &r,
            &view(world_from_grid(), eye),
            CellScalars::LightModulatedByDensity,
        )
        .unwrap();
        let by_light = lod_batch_with(
            &lit,
            &r,
            &view(world_from_grid(), eye),
            CellScalars::DensityModulatedByLight,
        )
        .unwrap();
        assert_eq!(by_density.modulators.len(), by_density.len());
        // The density morphs exactly as in the unlit batch, whichever role it
        // plays; the light morphs as the density would if it were the field.
        let light_only = VolumeHierarchy::new(&light, 2.0).unwrap();
        let light_plain = lod_batch(&light_only, &r, &view(world_from_grid(), eye)).unwrap();
        for i in 0..plain.len() {
            for v in 0..4 {
                assert_eq!(
                    by_light.tetrahedra[i].vertices[v],
                    plain.tetrahedra[i].vertices[v]
                );
                assert_eq!(
                    by_density.modulators[i][v],
                    plain.tetrahedra[i].vertices[v][3]
                );
                assert_eq!(
                    by_light.modulators[i][v],
                    light_plain.tetrahedra[i].vertices[v][3]
                );
                assert_eq!(
                    by_density.tetrahedra[i].vertices[v],
                    light_plain.tetrahedra[i].vertices[v]
                );
            }
        }
        assert_one_value_per_point(&by_density);

        assert_eq!(
            lod_batch_with(
                &unlit,
                &r,
                &view(world_from_grid(), eye),
                CellScalars::LightModulatedByDensity
            ),
            Err(RefinementError::MissingLightField)
        );
        assert_eq!(
            VolumeHierarchy::with_light(&density, &field([9, 9, 9], 1), 2.0),
            Err(HierarchyError::LightDimsMismatch {
                density: dims,
                light: [9, 9, 9]
            })
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        #[test]
        fn random_eyes_and_accuracies_conform_stay_in_range_and_fill_the_box(
            seed in 0u64..1000,
            eye in (-8.0f64..40.0, -8.0f64..24.0, -4.0f64..14.0),
            accuracy in prop::sample::select(vec![0.0, 1.0, 4.0, 16.0, 64.0, 1e3]),
        ) {
            let h = hierarchy([33, 17, 9], seed);
            let eye = eye_at_index(&h, DVec3::new(eye.0, eye.1, eye.2));
            let r = refined(&h, eye, accuracy);
            let batch = lod_batch(&h, &r, &view(world_from_grid(), eye)).unwrap();
            prop_assert_eq!(batch.len(), 6 * r.leaves.len());
            assert_one_value_per_point(&batch);
            let volume: f64 = batch.tetrahedra.iter().map(|c| c.to_tetrahedron().volume()).sum();
            let box_volume = 32.0 * 16.0 * 8.0 * 0.5f64.powi(3);
            prop_assert!((volume - box_volume).abs() < 1e-4 * box_volume, "{} vs {}", volume, box_volume);
        }
    }
}
