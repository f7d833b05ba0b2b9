//! Pre-integration tables for cell projection (Röttger 2004 ch. 8-9,
//! Röttger and Ertl 2003 §4): the ray integral of a linear segment looked up instead of
//! integrated, for every optical mode, plus the zero-opacity test.
//!
//! A [`PreintegrationTable`] holds, for one [`TransferFunction`]:
//!
//! - **colour** (3D, Röttger 2004 §8.4 eq. 8.1): premultiplied RGB and α of the sorted
//!   (emission-absorption) segment over `(s_f, s_b, l)`, default 64×64×128,
//!   `l` from 0 to [`PreintegrationConfig::max_length`].
//! - **ρ̂** (2D, Röttger 2004 §9.1.1 eq. 9.1): the exact mean density over `(s_f, s_b)`.
//!   With it opacity is exact in `l`: `α = 1 − exp(−l ρ̂)` (eq. 9.2). Sorted
//!   rendering takes RGB from the 3D table and α from this pair.
//! - **emission** (2D, Röttger 2004 §10.3, PCP): RGB = `∫_0^1 E(s(x)) dx` with `E = κρ`,
//!   so the emissive segment is `C = l · RGB`; A repeats ρ̂ so one fetch gives
//!   the emissive α = `1 − exp(−l A)` too.
//! - **maximum** (2D, MIP): RGB = the per-channel maximum of `E` between `s_f`
//!   and `s_b`, A = the largest ρ there (MIP α = `1 − exp(−l A)`).
//!
//! Every value is the f64 integral of [`crate::segment`] rounded to f32, except
//! the 3D colour, which is integrated by quadrature (below).
//!
//! # Layout and sampling
//!
//! Tables are flat vectors ready for GPU textures, `x` fastest: the 3D table is
//! indexed `(k · n + j) · n + i` and the 2D ones `j · n + i`, with `x = s_f`,
//! `y = s_b`, `z = l`, `n` = [`PreintegrationConfig::scalar_size`] and `m` =
//! [`PreintegrationConfig::length_size`]. Samples sit at the endpoints,
//! inclusive: node `i` holds `s = i / (n − 1)` and node `k` holds
//! `l = k · max_length / (m − 1)`, so `s = 0` and `s = 1` are sampled exactly
//! and `k = 0` is the exact `l = 0` (all zero). Node `i` is the centre of texel
//! `i`, so a shader with linear filtering samples scalar `s` at the texture
//! coordinate `(s · (n − 1) + 0.5) / n` and length `l` at
//! `(l / max_length · (m − 1) + 0.5) / m` (clamped to the edge beyond
//! `max_length`: choose it as the longest segment drawn).
//! [`PreintegrationTable::segment`] emulates exactly that lookup on the CPU.
//!
//! # How the 3D table is built
//!
//! For fixed `(s_f, s_b)` the colour is a Laplace-type integral in `l`:
//! `C(l) = l ∫_0^1 E(x) exp(−l R(x)) dx`, `R(x) = ∫_0^x ρ`. The integral over
//! `x` is done once per pair with 3-point Gauss–Legendre nodes `x_q` on pieces
//! split at the transfer function's control points (so the integrand is smooth
//! per piece) and further split so each holds an optical depth of at most 2
//! at every length for which it is still visible (depth ≤ 11 from the front).
//! Then every length column follows from `exp(−l_k R) = z^k`, `z = exp(−Δl R)`:
//! `C(l_k) = l_k Σ_q w_q E_q z_q^k`, one multiply and three multiply-adds per
//! node and length, nodes dropped once `l_k R_q > 36`. α in the 3D table is
//! the exact `1 − exp(−l ρ̂)`. Pairs are independent and split across threads
//! (`std::thread::scope`).
//!
//! # Accuracy (measured)
//!
//! Measured by [`PreintegrationTable::node_error`] and
//! [`PreintegrationTable::interpolation_error`] (the `optics` bench writes both
//! to `target/nebel/preintegration.csv`; the tests assert them for random
//! transfer functions):
//!
//! - At the nodes, against [`exact_segment`]: the 3D colour is within 1e-4
//!   absolute for κ ≤ 1 (it scales with max κ; measured 1e-6 to 3e-5 for the
//!   presets, 64×64×128, `max_length` 4, optical depth up to 4); the ρ̂,
//!   emission and maximum tables only carry f32 rounding (≤ 3e-8 measured),
//!   so the exact-opacity pair is exact to f32.
//! - Between nodes the error is that of linear interpolation at the table's
//!   resolution and depends on how sharp the transfer function is: for the
//!   presets at 64×64×128 the interpolated sorted colour is off by 2e-4
//!   (ground fog, search light) to 1.4e-2 (cloud, whose ρ steps at its
//!   cut-off); it halves roughly with each doubling of the table.
//! - Build time, 64×64×128, one thread: about 22-25 ms on-CPU on the 2-core
//!   development machine (under load; the `optics` bench reports it).
//!
//! # Zero-opacity test
//!
//! [`PreintegrationTable::is_transparent`] answers from the transfer function's
//! control points ([`TransferFunction::is_transparent`]): exact and
//! conservative for any transfer function.

