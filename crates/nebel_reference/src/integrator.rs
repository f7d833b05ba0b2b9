//! The exact CPU reference renderer.
//!
//! For every pixel it integrates the optical model of Röttger 2004 ch. 6-8
//! (emission-absorption, eq. 8.1; emission only, §10.3; maximum intensity)
//! along the ray through the pixel centre, in f64, against an optional opaque
//! depth. Two volume sources separate two errors of the real-time renderer:
//!
//! - [`ReferenceVolume::Cells`]: a tetrahedral mesh with a scalar per vertex.
//!   Every cell the ray crosses gives an exact segment ([`Tetrahedron::intersect`]:
//!   entry, exit and barycentric scalars), whose integral is
//!   [`exact_segment`]; segments are composited in exact front-to-back order of
//!   their entry distance (the cells of a conforming mesh do not overlap). This
//!   reference has no discretisation error at all, so the difference to a GPU
//!   image of the same cells is the error of projection and pre-integration.
//! - [`ReferenceVolume::Grid`]: a trilinear [`DensityGrid`] directly. The ray
//!   walks the grid cells in order (a 3D DDA: all cell-plane crossings sorted
//!   along the ray). Inside a cell the trilinear scalar along the ray is a cubic
//!   in the distance; it is cut into equal pieces on which the cubic deviates
//!   from its chord by at most [`ReferenceScene::scalar_tolerance`] (the
//!   bound `h² / 8 · max |s''|`, rigorous since `s''` is linear), and each piece
//!   is integrated exactly as a linear segment. The difference to a GPU image
//!   is then the total error, LOD included.
//!
//! # Camera and depth conventions
//!
//! The camera follows Bevy: it looks along its local −Z with +Y up and +X
//! right; rays start at the eye and pass through pixel centres, row 0 at the
//! top. The near plane and the opaque depth are **view-space depths**
//! (distance along the camera's forward axis, as a linearised depth buffer
//! holds), not distances along the ray; a ray with direction `d` converts depth
//! `z` to distance `t = z / (d · forward)`.
//!
//! # Output
//!
//! A [`LinearImage`] of premultiplied linear RGBA: the volume composited over
//! [`ReferenceScene::background`] with the mode's operator
//! ([`OpticalMode::composite`]). To put the volume over an opaque scene image,
//! keep the background transparent and composite `C + (1 − α) · scene`.
//! Rows are shared among all cores with `std::thread::scope`.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU32, Ordering};

use glam::{DMat3, DQuat, DVec3, DVec4};

use crate::fog::ReferenceFog;
use crate::image_metrics::LinearImage;
use nebel_core::budget::BudgetError;
use nebel_core::cell::{CellSegment, PreparedTetrahedron, Ray, Tetrahedron};
use nebel_core::field::DensityGrid;
use nebel_core::fog_sunlight::FogSunlight;
use nebel_core::joint_segment::{JointMedium, exact_joint_segment};
use nebel_core::local_light::{LightResponse, LocalLight};
use nebel_core::occluder::{Occluder, hides_sun, sun_lit_spans};
use nebel_core::optics::{MODULATOR_PIECES, OpticalMode, PremultipliedRgba, henyey_greenstein};
use nebel_core::segment::{exact_segment, rho_hat};
use nebel_core::transfer::TransferFunction;

/// Default [`ReferenceScene::scalar_tolerance`]: the largest deviation, in
/// scalar units, of the piecewise-linear scalar from the trilinear one.
pub const DEFAULT_SCALAR_TOLERANCE: f64 = 1e-5;

/// Most pieces one grid cell is cut into along a ray, whatever the tolerance.
const MAX_PIECES_PER_CELL: f64 = 4096.0;

/// Transmittance below which a sorted ray stops (what lies behind would change
/// the pixel by less than this times the brightest κ).
const MIN_TRANSMITTANCE: f64 = 1e-12;

/// Intervals of Gauss-Legendre quadrature in the angle per stretch of a ray
/// lit by a local light ([`LocalLight::scattered`]).
pub(crate) const LIGHT_INTERVALS: u32 = 32;

/// Side of the square pixel tiles that cells are binned into.
const TILE_SIZE: u32 = 8;

/// A perspective pinhole camera (Bevy conventions, see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReferenceCamera {
    /// Eye position, world units. Default origin.
    pub position: DVec3,
    /// Orientation; the camera looks along `rotation * −Z` with `rotation * +Y`
    /// up. Default identity (looking along −Z).
    pub rotation: DQuat,
    /// Vertical field of view, radians, in (0, π). Default π/4 (Bevy's).
    pub vertical_fov: f64,
    /// Image width, pixels, ≥ 1. Default 256.
    pub width: u32,
    /// Image height, pixels, ≥ 1. Default 256.
    pub height: u32,
    /// View-space depth of the near plane, world units, > 0. Default 0.1 (Bevy's).
    pub near: f64,
}

impl Default for ReferenceCamera {
    fn default() -> Self {
        Self {
            position: DVec3::ZERO,
            rotation: DQuat::IDENTITY,
            vertical_fov: std::f64::consts::FRAC_PI_4,
            width: 256,
            height: 256,
            near: 0.1,
        }
    }
}

impl ReferenceCamera {
    /// Turns the camera to look at `target` with `up` as close to its up
    /// direction as possible (like Bevy's `Transform::looking_at`). When `up` is
    /// parallel to the view direction another perpendicular up is chosen; when
    /// `target` equals the position the rotation is kept.
    pub fn looking_at(mut self, target: DVec3, up: DVec3) -> Self {
        let Some(back) = (self.position - target).try_normalize() else {
            return self;
        };
        let right = up
            .cross(back)
            .try_normalize()
            .unwrap_or_else(|| back.any_orthonormal_vector());
        let up = back.cross(right);
        self.rotation = DQuat::from_mat3(&DMat3::from_cols(right, up, back));
        self
    }

    /// Unit view direction, `rotation * −Z`.
    pub fn forward(&self) -> DVec3 {
        self.rotation * DVec3::NEG_Z
    }

    /// The ray through the centre of pixel `(x, y)` (row 0 at the top) and the
    /// factor `d · forward` that converts view-space depth to ray distance
    /// (`t = depth / factor`).
    pub fn pixel_ray(&self, x: u32, y: u32) -> (Ray, f64) {
        let tan_half = (0.5 * self.vertical_fov).tan();
        let aspect = f64::from(self.width) / f64::from(self.height);
        let ndc_x = 2.0 * (f64::from(x) + 0.5) / f64::from(self.width) - 1.0;
        let ndc_y = 1.0 - 2.0 * (f64::from(y) + 0.5) / f64::from(self.height);
        let view = DVec3::new(ndc_x * tan_half * aspect, ndc_y * tan_half, -1.0);
        let length = view.length();
        let ray = Ray {
            origin: self.position,
            direction: self.rotation * (view / length),
        };
        (ray, 1.0 / length)
    }

    /// Pixel coordinates (fractional, pixel centres at `i + 0.5`) and view-space
    /// depth of a world point.
    fn project(&self, point: DVec3) -> (f64, f64, f64) {
        let view = self.rotation.inverse() * (point - self.position);
        let depth = -view.z;
        let tan_half = (0.5 * self.vertical_fov).tan();
        let aspect = f64::from(self.width) / f64::from(self.height);
        let ndc_x = view.x / (depth * tan_half * aspect);
        let ndc_y = view.y / (depth * tan_half);
        (
            0.5 * (ndc_x + 1.0) * f64::from(self.width),
            0.5 * (1.0 - ndc_y) * f64::from(self.height),
            depth,
        )
    }

    fn validate(&self) -> Result<(), ReferenceError> {
        let invalid = |field: &'static str, value: String, requirement: &'static str| {
            Err(ReferenceError::InvalidCamera {
                field,
                value,
                requirement,
            })
        };
        if !self.position.is_finite() {
            return invalid("position", format!("{}", self.position), "finite");
        }
        if !(self.rotation.is_finite() && (self.rotation.length() - 1.0).abs() < 1e-6) {
            return invalid(
                "rotation",
                format!("{}", self.rotation),
                "a finite unit quaternion",
            );
        }
        if !(self.vertical_fov > 0.0 && self.vertical_fov < std::f64::consts::PI) {
            return invalid(
                "vertical_fov",
                self.vertical_fov.to_string(),
                "in (0, π) radians",
            );
        }
        if self.width == 0 || self.height == 0 {
            return invalid(
                "width × height",
                format!("{}×{}", self.width, self.height),
                "at least 1×1",
            );
        }
        if !(self.near.is_finite() && self.near > 0.0) {
            return invalid("near", self.near.to_string(), "finite and positive");
        }
        Ok(())
    }
}

/// The volume a reference image integrates through.
#[derive(Clone, Debug, PartialEq)]
pub enum ReferenceVolume {
    /// A tetrahedral mesh, scalar per vertex; the cells must not overlap
    /// (degenerate cells are allowed and contribute nothing).
    Cells(Vec<Tetrahedron>),
    /// A density grid, trilinear inside its box.
    Grid(DensityGrid),
}

/// A second field that scales the length of every ray segment before its
/// integral: `l' = l · m̄`, `m̄` the mean of the modulator `m` over the piece
/// (Röttger and Ertl 2003 §5.1 Eq. 9, `l' = l · f / f_max`, the lit-cloud model of
/// `nebel_lod::Cells`). Cells: each segment in
/// [`nebel_core::optics::MODULATOR_PIECES`] equal pieces, each with the mean
/// of the linear modulator over it, exactly what the GPU computes. Grid: the trilinear modulator is
/// integrated along with the scalar, piece by piece (the pieces are refined
/// to the same tolerance for both fields), so the image converges to the
/// continuous model `∫ κ(s) ρ(s) m e^{−∫ ρ(s) m}` (the modulator's pieces
/// are refined to 100 × [`ReferenceScene::scalar_tolerance`]).
#[derive(Clone, Debug, PartialEq)]
pub enum Modulation {
    /// For [`ReferenceVolume::Cells`]: per cell, the modulator at its four
    /// vertices, one entry per cell.
    Cells(Vec<[f64; 4]>),
    /// For [`ReferenceVolume::Grid`]: a grid with the volume grid's points
    /// (its own spacing and origin are ignored).
    Grid(DensityGrid),
}

/// Everything the reference renderer needs for one image.
#[derive(Clone, Debug, PartialEq)]
pub struct ReferenceScene {
    /// The view.
    pub camera: ReferenceCamera,
    /// What the rays integrate through.
    pub volume: ReferenceVolume,
    /// κ and ρ over the scalar.
    pub transfer_function: TransferFunction,
    /// How segments combine.
    pub mode: OpticalMode,
    /// Optional segment-length modulator (lit clouds). Default `None`.
    pub modulation: Option<Modulation>,
    /// Optional opaque depth: view-space depth per pixel (world units, ≥ 0,
    /// `+∞` where nothing is opaque), `width · height` values, row-major, top row
    /// first. Rays stop there. Default `None`.
    pub opaque_depth: Option<Vec<f32>>,
    /// Premultiplied linear RGBA behind the volume. Default transparent black.
    pub background: PremultipliedRgba,
    /// Grid volumes only: the largest deviation, in scalar units, of the
    /// piecewise-linear scalar integrated from the trilinear scalar along the
    /// ray, > 0. Default [`DEFAULT_SCALAR_TOLERANCE`].
    pub scalar_tolerance: f64,
    /// Sorted volumes only: single scattering of the sun, applied to every
    /// segment. Default `None` (the segments' colours as integrated).
    pub scattering: Option<SegmentScattering>,
    /// Fog layers the volume is seen through: every segment is conjugated by
    /// the fog in front of it (see [`ReferenceFog`]). The image is then the
    /// volume alone, to go over the fogged background
    /// ([`ReferenceFog::over`]); [`ReferenceScene::background`] is
    /// composited as it is. Default `None`.
    pub fog: Option<ReferenceFog>,
    /// Sorted volumes only: point and spot lights whose light the medium
    /// scatters toward the eye, `∫ ρ s κ T E 4π p_HG dt` along every segment
    /// ([`nebel_core::local_light`]; κ read as white for a volume with
    /// [`ReferenceScene::scattering`], whose colour is its light toward the
    /// sun), converged by [`LocalLight::scattered`]. Default none.
    pub local_lights: Vec<LocalLight>,
    /// How the medium scatters them: the phase's asymmetry and the factor
    /// `s` on κ ([`LightResponse::checked`]). Default: isotropic, 1.
    pub light_response: LightResponse,
    /// Opaque shapes that shade the local lights that cast shadows
    /// ([`LocalLight::scattered_past`]). Default none.
    pub occluders: Vec<Occluder>,
    /// Sorted volumes only: the sun lighting a ground fog, `c ⊙ 4π p_HG ∫ ρ
    /// κ T V T_sun dt` along every segment, cut where the rays cross the
    /// terrain's shadow ([`FogSunlight::scattered`]). Default `None`.
    pub sunlight: Option<FogSunlight>,
}

