//! One volume's cell batch, frame after frame, rebuilt only when it changes.
//!
//! A [`VolumeBatcher`] owns a volume's source, what is built from it once
//! ([`VolumeBatcher::new`]; `Send + Sync`, so it can be built on a worker) and
//! its current [`Cells`]. A renderer calls [`VolumeBatcher::update`] every
//! frame with the [`View`] and [`FrameInputs`] and uploads the batch when it
//! changed. It picks one of the crate's builders:
//!
//! - a grid at full resolution, by default whole ([`GridDrawing::RayCast`],
//!   [`Cells::from_grid`]): the renderer ray casts its tetrahedra, so only a
//!   new placement or transfer function builds it again, with its bricks'
//!   zero-opacity test ([`CellGrid::with_occupancy`]; none visible leaves
//!   the batch empty); a lit grid carries its [`light_field`]
//!   ([`CellGrid::with_modulators`]);
//! - a grid at full resolution as projected cells
//!   ([`GridDrawing::ProjectedCells`]): [`full_resolution_batch`] over a [`BrickTable`]
//!   (Röttger 2004 §8.1); back to front it is rebuilt when its [`order_key`] or
//!   the frustum changes, unordered not for the camera at all;
//! - a grid through the octree C-LOD ([`BatchSettings::octree`]): zero-padded
//!   to `2^n + 1` points per axis ([`PadFill::Value`]), with a lit cloud's
//!   [`light_field`] (Röttger and Ertl 2003 §5), then
//!   [`refine`](fn@crate::octree::refine) and [`lod_batch_with`], back to
//!   front, rebuilt when the criterion changes or the view left what the
//!   batch serves ([`crate::octree::refresh`]). Lighting needs the octree or
//!   ray casting ([`VolumeBatchError::LightingWithoutOctree`]);
//! - a cell mesh: back to front by MPVO ([`CellAdjacency`], [`sorted_batch`],
//!   Williams 1992), rebuilt when the eye moves, or unordered.
//!
//! Every kind is also rebuilt on the first update, when `world_from_local`,
//! the transfer function ([`TransferFunction::content_hash`]) or the
//! viewport's emptiness changes. A failed update keeps the previous batch.
//!
//! # Example
//!
//! ```
//! use std::sync::Arc;
//!
//! use glam::{DAffine3, DVec3, UVec2};
//! use nebel_core::field::DensityGrid;
//! use nebel_core::transfer::{TransferFunction, TransferPreset};
//! use nebel_lod::octree::LodCriterion;
//! use nebel_lod::{BatchSettings, FrameInputs, OctreeSettings, View, VolumeBatcher, VolumeSource};
//!
//! // 6 × 5 × 7 points: padded to 9 × 5 × 9 for the octree.
//! let grid = DensityGrid::new([6, 5, 7], DVec3::ONE, DVec3::ZERO, vec![0.5; 6 * 5 * 7])?;
//! let settings = BatchSettings { octree: Some(OctreeSettings::default()), ..Default::default() };
//! let mut batcher = VolumeBatcher::new(VolumeSource::Grid(Arc::new(grid)), &settings)?;
//! let transfer = TransferFunction::preset(TransferPreset::Cloud);
//! let criterion = LodCriterion::distance(16.0);
//! let inputs = FrameInputs { transfer: &transfer, criterion, blend: 0.0, blend_span: 0.0 };
//! let view = View::new(DAffine3::IDENTITY, DVec3::new(3.0, 2.0, -20.0), UVec2::new(1280, 720));
//! assert!(batcher.update(&view, &inputs)?); // the first frame builds
//! assert!(!batcher.update(&view, &inputs)?); // the same view keeps it
//! assert!(!batcher.batch().is_empty());
//! assert_eq!(batcher.full_resolution_cells(), 6 * 5 * 4 * 6);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::sync::Arc;

use glam::DAffine3;

use nebel_core::budget::{BudgetError, Dims, check_allocation};
use nebel_core::cell::Tetrahedron;
use nebel_core::field::{
    CloudLighting, DensityGrid, FieldError, PadFill, light_field, power_of_two_plus_one,
};
use nebel_core::pacing::drop_paced;
use nebel_core::transfer::TransferFunction;
use thiserror::Error;

use crate::batch::{Cells, GpuCell};
use crate::cell_grid::CellGrid;
use crate::frustum::Frustum;
use crate::full_resolution::{BatchError, BrickTable, CellOrder, full_resolution_batch, order_key};
use crate::octree::refresh::Latency;
use crate::octree::{
    CellScalars, HierarchyError, LodCriterion, RefinementError, RefinementSettings,
    VolumeHierarchy, k_max, lod_batch_with, refine, refresh,
};
use crate::view::View;
use crate::visibility::{CellAdjacency, sorted_batch};