use std::num::NonZeroUsize;

use glam::{DVec3, DVec4};
use thiserror::Error;

use crate::budget::{BudgetError, Dims, check_bytes};
use crate::optics::{OpticalMode, PremultipliedRgba};
use crate::segment::{Piece, exact_segment, for_each_piece, piece_max_emission};
use crate::transfer::TransferFunction;

/// Largest table side accepted (a 1024³ RGBA f32 table is 16 GiB, beyond the
/// memory budget: the sizes must also pass [`PreintegrationConfig::check_budget`]).
pub const MAX_TABLE_SIDE: u32 = 1024;

/// Optical depth at which a quadrature interval stops being refined: what lies
/// behind it weighs less than e^−11 ≈ 1.7e-5.
const VISIBLE_DEPTH: f64 = 11.0;

/// Largest optical depth of one quadrature interval while it is visible.
const INTERVAL_DEPTH: f64 = 1.5;

/// Optical depth beyond which a quadrature node is dropped (e^−36 ≈ 2e-16).
const NODE_DEPTH: f64 = 36.0;

/// Nodes summed together in the inner loop (vectorizes).
const LANES: usize = 4;

/// 4-point Gauss–Legendre nodes on [0, 1].
const GAUSS_NODES: [f64; 4] = [
    0.069_431_844_202_973_71,
    0.330_009_478_207_571_87,
    0.669_990_521_792_428_1,
    0.930_568_155_797_026_3,
];

/// 4-point Gauss–Legendre weights on [0, 1].
const GAUSS_WEIGHTS: [f64; 4] = [
    0.173_927_422_568_726_93,
    0.326_072_577_431_273_07,
    0.326_072_577_431_273_07,
    0.173_927_422_568_726_93,
];

/// Size of a [`PreintegrationTable`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreintegrationConfig {
    /// Samples along `s_f` and along `s_b`, 2..=[`MAX_TABLE_SIDE`]. Default 64.
    pub scalar_size: u32,
    /// Samples along `l`, 2..=[`MAX_TABLE_SIDE`]. Default 128.
    pub length_size: u32,
    /// The longest segment the 3D table covers, world units, finite and > 0.
    /// Default 1. Longer segments read the colour at this length.
    pub max_length: f32,
}

impl PreintegrationConfig {
    /// The bytes the tables of this size take while they are built, checked
    /// against the memory budget: the 3D colour table (16 bytes per sample)
    /// and the three 2D tables (36 bytes per `(s_f, s_b)` pair), twice, since
    /// the rows are built first and then copied into place. The default size
    /// takes about 16 MiB. Errors name the `pre-integration table of n × n × m
    /// samples`.
    pub fn check_budget(&self) -> Result<u64, BudgetError> {
        let (n, m) = (self.scalar_size as usize, self.length_size as usize);
        let pairs = (n as u128) * (n as u128);
        let colour = size_of::<[f32; 4]>() as u128;
        let pair_bytes = (size_of::<f32>() + 2 * size_of::<[f32; 4]>()) as u128;
        let table = pairs * (colour * m as u128 + pair_bytes);
        check_bytes(
            || format!("pre-integration table of {} samples", Dims(&[n, n, m])),
            2 * table,
        )
    }
}

impl Default for PreintegrationConfig {
    fn default() -> Self {
        Self {
            scalar_size: 64,
            length_size: 128,
            max_length: 1.0,
        }
    }
}

/// Why a [`PreintegrationTable`] could not be built.
#[derive(Debug, Error, PartialEq)]
pub enum PreintegrationError {
    /// A table side is below 2 or above [`MAX_TABLE_SIDE`].
    #[error(
        "pre-integration table size {scalar_size}×{scalar_size}×{length_size} is invalid: each side must be in 2..={MAX_TABLE_SIDE}"
    )]
    InvalidSize {
        /// The requested samples along `s_f` and `s_b`.
        scalar_size: u32,
        /// The requested samples along `l`.
        length_size: u32,
    },
    /// The maximum length is not finite or not positive.
    #[error("pre-integration maximum segment length {max_length} must be finite and > 0")]
    InvalidMaxLength {
        /// The requested maximum length.
        max_length: f32,
    },
    /// The tables of this size would exceed the memory budget; nothing was
    /// allocated.
    #[error(transparent)]
    OverBudget(#[from] BudgetError),
}

/// Largest absolute errors of a table against [`exact_segment`], per table.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TableAccuracy {
    /// 3D table, premultiplied RGB and α of the sorted mode.
    pub colour: f64,
    /// α of the exact-opacity pair (ρ̂ table and `1 − exp(−l ρ̂)`).
    pub opacity: f64,
    /// Emission table RGB, `∫_0^1 E dx` (emission per world unit).
    pub emission: f64,
    /// Maximum table RGB, the largest `E` (emission per world unit).
    pub maximum: f64,
}