/// Single scattering of the sun (Nes 2008) for a volume integrated over the
/// transmittance toward the sun: each segment's premultiplied colour `C` and
/// opacity `α` become `ambient · α + sunlight · 4π p_HG(θ) · C` (`ambient` the
/// sky's light per channel), θ between the
/// ray and the direction toward the sun, as the GPU's `SCATTERING` variant
/// computes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegmentScattering {
    /// The ambient (sky) light's weight per channel: its strength times the
    /// sky's colour.
    pub ambient: DVec3,
    /// The sunlight's weight.
    pub sunlight: f64,
    /// Unit direction toward the sun.
    pub sun_direction: DVec3,
    /// The Henyey-Greenstein asymmetry `g`.
    pub asymmetry: f64,
    /// The sun casts shadows: [`ReferenceScene::occluders`] hide it from the
    /// medium behind them (Bevy's shadow map of it), which there scatters
    /// the sky's light only.
    pub shadows: bool,
}

impl ReferenceScene {
    /// A scene with no opaque depth, a transparent background and the default
    /// tolerance.
    pub fn new(
        camera: ReferenceCamera,
        volume: ReferenceVolume,
        transfer_function: TransferFunction,
        mode: OpticalMode,
    ) -> Self {
        Self {
            camera,
            volume,
            transfer_function,
            mode,
            modulation: None,
            opaque_depth: None,
            background: DVec4::ZERO,
            scalar_tolerance: DEFAULT_SCALAR_TOLERANCE,
            scattering: None,
            fog: None,
            local_lights: Vec::new(),
            light_response: LightResponse::default(),
            occluders: Vec::new(),
            sunlight: None,
        }
    }

    fn validate(&self) -> Result<(), ReferenceError> {
        self.camera.validate()?;
        if let ReferenceVolume::Cells(cells) = &self.volume {
            let finite = |tet: &Tetrahedron| {
                tet.positions.iter().all(|p| p.is_finite())
                    && tet.scalars.iter().all(|s| s.is_finite())
            };
            if let Some(index) = cells.iter().position(|tet| !finite(tet)) {
                return Err(ReferenceError::NonFiniteCell { index });
            }
        }
        match (&self.volume, &self.modulation) {
            (_, None) => {}
            (ReferenceVolume::Cells(cells), Some(Modulation::Cells(modulators))) => {
                if modulators.len() != cells.len() {
                    return Err(ReferenceError::ModulationMismatch {
                        reason: format!(
                            "{} modulators for {} cells",
                            modulators.len(),
                            cells.len()
                        ),
                    });
                }
                if let Some(index) = modulators
                    .iter()
                    .position(|m| !m.iter().all(|v| v.is_finite()))
                {
                    return Err(ReferenceError::NonFiniteCell { index });
                }
            }
            (ReferenceVolume::Grid(grid), Some(Modulation::Grid(modulator))) => {
                if grid.dims() != modulator.dims() {
                    return Err(ReferenceError::ModulationMismatch {
                        reason: format!(
                            "a modulator grid of {:?} points for a volume of {:?}",
                            modulator.dims(),
                            grid.dims()
                        ),
                    });
                }
            }
            _ => {
                return Err(ReferenceError::ModulationMismatch {
                    reason: "cells need per-cell modulators and a grid a modulator grid".into(),
                });
            }
        }
        if let Some(depth) = &self.opaque_depth {
            let expected = self.camera.width as usize * self.camera.height as usize;
            if depth.len() != expected {
                return Err(ReferenceError::DepthImageSize {
                    width: self.camera.width,
                    height: self.camera.height,
                    actual: depth.len(),
                });
            }
            if let Some(index) = depth.iter().position(|d| d.is_nan() || *d < 0.0) {
                return Err(ReferenceError::InvalidDepth {
                    x: index as u32 % self.camera.width,
                    y: index as u32 / self.camera.width,
                    value: depth[index],
                });
            }
        }
        let background = self.background;
        if !(background.is_finite() && background.min_element() >= 0.0 && background.w <= 1.0) {
            return Err(ReferenceError::InvalidBackground {
                value: format!("{background}"),
            });
        }
        if let Some(reason) = self.fog.as_ref().and_then(ReferenceFog::invalid) {
            return Err(ReferenceError::InvalidFog { reason });
        }
        if let Some((index, reason)) = self
            .local_lights
            .iter()
            .enumerate()
            .find_map(|(index, light)| Some((index, light.invalid()?)))
        {
            return Err(ReferenceError::InvalidLight { index, reason });
        }
        if !(self.scalar_tolerance.is_finite() && self.scalar_tolerance > 0.0) {
            return Err(ReferenceError::InvalidTolerance {
                value: self.scalar_tolerance,
            });
        }
        Ok(())
    }
}

/// How far a render has come, passed to the progress callback after each row.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RenderProgress {
    /// Rows finished so far.
    pub rows_done: u32,
    /// Rows in the image.
    pub rows_total: u32,
}

/// Why a reference image could not be rendered.
#[derive(Debug, thiserror::Error)]
pub enum ReferenceError {
    /// A camera field is out of range.
    #[error("reference camera: {field} = {value} is invalid: it must be {requirement}")]
    InvalidCamera {
        /// The field, e.g. `vertical_fov`.
        field: &'static str,
        /// Its value, formatted.
        value: String,
        /// What it must satisfy.
        requirement: &'static str,
    },
    /// A volume could not be prepared (its generator or light field failed).
    #[error("reference volume: {reason}")]
    InvalidVolume {
        /// What failed.
        reason: String,
    },
    /// A modulator does not fit the volume (wrong count, dims or kind).
    #[error("reference modulation: {reason}")]
    ModulationMismatch {
        /// What does not fit.
        reason: String,
    },
    /// A cell has a NaN or infinite position or scalar.
    #[error("reference cells: cell {index} has a non-finite position or scalar")]
    NonFiniteCell {
        /// Index in the cell list.
        index: usize,
    },
    /// The depth image does not match the camera's size.
    #[error("opaque depth: a {width}×{height} camera needs {} depth values, found {actual}", *width as usize * *height as usize)]
    DepthImageSize {
        /// Camera width.
        width: u32,
        /// Camera height.
        height: u32,
        /// Values given.
        actual: usize,
    },
    /// A depth value is NaN or negative.
    #[error("opaque depth: pixel ({x}, {y}) has depth {value}; depths must be ≥ 0 (+inf for none)")]
    InvalidDepth {
        /// Column.
        x: u32,
        /// Row, from the top.
        y: u32,
        /// The value found.
        value: f32,
    },
    /// The background is not a valid premultiplied colour.
    #[error("background {value} is invalid: channels must be finite and ≥ 0, alpha ≤ 1")]
    InvalidBackground {
        /// The value, formatted.
        value: String,
    },
    /// The fog layers' colour, sunlight or distances are out of range.
    #[error("reference fog: {reason}")]
    InvalidFog {
        /// What is wrong.
        reason: String,
    },
    /// A local light is out of range.
    #[error("reference local light {index}: {reason}")]
    InvalidLight {
        /// Index in [`ReferenceScene::local_lights`].
        index: usize,
        /// What is wrong.
        reason: String,
    },
    /// Scenes given to [`render_together`] cannot be rendered together.
    #[error("volumes rendered together: {reason}")]
    NotJoint {
        /// Why not.
        reason: String,
    },
    /// The scalar tolerance is not positive.
    #[error("scalar_tolerance = {value} is invalid: it must be finite and positive")]
    InvalidTolerance {
        /// The value found.
        value: f64,
    },
    /// The image (or another buffer of the camera's size) would exceed the
    /// memory budget; nothing was allocated.
    #[error(transparent)]
    OverBudget(#[from] BudgetError),
}

/// Renders `scene` (see the module docs). `progress`, when given, is called
/// from the worker threads after every finished row. Errors: a
/// [`ReferenceError`] for an invalid scene, [`ReferenceError::OverBudget`]
/// when the image exceeds the memory budget
/// ([`LinearImage::check_budget`]), before anything is allocated.
pub fn render(
    scene: &ReferenceScene,
    progress: Option<&(dyn Fn(RenderProgress) + Sync)>,
) -> Result<LinearImage, ReferenceError> {
    scene.validate()?;
    LinearImage::check_budget(scene.camera.width, scene.camera.height)?;
    let integrator = Integrator::new(scene);
    Ok(render_rows(&scene.camera, progress, |scratch, x, y| {
        render_pixel(scene, &integrator, scratch, x, y)
    }))
}

/// Renders the volumes of `scenes` along every ray together: the media are
/// integrated as one, so volumes that interpenetrate absorb and emit jointly
/// ([`nebel_core::joint_segment`]) and volumes that do not are composited in
/// their order along each ray, whatever their centres. Sorted volumes absorb;
/// emissive ones only emit, attenuated by what lies in front of them (their
/// opacity is not kept: the image's α is the sorted volumes' alone). Each
/// scene gives its volume, transfer function, mode, modulation, scattering,
/// scalar tolerance and opaque depth (where its rays end); the camera, fog
/// and background are shared and must be equal in every scene.
///
/// Errors: the errors of [`render`] for each scene, and
/// [`ReferenceError::NotJoint`] for no scene, a MIP volume (MIP is composited
/// on its own, with [`render`]) or scenes that differ in camera, fog or
/// background.
pub fn render_together(
    scenes: &[ReferenceScene],
    progress: Option<&(dyn Fn(RenderProgress) + Sync)>,
) -> Result<LinearImage, ReferenceError> {
    let Some(first) = scenes.first() else {
        return Err(ReferenceError::NotJoint {
            reason: "no volume".into(),
        });
    };
    for (index, scene) in scenes.iter().enumerate() {
        scene.validate()?;
        let differs = |what: &str| ReferenceError::NotJoint {
            reason: format!("volume {index} has another {what} than volume 0"),
        };
        if scene.mode == OpticalMode::Mip {
            return Err(ReferenceError::NotJoint {
                reason: format!("volume {index} is MIP, which is composited on its own"),
            });
        }
        if scene.camera != first.camera {
            return Err(differs("camera"));
        }
        if scene.fog != first.fog {
            return Err(differs("fog"));
        }
        if scene.background != first.background {
            return Err(differs("background"));
        }
    }
    LinearImage::check_budget(first.camera.width, first.camera.height)?;
    let integrators: Vec<Integrator<'_>> = scenes.iter().map(Integrator::new).collect();
    Ok(render_rows(&first.camera, progress, |scratch, x, y| {
        render_pixel_together(scenes, &integrators, scratch, x, y)
    }))
}

/// An image of `camera`'s size, each pixel from `pixel`, rows shared among
/// all cores.
fn render_rows(
    camera: &ReferenceCamera,
    progress: Option<&(dyn Fn(RenderProgress) + Sync)>,
    pixel: impl Fn(&mut Scratch, u32, u32) -> PremultipliedRgba + Sync,
) -> LinearImage {
    let (width, height) = (camera.width, camera.height);
    let mut image = LinearImage::transparent(width, height);
    let rows = Mutex::new(image.pixels.chunks_mut(width as usize).enumerate());
    let rows_done = AtomicU32::new(0);
    let threads = std::thread::available_parallelism()
        .map_or(1, std::num::NonZero::get)
        .min(height as usize);
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(|| {
                let mut scratch = Scratch::default();
                loop {
                    let next = rows
                        .lock()
                        .unwrap_or_else(std::sync::PoisonError::into_inner)
                        .next();
                    let Some((y, row)) = next else { break };
                    for (x, out) in row.iter_mut().enumerate() {
                        *out = pixel(&mut scratch, x as u32, y as u32).as_vec4().to_array();
                    }
                    let done = rows_done.fetch_add(1, Ordering::Relaxed) + 1;
                    if let Some(progress) = progress {
                        progress(RenderProgress {
                            rows_done: done,
                            rows_total: height,
                        });
                    }
                }
            });
        }
    });
    image
}