/// Where a volume's scalar comes from, in the volume's local frame (the frame
/// [`View::world_from_local`] places).
#[derive(Clone, Debug)]
pub enum VolumeSource {
    /// A density grid: point `(i, j, k)` at `origin + (i, j, k) · spacing`,
    /// six tetrahedra per voxel (Kuhn's, [`crate::full_resolution`]).
    Grid(Arc<DensityGrid>),
    /// Tetrahedra, a conforming mesh for back-to-front order (see
    /// [`crate::visibility`]).
    Cells(Arc<Vec<Tetrahedron>>),
}

/// How a volume is batched: the settings whose change needs a new
/// [`VolumeBatcher`] (the per-frame ones are [`FrameInputs`]). The default
/// draws at full resolution, back to front, unlit.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BatchSettings {
    /// Back to front (the sorted emission-absorption model) or unordered (the
    /// emissive and MIP modes). The octree is always back to front. Default
    /// [`CellOrder::BackToFront`].
    pub order: CellOrder,
    /// Draw a grid through the octree C-LOD; `None` (the default) draws it at
    /// full resolution. Only for [`VolumeSource::Grid`].
    pub octree: Option<OctreeSettings>,
    /// Light the cloud (Röttger and Ertl 2003 §5); needs `octree` or
    /// [`GridDrawing::RayCast`]. Default `None`.
    pub lighting: Option<BatchLighting>,
    /// How a grid at full resolution is drawn. Default
    /// [`GridDrawing::RayCast`].
    pub drawing: GridDrawing,
}

/// How a grid at full resolution (without the octree) is drawn; both are
/// exact for the grid's tetrahedra.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum GridDrawing {
    /// The whole grid, ray cast front to back through its tetrahedra
    /// ([`crate::cell_grid`]): no batch to rebuild when the eye moves, and
    /// a pixel stops once it is opaque. The default.
    #[default]
    RayCast,
    /// Its tetrahedra emitted in visibility order and projected
    /// ([`crate::full_resolution`]), as Röttger 2004 §8 draws them.
    ProjectedCells,
}

/// The view-independent settings of the octree C-LOD.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OctreeSettings {
    /// The minimum accuracy `C` of Röttger and Ertl 2003 Eq. 1, finite and > √3: how many
    /// node sizes away a node must be before it may stay coarse; it also sets
    /// the deviation propagation `K_max = C / (2C − √3/2)` the hierarchy is
    /// built with. Default [`OctreeSettings::DEFAULT_MIN_ACCURACY`].
    pub min_accuracy: f64,
}

impl OctreeSettings {
    /// The default minimum accuracy `C`, 4 (`K_max ≈ 0.56`).
    pub const DEFAULT_MIN_ACCURACY: f64 = 4.0;
}

impl Default for OctreeSettings {
    fn default() -> Self {
        Self {
            min_accuracy: Self::DEFAULT_MIN_ACCURACY,
        }
    }
}

/// A lit cloud: its light field and which field the cells carry as scalar and
/// which as segment-length modulator (Röttger and Ertl 2003 §5).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BatchLighting {
    /// The light field's settings ([`light_field`]), sun direction in the
    /// volume's local frame.
    pub light: CloudLighting,
    /// [`CellScalars::LightModulatedByDensity`] (§5.1) or
    /// [`CellScalars::DensityModulatedByLight`] (§5.2);
    /// [`CellScalars::Density`] would not draw the light and is refused.
    pub scalars: CellScalars,
}

/// What a volume's batch reads per frame besides the view.
#[derive(Clone, Copy, Debug)]
pub struct FrameInputs<'a> {
    /// The volume's transfer function: the zero-opacity test's (except for
    /// [`CellScalars::LightModulatedByDensity`], whose opacity is the
    /// density itself, so only density 0 is empty).
    pub transfer: &'a TransferFunction,
    /// The octree's error metric and tolerance
    /// ([`RefinementSettings::criterion`]); ignored without the octree. The
    /// screen-error criterion needs the view's projection
    /// ([`View::with_projection`]).
    pub criterion: LodCriterion,
    /// For a batcher of two keyframes ([`VolumeBatcher::with_next_keyframe`]),
    /// the blend toward the second that the octree is refined for
    /// ([`RefinementSettings::blend`]); a new value rebuilds the batch.
    /// Ignored otherwise.
    pub blend: f32,
    /// How far the blend may advance past [`FrameInputs::blend`] while the
    /// batch is drawn ([`RefinementSettings::blend_span`]); a new value
    /// rebuilds the batch. Ignored without two keyframes.
    pub blend_span: f32,
}