/// The pre-integration tables of one transfer function (see the
/// [module docs](self) for contents, layout and accuracy).
#[derive(Clone, Debug)]
pub struct PreintegrationTable {
    config: PreintegrationConfig,
    transfer: TransferFunction,
    colour: Vec<[f32; 4]>,
    rho_hat: Vec<f32>,
    emission: Vec<[f32; 4]>,
    maximum: Vec<[f32; 4]>,
}

/// Everything computed for one row `s_b = j / (n − 1)` of pairs.
struct Row {
    /// The row's 3D colour, `k · n + i` (contiguous runs per length node).
    colour: Vec<[f32; 4]>,
    rho_hat: Vec<f32>,
    emission: Vec<[f32; 4]>,
    maximum: Vec<[f32; 4]>,
}

impl PreintegrationTable {
    /// Builds the tables on all available cores.
    ///
    /// # Errors
    ///
    /// [`PreintegrationError`] for an invalid `config`, or one whose tables
    /// exceed the memory budget ([`PreintegrationConfig::check_budget`]).
    pub fn build(
        tf: &TransferFunction,
        config: PreintegrationConfig,
    ) -> Result<Self, PreintegrationError> {
        let threads = std::thread::available_parallelism().map_or(1, NonZeroUsize::get);
        Self::build_with_threads(tf, config, threads)
    }

    /// Builds the tables on `threads` threads (0 or 1: on the calling thread).
    ///
    /// # Errors
    ///
    /// [`PreintegrationError`] for an invalid `config`, or one whose tables
    /// exceed the memory budget ([`PreintegrationConfig::check_budget`]).
    pub fn build_with_threads(
        tf: &TransferFunction,
        config: PreintegrationConfig,
        threads: usize,
    ) -> Result<Self, PreintegrationError> {
        let sides = [config.scalar_size, config.length_size];
        if sides
            .iter()
            .any(|side| !(2..=MAX_TABLE_SIDE).contains(side))
        {
            return Err(PreintegrationError::InvalidSize {
                scalar_size: config.scalar_size,
                length_size: config.length_size,
            });
        }
        if !(config.max_length.is_finite() && config.max_length > 0.0) {
            return Err(PreintegrationError::InvalidMaxLength {
                max_length: config.max_length,
            });
        }
        config.check_budget()?;
        let n = config.scalar_size as usize;
        let m = config.length_size as usize;
        let pairs = n * n;
        let threads = threads.clamp(1, n);
        let builder = ColumnBuilder::new(tf, config);
        // Thread t builds rows t, t + threads, ... (interleaved for balance).
        let rows: Vec<Vec<Row>> = if threads == 1 {
            vec![(0..n).map(|j| builder.row(j)).collect()]
        } else {
            std::thread::scope(|scope| {
                let workers: Vec<_> = (0..threads)
                    .map(|t| {
                        let builder = &builder;
                        scope.spawn(move || {
                            (t..n)
                                .step_by(threads)
                                .map(|j| builder.row(j))
                                .collect::<Vec<_>>()
                        })
                    })
                    .collect();
                workers
                    .into_iter()
                    .map(|w| w.join().expect("pre-integration worker panicked"))
                    .collect()
            })
        };
        let mut table = Self {
            config,
            transfer: tf.clone(),
            colour: vec![[0.0; 4]; pairs * m],
            rho_hat: vec![0.0; pairs],
            emission: vec![[0.0; 4]; pairs],
            maximum: vec![[0.0; 4]; pairs],
        };
        for (t, worker) in rows.into_iter().enumerate() {
            for (r, row) in worker.into_iter().enumerate() {
                let j = t + r * threads;
                let run = j * n..(j + 1) * n;
                table.rho_hat[run.clone()].copy_from_slice(&row.rho_hat);
                table.emission[run.clone()].copy_from_slice(&row.emission);
                table.maximum[run].copy_from_slice(&row.maximum);
                for (k, slice) in row.colour.chunks_exact(n).enumerate() {
                    let start = k * pairs + j * n;
                    table.colour[start..start + n].copy_from_slice(slice);
                }
            }
        }
        Ok(table)
    }

    /// The size the table was built with.
    pub fn config(&self) -> PreintegrationConfig {
        self.config
    }

    /// [`TransferFunction::content_hash`] of the transfer function the table
    /// was built from: rebuild when the current one differs.
    pub fn transfer_hash(&self) -> u64 {
        self.transfer.content_hash()
    }

    /// The 3D table, premultiplied RGB and α, index `(k · n + j) · n + i`.
    pub fn colour(&self) -> &[[f32; 4]] {
        &self.colour
    }

    /// The 2D ρ̂ table (1/world unit), index `j · n + i`.
    pub fn rho_hat(&self) -> &[f32] {
        &self.rho_hat
    }

    /// The 2D emission table: RGB = `∫_0^1 E dx`, A = ρ̂; index `j · n + i`.
    pub fn emission(&self) -> &[[f32; 4]] {
        &self.emission
    }