/// Per-thread buffers reused across pixels.
#[derive(Default)]
struct Scratch {
    /// A segment and the modulator at its entry and exit (`None` when
    /// unmodulated).
    segments: Vec<(CellSegment, Option<[f64; 2]>)>,
    crossings: Vec<f64>,
    /// Rendering together: every medium's pieces along the ray and those
    /// over the current stretch.
    pieces: Vec<RayPiece>,
    active: Vec<RayPiece>,
}

/// The prepared volume.
enum Integrator<'a> {
    /// The visible non-degenerate cells, prepared (with their modulator as a
    /// second prepared cell of the same geometry), and their screen bins.
    Cells {
        cells: Vec<(PreparedTetrahedron, Option<PreparedTetrahedron>)>,
        bins: CellBins,
    },
    Grid(GridFields<'a>),
}

impl<'a> Integrator<'a> {
    fn new(scene: &'a ReferenceScene) -> Self {
        match &scene.volume {
            ReferenceVolume::Cells(cells) => {
                let modulators = match &scene.modulation {
                    Some(Modulation::Cells(modulators)) => Some(modulators.as_slice()),
                    _ => None,
                };
                let (cells, bins) = CellBins::new(&scene.camera, cells, modulators);
                Integrator::Cells { cells, bins }
            }
            ReferenceVolume::Grid(grid) => Integrator::Grid(GridFields {
                grid,
                modulator: match &scene.modulation {
                    Some(Modulation::Grid(modulator)) => Some(modulator),
                    _ => None,
                },
            }),
        }
    }

    /// Marches `ray` over `[t_near, t_far]`, giving the pieces to `sink`.
    fn march(
        &self,
        sink: &mut impl PieceSink,
        scene: &ReferenceScene,
        ray: &Ray,
        (x, y, t_near, t_far): (u32, u32, f64, f64),
        segments: &mut Vec<(CellSegment, Option<[f64; 2]>)>,
        crossings: &mut Vec<f64>,
    ) {
        match self {
            Integrator::Cells { cells, bins } => march_cells(
                sink,
                cells,
                bins.candidates(x, y),
                ray,
                t_near,
                t_far,
                segments,
            ),
            Integrator::Grid(fields) => march_grid(
                sink,
                fields,
                scene.scalar_tolerance,
                ray,
                t_near,
                t_far,
                crossings,
            ),
        }
    }
}

/// The ray's ambient and sunlight weights of single scattering, for a sorted
/// volume with scattering.
fn ray_light(scene: &ReferenceScene, ray: &Ray) -> Option<(DVec3, f64)> {
    scene
        .scattering
        .filter(|_| scene.mode == OpticalMode::Sorted)
        .map(|scattering| {
            let cos_theta = ray.direction.dot(scattering.sun_direction);
            (
                scattering.ambient,
                scattering.sunlight * henyey_greenstein(scattering.asymmetry, cos_theta),
            )
        })
}

/// The ray distance where `scene`'s volume ends along the ray through pixel
/// `(x, y)`: its opaque depth, converted.
fn far_distance(scene: &ReferenceScene, x: u32, y: u32, depth_to_distance: f64) -> f64 {
    scene.opaque_depth.as_ref().map_or(f64::INFINITY, |depth| {
        f64::from(depth[(y * scene.camera.width + x) as usize]) / depth_to_distance
    })
}

fn render_pixel(
    scene: &ReferenceScene,
    integrator: &Integrator<'_>,
    scratch: &mut Scratch,
    x: u32,
    y: u32,
) -> PremultipliedRgba {
    let camera = &scene.camera;
    let (ray, depth_to_distance) = camera.pixel_ray(x, y);
    let t_near = camera.near / depth_to_distance;
    let t_far = far_distance(scene, x, y, depth_to_distance);
    let volume = if t_near < t_far {
        let mut march = March {
            medium: Medium::of(scene, &ray),
            colour: DVec4::ZERO,
            ray,
            fog: scene.fog.as_ref(),
        };
        integrator.march(
            &mut march,
            scene,
            &ray,
            (x, y, t_near, t_far),
            &mut scratch.segments,
            &mut scratch.crossings,
        );
        march.colour
    } else {
        DVec4::ZERO
    };
    scene.mode.composite(volume, scene.background)
}

/// A pixel of [`render_together`]: every medium's pieces along the ray,
/// merged by distance; where pieces of several media overlap, the stretch is
/// integrated jointly.
fn render_pixel_together(
    scenes: &[ReferenceScene],
    integrators: &[Integrator<'_>],
    scratch: &mut Scratch,
    x: u32,
    y: u32,
) -> PremultipliedRgba {
    let first = &scenes[0];
    let (ray, depth_to_distance) = first.camera.pixel_ray(x, y);
    let t_near = first.camera.near / depth_to_distance;
    let Scratch {
        segments,
        crossings,
        pieces,
        active,
    } = scratch;
    pieces.clear();
    for (medium, (scene, integrator)) in scenes.iter().zip(integrators).enumerate() {
        let t_far = far_distance(scene, x, y, depth_to_distance);
        if t_near < t_far {
            let mut collector = Collector {
                pieces,
                medium,
                reach: f64::NEG_INFINITY,
            };
            integrator.march(
                &mut collector,
                scene,
                &ray,
                (x, y, t_near, t_far),
                segments,
                crossings,
            );
        }
    }
    pieces.sort_by(|a, b| a.t_front.total_cmp(&b.t_front));
    let media: Vec<Medium<'_>> = scenes.iter().map(|scene| Medium::of(scene, &ray)).collect();
    let mut march = JointMarch {
        colour: DVec4::ZERO,
        ray,
        fog: first.fog.as_ref(),
    };
    // Sweep the pieces front to back; `active` holds those over `position`.
    active.clear();
    let (mut next, mut position) = (0, f64::NEG_INFINITY);
    loop {
        if active.is_empty() {
            let Some(piece) = pieces.get(next) else { break };
            position = piece.t_front;
        }
        while let Some(piece) = pieces.get(next).filter(|piece| piece.t_front <= position) {
            active.push(*piece);
            next += 1;
        }
        let end = active
            .iter()
            .map(|piece| piece.t_back)
            .chain(pieces.get(next).map(|piece| piece.t_front))
            .fold(f64::INFINITY, f64::min);
        if end > position {
            march.add(&media, active, position, end);
            if march.is_opaque() {
                break;
            }
        }
        position = end;
        active.retain(|piece| piece.t_back > position);
    }
    OpticalMode::Sorted.composite(march.colour, first.background)
}

/// One medium as a ray sees it.
#[derive(Clone, Copy)]
struct Medium<'a> {
    transfer_function: &'a TransferFunction,
    mode: OpticalMode,
    /// The ray's ambient and sunlight weights of single scattering.
    light: Option<(DVec3, f64)>,
    /// The local lights it scatters, and how.
    local_lights: &'a [LocalLight],
    response: LightResponse,
    /// What shades the lights that cast shadows.
    occluders: &'a [Occluder],
    sunlight: Option<&'a FogSunlight>,
    /// Toward the sun, where its light scattered by the medium is hidden by
    /// the occluders (a sun that casts shadows).
    shaded_sun: Option<DVec3>,
}

impl<'a> Medium<'a> {
    /// `scene`'s medium as `ray` sees it.
    fn of(scene: &'a ReferenceScene, ray: &Ray) -> Self {
        let sorted = scene.mode == OpticalMode::Sorted;
        Self {
            transfer_function: &scene.transfer_function,
            mode: scene.mode,
            light: ray_light(scene, ray),
            local_lights: if sorted { &scene.local_lights } else { &[] },
            response: scene.light_response.checked(),
            occluders: &scene.occluders,
            sunlight: scene.sunlight.as_ref().filter(|_| sorted),
            shaded_sun: scene
                .scattering
                .filter(|scattering| sorted && scattering.shadows && !scene.occluders.is_empty())
                .map(|scattering| scattering.sun_direction),
        }
    }

    /// Whether the occluders hide the sun from the point `p` (none hide it
    /// from a medium whose sun casts no shadows).
    fn sun_hidden(&self, p: DVec3) -> bool {
        self.shaded_sun
            .is_some_and(|sun| hides_sun(self.occluders, p, sun))
    }

    /// The local lights' colour where it scatters them, per unit of its
    /// emission weight: κ, or white where its colour is the sun's light,
    /// times the response's strength.
    fn albedo(&self, s: f64) -> DVec3 {
        let colour = if self.light.is_some() {
            DVec3::ONE
        } else {
            self.transfer_function.evaluate(s).kappa
        };
        colour * f64::from(self.response.strength)
    }

    /// The exact segment `s_front → s_back` of (modulated) `length`, lit
    /// (its sunlight held back where `hidden`).
    fn segment(&self, s_front: f64, s_back: f64, length: f64, hidden: bool) -> PremultipliedRgba {
        let segment = exact_segment(self.transfer_function, self.mode, s_front, s_back, length);
        self.light.map_or(segment, |(ambient, sunlight)| {
            let sunlight = if hidden { 0.0 } else { sunlight };
            (ambient * segment.w + sunlight * segment.truncate()).extend(segment.w)
        })
    }

    /// Its share of a joint segment over `piece`'s stretch `[t0, t1]` (its
    /// sunlight held back where `hidden`).
    fn joint(&self, piece: &RayPiece, t0: f64, t1: f64, hidden: bool) -> JointMedium<'_> {
        let (s_front, s_back, length) = piece.part(t0, t1);
        let (ambient, emission_weight) = match self.light {
            Some((ambient, _)) if hidden => (ambient, 0.0),
            light => light.unwrap_or((DVec3::ZERO, 1.0)),
        };
        JointMedium {
            transfer_function: self.transfer_function,
            s_front,
            s_back,
            density_scale: length / (t1 - t0),
            absorbs: self.mode == OpticalMode::Sorted,
            emission_weight,
            ambient,
        }
    }
}