/// Why a [`VolumeBatcher`] could not be built or updated.
#[derive(Clone, Debug, Error)]
pub enum VolumeBatchError {
    /// Padding the grid or computing its light field failed (shared, since a
    /// [`FieldError`] cannot be cloned). Two are equal when their messages
    /// are.
    #[error(transparent)]
    Field(Arc<FieldError>),
    /// The octree's hierarchy could not be built.
    #[error(transparent)]
    Hierarchy(#[from] HierarchyError),
    /// The octree could not be refined or emitted for the view and inputs.
    #[error(transparent)]
    Refinement(#[from] RefinementError),
    /// A full-resolution or cell-mesh batch could not be built for the view.
    #[error(transparent)]
    Batch(#[from] BatchError),
    /// [`BatchSettings::lighting`] with projected cells at full resolution
    /// ([`GridDrawing::ProjectedCells`] without [`BatchSettings::octree`]).
    #[error(
        "lighting needs the octree (BatchSettings::octree) or a ray-cast grid (GridDrawing::RayCast): projected cells at full resolution carry no light field"
    )]
    LightingWithoutOctree,
    /// [`BatchSettings::octree`] with a cell mesh.
    #[error("the octree needs a density grid (VolumeSource::Grid), not a cell mesh")]
    OctreeWithoutGrid,
    /// The full-resolution batch of the grid would exceed the memory budget
    /// (`nebel_core::budget`); draw it through the octree instead.
    #[error("{0}; draw the grid through the octree (BatchSettings::octree)")]
    OverBudget(#[from] BudgetError),
    /// [`BatchLighting::scalars`] is [`CellScalars::Density`].
    #[error(
        "lighting needs cell scalars that carry the light (CellScalars::LightModulatedByDensity or CellScalars::DensityModulatedByLight), not CellScalars::Density"
    )]
    UnlitScalars,
    /// [`VolumeBatcher::with_next_keyframe`] of batchers that do not both
    /// draw a grid through the octree, or both ray cast one, with the same
    /// cell scalars.
    #[error(
        "keyframes blend only grids drawn alike (both through the octree or both ray cast: BatchSettings::octree, BatchSettings::drawing) with the same cell scalars (BatchLighting::scalars)"
    )]
    MismatchedKeyframes,
}

impl From<FieldError> for VolumeBatchError {
    fn from(error: FieldError) -> Self {
        Self::Field(Arc::new(error))
    }
}

impl PartialEq for VolumeBatchError {
    fn eq(&self, other: &Self) -> bool {
        match (self, other) {
            (Self::Field(a), Self::Field(b)) => Arc::ptr_eq(a, b) || a.to_string() == b.to_string(),
            (Self::Hierarchy(a), Self::Hierarchy(b)) => a == b,
            (Self::Refinement(a), Self::Refinement(b)) => a == b,
            (Self::Batch(a), Self::Batch(b)) => a == b,
            (Self::OverBudget(a), Self::OverBudget(b)) => a == b,
            (Self::LightingWithoutOctree, Self::LightingWithoutOctree)
            | (Self::OctreeWithoutGrid, Self::OctreeWithoutGrid)
            | (Self::UnlitScalars, Self::UnlitScalars)
            | (Self::MismatchedKeyframes, Self::MismatchedKeyframes) => true,
            _ => false,
        }
    }
}

/// What was built once, per kind (module docs).
#[derive(Debug)]
enum Kind {
    /// A grid at full resolution, ray cast whole.
    RayCastGrid {
        /// The grid and a lit grid's light field.
        fields: RayCastFields,
        /// Which field is the scalar ([`CellScalars::Density`] unlit).
        scalars: CellScalars,
        /// The density's brick ranges, for the zero-opacity test, spanning
        /// both keyframes of a pair.
        bricks: BrickTable,
        /// A pair's next keyframe.
        next: Option<RayCastFields>,
    },
    /// A grid at full resolution, as projected cells.
    FullResolution {
        /// The grid.
        grid: Arc<DensityGrid>,
        /// Its bricks' scalar ranges.
        bricks: BrickTable,
        /// Back to front (culled) or unordered (not culled).
        order: CellOrder,
    },
    /// A grid through the octree; the grid itself is not kept.
    Octree {
        /// The padded grid's hierarchy, with the light field when lit
        /// (shared with a [`RefinementStep`] in flight).
        hierarchy: Arc<VolumeHierarchy>,
        /// The cells' scalar and modulator.
        scalars: CellScalars,
    },
    /// A cell mesh in back-to-front order.
    SortedCells {
        /// The cells, local frame.
        cells: Arc<Vec<Tetrahedron>>,
        /// Their shared faces.
        adjacency: CellAdjacency,
    },
    /// A cell mesh drawn as given.
    UnorderedCells {
        /// The cells, local frame.
        cells: Arc<Vec<Tetrahedron>>,
    },
}

/// A ray-cast grid's fields at one keyframe.
#[derive(Clone, Debug)]
struct RayCastFields {
    /// The density.
    density: Arc<DensityGrid>,
    /// A lit grid's light field.
    light: Option<Arc<DensityGrid>>,
}

impl RayCastFields {
    /// The fields placed by `world_from_local`: the scalar, and a lit grid's
    /// modulator, as `scalars` picks them.
    fn placed(
        &self,
        scalars: CellScalars,
        world_from_local: DAffine3,
    ) -> Result<CellGrid, BatchError> {
        match (&self.light, scalars) {
            (Some(light), CellScalars::LightModulatedByDensity) => {
                CellGrid::new(light.clone(), world_from_local)?
                    .with_modulators(self.density.clone())
            }
            (Some(light), _) => CellGrid::new(self.density.clone(), world_from_local)?
                .with_modulators(light.clone()),
            (None, _) => CellGrid::new(self.density.clone(), world_from_local),
        }
    }
}