    /// The 2D MIP table: RGB = max `E`, A = max ρ; index `j · n + i`.
    pub fn maximum(&self) -> &[[f32; 4]] {
        &self.maximum
    }

    /// The scalar of node `i` along `s_f` or `s_b`: `i / (n − 1)`.
    pub fn scalar_at(&self, i: u32) -> f64 {
        f64::from(i) / f64::from(self.config.scalar_size - 1)
    }

    /// The length of node `k` along `l`: `k · max_length / (m − 1)`.
    pub fn length_at(&self, k: u32) -> f64 {
        f64::from(k) * f64::from(self.config.max_length) / f64::from(self.config.length_size - 1)
    }

    /// Whether ρ is exactly zero on `[s_min, s_max]` (the zero-opacity test;
    /// see [`TransferFunction::is_transparent`]): a cell or octree node whose
    /// scalar range passes contributes nothing in any mode at any length.
    pub fn is_transparent(&self, s_min: f64, s_max: f64) -> bool {
        self.transfer.is_transparent(s_min, s_max)
    }

    /// The segment as the GPU computes it from these tables with linear
    /// filtering: sorted RGB from the 3D table with α from the exact-opacity
    /// pair, emissive `l ·` emission table, MIP maximum table; α is always
    /// `1 − exp(−l A)` with A from the 2D table. Inputs are clamped as in
    /// [`exact_segment`]; `l` beyond `max_length` reads the colour at
    /// `max_length`.
    pub fn segment(
        &self,
        mode: OpticalMode,
        s_front: f64,
        s_back: f64,
        length: f64,
    ) -> PremultipliedRgba {
        let l = crate::segment::sanitize_length(length);
        if l == 0.0 {
            return DVec4::ZERO;
        }
        let (x, y) = (
            self.scalar_coordinate(s_front),
            self.scalar_coordinate(s_back),
        );
        let opacity = |a: f64| -(-l * a).exp_m1();
        match mode {
            OpticalMode::Sorted => {
                let rho_hat = self
                    .bilinear(x, y, |p| DVec4::splat(f64::from(self.rho_hat[p])))
                    .x;
                let z = (l / f64::from(self.config.max_length)).min(1.0)
                    * f64::from(self.config.length_size - 1);
                self.trilinear(x, y, z).truncate().extend(opacity(rho_hat))
            }
            OpticalMode::Emissive => {
                let e = self.bilinear(x, y, |p| DVec4::from(self.emission[p].map(f64::from)));
                (l * e.truncate()).extend(opacity(e.w))
            }
            OpticalMode::Mip => {
                let e = self.bilinear(x, y, |p| DVec4::from(self.maximum[p].map(f64::from)));
                e.truncate().extend(opacity(e.w))
            }
        }
    }

    /// Largest errors at `count` table nodes chosen pseudo-randomly (fixed
    /// seed), against [`exact_segment`] at the node's exact `(s_f, s_b, l)`:
    /// the build error, without interpolation.
    pub fn node_error(&self, count: usize) -> TableAccuracy {
        let (n, m) = (self.config.scalar_size, self.config.length_size);
        let mut random = SplitMix64(0x6e65_6265_6c5f_6e6f);
        let mut accuracy = TableAccuracy::default();
        for _ in 0..count {
            let i = random.below(n);
            let j = random.below(n);
            let k = random.below(m);
            let (s_f, s_b, l) = (self.scalar_at(i), self.scalar_at(j), self.length_at(k));
            let (n, i, j, k) = (n as usize, i as usize, j as usize, k as usize);
            let pair = j * n + i;
            let exact = exact_segment(&self.transfer, OpticalMode::Sorted, s_f, s_b, l);
            let stored = DVec4::from(self.colour[k * n * n + pair].map(f64::from));
            accuracy.colour = accuracy.colour.max((stored - exact).abs().max_element());
            let alpha = -(-l * f64::from(self.rho_hat[pair])).exp_m1();
            accuracy.opacity = accuracy.opacity.max((alpha - exact.w).abs());
            let emissive = exact_segment(&self.transfer, OpticalMode::Emissive, s_f, s_b, 1.0);
            let stored = DVec4::from(self.emission[pair].map(f64::from)).truncate();
            accuracy.emission = accuracy
                .emission
                .max((stored - emissive.truncate()).abs().max_element());
            let mip = exact_segment(&self.transfer, OpticalMode::Mip, s_f, s_b, 1.0);
            let stored = DVec4::from(self.maximum[pair].map(f64::from)).truncate();
            accuracy.maximum = accuracy
                .maximum
                .max((stored - mip.truncate()).abs().max_element());
        }
        accuracy
    }