/// The local lights scattered toward the eye over `[t0, t1]` by the pieces
/// `active` of `media` (each covering the stretch): `Σ ∫ ρ κ T E 4π p_HG dt`
/// over each medium's lights, `T` the joint transmittance of the absorbing
/// media from `t0`.
fn in_scattered(media: &[Medium<'_>], active: &[RayPiece], ray: &Ray, t0: f64, t1: f64) -> DVec3 {
    let mut sum = DVec3::ZERO;
    let lit = active.iter().any(|piece| {
        let medium = &media[piece.medium];
        !medium.local_lights.is_empty() || medium.sunlight.is_some()
    });
    if !lit || t1.partial_cmp(&t0) != Some(std::cmp::Ordering::Greater) {
        return sum;
    }
    // Per piece: its scalar over the stretch, linear from `s0` to `s1`, and
    // its density scale (the modulated length over the stretch's).
    let parts: Vec<(Medium<'_>, f64, f64, f64)> = active
        .iter()
        .map(|piece| {
            let (s0, s1, length) = piece.part(t0, t1);
            (media[piece.medium], s0, s1, length / (t1 - t0))
        })
        .collect();
    let scalar = |(_, s0, s1, _): &(Medium<'_>, f64, f64, f64), t: f64| {
        s0 + (s1 - s0) * ((t - t0) / (t1 - t0))
    };
    let transmittance = |t: f64| {
        let depth: f64 = parts
            .iter()
            .filter(|(medium, ..)| medium.mode == OpticalMode::Sorted)
            .map(|part| {
                part.3 * (t - t0) * rho_hat(part.0.transfer_function, part.1, scalar(part, t))
            })
            .sum();
        (-depth).exp()
    };
    for part in &parts {
        let medium = part.0;
        for light in medium.local_lights {
            sum += light.scattered_past(
                medium.occluders,
                ray,
                (t0, t1),
                f64::from(medium.response.asymmetry),
                LIGHT_INTERVALS,
                |t| {
                    let s = scalar(part, t);
                    let rho = medium.transfer_function.evaluate(s).rho;
                    medium.albedo(s) * (part.3 * rho * transmittance(t))
                },
            );
        }
        if let Some(sunlight) = medium.sunlight {
            sum += sunlight.scattered(ray.origin, ray.direction, (t0, t1), |t| {
                let sample = medium.transfer_function.evaluate(scalar(part, t));
                sample.kappa * (part.3 * sample.rho * transmittance(t))
            });
        }
    }
    sum
}

/// The exact segment of the pieces `active` of `media` (each covering the
/// stretch) over `[t0, t1]` along `ray`: one alone as its own exact segment,
/// several as their joint segment; cut where the occluders hide the sun from
/// a medium whose sun casts shadows, each part with its sunlight or without,
/// the parts composited front to back.
fn stretch_segment(
    media: &[Medium<'_>],
    active: &[RayPiece],
    ray: &Ray,
    t0: f64,
    t1: f64,
) -> PremultipliedRgba {
    // The exact segment over [a, b], each medium's sunlight held back
    // where the occluders hide its sun from the middle.
    let part = |a: f64, b: f64| {
        let middle = ray.at(0.5 * (a + b));
        if let [piece] = active {
            let medium = &media[piece.medium];
            let (s_front, s_back, length) = piece.part(a, b);
            medium.segment(s_front, s_back, length, medium.sun_hidden(middle))
        } else {
            let joint: Vec<JointMedium<'_>> = active
                .iter()
                .map(|piece| {
                    let medium = &media[piece.medium];
                    medium.joint(piece, a, b, medium.sun_hidden(middle))
                })
                .collect();
            exact_joint_segment(&joint, b - a)
        }
    };
    let mut cuts = Vec::new();
    for piece in active {
        let medium = &media[piece.medium];
        if let Some(sun) = medium.shaded_sun {
            for (a, b) in sun_lit_spans(medium.occluders, sun, ray, (t0, t1)) {
                cuts.extend([a, b]);
            }
        }
    }
    if cuts.is_empty() {
        return part(t0, t1);
    }
    cuts.extend([t0, t1]);
    cuts.sort_by(f64::total_cmp);
    cuts.dedup();
    cuts.windows(2)
        .filter(|pair| pair[1] > pair[0])
        .fold(DVec4::ZERO, |colour, pair| {
            OpticalMode::Sorted.composite(colour, part(pair[0], pair[1]))
        })
}

/// Where a march puts the linear pieces of a volume along a ray.
trait PieceSink {
    /// Takes the linear segment `s_front → s_back` of (modulated) `length`,
    /// lying over `[t_front, t_back]` along the ray.
    fn add(&mut self, t_front: f64, t_back: f64, s_front: f64, s_back: f64, length: f64);

    /// Whether nothing behind can change the pixel any more.
    fn is_opaque(&self) -> bool;
}

/// Front-to-back accumulation of one volume along one ray.
struct March<'a> {
    medium: Medium<'a>,
    colour: PremultipliedRgba,
    ray: Ray,
    fog: Option<&'a ReferenceFog>,
}

impl PieceSink for March<'_> {
    fn add(&mut self, t_front: f64, t_back: f64, s_front: f64, s_back: f64, length: f64) {
        let (medium, mode, ray) = (self.medium, self.medium.mode, self.ray);
        let piece = RayPiece {
            t_front,
            t_back,
            s_front,
            s_back,
            length,
            medium: 0,
        };
        let lit = |segment: PremultipliedRgba, t0: f64, t1: f64| {
            segment + in_scattered(&[medium], &[piece], &ray, t0, t1).extend(0.0)
        };
        let whole = lit(
            stretch_segment(&[medium], &[piece], &ray, t_front, t_back),
            t_front,
            t_back,
        );
        let Some(fog) = self.fog else {
            self.colour = mode.composite(self.colour, whole);
            return;
        };
        let ray = self.ray;
        fog.conjugated_pieces(
            &ray,
            t_front,
            t_back,
            whole,
            mode == OpticalMode::Sorted,
            |k, count| {
                let t_at = |k: usize| t_front + (t_back - t_front) * k as f64 / count as f64;
                lit(
                    stretch_segment(&[medium], &[piece], &ray, t_at(k), t_at(k + 1)),
                    t_at(k),
                    t_at(k + 1),
                )
            },
            |part| {
                self.colour = mode.composite(self.colour, part);
                self.is_opaque()
            },
        );
    }

    fn is_opaque(&self) -> bool {
        self.medium.mode == OpticalMode::Sorted && 1.0 - self.colour.w < MIN_TRANSMITTANCE
    }
}

/// A linear piece of one medium along a ray, for [`render_together`].
#[derive(Clone, Copy, Debug)]
struct RayPiece {
    t_front: f64,
    t_back: f64,
    s_front: f64,
    s_back: f64,
    /// The (modulated) length.
    length: f64,
    /// Index of the medium (scene).
    medium: usize,
}

impl RayPiece {
    /// The scalars and (modulated) length over `[t0, t1]` ⊆ the piece; the
    /// piece's own where the stretch is the whole piece.
    fn part(&self, t0: f64, t1: f64) -> (f64, f64, f64) {
        let span = self.t_back - self.t_front;
        let s_at = |t: f64| {
            if t == self.t_front {
                self.s_front
            } else if t == self.t_back {
                self.s_back
            } else {
                self.s_front + (self.s_back - self.s_front) * ((t - self.t_front) / span)
            }
        };
        let length = if t0 == self.t_front && t1 == self.t_back {
            self.length
        } else {
            self.length * ((t1 - t0) / span)
        };
        (s_at(t0), s_at(t1), length)
    }
}

/// Collects one medium's pieces for [`render_together`]. The pieces of one
/// medium come front to back and do not overlap: where rounding makes a cell's
/// entry fall before the previous cell's exit, the piece starts at that exit.
struct Collector<'a> {
    pieces: &'a mut Vec<RayPiece>,
    medium: usize,
    /// The farthest exit so far.
    reach: f64,
}

impl PieceSink for Collector<'_> {
    fn add(&mut self, t_front: f64, t_back: f64, s_front: f64, s_back: f64, length: f64) {
        let t_front = t_front.max(self.reach);
        if t_back > t_front {
            self.reach = t_back;
            self.pieces.push(RayPiece {
                t_front,
                t_back,
                s_front,
                s_back,
                length,
                medium: self.medium,
            });
        }
    }

    fn is_opaque(&self) -> bool {
        false
    }
}

/// Front-to-back accumulation of several media along one ray, for
/// [`render_together`]: "over", with the emissive media's opacity dropped.
struct JointMarch<'a> {
    colour: PremultipliedRgba,
    ray: Ray,
    fog: Option<&'a ReferenceFog>,
}

impl JointMarch<'_> {
    /// Adds the stretch `[t0, t1]` over which the pieces `active` (at least
    /// one, each covering it) lie: one alone as its own exact segment,
    /// several as their joint segment.
    fn add(&mut self, media: &[Medium<'_>], active: &[RayPiece], t0: f64, t1: f64) {
        let absorbs = active
            .iter()
            .any(|piece| media[piece.medium].mode == OpticalMode::Sorted);
        let ray = self.ray;
        let stretch = |a: f64, b: f64| {
            let (ta, tb) = if (a, b) == (0.0, 1.0) {
                (t0, t1)
            } else {
                (t0 + (t1 - t0) * a, t0 + (t1 - t0) * b)
            };
            stretch_segment(media, active, &ray, ta, tb)
                + in_scattered(media, active, &ray, ta, tb).extend(0.0)
        };
        let coverage = |part: PremultipliedRgba| {
            if absorbs {
                part
            } else {
                part.truncate().extend(0.0)
            }
        };
        let whole = stretch(0.0, 1.0);
        let Some(fog) = self.fog else {
            self.colour = OpticalMode::Sorted.composite(self.colour, coverage(whole));
            return;
        };
        fog.conjugated_pieces(
            &ray,
            t0,
            t1,
            whole,
            absorbs,
            |k, count| stretch(k as f64 / count as f64, (k + 1) as f64 / count as f64),
            |part| {
                self.colour = OpticalMode::Sorted.composite(self.colour, coverage(part));
                self.is_opaque()
            },
        );
    }

    fn is_opaque(&self) -> bool {
        1.0 - self.colour.w < MIN_TRANSMITTANCE
    }
}

fn march_cells(
    march: &mut impl PieceSink,
    cells: &[(PreparedTetrahedron, Option<PreparedTetrahedron>)],
    candidates: &[u32],
    ray: &Ray,
    t_near: f64,
    t_far: f64,
    segments: &mut Vec<(CellSegment, Option<[f64; 2]>)>,
) {
    segments.clear();
    segments.extend(candidates.iter().filter_map(|&index| {
        let (cell, modulator) = &cells[index as usize];
        let segment = cell.intersect(ray)?.clip_to_range(t_near, t_far)?;
        let modulation = match modulator {
            Some(modulator) => {
                let m = modulator.intersect(ray)?.clip_to_range(t_near, t_far)?;
                Some([m.s_entry, m.s_exit])
            }
            None => None,
        };
        (segment.length() > 0.0).then_some((segment, modulation))
    }));
    // Front to back (what emissive and MIP sums need not, but a collector does).
    segments.sort_unstable_by(|a, b| a.0.t_entry.total_cmp(&b.0.t_entry));
    'segments: for (segment, modulation) in segments.iter() {
        // The GPU's pieces, each with the mean of the linear modulator; an
        // unmodulated segment is one piece (WGSL's `mix`, exact at 0 and 1,
        // so that piece is the segment itself).
        let (pieces, [m_entry, m_exit]) = match *modulation {
            Some(ends) => (MODULATOR_PIECES, ends),
            None => (1, [1.0, 1.0]),
        };
        let at = |piece: u32| f64::from(piece) / f64::from(pieces);
        let lerp = |a: f64, b: f64, x: f64| a * (1.0 - x) + b * x;
        for piece in 0..pieces {
            let (a, b) = (at(piece), at(piece + 1));
            let mean = 0.5 * (lerp(m_entry, m_exit, a) + lerp(m_entry, m_exit, b));
            march.add(
                lerp(segment.t_entry, segment.t_exit, a),
                lerp(segment.t_entry, segment.t_exit, b),
                lerp(segment.s_entry, segment.s_exit, a),
                lerp(segment.s_entry, segment.s_exit, b),
                segment.length() * (b - a) * mean,
            );
            if march.is_opaque() {
                break 'segments;
            }
        }
    }
}

/// Prepared cells binned by the screen tiles their projection may cover.
struct CellBins {
    tiles_x: u32,
    bins: Vec<Vec<u32>>,
}