/// What the current batch was built from.
#[derive(Debug)]
struct BuiltFor {
    /// The view.
    view: View,
    /// [`TransferFunction::content_hash`] of the transfer function.
    transfer: u64,
    /// The octree's criterion.
    criterion: LodCriterion,
    /// The keyframe blend and span the octree was refined for.
    blends: Blends,
    /// The view's [`order_key`] for a grid at full resolution back to front,
    /// `None` for the other kinds.
    order_key: Option<[i64; 6]>,
    /// The frustum the octree culled with ([`refresh::culling`]); `None`
    /// for the other kinds, which cull with the view's own.
    culling: Option<Frustum>,
}

/// A volume's per-frame batching (module docs): built once per source and
/// settings, updated every frame.
#[derive(Debug)]
pub struct VolumeBatcher {
    /// What was built once.
    kind: Kind,
    /// The settings it was built with.
    settings: BatchSettings,
    /// Cells of the source at full resolution.
    full_resolution_cells: usize,
    /// The current batch.
    batch: Arc<Cells>,
    /// What `batch` was built from; `None` before the first successful
    /// update.
    built: Option<BuiltFor>,
}

impl VolumeBatcher {
    /// Does the view-independent work for `source` drawn with `settings`
    /// (module docs: padding, light field and hierarchy for the octree, the
    /// brick table of a grid at full resolution, the adjacency of a sorted
    /// cell mesh). A grid that already has `2^n + 1` points per axis, as a
    /// cloud's, goes into the octree as it is, not copied; others are padded
    /// at their high ends with density 0, empty under any transfer function
    /// with `ρ(0) = 0`. The batch is empty until the first
    /// [`VolumeBatcher::update`].
    ///
    /// Errors: [`VolumeBatchError::LightingWithoutOctree`],
    /// [`VolumeBatchError::OctreeWithoutGrid`] and
    /// [`VolumeBatchError::UnlitScalars`] for contradictory settings,
    /// [`VolumeBatchError::Hierarchy`] for a minimum accuracy `C` that is not
    /// finite and > √3 (checked before any heavy work),
    /// [`VolumeBatchError::Field`] for invalid light-field settings.
    pub fn new(source: VolumeSource, settings: &BatchSettings) -> Result<Self, VolumeBatchError> {
        if let Some(lighting) = settings.lighting {
            if settings.octree.is_none() && settings.drawing == GridDrawing::ProjectedCells {
                return Err(VolumeBatchError::LightingWithoutOctree);
            }
            if lighting.scalars == CellScalars::Density {
                return Err(VolumeBatchError::UnlitScalars);
            }
        }
        let full_resolution_cells = match &source {
            VolumeSource::Grid(grid) => 6 * grid.dims().map(|n| n - 1).iter().product::<usize>(),
            VolumeSource::Cells(cells) => cells.len(),
        };
        let kind = match (source, settings.octree) {
            (VolumeSource::Grid(grid), None) if settings.drawing == GridDrawing::RayCast => {
                let light = match settings.lighting {
                    Some(lighting) => Some(Arc::new(light_field(&grid, &lighting.light)?)),
                    None => None,
                };
                Kind::RayCastGrid {
                    bricks: BrickTable::new(&grid, BrickTable::DEFAULT_BRICK_SIZE),
                    fields: RayCastFields {
                        density: grid,
                        light,
                    },
                    scalars: settings
                        .lighting
                        .map_or(CellScalars::Density, |lighting| lighting.scalars),
                    next: None,
                }
            }
            (VolumeSource::Grid(grid), None) => {
                // The batch of a grid whose every brick is kept.
                let voxels = grid.dims().map(|n| n - 1);
                check_allocation(
                    || format!("full-resolution batch of {} voxels", Dims(&voxels)),
                    &[voxels[0], voxels[1], voxels[2], 5],
                    size_of::<GpuCell>() as u64,
                )?;
                Kind::FullResolution {
                    bricks: BrickTable::new(&grid, BrickTable::DEFAULT_BRICK_SIZE),
                    grid,
                    order: settings.order,
                }
            }
            (VolumeSource::Grid(grid), Some(octree)) => {
                k_max(octree.min_accuracy)?;
                // A grid of 2^n+1 points per axis (a cloud's keyframe) is
                // used as it is, another padded with zero density. The fields
                // are freed as soon as they are used, each a unit of a paced
                // build of its own.
                let padded = if grid.dims() == grid.dims().map(power_of_two_plus_one) {
                    grid
                } else {
                    let padded = grid.padded_to_power_of_two_plus_one(PadFill::Value(0.0))?;
                    drop_paced(grid);
                    Arc::new(padded)
                };
                let octree_kind = match settings.lighting {
                    Some(lighting) => {
                        let light = light_field(&padded, &lighting.light)?;
                        let hierarchy =
                            VolumeHierarchy::with_light(&padded, &light, octree.min_accuracy)?;
                        drop_paced(light);
                        Kind::Octree {
                            hierarchy: Arc::new(hierarchy),
                            scalars: lighting.scalars,
                        }
                    }
                    None => Kind::Octree {
                        hierarchy: Arc::new(VolumeHierarchy::new(&padded, octree.min_accuracy)?),
                        scalars: CellScalars::Density,
                    },
                };
                drop_paced(padded);
                octree_kind
            }
            (VolumeSource::Cells(_), Some(_)) => return Err(VolumeBatchError::OctreeWithoutGrid),
            (VolumeSource::Cells(cells), None) => match settings.order {
                CellOrder::BackToFront => Kind::SortedCells {
                    adjacency: CellAdjacency::new(&cells),
                    cells,
                },
                CellOrder::Unordered => Kind::UnorderedCells { cells },
            },
        };
        Ok(Self {
            kind,
            settings: *settings,
            full_resolution_cells,
            batch: Arc::default(),
            built: None,
        })
    }