    /// Largest errors of [`PreintegrationTable::segment`] (the interpolated
    /// lookup) at `count` pseudo-random `(s_f, s_b, l)` with `l` in
    /// `(0, max_length]` (fixed seed), against [`exact_segment`]: the error a
    /// renderer sees, dominated by the table's resolution. Emission and maximum
    /// are compared per unit length (`l = 1`).
    pub fn interpolation_error(&self, count: usize) -> TableAccuracy {
        let mut random = SplitMix64(0x7072_6569_6e74_6567);
        let mut accuracy = TableAccuracy::default();
        let max_length = f64::from(self.config.max_length);
        for _ in 0..count {
            let (s_f, s_b) = (random.unit(), random.unit());
            let l = max_length * (1.0 - random.unit());
            let exact = exact_segment(&self.transfer, OpticalMode::Sorted, s_f, s_b, l);
            let table = self.segment(OpticalMode::Sorted, s_f, s_b, l);
            accuracy.colour = accuracy
                .colour
                .max((table - exact).truncate().abs().max_element());
            accuracy.opacity = accuracy.opacity.max((table.w - exact.w).abs());
            for (mode, error) in [
                (OpticalMode::Emissive, &mut accuracy.emission),
                (OpticalMode::Mip, &mut accuracy.maximum),
            ] {
                let exact = exact_segment(&self.transfer, mode, s_f, s_b, 1.0);
                let table = self.segment(mode, s_f, s_b, 1.0);
                *error = error.max((table - exact).truncate().abs().max_element());
            }
        }
        accuracy
    }

    /// Continuous node coordinate of a scalar, in [0, n − 1].
    fn scalar_coordinate(&self, s: f64) -> f64 {
        crate::segment::sanitize_scalar(s) * f64::from(self.config.scalar_size - 1)
    }

    /// Bilinear interpolation of a 2D table at node coordinates `(x, y)`.
    fn bilinear(&self, x: f64, y: f64, fetch: impl Fn(usize) -> DVec4) -> DVec4 {
        let n = self.config.scalar_size as usize;
        let (x0, tx) = split_coordinate(x, n);
        let (y0, ty) = split_coordinate(y, n);
        let row = |y: usize| fetch(y * n + x0).lerp(fetch(y * n + x0 + 1), tx);
        row(y0).lerp(row(y0 + 1), ty)
    }

    /// Trilinear interpolation of the 3D table at node coordinates.
    fn trilinear(&self, x: f64, y: f64, z: f64) -> DVec4 {
        let n = self.config.scalar_size as usize;
        let m = self.config.length_size as usize;
        let (z0, tz) = split_coordinate(z, m);
        let slice = |k: usize| {
            self.bilinear(x, y, |p| {
                DVec4::from(self.colour[k * n * n + p].map(f64::from))
            })
        };
        slice(z0).lerp(slice(z0 + 1), tz)
    }
}

/// Splits a node coordinate in [0, size − 1] into a cell index in
/// [0, size − 2] and a fraction in [0, 1].
fn split_coordinate(c: f64, size: usize) -> (usize, f64) {
    let last = (size - 2) as f64;
    let cell = c.floor().clamp(0.0, last);
    (cell as usize, (c - cell).clamp(0.0, 1.0))
}

/// Per-table constants shared by all pair computations.
struct ColumnBuilder<'a> {
    tf: &'a TransferFunction,
    n: usize,
    m: usize,
    max_length: f64,
    step: f64,
}

/// Buffers reused from pair to pair: the pieces of a segment and its
/// quadrature nodes (structure of arrays: depth `∫_0^x ρ`, weight times
/// emission per channel, `exp(−Δl · depth)` and its running power).
#[derive(Default)]
struct Scratch {
    pieces: Vec<Piece>,
    depth: Vec<f64>,
    red: Vec<f64>,
    green: Vec<f64>,
    blue: Vec<f64>,
    factor: Vec<f64>,
    power: Vec<f64>,
}

impl<'a> ColumnBuilder<'a> {
    fn new(tf: &'a TransferFunction, config: PreintegrationConfig) -> Self {
        let max_length = f64::from(config.max_length);
        let m = config.length_size as usize;
        Self {
            tf,
            n: config.scalar_size as usize,
            m,
            max_length,
            step: max_length / (m - 1) as f64,
        }
    }

    /// All tables' entries for the row of pairs `s_b = j / (n − 1)`.
    fn row(&self, j: usize) -> Row {
        let mut row = Row {
            colour: vec![[0.0; 4]; self.n * self.m],
            rho_hat: vec![0.0; self.n],
            emission: vec![[0.0; 4]; self.n],
            maximum: vec![[0.0; 4]; self.n],
        };
        let mut scratch = Scratch::default();
        for i in 0..self.n {
            self.column(i, j, &mut row, &mut scratch);
        }
        row
    }