impl CellBins {
    /// Prepares the visible, non-degenerate cells and bins them; bin entries
    /// index the returned cells.
    fn new(
        camera: &ReferenceCamera,
        cells: &[Tetrahedron],
        modulators: Option<&[[f64; 4]]>,
    ) -> (
        Vec<(PreparedTetrahedron, Option<PreparedTetrahedron>)>,
        Self,
    ) {
        let tiles_x = camera.width.div_ceil(TILE_SIZE);
        let tiles_y = camera.height.div_ceil(TILE_SIZE);
        let mut bins = vec![Vec::new(); (tiles_x * tiles_y) as usize];
        let mut prepared = Vec::with_capacity(cells.len());
        for (index, cell) in cells.iter().enumerate() {
            let Some(prepared_cell) = cell.prepare() else {
                continue;
            };
            let modulator = modulators.and_then(|m| {
                Tetrahedron {
                    positions: cell.positions,
                    scalars: m[index],
                }
                .prepare()
            });
            let projected = cell.positions.map(|p| camera.project(p));
            // Rays only see view depths ≥ near.
            if projected.iter().all(|&(_, _, depth)| depth < camera.near) {
                continue;
            }
            let (tx, ty) = if projected.iter().any(|&(_, _, depth)| depth < camera.near) {
                // Crosses the near plane: the projection is unbounded.
                ((0, tiles_x - 1), (0, tiles_y - 1))
            } else {
                let tile_range = |coordinates: [f64; 4], tiles: u32| {
                    let lo = coordinates.iter().copied().fold(f64::INFINITY, f64::min) - 1.0;
                    let hi = coordinates
                        .iter()
                        .copied()
                        .fold(f64::NEG_INFINITY, f64::max)
                        + 1.0;
                    let limit = f64::from(tiles * TILE_SIZE);
                    if hi < 0.0 || lo > limit {
                        return None;
                    }
                    let tile =
                        |c: f64| ((c.clamp(0.0, limit - 1.0) as u32) / TILE_SIZE).min(tiles - 1);
                    Some((tile(lo), tile(hi)))
                };
                let (Some(tx), Some(ty)) = (
                    tile_range(projected.map(|p| p.0), tiles_x),
                    tile_range(projected.map(|p| p.1), tiles_y),
                ) else {
                    continue;
                };
                (tx, ty)
            };
            let index = prepared.len() as u32;
            prepared.push((prepared_cell, modulator));
            for tile_y in ty.0..=ty.1 {
                for tile_x in tx.0..=tx.1 {
                    bins[(tile_y * tiles_x + tile_x) as usize].push(index);
                }
            }
        }
        (prepared, Self { tiles_x, bins })
    }

    /// Cells that may cover pixel `(x, y)`.
    fn candidates(&self, x: u32, y: u32) -> &[u32] {
        &self.bins[((y / TILE_SIZE) * self.tiles_x + x / TILE_SIZE) as usize]
    }
}

/// A cubic `c0 + c1 x + c2 x² + c3 x³`.
#[derive(Clone, Copy, Default)]
struct Cubic([f64; 4]);

impl Cubic {
    fn linear(c0: f64, c1: f64) -> Self {
        Self([c0, c1, 0.0, 0.0])
    }

    /// `self + (other − self) · weight`; the degrees must add up to ≤ 3.
    fn lerp(self, other: Self, weight: Self) -> Self {
        let mut out = self.0;
        for i in 0..4 {
            for j in 0..4 - i {
                out[i + j] += (other.0[i] - self.0[i]) * weight.0[j];
            }
        }
        Self(out)
    }

    fn at(&self, x: f64) -> f64 {
        let [c0, c1, c2, c3] = self.0;
        c0 + x * (c1 + x * (c2 + x * c3))
    }

    fn second_derivative(&self, x: f64) -> f64 {
        2.0 * self.0[2] + 6.0 * self.0[3] * x
    }
}

/// A grid volume and its optional modulator grid of the same points.
struct GridFields<'a> {
    grid: &'a DensityGrid,
    modulator: Option<&'a DensityGrid>,
}