    /// Brings the batch up to date for `view` and `inputs`: rebuilds it when
    /// they differ from the last successful build in something the batch
    /// depends on (module docs), and returns whether it did, i.e. whether
    /// [`VolumeBatcher::batch`] is to be uploaded again.
    ///
    /// An unordered grid or cell mesh ignores the eye and the frustum, and
    /// only the octree reads the criterion. The transfer function's content
    /// is compared for every kind, also those whose cells do not read it, so
    /// a rebuild always pairs the batch with the current inputs. While the
    /// viewport stays empty nothing is rebuilt; its size is read only by the
    /// screen error.
    ///
    /// Errors (the batch and what it was built from then stay as they were):
    /// - [`VolumeBatchError::Batch`] for a grid at full resolution or a cell
    ///   mesh: [`BatchError::SingularTransform`] unless `world_from_local` is
    ///   finite and invertible, [`BatchError::NonFiniteEye`] for a
    ///   back-to-front batch and a NaN or infinite eye;
    /// - [`VolumeBatchError::Refinement`] for the octree: the same two, and
    ///   [`RefinementError::InvalidAccuracy`] for an accuracy `c` that is NaN
    ///   or negative, [`RefinementError::InvalidImageError`] for a tolerance
    ///   that is not finite and positive, [`RefinementError::MissingProjection`]
    ///   for the screen error without the view's projection.
    pub fn update(&mut self, view: &View, inputs: &FrameInputs) -> Result<bool, VolumeBatchError> {
        let transfer = inputs.transfer.content_hash();
        let order_key = self.order_key(view);
        if let Some(built) = &self.built
            && !self.needs_rebuild(built, view, inputs, transfer, order_key)
        {
            return Ok(false);
        }
        let culling = match &self.kind {
            Kind::Octree { hierarchy, .. } => refresh::culling(hierarchy, view, Latency::default()),
            _ => None,
        };
        self.batch = Arc::new(self.build(view, culling.as_ref(), inputs)?);
        self.built = Some(BuiltFor {
            view: view.clone(),
            transfer,
            criterion: inputs.criterion,
            blends: Blends::of(inputs),
            order_key,
            culling,
        });
        Ok(true)
    }

    /// A batcher that blends from this batcher's keyframe to `next`'s (the
    /// octree of both with [`VolumeHierarchy::with_next_keyframe`], or a
    /// ray-cast grid with both keyframes' fields,
    /// [`CellGrid::with_next_keyframe`]; its batches carry `next`'s values
    /// too, `Cells`'s keyframe blending). Built from `self`'s settings;
    /// `next` may differ only in its light's settings (a keyframe of a
    /// moving sun). The batch is empty until the first
    /// [`VolumeBatcher::update`].
    ///
    /// Errors: [`VolumeBatchError::MismatchedKeyframes`] unless both draw a
    /// grid through the octree, or both ray cast one, with the same cell
    /// scalars, [`VolumeBatchError::Hierarchy`] when the octrees' grids or
    /// minimum accuracies differ, [`VolumeBatchError::Batch`] when the
    /// ray-cast grids differ in size.
    pub fn with_next_keyframe(&self, next: &VolumeBatcher) -> Result<Self, VolumeBatchError> {
        let kind = match (&self.kind, &next.kind) {
            (
                Kind::Octree { hierarchy, scalars },
                Kind::Octree {
                    hierarchy: next_hierarchy,
                    scalars: next_scalars,
                },
            ) if scalars == next_scalars => Kind::Octree {
                hierarchy: Arc::new(hierarchy.with_next_keyframe(next_hierarchy)?),
                scalars: *scalars,
            },
            (
                Kind::RayCastGrid {
                    fields,
                    scalars,
                    bricks,
                    next: None,
                },
                Kind::RayCastGrid {
                    fields: next_fields,
                    scalars: next_scalars,
                    bricks: next_bricks,
                    next: None,
                },
            ) if scalars == next_scalars => Kind::RayCastGrid {
                fields: fields.clone(),
                scalars: *scalars,
                bricks: bricks.spanning(next_bricks)?,
                next: Some(next_fields.clone()),
            },
            _ => return Err(VolumeBatchError::MismatchedKeyframes),
        };
        Ok(Self {
            kind,
            settings: self.settings,
            full_resolution_cells: self.full_resolution_cells,
            batch: Arc::default(),
            built: None,
        })
    }