    /// All tables' entries for the pair of nodes `(i, j)`, into its row.
    fn column(&self, i: usize, j: usize, row: &mut Row, scratch: &mut Scratch) {
        let last = (self.n - 1) as f64;
        let (s_f, s_b) = (i as f64 / last, j as f64 / last);
        scratch.pieces.clear();
        for_each_piece(self.tf, s_f, s_b, |p| scratch.pieces.push(p));
        let pieces = &scratch.pieces;
        let rho_hat: f64 = pieces.iter().map(Piece::depth).sum();
        let emission: DVec3 = pieces.iter().map(Piece::emission).sum();
        let maximum = pieces
            .iter()
            .map(piece_max_emission)
            .fold(DVec3::ZERO, DVec3::max);
        let rho_max = pieces
            .iter()
            .map(|p| p.rho0.max(p.rho1))
            .fold(0.0, f64::max);
        row.rho_hat[i] = rho_hat as f32;
        row.emission[i] = emission.extend(rho_hat).as_vec4().to_array();
        row.maximum[i] = maximum.extend(rho_max).as_vec4().to_array();
        let alpha = |k: usize| -(-(k as f64) * self.step * rho_hat).exp_m1();
        if s_f == s_b {
            // One constant piece: C = κ α exactly.
            let kappa = pieces[0].kappa0;
            for k in 0..self.m {
                let a = alpha(k);
                row.colour[k * self.n + i] = (kappa * a).extend(a).as_vec4().to_array();
            }
        } else {
            self.sorted_column(i, row, scratch, alpha);
        }
    }

    /// The sorted colour of pair `i` of a row for every length node, by
    /// quadrature in `x` and powers in `l` (see the module docs).
    fn sorted_column(
        &self,
        i: usize,
        row: &mut Row,
        scratch: &mut Scratch,
        alpha: impl Fn(usize) -> f64,
    ) {
        let Scratch {
            pieces,
            depth,
            red,
            green,
            blue,
            factor,
            power,
        } = scratch;
        self.nodes(pieces, depth, red, green, blue);
        // Pad to whole lanes with zero-weight nodes.
        let count = depth.len();
        let len = count.next_multiple_of(LANES);
        for values in [&mut *red, &mut *green, &mut *blue] {
            values.resize(len, 0.0);
        }
        factor.clear();
        factor.extend(depth.iter().map(|d| (-self.step * d).exp()));
        factor.resize(len, 0.0);
        power.clear();
        power.resize(len, 1.0);
        // Nodes are sorted by depth (built front to back): node q is visible at
        // length node k while k · step · depth_q ≤ NODE_DEPTH.
        let mut active = count;
        row.colour[i] = [0.0; 4];
        for k in 1..self.m {
            let reach = k as f64 * self.step;
            while active > 0 && reach * depth[active - 1] > NODE_DEPTH {
                active -= 1;
            }
            let lanes = active.next_multiple_of(LANES);
            let mut sums = [[0.0; LANES]; 3];
            for q in (0..lanes).step_by(LANES) {
                for lane in 0..LANES {
                    let p = power[q + lane] * factor[q + lane];
                    power[q + lane] = p;
                    sums[0][lane] += red[q + lane] * p;
                    sums[1][lane] += green[q + lane] * p;
                    sums[2][lane] += blue[q + lane] * p;
                }
            }
            let [r, g, b] = sums.map(|s| s.iter().sum::<f64>());
            row.colour[k * self.n + i] = (reach * DVec3::new(r, g, b))
                .extend(alpha(k))
                .as_vec4()
                .to_array();
        }
    }

    /// Gauss–Legendre nodes over the visible part of the segment, on intervals
    /// of optical depth ≤ [`INTERVAL_DEPTH`] at every length that still sees them.
    fn nodes(
        &self,
        pieces: &[Piece],
        depth: &mut Vec<f64>,
        red: &mut Vec<f64>,
        green: &mut Vec<f64>,
        blue: &mut Vec<f64>,
    ) {
        for values in [&mut *depth, &mut *red, &mut *green, &mut *blue] {
            values.clear();
        }
        let mut depth_before = 0.0;
        'pieces: for piece in pieces {
            let piece_depth = piece.depth();
            if piece_depth <= 0.0 {
                continue;
            }
            let width = piece.width();
            let mut u = 0.0;
            while u < width {
                let local = piece.depth_at(u);
                let here = depth_before + local;
                if here * self.step > VISIBLE_DEPTH {
                    break 'pieces;
                }
                let length = if here > 0.0 {
                    self.max_length.min(VISIBLE_DEPTH / here)
                } else {
                    self.max_length
                };
                let target = local + INTERVAL_DEPTH / length;
                let next = if target >= piece_depth {
                    width
                } else {
                    piece
                        .u_at_depth(target)
                        .max(u + f64::EPSILON * width)
                        .min(width)
                };
                let span = next - u;
                for (x, w) in GAUSS_NODES.iter().zip(GAUSS_WEIGHTS) {
                    let at = u + x * span;
                    let (kappa, rho) = piece.at(at);
                    let weighted = kappa * (rho * w * span);
                    red.push(weighted.x);
                    green.push(weighted.y);
                    blue.push(weighted.z);
                    depth.push(depth_before + piece.depth_at(at));
                }
                u = next;
            }
            depth_before += piece_depth;
        }
    }
}