fn march_grid(
    march: &mut impl PieceSink,
    &GridFields { grid, modulator }: &GridFields<'_>,
    tolerance: f64,
    ray: &Ray,
    t_near: f64,
    t_far: f64,
    crossings: &mut Vec<f64>,
) {
    let dims = grid.dims();
    // The ray in grid units: u(t) = start + t · step.
    let start = (ray.origin - grid.origin()) / grid.spacing();
    let step = ray.direction / grid.spacing();
    let last = DVec3::new(
        (dims[0] - 1) as f64,
        (dims[1] - 1) as f64,
        (dims[2] - 1) as f64,
    );
    let (mut t_enter, mut t_exit) = (t_near, t_far);
    for axis in 0..3 {
        if step[axis] == 0.0 {
            if !(0.0..=last[axis]).contains(&start[axis]) {
                return;
            }
            continue;
        }
        let a = (0.0 - start[axis]) / step[axis];
        let b = (last[axis] - start[axis]) / step[axis];
        t_enter = t_enter.max(a.min(b));
        t_exit = t_exit.min(a.max(b));
    }
    if t_enter.is_nan() || t_exit.is_nan() || t_enter >= t_exit {
        return;
    }
    // Every crossing of a cell plane inside (t_enter, t_exit), sorted.
    crossings.clear();
    crossings.push(t_enter);
    for axis in 0..3 {
        if step[axis] == 0.0 {
            continue;
        }
        let (u0, u1) = (
            start[axis] + t_enter * step[axis],
            start[axis] + t_exit * step[axis],
        );
        let (lo, hi) = (
            u0.min(u1).ceil().max(0.0),
            u0.max(u1).floor().min(last[axis]),
        );
        let mut plane = lo;
        while plane <= hi {
            let t = (plane - start[axis]) / step[axis];
            if t > t_enter && t < t_exit {
                crossings.push(t);
            }
            plane += 1.0;
        }
    }
    crossings.push(t_exit);
    crossings.sort_unstable_by(f64::total_cmp);

    for window in crossings.windows(2) {
        let (ta, tb) = (window[0], window[1]);
        let length = tb - ta;
        if length.is_nan() || length <= 0.0 {
            continue;
        }
        let middle = start + (0.5 * (ta + tb)) * step;
        let cell = [0, 1, 2].map(|a| (middle[a].floor().max(0.0) as usize).min(dims[a] - 2));
        // Local coordinates along the piece, linear in x = t − ta.
        let local = |axis: usize| {
            let origin = start[axis] + ta * step[axis] - cell[axis] as f64;
            Cubic::linear(origin, step[axis])
        };
        let (wx, wy, wz) = (local(0), local(1), local(2));
        let trilinear = |field: &DensityGrid| {
            let corner = |dx: usize, dy: usize, dz: usize| {
                Cubic::linear(
                    f64::from(field.value(cell[0] + dx, cell[1] + dy, cell[2] + dz)),
                    0.0,
                )
            };
            let edge = |dy: usize, dz: usize| corner(0, dy, dz).lerp(corner(1, dy, dz), wx);
            let face = |dz: usize| edge(0, dz).lerp(edge(1, dz), wy);
            face(0).lerp(face(1), wz)
        };
        let scalar = trilinear(grid);
        let modulation = modulator.map(trilinear);
        let bend = |cubic: &Cubic| {
            cubic
                .second_derivative(0.0)
                .abs()
                .max(cubic.second_derivative(length).abs())
        };
        let curvature = bend(&scalar).max(modulation.as_ref().map_or(0.0, bend));
        // A modulated piece uses one mean modulator: split until the
        // modulator changes by at most 100 × the tolerance along a piece (the
        // mean is exact for the optical depth of a linear modulator; what is
        // left is second order in that change).
        let modulator_pieces = modulation.as_ref().map_or(0.0, |m| {
            (m.at(length) - m.at(0.0)).abs() / (100.0 * tolerance)
        });
        let pieces = (length * (curvature / (8.0 * tolerance)).sqrt())
            .max(modulator_pieces)
            .ceil()
            .clamp(1.0, MAX_PIECES_PER_CELL) as usize;
        let piece_length = length / pieces as f64;
        let modulator_at = |x: f64| modulation.as_ref().map_or(1.0, |m| m.at(x));
        let (mut s_front, mut m_front) = (scalar.at(0.0), modulator_at(0.0));
        for piece in 1..=pieces {
            let x = piece as f64 * piece_length;
            let (s_back, m_back) = (scalar.at(x), modulator_at(x));
            march.add(
                ta + x - piece_length,
                ta + x,
                s_front,
                s_back,
                piece_length * 0.5 * (m_front + m_back),
            );
            if march.is_opaque() {
                return;
            }
            (s_front, m_front) = (s_back, m_back);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec2;
    use nebel_core::transfer::ControlPoint;

    /// κ = (1, 0.5, 0.25) everywhere; ρ = 2 everywhere.
    fn constant_tf() -> TransferFunction {
        TransferFunction::new(vec![
            ControlPoint {
                s: 0.0,
                kappa: [1.0, 0.5, 0.25],
                rho: 2.0,
            },
            ControlPoint {
                s: 1.0,
                kappa: [1.0, 0.5, 0.25],
                rho: 2.0,
            },
        ])
        .unwrap()
    }

    /// κ and ρ varying with s.
    fn ramp_tf() -> TransferFunction {
        TransferFunction::new(vec![
            ControlPoint {
                s: 0.0,
                kappa: [0.2, 0.4, 1.0],
                rho: 0.0,
            },
            ControlPoint {
                s: 0.4,
                kappa: [1.0, 0.8, 0.2],
                rho: 1.5,
            },
            ControlPoint {
                s: 1.0,
                kappa: [1.0, 0.2, 0.1],
                rho: 4.0,
            },
        ])
        .unwrap()
    }

    /// Grid over the box [−1, 1]³ with values from `field`.
    fn grid(n: usize, field: impl Fn(DVec3) -> f64) -> DensityGrid {
        let spacing = DVec3::splat(2.0 / (n - 1) as f64);
        let origin = DVec3::splat(-1.0);
        let mut values = Vec::new();
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    let p = origin + DVec3::new(i as f64, j as f64, k as f64) * spacing;
                    values.push(field(p) as f32);
                }
            }
        }
        DensityGrid::new([n, n, n], spacing, origin, values).unwrap()
    }

    /// Camera on +z looking at the origin, slightly off axis.
    fn camera() -> ReferenceCamera {
        ReferenceCamera {
            position: DVec3::new(0.3, -0.2, 6.0),
            width: 40,
            height: 30,
            vertical_fov: 0.5,
            ..Default::default()
        }
    }

    fn max_difference(a: &LinearImage, b: &LinearImage, channels: usize) -> f32 {
        a.pixels
            .iter()
            .zip(&b.pixels)
            .flat_map(|(p, q)| (0..channels).map(move |c| (p[c] - q[c]).abs()))
            .fold(0.0, f32::max)
    }

    /// Chord of the pixel's ray through the box [−1, 1]³ when it enters the
    /// front face z = 1 and leaves through the back face z = −1, or 0 when it
    /// misses both; `None` when it crosses a side face (not checked).
    fn box_chord(camera: &ReferenceCamera, x: u32, y: u32, back_depth: Option<f64>) -> Option<f64> {
        let (ray, _) = camera.pixel_ray(x, y);
        let at_z = |z: f64| ray.at((z - ray.origin.z) / ray.direction.z);
        let inside = |p: DVec3| p.x.abs() <= 1.0 && p.y.abs() <= 1.0;
        let (front, back) = (at_z(1.0), at_z(-1.0));
        let margin = |p: DVec3| (p.x.abs() - 1.0).abs().min((p.y.abs() - 1.0).abs());
        if margin(front) < 1e-9 || margin(back) < 1e-9 {
            return None;
        }
        match (inside(front), inside(back)) {
            (true, true) => {
                let z_end = back_depth.map_or(-1.0, |d| camera.position.z - d);
                Some(((1.0 - z_end) / -ray.direction.z).max(0.0))
            }
            (false, false)
                if (front.x.signum() == back.x.signum() && front.x.abs() > 1.0)
                    || (front.y.signum() == back.y.signum() && front.y.abs() > 1.0) =>
            {
                Some(0.0)
            }
            _ => None,
        }
    }

    /// The pixels whose ray crosses the box through its front and back
    /// faces or misses it (see [`box_chord`]), with their chords.
    fn box_pixels(camera: &ReferenceCamera, back_depth: Option<f64>) -> Vec<(u32, u32, f64)> {
        (0..camera.height)
            .flat_map(|y| (0..camera.width).map(move |x| (x, y)))
            .filter_map(|(x, y)| Some((x, y, box_chord(camera, x, y, back_depth)?)))
            .collect()
    }

    #[test]
    fn uniform_box_matches_the_closed_form() {
        let volume = ReferenceVolume::Grid(grid(5, |_| 0.5));
        let scene = ReferenceScene::new(camera(), volume, constant_tf(), OpticalMode::Sorted);
        let image = render(&scene, None).unwrap();
        let pixels = box_pixels(&scene.camera, None);
        for &(x, y, chord) in &pixels {
            let alpha = 1.0 - (-2.0 * chord).exp();
            let expected = [alpha, 0.5 * alpha, 0.25 * alpha, alpha];
            let pixel = image.pixels[(y * 40 + x) as usize];
            for c in 0..4 {
                assert!(
                    (f64::from(pixel[c]) - expected[c]).abs() < 1e-6,
                    "({x}, {y}) {pixel:?} vs {expected:?}"
                );
            }
        }
        assert!(pixels.len() > 600, "only {} pixels checked", pixels.len());
    }

    /// The uniform box (κ = (1, 0.5, 0.25), ρ = 2) scattering a sun
    /// straight up that casts shadows, a rectangle above hiding it from the
    /// box's front half (z > 0): along each ray through the front and back
    /// faces the first half of the chord scatters the sky's light only.
    #[test]
    fn an_occluder_hides_the_sun_from_the_part_of_a_scattering_box_below_it() {
        let volume = ReferenceVolume::Grid(grid(5, |_| 0.5));
        let mut scene = ReferenceScene::new(camera(), volume, constant_tf(), OpticalMode::Sorted);
        let (ambient, sunlight) = (DVec3::new(0.1, 0.2, 0.3), 2.0);
        scene.scattering = Some(SegmentScattering {
            ambient,
            sunlight,
            sun_direction: DVec3::Y,
            asymmetry: 0.0,
            shadows: true,
        });
        scene.occluders = vec![Occluder::Rectangle {
            centre: DVec3::new(0.0, 5.0, 5.0),
            half_size: DVec2::new(10.0, 5.0),
        }];
        let image = render(&scene, None).unwrap();
        let kappa = DVec3::new(1.0, 0.5, 0.25);
        let pixels = box_pixels(&scene.camera, None);
        for &(x, y, chord) in &pixels {
            let alpha = 1.0 - (-chord).exp();
            let (front, back) = (ambient * alpha, (ambient + sunlight * kappa) * alpha);
            let colour = front + (1.0 - alpha) * back;
            let expected = colour.extend(1.0 - (1.0 - alpha) * (1.0 - alpha));
            let pixel = image.pixels[(y * 40 + x) as usize];
            for c in 0..4 {
                assert!(
                    (f64::from(pixel[c]) - expected[c]).abs() < 1e-6,
                    "({x}, {y}) {pixel:?} vs {expected}"
                );
            }
        }
        assert!(pixels.len() > 600, "only {} pixels checked", pixels.len());
        // A sun without shadows lights the whole chord.
        scene.scattering = scene.scattering.map(|scattering| SegmentScattering {
            shadows: false,
            ..scattering
        });
        let unshaded = render(&scene, None).unwrap();
        let (x, y, chord) = pixels[pixels.len() / 2];
        let alpha = 1.0 - (-2.0 * chord).exp();
        let pixel = unshaded.pixels[(y * 40 + x) as usize];
        let expected = (ambient + sunlight * kappa) * alpha;
        assert!(
            (f64::from(pixel[1]) - expected.y).abs() < 1e-6,
            "{pixel:?} vs {expected}"
        );
    }

    #[test]
    fn a_box_lit_by_a_point_light_matches_the_integral_in_distance() {
        use nebel_core::local_light::{LightResponse, LocalLight};
        // The uniform box (κ = (1, 0.5, 0.25), ρ = 2) with a point light
        // above it, scattering forward: its own colour κ α plus
        // 1.5 ∫ ρ κ e^{−ρ (t − t_in)} E(x) 4π p_HG dt, here by the midpoint rule
        // in t (the reference integrates in the angle).
        let light = LocalLight::from_lumens(
            DVec3::new(0.2, 1.4, 0.3),
            DVec3::new(1.0, 0.7, 0.4),
            2e5,
            6.0,
        );
        let volume = ReferenceVolume::Grid(grid(5, |_| 0.5));
        let mut scene = ReferenceScene::new(camera(), volume, constant_tf(), OpticalMode::Sorted);
        scene.local_lights = vec![light];
        scene.light_response = LightResponse {
            asymmetry: 0.4,
            strength: 1.5,
        };
        let image = render(&scene, None).unwrap();
        let kappa = DVec3::new(1.0, 0.5, 0.25);
        let pixels = box_pixels(&scene.camera, None);
        let mut brightest: f64 = 0.0;
        for &(x, y, chord) in &pixels {
            let (ray, _) = scene.camera.pixel_ray(x, y);
            let t_in = (1.0 - ray.origin.z) / ray.direction.z;
            let steps = 20_000;
            let step = chord / f64::from(steps);
            let scattered: DVec3 = (0..steps)
                .map(|i| {
                    let t = t_in + step * (f64::from(i) + 0.5);
                    let at = ray.at(t);
                    let cos_theta = ray.direction.dot((at - light.position).normalize());
                    2.0 * kappa
                        * (-2.0 * (t - t_in)).exp()
                        * light.illuminance(at)
                        * henyey_greenstein(0.4, cos_theta)
                        * step
                })
                .sum();
            let expected = kappa * (1.0 - (-2.0 * chord).exp()) + 1.5 * scattered;
            brightest = brightest.max(scattered.max_element());
            let pixel = image.pixels[(y * 40 + x) as usize];
            for c in 0..3 {
                assert!(
                    (f64::from(pixel[c]) - expected[c]).abs() < 1e-5,
                    "({x}, {y}) {pixel:?} vs {expected}"
                );
            }
        }
        assert!(brightest > 0.2, "the light adds only {brightest}");
        // A box around the light hides it from the whole medium once it casts
        // shadows: the medium's own colour alone, as without the light.
        scene.occluders = vec![Occluder::Box {
            min: light.position - 0.05,
            max: light.position + 0.05,
        }];
        assert_eq!(image.pixels, render(&scene, None).unwrap().pixels);
        scene.local_lights[0].shadows = true;
        let shaded = render(&scene, None).unwrap();
        scene.local_lights.clear();
        assert_eq!(shaded.pixels, render(&scene, None).unwrap().pixels);
        scene.local_lights = vec![light];
        scene.occluders.clear();
        // An emissive medium scatters nothing; a bad light is refused by index.
        scene.mode = OpticalMode::Emissive;
        let emissive = render(&scene, None).unwrap();
        scene.local_lights.clear();
        assert_eq!(emissive.pixels, render(&scene, None).unwrap().pixels);
        scene.local_lights = vec![
            light,
            LocalLight {
                range: -1.0,
                ..light
            },
        ];
        let error = render(&scene, None).unwrap_err().to_string();
        assert!(
            error.contains("local light 1") && error.contains("range"),
            "{error}"
        );
    }

    #[test]
    fn a_box_inside_fog_matches_the_closed_form_of_both_media() {
        use crate::fog::ReferenceFog;
        use nebel_core::height_fog::{HeightFog, HeightFogLayer};
        // Fog ρ_f = 0.3 everywhere near the box, colour c; the box ρ = 2,
        // κ = (1, 0.5, 0.25). Along a ray: fog to the box, both media inside
        // it (extinction ρ + ρ_f, source ρκ + ρ_f c, constant), fog behind to
        // the largest distance, then the background.
        let fog = ReferenceFog {
            fog: HeightFog::new(vec![HeightFogLayer::Constant {
                bottom: -100.0,
                top: 100.0,
                density: 0.3,
            }])
            .unwrap(),
            colour: DVec3::new(0.2, 0.4, 0.9),
            sun: None,
            start_distance: 0.0,
            max_distance: 40.0,
            lights: Vec::new(),
            light_response: LightResponse::default(),
            occluders: Vec::new(),
            clouds: Vec::new(),
            terrain: None,
        };
        let kappa = DVec3::new(1.0, 0.5, 0.25);
        let background = DVec4::new(0.05, 0.1, 0.0, 1.0);
        for (volume, mode) in [
            (ReferenceVolume::Grid(grid(5, |_| 0.5)), OpticalMode::Sorted),
            (
                ReferenceVolume::Cells(grid(3, |_| 0.5).tetrahedra()),
                OpticalMode::Sorted,
            ),
            (
                ReferenceVolume::Grid(grid(5, |_| 0.5)),
                OpticalMode::Emissive,
            ),
        ] {
            let mut scene = ReferenceScene::new(camera(), volume, constant_tf(), mode);
            scene.fog = Some(fog.clone());
            let image = render(&scene, None).unwrap();
            let pixels = box_pixels(&scene.camera, None);
            for &(x, y, chord) in &pixels {
                {
                    let (ray, _) = scene.camera.pixel_ray(x, y);
                    let t_entry = if chord > 0.0 {
                        (1.0 - ray.origin.z) / ray.direction.z
                    } else {
                        40.0
                    };
                    let fog_layer = |length: f64| {
                        let alpha = 1.0 - (-0.3 * length).exp();
                        (fog.colour * alpha).extend(alpha)
                    };
                    let inside = match mode {
                        OpticalMode::Sorted => {
                            let alpha = 1.0 - (-2.3 * chord).exp();
                            ((2.0 * kappa + 0.3 * fog.colour) / 2.3 * alpha).extend(alpha)
                        }
                        _ => {
                            let alpha = 1.0 - (-0.3 * chord).exp();
                            ((2.0 * kappa + 0.3 * fog.colour) / 0.3 * alpha).extend(alpha)
                        }
                    };
                    let over = |front: DVec4, back: DVec4| front + (1.0 - front.w) * back;
                    let behind = fog_layer(40.0 - t_entry - chord);
                    let expected = over(fog_layer(t_entry), over(inside, over(behind, background)));
                    // The reference: the volume seen through the fog, over
                    // the fogged background.
                    let volume = DVec4::from(image.pixels[(y * 40 + x) as usize].map(f64::from));
                    let fogged = fog.over(&ray, f64::INFINITY, background);
                    let pixel = match mode {
                        OpticalMode::Sorted => over(volume, fogged),
                        _ => volume.truncate().extend(0.0) + fogged,
                    };
                    assert!(
                        (pixel - expected).truncate().abs().max_element() < 2e-6,
                        "{mode:?} ({x}, {y}): {pixel} vs {expected}"
                    );
                }
            }
            assert!(pixels.len() > 600, "only {} pixels checked", pixels.len());
        }
    }

    #[test]
    fn opaque_depth_cuts_the_ray() {
        let camera = camera();
        // View depth 6 is the plane z = 0 (the camera looks straight down −z).
        let depth = vec![6.0f32; 40 * 30];
        let volume = ReferenceVolume::Grid(grid(3, |_| 0.5));
        let mut scene = ReferenceScene::new(camera, volume, constant_tf(), OpticalMode::Emissive);
        scene.opaque_depth = Some(depth);
        let image = render(&scene, None).unwrap();
        let mut checked = 0;
        for y in 0..30 {
            for x in 0..40 {
                let Some(chord) = box_chord(&camera, x, y, Some(6.0)) else {
                    continue;
                };
                // Emission only: C = κ ρ L.
                let pixel = image.pixels[(y * 40 + x) as usize];
                assert!(
                    (f64::from(pixel[0]) - 2.0 * chord).abs() < 1e-5,
                    "({x}, {y})"
                );
                checked += 1;
            }
        }
        assert!(checked > 600);
        // A depth before the near plane or the volume hides everything.
        let mut blocked = scene.clone();
        blocked.opaque_depth = Some(vec![0.05; 40 * 30]);
        blocked.background = DVec4::new(0.0, 0.1, 0.0, 1.0);
        let image = render(&blocked, None).unwrap();
        assert!(image.pixels.iter().all(|p| *p == [0.0, 0.1, 0.0, 1.0]));
    }

    #[test]
    fn cell_and_grid_paths_agree_on_a_linear_field() {
        let field = |p: DVec3| 0.5 + 0.2 * p.x - 0.15 * p.y + 0.1 * p.z;
        let density = grid(4, field);
        let cells = density.tetrahedra();
        for mode in [OpticalMode::Sorted, OpticalMode::Emissive, OpticalMode::Mip] {
            let camera = ReferenceCamera {
                position: DVec3::new(2.5, 1.5, 3.5),
                ..camera()
            }
            .looking_at(DVec3::ZERO, DVec3::Y);
            let from_grid = render(
                &ReferenceScene::new(
                    camera,
                    ReferenceVolume::Grid(density.clone()),
                    ramp_tf(),
                    mode,
                ),
                None,
            )
            .unwrap();
            let from_cells = render(
                &ReferenceScene::new(
                    camera,
                    ReferenceVolume::Cells(cells.clone()),
                    ramp_tf(),
                    mode,
                ),
                None,
            )
            .unwrap();
            // MIP opacity depends on how the ray is cut into segments; compare colour.
            let channels = if mode == OpticalMode::Mip { 3 } else { 4 };
            let difference = max_difference(&from_grid, &from_cells, channels);
            assert!(difference < 1e-5, "{mode:?}: {difference}");
            assert!(
                from_grid.pixels.iter().any(|p| p[3] > 0.1),
                "{mode:?}: the volume is visible"
            );
        }
    }

    #[test]
    fn a_constant_modulator_scales_the_optical_density() {
        // ∫_0^{l m} κ ρ e^{−∫ρ} = ∫_0^l κ (ρ m) e^{−∫ρ m}: a constant m is a
        // density scale, for the cell and the grid path alike.
        let density = grid(4, |p: DVec3| 0.5 + 0.3 * (2.0 * p.x).sin() * p.y.cos());
        let cells = density.tetrahedra();
        let camera = ReferenceCamera {
            position: DVec3::new(2.5, 1.5, 3.5),
            ..camera()
        }
        .looking_at(DVec3::ZERO, DVec3::Y);
        let half = grid(4, |_| 0.5);
        let scaled = ramp_tf().scale_density(0.5).unwrap();
        for (volume, modulation) in [
            (
                ReferenceVolume::Cells(cells.clone()),
                Modulation::Cells(vec![[0.5; 4]; cells.len()]),
            ),
            (
                ReferenceVolume::Grid(density.clone()),
                Modulation::Grid(half.clone()),
            ),
        ] {
            let mut modulated =
                ReferenceScene::new(camera, volume.clone(), ramp_tf(), OpticalMode::Sorted);
            modulated.modulation = Some(modulation);
            let expected = ReferenceScene::new(camera, volume, scaled.clone(), OpticalMode::Sorted);
            let (a, b) = (
                render(&modulated, None).unwrap(),
                render(&expected, None).unwrap(),
            );
            assert!(max_difference(&a, &b, 4) < 1e-6);
            assert!(a.pixels.iter().any(|p| p[3] > 0.1));
        }
    }

    #[test]
    fn cell_and_grid_modulation_agree_on_linear_fields() {
        let density = grid(4, |p: DVec3| 0.5 + 0.2 * p.x - 0.15 * p.y + 0.1 * p.z);
        let modulator = grid(4, |p: DVec3| 0.5 - 0.2 * p.x + 0.25 * p.z);
        let cells = density.tetrahedra();
        let modulators = modulator.tetrahedra().iter().map(|t| t.scalars).collect();
        let camera = ReferenceCamera {
            position: DVec3::new(-2.0, 2.5, 3.0),
            ..camera()
        }
        .looking_at(DVec3::ZERO, DVec3::Y);
        let mut from_grid = ReferenceScene::new(
            camera,
            ReferenceVolume::Grid(density),
            ramp_tf(),
            OpticalMode::Sorted,
        );
        from_grid.modulation = Some(Modulation::Grid(modulator));
        let mut from_cells = ReferenceScene::new(
            camera,
            ReferenceVolume::Cells(cells),
            ramp_tf(),
            OpticalMode::Sorted,
        );
        from_cells.modulation = Some(Modulation::Cells(modulators));
        let (a, b) = (
            render(&from_grid, None).unwrap(),
            render(&from_cells, None).unwrap(),
        );
        let unmodulated = render(
            &ReferenceScene {
                modulation: None,
                ..from_cells.clone()
            },
            None,
        )
        .unwrap();
        // The grid path splits rays until the modulator is nearly constant per
        // piece (the continuous model); a cell uses one mean over its whole
        // segment (the GPU's model), which converges to it as cells shrink.
        let finer = |n: usize| {
            let density = grid(n, |p: DVec3| 0.5 + 0.2 * p.x - 0.15 * p.y + 0.1 * p.z);
            let modulator = grid(n, |p: DVec3| 0.5 - 0.2 * p.x + 0.25 * p.z);
            let mut scene = ReferenceScene::new(
                camera,
                ReferenceVolume::Cells(density.tetrahedra()),
                ramp_tf(),
                OpticalMode::Sorted,
            );
            scene.modulation = Some(Modulation::Cells(
                modulator.tetrahedra().iter().map(|t| t.scalars).collect(),
            ));
            render(&scene, None).unwrap()
        };
        let (coarse_error, fine_error) =
            (max_difference(&a, &b, 4), max_difference(&a, &finer(13), 4));
        assert!(coarse_error < 1e-2, "{coarse_error}");
        assert!(
            fine_error < 0.4 * coarse_error,
            "{fine_error} vs {coarse_error}"
        );
        assert!(max_difference(&a, &unmodulated, 4) > 2e-2);

        from_cells.modulation = Some(Modulation::Cells(vec![[1.0; 4]]));
        assert!(matches!(
            render(&from_cells, None),
            Err(ReferenceError::ModulationMismatch { .. })
        ));
    }

    #[test]
    fn nonlinear_grid_converges_with_the_tolerance() {
        // A trilinear field with strong cross terms: the cubic along each ray
        // must be resolved by subdivision.
        let density = grid(3, |p| (0.5 + 0.5 * p.x * p.y * p.z).clamp(0.0, 1.0));
        let render_with = |tolerance| {
            let mut scene = ReferenceScene::new(
                camera(),
                ReferenceVolume::Grid(density.clone()),
                ramp_tf(),
                OpticalMode::Sorted,
            );
            scene.scalar_tolerance = tolerance;
            render(&scene, None).unwrap()
        };
        let (coarse, fine, finest) = (render_with(1e-1), render_with(1e-5), render_with(1e-8));
        assert!(max_difference(&fine, &finest, 4) < 1e-4);
        assert!(max_difference(&coarse, &finest, 4) > max_difference(&fine, &finest, 4));
    }

    #[test]
    fn eye_inside_the_volume_and_progress() {
        let density = grid(5, |p| 0.3 + 0.1 * p.x);
        let cells = density.tetrahedra();
        let camera = ReferenceCamera {
            position: DVec3::new(0.1, 0.05, 0.2),
            width: 20,
            height: 16,
            ..Default::default()
        };
        let from_grid = render(
            &ReferenceScene::new(
                camera,
                ReferenceVolume::Grid(density),
                ramp_tf(),
                OpticalMode::Sorted,
            ),
            None,
        )
        .unwrap();
        let rows = AtomicU32::new(0);
        let count_rows = |p: RenderProgress| {
            assert_eq!(p.rows_total, 16);
            rows.fetch_add(1, Ordering::Relaxed);
        };
        let from_cells = render(
            &ReferenceScene::new(
                camera,
                ReferenceVolume::Cells(cells),
                ramp_tf(),
                OpticalMode::Sorted,
            ),
            Some(&count_rows),
        )
        .unwrap();
        assert_eq!(rows.load(Ordering::Relaxed), 16);
        assert!(max_difference(&from_grid, &from_cells, 4) < 1e-5);
        assert!(
            from_grid
                .pixels
                .iter()
                .all(|p| p[3] > 0.0 && p.iter().all(|c| c.is_finite()))
        );
    }

    /// A grid of one cell over the box `min..max`, the scalar `value` at
    /// every corner.
    fn box_grid(min: DVec3, max: DVec3, value: f32) -> ReferenceVolume {
        ReferenceVolume::Grid(DensityGrid::new([2, 2, 2], max - min, min, vec![value; 8]).unwrap())
    }

    /// The uniform transfer function of colour `kappa`, density `rho`.
    fn uniform_tf(kappa: [f32; 3], rho: f32) -> TransferFunction {
        TransferFunction::new(vec![ControlPoint { s: 0.5, kappa, rho }]).unwrap()
    }

    /// Camera on +z looking down −z at the origin.
    fn axis_camera() -> ReferenceCamera {
        ReferenceCamera {
            position: DVec3::new(0.0, 0.0, 6.0),
            width: 40,
            height: 30,
            vertical_fov: 0.3,
            ..Default::default()
        }
    }

    #[test]
    fn overlapping_volumes_together_match_the_closed_form() {
        // A over z ∈ [−1, 1], B over z ∈ [−2, 0], both |x|, |y| ≤ 1: along a
        // ray A alone, then both, then B alone.
        let (ka, ra) = (DVec3::new(1.0, 0.25, 0.125), 2.0);
        let (kb, rb) = (DVec3::new(0.125, 0.25, 1.0), 0.5);
        let camera = axis_camera();
        let scene = |volume, tf| ReferenceScene::new(camera, volume, tf, OpticalMode::Sorted);
        let a = scene(
            box_grid(DVec3::splat(-1.0), DVec3::splat(1.0), 0.5),
            uniform_tf([1.0, 0.25, 0.125], 2.0),
        );
        let b = scene(
            box_grid(DVec3::new(-1.0, -1.0, -2.0), DVec3::new(1.0, 1.0, 0.0), 0.5),
            uniform_tf([0.125, 0.25, 1.0], 0.5),
        );
        let together = render_together(&[b, a], None).unwrap();
        let segment = |kappa: DVec3, rho: f64, l: f64| {
            let alpha = -(-rho * l).exp_m1();
            (kappa * alpha).extend(alpha)
        };
        let mut checked = 0;
        for (x, y) in (0..camera.height).flat_map(|y| (0..camera.width).map(move |x| (x, y))) {
            let (ray, _) = camera.pixel_ray(x, y);
            let at_z = |z: f64| ray.at((z - ray.origin.z) / ray.direction.z);
            let inside = |p: DVec3| p.x.abs() < 0.99 && p.y.abs() < 0.99;
            if !(inside(at_z(1.0)) && inside(at_z(-2.0))) {
                continue;
            }
            let l = 1.0 / -ray.direction.z;
            let both = segment((ka * ra + kb * rb) / (ra + rb), ra + rb, l);
            let expected = OpticalMode::Sorted.composite(
                segment(ka, ra, l),
                OpticalMode::Sorted.composite(both, segment(kb, rb, l)),
            );
            let pixel =
                DVec4::from(together.pixels[(y * camera.width + x) as usize].map(f64::from));
            assert!(
                (pixel - expected).abs().max_element() < 1e-6,
                "({x}, {y}): {pixel} vs {expected}"
            );
            checked += 1;
        }
        assert!(checked > 100, "only {checked} pixels checked");
    }

    #[test]
    fn a_lit_medium_in_two_overlapping_halves_is_the_whole() {
        // The same box twice at half the density, rendered together, scatters
        // a point and a spot light as the box alone: the joint path sums each
        // medium's in-scattering under their joint transmittance.
        let lights = vec![
            LocalLight::from_lumens(
                DVec3::new(0.3, 0.2, 0.4),
                DVec3::new(1.0, 0.7, 0.4),
                1e5,
                5.0,
            ),
            LocalLight {
                cone: Some(nebel_core::local_light::SpotCone::new(
                    DVec3::NEG_Y,
                    0.2,
                    0.5,
                )),
                ..LocalLight::from_lumens(DVec3::new(-0.2, 2.0, 0.0), DVec3::ONE, 4e5, 8.0)
            },
        ];
        let camera = axis_camera();
        let lit = |tf| {
            let mut scene = ReferenceScene::new(
                camera,
                box_grid(DVec3::splat(-1.0), DVec3::splat(1.0), 0.5),
                tf,
                OpticalMode::Sorted,
            );
            scene.local_lights = lights.clone();
            scene.light_response = LightResponse {
                asymmetry: 0.5,
                strength: 2.0,
            };
            scene
        };
        let whole = render(&lit(uniform_tf([0.5, 0.4, 0.3], 1.5)), None).unwrap();
        let half = || lit(uniform_tf([0.5, 0.4, 0.3], 0.75));
        let together = render_together(&[half(), half()], None).unwrap();
        let unlit = render(
            &ReferenceScene {
                local_lights: Vec::new(),
                ..lit(uniform_tf([0.5, 0.4, 0.3], 1.5))
            },
            None,
        )
        .unwrap();
        assert!(max_difference(&whole, &together, 4) < 1e-5);
        assert!(
            max_difference(&whole, &unlit, 3) > 0.1,
            "the lights add little"
        );
    }

    #[test]
    fn volumes_apart_together_are_each_alone_in_ray_order() {
        // A sorted ramp in front of an emissive ramp and a sorted box: each
        // ray meets them one after the other, so rendering them together is
        // compositing each alone, front to back (the emissive one without
        // opacity), whatever the order they are given in.
        let camera = camera();
        let front = ReferenceScene::new(
            camera,
            ReferenceVolume::Grid(grid(5, |p| (0.5 + 0.4 * p.x * p.y).clamp(0.0, 1.0))),
            ramp_tf(),
            OpticalMode::Sorted,
        );
        let shifted = |z: f64| {
            let ReferenceVolume::Grid(grid) = &front.volume else {
                unreachable!()
            };
            let values = (0..125).map(|i| (i % 7) as f32 / 6.0).collect();
            ReferenceVolume::Grid(
                DensityGrid::new(
                    grid.dims(),
                    grid.spacing(),
                    grid.origin() - DVec3::Z * z,
                    values,
                )
                .unwrap(),
            )
        };
        let emissive = ReferenceScene::new(camera, shifted(2.5), ramp_tf(), OpticalMode::Emissive);
        let back = ReferenceScene::new(camera, shifted(5.0), constant_tf(), OpticalMode::Sorted);
        let together =
            render_together(&[back.clone(), front.clone(), emissive.clone()], None).unwrap();
        let [front, emissive, back] =
            [front, emissive, back].map(|scene| render(&scene, None).unwrap());
        let mut lit = 0;
        for (index, pixel) in together.pixels.iter().enumerate() {
            let at = |image: &LinearImage| DVec4::from(image.pixels[index].map(f64::from));
            let glow = at(&emissive).truncate().extend(0.0);
            let expected = OpticalMode::Sorted
                .composite(at(&front), OpticalMode::Sorted.composite(glow, at(&back)));
            let pixel = DVec4::from(pixel.map(f64::from));
            assert!(
                (pixel - expected).abs().max_element() < 1e-6,
                "pixel {index}: {pixel} vs {expected}"
            );
            lit += usize::from(at(&front).w > 0.01 && glow.max_element() > 0.01);
        }
        assert!(lit > 100, "only {lit} pixels see both");
    }

    #[test]
    fn scenes_that_cannot_go_together_are_refused() {
        let scene = ReferenceScene::new(
            camera(),
            ReferenceVolume::Grid(grid(3, |_| 0.5)),
            constant_tf(),
            OpticalMode::Sorted,
        );
        let refused = |scenes: &[ReferenceScene]| {
            matches!(
                render_together(scenes, None),
                Err(ReferenceError::NotJoint { .. })
            )
        };
        assert!(refused(&[]));
        let mip = ReferenceScene {
            mode: OpticalMode::Mip,
            ..scene.clone()
        };
        assert!(refused(&[scene.clone(), mip]));
        let moved = ReferenceScene {
            camera: ReferenceCamera {
                position: DVec3::ONE,
                ..scene.camera
            },
            ..scene.clone()
        };
        assert!(refused(&[scene.clone(), moved]));
        let grey = ReferenceScene {
            background: DVec4::new(0.1, 0.1, 0.1, 1.0),
            ..scene.clone()
        };
        assert!(refused(&[scene.clone(), grey]));
        assert!(render_together(&[scene.clone(), scene], None).is_ok());
    }

    #[test]
    fn bad_scenes_are_refused() {
        let volume = || ReferenceVolume::Grid(grid(2, |_| 0.5));
        let scene =
            |camera| ReferenceScene::new(camera, volume(), constant_tf(), OpticalMode::Sorted);
        let message = |scene: &ReferenceScene| render(scene, None).unwrap_err().to_string();
        let bad_fov = ReferenceCamera {
            vertical_fov: 0.0,
            ..camera()
        };
        assert!(message(&scene(bad_fov)).contains("vertical_fov"));
        let bad_size = ReferenceCamera {
            width: 0,
            ..camera()
        };
        assert!(message(&scene(bad_size)).contains("0×30"));
        let bad_near = ReferenceCamera {
            near: f64::NAN,
            ..camera()
        };
        assert!(message(&scene(bad_near)).contains("near"));
        let bad_position = ReferenceCamera {
            position: DVec3::INFINITY,
            ..camera()
        };
        assert!(message(&scene(bad_position)).contains("position"));

        let mut short_depth = scene(camera());
        short_depth.opaque_depth = Some(vec![1.0; 5]);
        assert!(message(&short_depth).contains("needs 1200 depth values, found 5"));
        let mut nan_depth = scene(camera());
        let mut depth = vec![f32::INFINITY; 1200];
        depth[41] = f32::NAN;
        nan_depth.opaque_depth = Some(depth);
        assert!(message(&nan_depth).contains("pixel (1, 1)"));
        let mut tolerance = scene(camera());
        tolerance.scalar_tolerance = 0.0;
        assert!(message(&tolerance).contains("scalar_tolerance"));
        let mut background = scene(camera());
        background.background = DVec4::new(0.0, f64::NAN, 0.0, 1.0);
        assert!(message(&background).contains("background"));

        let mut cells = grid(2, |_| 0.5).tetrahedra();
        cells[3].scalars[1] = f64::INFINITY;
        let bad_cells = ReferenceScene::new(
            camera(),
            ReferenceVolume::Cells(cells),
            constant_tf(),
            OpticalMode::Sorted,
        );
        assert!(message(&bad_cells).contains("cell 3"));
        // Degenerate cells are fine and invisible.
        let flat = Tetrahedron {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::X + DVec3::Y],
            scalars: [1.0; 4],
        };
        let image = render(
            &ReferenceScene::new(
                camera(),
                ReferenceVolume::Cells(vec![flat]),
                constant_tf(),
                OpticalMode::Sorted,
            ),
            None,
        )
        .unwrap();
        assert!(image.pixels.iter().all(|p| *p == [0.0; 4]));
    }

    #[test]
    fn an_image_beyond_the_memory_budget_is_refused_before_allocating() {
        let scene = ReferenceScene::new(
            ReferenceCamera {
                width: 100_000,
                height: 100_000,
                ..camera()
            },
            ReferenceVolume::Grid(grid(2, |_| 0.5)),
            constant_tf(),
            OpticalMode::Sorted,
        );
        let error = render(&scene, None).unwrap_err();
        assert!(matches!(error, ReferenceError::OverBudget(_)), "{error}");
        assert!(
            error.to_string().starts_with(
                "linear image of 100000 × 100000 pixels needs 160,000,000,000 bytes (149 GiB)"
            ),
            "{error}"
        );
    }
}