    /// The rebuild [`VolumeBatcher::update`] would make for `view` and
    /// `inputs`, detached, for a grid through the octree: a refinement a
    /// caller may run on another thread ([`RefinementStep::build`]) and hand
    /// back with [`VolumeBatcher::adopt`] while the current batch is drawn
    /// (the camera moved, a keyframe blend advanced, the criterion or the
    /// transfer function changed). `None` when `update` would not rebuild,
    /// and for the other kinds, whose rebuilds are not detached.
    pub fn refinement_step(&self, view: &View, inputs: &FrameInputs) -> Option<RefinementStep> {
        let Kind::Octree { hierarchy, scalars } = &self.kind else {
            return None;
        };
        let rebuild = self.built.as_ref().is_none_or(|built| {
            self.needs_rebuild(built, view, inputs, inputs.transfer.content_hash(), None)
        });
        rebuild.then(|| RefinementStep::new(hierarchy, *scalars, view, inputs))
    }

    /// Whether the batch was last built or adopted for `inputs` (the same
    /// transfer function, criterion and blends) and a view that serves
    /// `view` (module docs): then an update or a refinement step for them
    /// would change nothing.
    pub fn is_built_for(&self, view: &View, inputs: &FrameInputs) -> bool {
        self.built.as_ref().is_some_and(|built| {
            built.blends == Blends::of(inputs)
                && built.criterion == inputs.criterion
                && !self.needs_rebuild(
                    built,
                    view,
                    inputs,
                    inputs.transfer.content_hash(),
                    self.order_key(view),
                )
        })
    }

    /// The first build of a batcher of two keyframes, detached as
    /// [`VolumeBatcher::refinement_step`]: the next pair's batch made ahead for the
    /// current view, adopted before it is drawn. `None` once built or for
    /// other batchers.
    pub fn first_build(&self, view: &View, inputs: &FrameInputs) -> Option<RefinementStep> {
        let Kind::Octree { hierarchy, scalars } = &self.kind else {
            return None;
        };
        (self.built.is_none() && hierarchy.has_next_keyframe())
            .then(|| RefinementStep::new(hierarchy, *scalars, view, inputs))
    }

    /// Takes the batch of a finished [`RefinementStep`] of this batcher's octree
    /// (one of another batcher is ignored) as the current batch, as
    /// [`VolumeBatcher::update`] would have built it; returns whether it did.
    /// A failed step is its error, and changes nothing.
    pub fn adopt(&mut self, built: BuiltRefinementStep) -> Result<bool, VolumeBatchError> {
        let Kind::Octree { hierarchy, .. } = &self.kind else {
            return Ok(false);
        };
        if !Arc::ptr_eq(hierarchy, &built.step.hierarchy) {
            return Ok(false);
        }
        let step = built.step;
        self.batch = Arc::new(built.batch?);
        self.built = Some(BuiltFor {
            view: step.view,
            transfer: step.transfer.content_hash(),
            criterion: step.criterion,
            blends: step.blends,
            order_key: None,
            culling: built.culling,
        });
        Ok(true)
    }

    /// Whether the batcher has a batch: built by [`VolumeBatcher::update`]
    /// or adopted from a detached build ([`VolumeBatcher::adopt`]), for some
    /// view.
    pub fn is_built(&self) -> bool {
        self.built.is_some()
    }

    /// The current batch: world space, in draw order, modulated for a lit
    /// cloud. Empty before the first successful [`VolumeBatcher::update`].
    /// Shared: a renderer keeps it without copying the cells, and a rebuild
    /// makes a new one.
    pub fn batch(&self) -> &Arc<Cells> {
        &self.batch
    }

    /// The source's cells at full resolution (six per voxel of the grid as
    /// given, before any padding; the mesh's cell count), for counters that
    /// compare the drawn cells with them.
    pub fn full_resolution_cells(&self) -> usize {
        self.full_resolution_cells
    }

    /// The settings the batcher was built with; a caller whose settings
    /// differ builds a new batcher.
    pub fn settings(&self) -> &BatchSettings {
        &self.settings
    }