/// A small deterministic generator for reproducible error samples.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in 0..bound.
    fn below(&mut self, bound: u32) -> u32 {
        (self.next() % u64::from(bound)) as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::arbitrary_transfer_function;
    use crate::transfer::{ControlPoint, TransferPreset};
    use proptest::prelude::*;

    fn small() -> PreintegrationConfig {
        PreintegrationConfig {
            scalar_size: 16,
            length_size: 32,
            max_length: 3.0,
        }
    }

    #[test]
    fn presets_meet_the_stated_node_accuracy() {
        for preset in TransferPreset::ALL {
            let tf = TransferFunction::preset(preset);
            let table = PreintegrationTable::build(&tf, small()).unwrap();
            let error = table.node_error(500);
            assert!(error.colour < 1e-4, "{preset:?}: {error:?}");
            assert!(error.opacity < 1e-6, "{preset:?}: {error:?}");
            assert!(
                error.emission < 1e-6 && error.maximum < 1e-6,
                "{preset:?}: {error:?}"
            );
        }
    }

    #[test]
    fn threads_give_identical_tables() {
        let tf = TransferFunction::preset(TransferPreset::Fire);
        let one = PreintegrationTable::build_with_threads(&tf, small(), 1).unwrap();
        let three = PreintegrationTable::build_with_threads(&tf, small(), 3).unwrap();
        assert_eq!(one.colour(), three.colour());
        assert_eq!(one.rho_hat(), three.rho_hat());
        assert_eq!(one.emission(), three.emission());
        assert_eq!(one.maximum(), three.maximum());
        assert_eq!(one.transfer_hash(), tf.content_hash());
    }

    #[test]
    fn layout_and_closed_forms() {
        let tf = TransferFunction::preset(TransferPreset::Cloud);
        let table = PreintegrationTable::build(&tf, small()).unwrap();
        let (n, m) = (16, 32);
        assert_eq!(table.colour().len(), n * n * m);
        // l = 0 slice is exactly zero.
        assert!(table.colour()[..n * n].iter().all(|c| *c == [0.0; 4]));
        // Diagonal: α = 1 − e^{−lρ}, C = κ α, at node (i, i, k).
        for (i, k) in [(3, 5), (15, 31), (9, 1)] {
            let (s, l) = (table.scalar_at(i), table.length_at(k));
            let sample = tf.evaluate(s);
            let alpha = -(-l * sample.rho).exp_m1();
            let stored = table.colour()[(k as usize * n + i as usize) * n + i as usize];
            let expected = (sample.kappa * alpha).extend(alpha).as_vec4().to_array();
            for (a, b) in stored.iter().zip(expected) {
                assert!((a - b).abs() < 1e-6, "{stored:?} {expected:?}");
            }
        }
        // x = s_f, y = s_b: an entry with s_f ≠ s_b matches that orientation.
        let (i, j, k) = (2, 13, 20);
        let stored = table.colour()[(k * n + j) * n + i];
        let exact = exact_segment(
            &tf,
            OpticalMode::Sorted,
            table.scalar_at(i as u32),
            table.scalar_at(j as u32),
            table.length_at(k as u32),
        );
        assert!(
            (DVec4::from(stored.map(f64::from)) - exact)
                .abs()
                .max_element()
                < 1e-4
        );
    }

    #[test]
    fn lookups_clamp_and_stay_finite() {
        let tf = TransferFunction::preset(TransferPreset::Smoke);
        let table = PreintegrationTable::build(&tf, small()).unwrap();
        for mode in [OpticalMode::Sorted, OpticalMode::Emissive, OpticalMode::Mip] {
            for (s_f, s_b, l) in [
                (f64::NAN, 0.5, 1.0),
                (-1.0, 2.0, 1e9),
                (0.5, 0.5, f64::INFINITY),
                (0.3, 0.7, f64::NAN),
            ] {
                let c = table.segment(mode, s_f, s_b, l);
                assert!(c.is_finite() && (0.0..=1.0).contains(&c.w), "{mode:?} {c}");
            }
            assert_eq!(table.segment(mode, 0.3, 0.7, 0.0), DVec4::ZERO);
        }
    }

    #[test]
    fn interpolated_lookups_converge_with_size() {
        let tf = TransferFunction::preset(TransferPreset::GroundFog);
        let coarse = PreintegrationTable::build(&tf, small()).unwrap();
        let fine = PreintegrationTable::build(
            &tf,
            PreintegrationConfig {
                scalar_size: 64,
                length_size: 128,
                ..small()
            },
        )
        .unwrap();
        let (coarse, fine) = (
            coarse.interpolation_error(500),
            fine.interpolation_error(500),
        );
        assert!(fine.colour < coarse.colour, "{coarse:?} {fine:?}");
        assert!(fine.colour < 1e-3, "{fine:?}");
    }

    #[test]
    fn narrow_peak_table_is_a_heaviside_isosurface() {
        // Röttger 2004 §8.13: a thin, dense peak at s = 0.5 between grid nodes of a
        // 17-node table (nodes at multiples of 1/16).
        let point = |s, rho| ControlPoint {
            s,
            kappa: [1.0, 0.2, 0.0],
            rho,
        };
        let tf = TransferFunction::new([
            point(0.0, 0.0),
            point(0.499, 0.0),
            point(0.5, 1e5),
            point(0.501, 0.0),
        ])
        .unwrap();
        let config = PreintegrationConfig {
            scalar_size: 17,
            length_size: 16,
            max_length: 1.0,
        };
        let table = PreintegrationTable::build(&tf, config).unwrap();
        let entry = |i: usize, j: usize, k: usize| table.colour()[(k * 17 + j) * 17 + i];
        for k in 1..16 {
            // Crossing the peak: opaque, the peak's colour.
            let crossing = entry(4, 12, k);
            assert!(crossing[3] > 0.999, "{k}: {crossing:?}");
            assert!((crossing[0] - crossing[3]).abs() < 1e-3, "{crossing:?}");
            assert!(
                (crossing[1] - 0.2 * crossing[3]).abs() < 1e-3,
                "{crossing:?}"
            );
            // Not crossing: transparent.
            assert_eq!(entry(1, 7, k), [0.0; 4]);
            assert_eq!(entry(15, 9, k), [0.0; 4]);
        }
        assert!(table.is_transparent(0.0, 0.49));
        assert!(!table.is_transparent(0.49, 0.6));
    }

    #[test]
    fn zero_opacity_query_is_exact_and_conservative() {
        let tf = TransferFunction::preset(TransferPreset::Cloud);
        let table = PreintegrationTable::build(&tf, small()).unwrap();
        assert!(table.is_transparent(0.0, 0.049));
        assert!(table.is_transparent(0.04, 0.0));
        // The cut-off at s = 0.05_f32: ρ = 0 up to it, > 0 just above it.
        let cut_off = f64::from(0.05_f32);
        assert!(table.is_transparent(0.0, cut_off));
        assert!(!table.is_transparent(0.0, cut_off.next_up()));
        assert!(!table.is_transparent(0.3, 0.4));
        assert!(!table.is_transparent(f64::NAN, 0.01));
    }

    #[test]
    fn invalid_configs_are_errors() {
        let tf = TransferFunction::preset(TransferPreset::Cloud);
        let too_small = PreintegrationConfig {
            scalar_size: 1,
            ..small()
        };
        let error = PreintegrationTable::build(&tf, too_small).unwrap_err();
        assert_eq!(
            error.to_string(),
            "pre-integration table size 1×1×32 is invalid: each side must be in 2..=1024"
        );
        for max_length in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let config = PreintegrationConfig {
                max_length,
                ..small()
            };
            let error = PreintegrationTable::build(&tf, config).unwrap_err();
            assert!(matches!(
                error,
                PreintegrationError::InvalidMaxLength { .. }
            ));
            assert!(error.to_string().contains("must be finite and > 0"));
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        #[test]
        fn random_tables_are_within_stated_error(tf in arbitrary_transfer_function(1..7, 1.0, 3.0), max_length in 0.1_f32..4.0) {
            let config = PreintegrationConfig { scalar_size: 12, length_size: 16, max_length };
            let table = PreintegrationTable::build(&tf, config).unwrap();
            prop_assert!(table.colour().iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
            let error = table.node_error(200);
            prop_assert!(error.colour < 1e-4, "{:?}", error);
            prop_assert!(error.opacity < 1e-6, "{:?}", error);
            // α in [0, 1], monotone in l, colour ≤ α max κ, for every pair.
            let (n, m) = (12, 16);
            let max_kappa = tf.max_chromaticity();
            for p in 0..n * n {
                for k in 1..m {
                    let (a, b) = (table.colour()[(k - 1) * n * n + p], table.colour()[k * n * n + p]);
                    prop_assert!((0.0..=1.0).contains(&b[3]) && b[3] >= a[3]);
                    prop_assert!(b[..3].iter().all(|c| *c <= b[3] * max_kappa + 1e-4));
                }
            }
        }
    }

    #[test]
    fn tables_beyond_the_memory_budget_are_refused_before_allocating() {
        let config = PreintegrationConfig {
            scalar_size: MAX_TABLE_SIDE,
            length_size: MAX_TABLE_SIDE,
            max_length: 1.0,
        };
        let tf = TransferFunction::preset(TransferPreset::Cloud);
        let error = PreintegrationTable::build(&tf, config).unwrap_err();
        let message = error.to_string();
        assert!(
            message.starts_with(
                "pre-integration table of 1024 × 1024 × 1024 samples needs 34,435,235,840 bytes"
            ),
            "{message}"
        );
        assert!(matches!(error, PreintegrationError::OverBudget(_)));
        // The default size: the four tables, twice.
        let default = PreintegrationConfig::default();
        let table = PreintegrationTable::build(&tf, default).unwrap();
        let held = size_of_val(table.colour())
            + size_of_val(table.rho_hat())
            + size_of_val(table.emission())
            + size_of_val(table.maximum());
        assert_eq!(default.check_budget(), Ok(2 * held as u64));
    }
}