#[cfg(test)]
mod sunlight_tests {
    use std::sync::Arc;

    use glam::{DAffine3, DVec2};
    use nebel_core::field::HeightField;
    use nebel_core::fog_sunlight::{FogColumn, FogSunMap, FogSunlight};
    use nebel_core::transfer::ControlPoint;

    use super::*;

    /// A uniform fog box over |x|, |y|, |z| ≤ 1, lit by a sun through the fog
    /// above each point (the box as a layer from the ground at y = −1 to its
    /// top at 1): each pixel is the box's own segment plus the closed form
    /// of `c ⊙ 4π p_HG ∫ ρ κ e^{−ρ (t − t_in)} e^{−ρ (1 − y(t))/μ} dt`.
    #[test]
    fn a_sunlit_fog_box_matches_the_closed_form() {
        let (kappa, rho) = (DVec3::new(0.5, 0.4, 0.3), 0.5);
        let tf = TransferFunction::new(vec![ControlPoint {
            s: 0.5,
            kappa: [0.5, 0.4, 0.3],
            rho: 0.5,
        }])
        .unwrap();
        let flat = |height: f32| {
            HeightField::new(
                [9, 9],
                DVec2::splat(1.0),
                DVec2::splat(-4.0),
                vec![height; 81],
            )
            .unwrap()
        };
        let sun = DVec3::new(0.6, 0.8, 0.0);
        let column = FogColumn::new(&[[0.0, 1.0], [1.0, 0.0]], &tf);
        let map = FogSunMap::compute(&flat(-1.0), &flat(2.0), column, sun, [9, 9], 1).unwrap();
        let (colour, asymmetry) = (DVec3::new(2.0, 1.5, 1.0), 0.3);
        let camera = ReferenceCamera {
            position: DVec3::new(0.0, 0.0, 6.0),
            width: 24,
            height: 18,
            vertical_fov: 0.3,
            ..Default::default()
        };
        let grid = DensityGrid::new(
            [2, 2, 2],
            DVec3::splat(2.0),
            DVec3::splat(-1.0),
            vec![0.5; 8],
        )
        .unwrap();
        let mut scene =
            ReferenceScene::new(camera, ReferenceVolume::Grid(grid), tf, OpticalMode::Sorted);
        scene.sunlight = Some(FogSunlight {
            map: Arc::new(map),
            map_from_world: DAffine3::IDENTITY,
            direction: sun,
            colour,
            asymmetry,
            clouds: Vec::new(),
            occluders: Vec::new(),
        });
        let image = render(&scene, None).unwrap();
        let mut checked = 0;
        for (x, y) in (0..camera.height).flat_map(|y| (0..camera.width).map(move |x| (x, y))) {
            let (ray, _) = camera.pixel_ray(x, y);
            let (t_in, t_out) = (
                (1.0 - 6.0) / ray.direction.z,
                (-1.0 - 6.0) / ray.direction.z,
            );
            let inside = |t: f64| ray.at(t).x.abs() < 0.99 && ray.at(t).y.abs() < 0.99;
            if !(inside(t_in) && inside(t_out)) {
                continue;
            }
            // e^{C + k t}: the transmittance to the eye and toward the sun.
            let (y0, dy) = (ray.origin.y, ray.direction.y);
            let k = -rho + rho * dy / 0.8;
            let c = rho * t_in - rho * (1.0 - y0) / 0.8;
            let integral = ((c + k * t_out).exp() - (c + k * t_in).exp()) / k;
            let phase = henyey_greenstein(asymmetry, ray.direction.dot(sun));
            let alpha = -(-rho * (t_out - t_in)).exp_m1();
            let expected = kappa * alpha + colour * phase * kappa * rho * integral;
            let pixel = DVec4::from(image.pixels[(y * camera.width + x) as usize].map(f64::from));
            assert!(
                (pixel.truncate() - expected).abs().max_element() < 1e-5,
                "({x}, {y}): {pixel} vs {expected}"
            );
            assert!((pixel.w - alpha).abs() < 1e-6);
            checked += 1;
        }
        assert!(checked > 50, "{checked} pixels through the box");
    }
}