    /// What the batch's cells carry: [`BatchLighting::scalars`] for a lit
    /// cloud, [`CellScalars::Density`] otherwise (the cells' scalar is then
    /// the source's, and the batch has no modulators).
    pub fn scalars(&self) -> CellScalars {
        match self.kind {
            Kind::Octree { scalars, .. } | Kind::RayCastGrid { scalars, .. } => scalars,
            _ => CellScalars::Density,
        }
    }

    /// Whether the batch depends on the eye or the frustum (back-to-front
    /// batches and the octree), so a moving camera may rebuild it; an
    /// unordered grid or cell mesh is only rebuilt for a new transform, a new
    /// transfer function or a viewport that became empty or non-empty.
    pub fn is_view_dependent(&self) -> bool {
        match self.kind {
            Kind::FullResolution { order, .. } => order == CellOrder::BackToFront,
            Kind::Octree { .. } | Kind::SortedCells { .. } => true,
            Kind::RayCastGrid { .. } | Kind::UnorderedCells { .. } => false,
        }
    }

    /// The [`order_key`] of `view` for a grid at full resolution back to
    /// front, `None` for the other kinds.
    fn order_key(&self, view: &View) -> Option<[i64; 6]> {
        match &self.kind {
            Kind::FullResolution {
                grid,
                order: CellOrder::BackToFront,
                ..
            } => order_key(grid, view),
            _ => None,
        }
    }

    /// Whether a batch built for `built` may differ from one for `view` and
    /// `inputs` (with the transfer function's content hash `transfer` and, for
    /// a sorted full-resolution grid, the view's `order_key`).
    fn needs_rebuild(
        &self,
        built: &BuiltFor,
        view: &View,
        inputs: &FrameInputs,
        transfer: u64,
        order_key: Option<[i64; 6]>,
    ) -> bool {
        let (was_empty, is_empty) = (built.view.viewport_is_empty(), view.viewport_is_empty());
        if was_empty && is_empty {
            return false;
        }
        if was_empty != is_empty
            || built.view.world_from_local != view.world_from_local
            || built.transfer != transfer
        {
            return true;
        }
        let eye_moved = built.view.eye != view.eye;
        let frustum_changed = built.view.frustum != view.frustum;
        match self.kind {
            Kind::FullResolution { order, .. } => match order {
                CellOrder::BackToFront => built.order_key != order_key || frustum_changed,
                CellOrder::Unordered => false,
            },
            Kind::Octree { ref hierarchy, .. } => {
                let blended = hierarchy.has_next_keyframe();
                built.criterion != inputs.criterion
                    || (blended && built.blends != Blends::of(inputs))
                    || !refresh::serves(
                        hierarchy,
                        &built.view,
                        built.culling.as_ref(),
                        view,
                        inputs.criterion,
                    )
            }
            Kind::SortedCells { .. } => eye_moved,
            Kind::RayCastGrid { .. } | Kind::UnorderedCells { .. } => false,
        }
    }

    /// The batch for `view` and `inputs`, built from scratch; the octree
    /// culls with `culling`, the other kinds with the view's frustum.
    fn build(
        &self,
        view: &View,
        culling: Option<&Frustum>,
        inputs: &FrameInputs,
    ) -> Result<Cells, VolumeBatchError> {
        let batch = match &self.kind {
            Kind::RayCastGrid {
                fields,
                scalars,
                bricks,
                next,
            } => {
                let mut grid = fields.placed(*scalars, view.world_from_local)?;
                if let Some(next) = next {
                    grid =
                        grid.with_next_keyframe(&next.placed(*scalars, view.world_from_local)?)?;
                }
                // The bricks are the density's: the scalar's, or the
                // modulator's where the density modulates the light.
                let grid = if *scalars == CellScalars::LightModulatedByDensity {
                    grid.with_modulator_occupancy(bricks)?
                } else {
                    grid.with_occupancy(bricks, inputs.transfer)?
                };
                if view.viewport_is_empty() || !grid.occupied().contains(&1) {
                    Cells::default()
                } else {
                    Cells::from_grid(grid)
                }
            }
            Kind::FullResolution {
                grid,
                bricks,
                order,
            } => match order {
                CellOrder::BackToFront => {
                    full_resolution_batch(grid, bricks, view, inputs.transfer, *order)?
                }
                CellOrder::Unordered => {
                    let unculled = View::new(view.world_from_local, view.eye, view.viewport);
                    full_resolution_batch(grid, bricks, &unculled, inputs.transfer, *order)?
                }
            },
            Kind::Octree { hierarchy, scalars } => {
                let settings = Blends::of(inputs).refinement(inputs.criterion, *scalars);
                let view = &View {
                    frustum: culling.cloned(),
                    ..view.clone()
                };
                let refinement = refine(hierarchy, view, inputs.transfer, &settings)?;
                lod_batch_with(hierarchy, &refinement, view, *scalars)?
            }
            Kind::SortedCells { cells, adjacency } => sorted_batch(cells, adjacency, view)?,
            Kind::UnorderedCells { cells } => unordered_batch(cells, view)?,
        };
        Ok(batch)
    }
}

/// The keyframe blend and span of [`FrameInputs`] a batch is refined for;
/// equal when bit for bit equal, so any new value rebuilds.
#[derive(Clone, Copy, Debug)]
struct Blends {
    /// [`FrameInputs::blend`].
    blend: f32,
    /// [`FrameInputs::blend_span`].
    span: f32,
}

impl Blends {
    fn of(inputs: &FrameInputs) -> Self {
        Self {
            blend: inputs.blend,
            span: inputs.blend_span,
        }
    }

    /// The refinement's settings for these blends.
    fn refinement(self, criterion: LodCriterion, scalars: CellScalars) -> RefinementSettings {
        RefinementSettings {
            criterion,
            scalars,
            blend: self.blend,
            blend_span: self.span,
        }
    }
}

impl PartialEq for Blends {
    fn eq(&self, other: &Self) -> bool {
        self.blend.to_bits() == other.blend.to_bits() && self.span.to_bits() == other.span.to_bits()
    }
}

/// An octree's refinement for a new view or new inputs, detached from its
/// batcher ([`VolumeBatcher::refinement_step`]).
#[derive(Debug)]
pub struct RefinementStep {
    hierarchy: Arc<VolumeHierarchy>,
    scalars: CellScalars,
    view: View,
    transfer: TransferFunction,
    criterion: LodCriterion,
    blends: Blends,
    latency: Latency,
}

impl RefinementStep {
    fn new(
        hierarchy: &Arc<VolumeHierarchy>,
        scalars: CellScalars,
        view: &View,
        inputs: &FrameInputs,
    ) -> Self {
        Self {
            hierarchy: hierarchy.clone(),
            scalars,
            view: view.clone(),
            transfer: inputs.transfer.clone(),
            criterion: inputs.criterion,
            blends: Blends::of(inputs),
            latency: Latency::default(),
        }
    }

    /// The step culling wider by `latency`, for a batch drawn that much
    /// later than its view ([`refresh::culling`]).
    pub fn with_latency(self, latency: Latency) -> Self {
        Self { latency, ..self }
    }

    /// Refines and emits the batch, as [`VolumeBatcher::update`] would.
    pub fn build(self) -> BuiltRefinementStep {
        let settings = self.blends.refinement(self.criterion, self.scalars);
        let culling = refresh::culling(&self.hierarchy, &self.view, self.latency);
        let view = View {
            frustum: culling.clone(),
            ..self.view.clone()
        };
        let batch = refine(&self.hierarchy, &view, &self.transfer, &settings)
            .and_then(|refinement| {
                lod_batch_with(&self.hierarchy, &refinement, &view, self.scalars)
            })
            .map_err(VolumeBatchError::from);
        BuiltRefinementStep {
            step: self,
            culling,
            batch,
        }
    }
}

/// A built [`RefinementStep`], for [`VolumeBatcher::adopt`].
#[derive(Debug)]
pub struct BuiltRefinementStep {
    step: RefinementStep,
    /// The frustum it culled with.
    culling: Option<Frustum>,
    batch: Result<Cells, VolumeBatchError>,
}

impl BuiltRefinementStep {
    /// Whether the step was made for `inputs` (the transfer function, the
    /// criterion and the blends), from any view: one the camera moved away
    /// from while it was made is still the newest batch for them.
    pub fn is_for_inputs(&self, inputs: &FrameInputs) -> bool {
        let step = &self.step;
        step.transfer.content_hash() == inputs.transfer.content_hash()
            && step.criterion == inputs.criterion
            && step.blends == Blends::of(inputs)
    }

    /// Whether the step was made for `inputs` and a view that serves `view`
    /// ([`crate::octree::refresh`]; a step made ahead for the next blend is
    /// adopted once the drawn blend reaches it).
    pub fn is_for(&self, view: &View, inputs: &FrameInputs) -> bool {
        let step = &self.step;
        let culling = self.culling.as_ref();
        self.is_for_inputs(inputs)
            && refresh::serves(&step.hierarchy, &step.view, culling, view, step.criterion)
    }

    /// How far `view` is from the view the step was made for.
    pub fn latency_to(&self, view: &View) -> Latency {
        Latency::between(&self.step.hierarchy, &self.step.view, view)
    }
}

/// `cells` (local frame) moved to world space by the view's
/// `world_from_local`, in their order ([`Cells::from_tetrahedra`]); empty
/// for an empty viewport. Errors: [`BatchError::SingularTransform`] unless
/// `world_from_local` is finite and invertible.
fn unordered_batch(cells: &[Tetrahedron], view: &View) -> Result<Cells, BatchError> {
    if view.local_from_world().is_none() {
        return Err(BatchError::SingularTransform {
            determinant: view.world_from_local.matrix3.determinant(),
        });
    }
    if view.viewport_is_empty() {
        return Ok(Cells::default());
    }
    let world: Vec<Tetrahedron> = cells.iter().map(|t| view.to_world(t)).collect();
    Ok(Cells::from_tetrahedra(&world))
}
