//! The light field γ of a lit cloud, with optional self-shadowing.
//!
//! γ(x, y, z) is the precomputed isotropic light intensity of Röttger and Ertl
//! 2003 §5, the second scalar field of a cloud beside its density `f`: §5.1
//! Eq. 9 lets κ(γ) colour each segment while `f` sets its effective length; γ
//! comes from "standard ambient and diffuse lighting" (§5.2), optionally
//! darkened by the transmittance toward the sun (Nes 2008 §2.2.6, Eq. 2.13:
//! self-shadowing through an attenuation volume swept from the light, §3.4). At
//! every grid point p, with L the unit vector toward the sun,
//!
//! `γ(p) = clamp(ambient · T_sky(p) + diffuse · T_sun(p) · lambert(p), 0, 1)`.
//!
//! **Lambert term.** With ∇f by central differences in world units and the
//! outward normal `n̂ = −∇f / |∇f|`, `lambert = (1 − w) + w · max(0, n̂ · L)`,
//! `w = |∇f| / (|∇f| + g0)`, `g0 = 0.05 / s̄` (`s̄` the geometric mean
//! spacing): 1 where the gradient vanishes (a uniform medium counts as lit),
//! plain Lambert on sharp edges ([`lambert_term`]).
//!
//! **Transmittance.** `T_sun(p) = exp(−τ)`, `τ = σ ∫ f ds` toward the sun to
//! the grid box's boundary (`σ = shadow_extinction`), swept in O(N) over the
//! slices of the axis the sun direction in index units mostly follows, from the
//! sun's side: one step of world length `Δs` to the previous slice,
//! `τ(p) = τ(q) + σ Δs (f(p) + f(q)) / 2` (trapezoid rule), τ(q) and f(q)
//! bilinear there, or a partial step to a side face. Interpolating τ rather
//! than T keeps a uniform slab exact; next to a side face under grazing light
//! the resampling smooths a kink in τ.
//!
//! **Multiple scattering** (optional): Wrenninge, Kulla and Lundqvist 2013's
//! octaves replace `e^{−τ}` by `Σ_k b^k e^{−a^k τ} / Σ_k b^k` over
//! `scattering_octaves` octaves, `a = b = 1/2`: light scattered more than once
//! reaches deeper, so the interiors are not flat (1 at τ = 0; the phase of
//! every octave is the first's).
//!
//! **Sky occlusion** (optional): the ambient sky light is dimmed by the cloud
//! above, `T_sky = e^{−1.66 τ_up}` with `τ_up = σ ∫ f ds` toward the zenith
//! (`sky_direction`, the grid's +y unless the grid is turned) to the box's
//! boundary, swept as the sun's τ is (exact along a grid axis): a
//! plane-parallel layer's diffuse transmittance with Elsasser's diffusivity
//! factor 1.66 for light from the whole sky, so the bases of thick clouds
//! darken. It takes the cloud straight above only, not the sky beside it. 1
//! without the option or without a shadow.
//!
//! The passes run along grid rows in the CPU's vector instructions, equal bit
//! for bit to the pointwise formulas (tests); the Lambert pass shares z-slices
//! among threads, the sweeps run on the calling thread. The derivation of the
//! sweep, its exactness and its limits are in `docs/cloud-field.md` in the
//! repository.

use glam::DVec3;

use super::{DensityGrid, FieldError, SAMPLE_BYTES, Settings, check_points};
use crate::optics::exp_neg;
use crate::pacing::{fill_slices, filled_paced, pace, worker_threads};

/// Density change per voxel at which the Lambert weight `w` is one half.
const GRADIENT_SOFTNESS: f64 = 0.05;

/// The largest optical depth kept: `exp(−800)` is 0 in f64.
const TAU_MAX: f64 = 800.0;

/// Slices of the shadow sweep read and written together when the sweep goes
/// along x: four 64-byte cache lines of f32 values. The 513 × 65 × 513
/// layer's light field with the sun along x took about 0.6 times as long as
/// with one slice at a time (on a 2-core x86-64 machine).
const SWEEP_BLOCK: usize = 64;

/// The most memory the buffers of a block of slices take (12 bytes per
/// point: τ in f64, the density in f32), bytes: fewer slices in a block
/// where the slices are large (26 MB for the 513 × 65 × 513 layer).
const SWEEP_BLOCK_BYTES: usize = 32 << 20;

/// Settings of [`light_field`]: ambient plus diffuse light with an optional
/// self-shadow toward the sun.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudLighting {
    /// Light everywhere, whatever the orientation and the sun's shadow (dimmed
    /// only by the cloud above with [`CloudLighting::sky_occlusion`]), in [0,
    /// 1]. Default 0.3.
    pub ambient: f32,
    /// Weight of the sun's diffuse (Lambert) light, in [0, 1]. Default 0.7.
    pub diffuse: f32,
    /// Direction toward the sun in the grid's frame (grid axes, y up), finite
    /// and non-zero; normalised by [`light_field`]. Default
    /// `normalize(0.4, 1.0, 0.3)`.
    pub sun_direction: DVec3,
    /// Extinction of the light toward the sun: optical depth per world unit at
    /// density 1, ≥ 0. 0 (the default) casts no shadow.
    pub shadow_extinction: f32,
    /// Whether the sun's light is shaded by the density gradient (the Lambert
    /// term above). `false` leaves `γ = ambient + diffuse · T_sun`: with
    /// `ambient = 0, diffuse = 1` the plain transmittance toward the sun, the
    /// light of single scattering (Nes 2008), where the phase function at
    /// the eye, not the gradient, orients the light. Default `true`.
    pub lambert: bool,
    /// Octaves of the multiple-scattering approximation of the sun's light
    /// (module docs), 1 to [`CloudLighting::MAX_SCATTERING_OCTAVES`]; 1 (the
    /// default) is single scattering.
    pub scattering_octaves: u32,
    /// Whether the cloud above a point dims its ambient (sky) light (module
    /// docs). Needs a shadow (`shadow_extinction > 0`). Default `false`.
    pub sky_occlusion: bool,
    /// Direction toward the zenith in the grid's frame, finite and non-zero
    /// (normalised), for [`CloudLighting::sky_occlusion`]: the grid's +y
    /// unless the grid is turned in the world. Default `+Y`.
    pub sky_direction: DVec3,
}

impl Default for CloudLighting {
    fn default() -> Self {
        Self {
            ambient: Self::DEFAULT_AMBIENT,
            diffuse: Self::DEFAULT_DIFFUSE,
            sun_direction: DVec3::new(0.4, 1.0, 0.3).normalize(),
            shadow_extinction: 0.0,
            lambert: true,
            scattering_octaves: 1,
            sky_occlusion: false,
            sky_direction: DVec3::Y,
        }
    }
}

impl CloudLighting {
    /// The default ambient light, 0.3: the shadowed side of a cloud keeps
    /// about a third of full light.
    pub const DEFAULT_AMBIENT: f32 = 0.3;
    /// The default weight of the sun's diffuse light, 0.7 (with the ambient
    /// part, a sunlit point reaches full light).
    pub const DEFAULT_DIFFUSE: f32 = 0.7;
    /// The most octaves of [`CloudLighting::scattering_octaves`].
    pub const MAX_SCATTERING_OCTAVES: u32 = 8;

    /// Ambient and Lambert-shaded diffuse light, shadowed toward
    /// `sun_direction` by `shadow_extinction` (Röttger and Ertl 2003 §5.2;
    /// every other setting as [`CloudLighting::default`]).
    pub fn shaded(
        ambient: f32,
        diffuse: f32,
        sun_direction: DVec3,
        shadow_extinction: f32,
    ) -> Self {
        Self {
            ambient,
            diffuse,
            sun_direction,
            shadow_extinction,
            ..Self::default()
        }
    }

    /// The light field of single scattering (Nes 2008): the plain
    /// transmittance toward the sun in the direction `sun_direction`, with no
    /// ambient part and no Lambert term; the renderer weighs the sun's and
    /// the sky's light per pixel instead.
    pub fn transmittance(sun_direction: DVec3, shadow_extinction: f32) -> Self {
        Self {
            ambient: 0.0,
            diffuse: 1.0,
            sun_direction,
            shadow_extinction,
            lambert: false,
            ..Self::default()
        }
    }

    /// Validates the settings; returns the unit directions toward the sun
    /// and the zenith.
    fn unit_directions(&self, name: &str) -> Result<[DVec3; 2], FieldError> {
        let settings = Settings(name);
        settings.fractions(&[("ambient", self.ambient), ("diffuse", self.diffuse)])?;
        settings.non_negative(&[("shadow_extinction", self.shadow_extinction)])?;
        let octaves = self.scattering_octaves;
        let ok = (1..=Self::MAX_SCATTERING_OCTAVES).contains(&octaves);
        settings.require(ok, "scattering_octaves", octaves, "between 1 and 8")?;
        let unit = |parameter, direction: DVec3| {
            let largest = direction.abs().max_element();
            (direction.is_finite() && largest > 0.0)
                .then(|| (direction / largest).try_normalize())
                .flatten()
                .ok_or_else(|| {
                    let (value, requirement) = (direction.to_string(), "finite and non-zero");
                    FieldError::invalid_parameter(name, parameter, value, requirement)
                })
        };
        Ok([
            unit("sun_direction", self.sun_direction)?,
            unit("sky_direction", self.sky_direction)?,
        ])
    }
}

/// The light intensity γ of Röttger and Ertl 2003 §5 at every point of `grid` (same
/// dimensions, spacing and origin), in [0, 1]; formulas in the module
/// documentation of `field::light`, in short
/// `γ = clamp(ambient · T_sky + diffuse · T_sun · lambert, 0, 1)`. Uses every
/// available core, or only the calling thread when it is paced
/// ([`crate::pacing`]: a yield point after every slice of each pass).
///
/// # Errors
///
/// [`FieldError::InvalidParameter`] naming `ambient`, `diffuse`,
/// `sun_direction`, `shadow_extinction` or `scattering_octaves`;
/// [`FieldError::OverBudget`] when
/// the light field (4 bytes per point, like the grid) exceeds the memory
/// budget, before it is allocated.
pub fn light_field(
    grid: &DensityGrid,
    lighting: &CloudLighting,
) -> Result<DensityGrid, FieldError> {
    light_field_with_threads(grid, lighting, worker_threads())
}

/// [`light_field`] on `threads` threads (0 or 1: on the calling thread); the
/// result does not depend on the number.
///
/// # Errors
///
/// As [`light_field`].
pub fn light_field_with_threads(
    grid: &DensityGrid,
    lighting: &CloudLighting,
    threads: usize,
) -> Result<DensityGrid, FieldError> {
    let name = "light_field";
    let [sun, zenith] = lighting.unit_directions(name)?;
    check_points("light field", &grid.dims(), SAMPLE_BYTES)
        .map_err(FieldError::over_budget(name))?;
    let ambient = f64::from(lighting.ambient);
    let diffuse = f64::from(lighting.diffuse);
    let sigma = f64::from(lighting.shadow_extinction);
    let shadow = sigma > 0.0;
    // The sky's share is added after the sun's when the cloud above dims it.
    let occlude_sky = shadow && lighting.sky_occlusion && ambient > 0.0;
    let [nx, ny, _] = grid.dims();
    let spacing = grid.spacing();
    let values = grid.values();
    let g0 = GRADIENT_SOFTNESS / (spacing.x * spacing.y * spacing.z).cbrt();

    // Lambert pass (and γ itself without a shadow), z-slices per thread.
    let mut out = vec![0.0f32; values.len()];
    let pass = LambertPass {
        grid,
        lambert: lighting.lambert,
        sun,
        g0,
        gamma_weights: (!shadow).then_some([ambient, diffuse]),
    };
    let fill = |first_slice: usize, chunk: &mut [f32]| {
        pulp::Arch::new().dispatch(LambertSlices {
            pass: &pass,
            first_slice,
            chunk,
        });
    };
    fill_slices(&mut out, nx * ny, threads, fill);

    if shadow {
        // The sun's light from the Lambert term: γ = clamp(ambient + diffuse ·
        // T_sun(τ) · lambert), without the sky's share when it is dimmed.
        let octaves = ScatteringOctaves::new(lighting.scattering_octaves);
        let sky = if occlude_sky { 0.0 } else { ambient };
        shade_along(grid, sun, sigma, &mut out, move |lambert, tau| {
            gamma(sky, diffuse, octaves.transmittance(tau) * lambert)
        });
    }
    if occlude_sky {
        // The sky's light through the cloud toward the zenith added to the
        // sun's: clamp(ambient · e^{−1.66 τ} + sun).
        shade_along(grid, zenith, sigma, &mut out, move |sun, tau| {
            gamma(ambient * exp_neg(SKY_DIFFUSIVITY * tau), 1.0, sun)
        });
    }
    DensityGrid::validated(name, grid.dims(), spacing, grid.origin(), out)
}

/// Elsasser's diffusivity factor: a plane-parallel layer of optical depth τ
/// passes about `e^{−1.66 τ}` of the light from a whole sky.
pub const SKY_DIFFUSIVITY: f64 = 1.66;

/// Attenuation `a` and contribution `b` from one octave of multiple
/// scattering to the next (Wrenninge et al. 2013).
const OCTAVE_ATTENUATION: f64 = 0.5;
/// See [`OCTAVE_ATTENUATION`].
const OCTAVE_CONTRIBUTION: f64 = 0.5;

/// The sun's transmittance at an optical depth τ with multiple scattering
/// (Wrenninge et al. 2013): `e^{−τ}` for one octave, over `n` octaves
/// `Σ_{k<n} b^k e^{−a^k τ} / Σ_{k<n} b^k` with `a = b = 1/2` (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScatteringOctaves {
    octaves: u32,
    /// `a^{n−1}`, the last octave's share of τ.
    last_scale: f64,
    /// `b^{n−1} / Σ_k b^k`, the last octave's normalised weight.
    last_weight: f64,
}

impl ScatteringOctaves {
    /// `octaves` octaves, clamped to 1 to
    /// [`CloudLighting::MAX_SCATTERING_OCTAVES`].
    pub fn new(octaves: u32) -> Self {
        let octaves = octaves.clamp(1, CloudLighting::MAX_SCATTERING_OCTAVES);
        let last = octaves as i32 - 1;
        // Σ_{k<n} b^k, a geometric series.
        let b = OCTAVE_CONTRIBUTION;
        let norm = (1.0 - b.powi(octaves as i32)) / (1.0 - b);
        Self {
            octaves,
            last_scale: OCTAVE_ATTENUATION.powi(last),
            last_weight: OCTAVE_CONTRIBUTION.powi(last) / norm,
        }
    }

    /// With `a = b = 1/2`, each octave's transmittance is the square of the
    /// next one's and its weight twice: one exponential, from the last
    /// octave back.
    #[inline(always)]
    pub fn transmittance(self, tau: f64) -> f64 {
        if self.octaves == 1 {
            return exp_neg(tau);
        }
        let mut transmittance = exp_neg(self.last_scale * tau);
        let mut weight = self.last_weight;
        let mut sum = 0.0;
        for _ in 0..self.octaves {
            sum += weight * transmittance;
            transmittance *= transmittance;
            weight *= 1.0 / OCTAVE_CONTRIBUTION;
        }
        sum
    }
}

/// `γ = clamp(ambient + diffuse · lit, 0, 1)` for the product `lit` of the
/// sun's transmittance and the Lambert term.
#[inline(always)]
fn gamma(ambient: f64, diffuse: f64, lit: f64) -> f32 {
    (ambient + diffuse * lit).clamp(0.0, 1.0) as f32
}

/// The light in `out` shaded by the optical depths toward the sun or the
/// zenith of a block of slices of a sweep ([`sweep_optical_depth`]: the
/// slices' τ one after another), in place, compiled for the
/// vector instructions the CPU has: along the rows of a slice where they
/// are contiguous in the grid, else (sweeping along x, where a block's
/// slices are consecutive points of every grid row) along each grid row's
/// run of the block's slices.
struct ShadeSlices<'a, F> {
    out: &'a mut [f32],
    axes: &'a SweepAxes,
    slices: &'a [usize],
    taus: &'a [f64],
    /// The new value from the one in `out` and τ.
    shade: F,
}

/// Shades `out` in place with `shade(value, τ)`, τ the optical depth toward
/// `toward` swept through `grid` ([`ShadeSlices`]).
fn shade_along(
    grid: &DensityGrid,
    toward: DVec3,
    sigma: f64,
    out: &mut [f32],
    shade: impl Fn(f64, f64) -> f32 + Copy,
) {
    let arch = pulp::Arch::new();
    sweep_optical_depth(grid, toward, sigma, |axes, slices, taus| {
        arch.dispatch(ShadeSlices {
            out: &mut *out,
            axes,
            slices,
            taus,
            shade,
        });
    });
}

impl<F: Fn(f64, f64) -> f32> pulp::WithSimd for ShadeSlices<'_, F> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let Self {
            out,
            axes,
            slices,
            taus,
            shade: new_value,
        } = self;
        let shade = |value: &mut f32, tau: f64| *value = new_value(f64::from(*value), tau);
        let [nb, nc] = [axes.dims[axes.b], axes.dims[axes.c]];
        let points = nb * nc;
        if let ([s], 1) = (slices, axes.strides[axes.b]) {
            for (v, taus) in taus.chunks_exact(nb).enumerate() {
                let start = axes.index(*s, 0, v);
                for (value, &tau) in out[start..start + nb].iter_mut().zip(taus) {
                    shade(value, tau);
                }
            }
            pace();
            return;
        }
        // Sweeping along x: the block's slices are consecutive points of
        // every grid row, so each row's run of them is shaded in one loop
        // from its τ gathered out of the slices.
        debug_assert_eq!(axes.strides[axes.a], 1, "only the sweep along x has blocks");
        let first = slices.iter().copied().min().unwrap_or(0);
        let mut row_taus = vec![0.0; slices.len()];
        for v in 0..nc {
            for u in 0..nb {
                let point = u + nb * v;
                for (&s, taus) in slices.iter().zip(taus.chunks_exact(points)) {
                    row_taus[s - first] = taus[point];
                }
                let start = axes.index(first, u, v);
                for (value, &tau) in out[start..][..slices.len()].iter_mut().zip(&row_taus) {
                    shade(value, tau);
                }
            }
            pace();
        }
    }
}

/// The Lambert pass: per point the Lambert term, or γ without a shadow.
struct LambertPass<'a> {
    grid: &'a DensityGrid,
    /// Whether the Lambert term is on (1 everywhere when off).
    lambert: bool,
    sun: DVec3,
    g0: f64,
    /// `[ambient, diffuse]` when the pass writes γ itself (no shadow).
    gamma_weights: Option<[f64; 2]>,
}

/// The [`LambertPass`] over the z-slices from `first_slice` that make up
/// `chunk`, compiled for the vector instructions the CPU has (`pulp`'s
/// runtime dispatch; the same values on every instruction set).
struct LambertSlices<'a> {
    pass: &'a LambertPass<'a>,
    first_slice: usize,
    chunk: &'a mut [f32],
}

impl pulp::WithSimd for LambertSlices<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let LambertPass {
            grid,
            lambert,
            sun,
            g0,
            gamma_weights,
        } = *self.pass;
        let [nx, ny, _] = grid.dims();
        let mut terms = vec![1.0; nx];
        for (dk, slice) in self.chunk.chunks_mut(nx * ny).enumerate() {
            for (j, row) in slice.chunks_mut(nx).enumerate() {
                if lambert {
                    lambert_row(grid, j, self.first_slice + dk, sun, g0, &mut terms);
                }
                for (value, &term) in row.iter_mut().zip(&terms) {
                    *value = match gamma_weights {
                        Some([ambient, diffuse]) => gamma(ambient, diffuse, term),
                        None => term as f32,
                    };
                }
            }
            pace();
        }
    }
}

/// [`lambert`] at every point of the grid row `(·, j, k)` into `terms`, bit
/// for bit: the points with all six neighbours inside the grid in one
/// branch-free loop over the neighbouring rows (central differences), the
/// others through [`lambert`]. Always inlined, so that it is compiled for
/// the instruction set [`LambertSlices`] dispatches to.
#[inline(always)]
fn lambert_row(grid: &DensityGrid, j: usize, k: usize, sun: DVec3, g0: f64, terms: &mut [f64]) {
    let [nx, ny, nz] = grid.dims();
    let interior = nx > 2 && (1..ny - 1).contains(&j) && (1..nz - 1).contains(&k);
    if !interior {
        for (i, term) in terms.iter_mut().enumerate() {
            *term = lambert(grid, [i, j, k], sun, g0);
        }
        return;
    }
    let values = grid.values();
    let row = |j: usize, k: usize| &values[(k * ny + j) * nx..][..nx];
    let (here, below, above, front, back) = (
        row(j, k),
        row(j - 1, k),
        row(j + 1, k),
        row(j, k - 1),
        row(j, k + 1),
    );
    let spacing = grid.spacing();
    // Differences times the reciprocal of their distance: one division per
    // row, not per point (the pointwise term does the same, so the two agree
    // bit for bit).
    let [dx, dy, dz] = [spacing.x, spacing.y, spacing.z].map(|s| 1.0 / (2.0 * s));
    let n = nx - 2;
    let (left, right) = (&here[..n], &here[2..]);
    let (below, above, front, back) = (
        &below[1..][..n],
        &above[1..][..n],
        &front[1..][..n],
        &back[1..][..n],
    );
    for (i, term) in terms[1..][..n].iter_mut().enumerate() {
        let gradient = DVec3::new(
            (f64::from(right[i]) - f64::from(left[i])) * dx,
            (f64::from(above[i]) - f64::from(below[i])) * dy,
            (f64::from(back[i]) - f64::from(front[i])) * dz,
        );
        *term = lambert_term(gradient, sun, g0);
    }
    for i in [0, nx - 1] {
        terms[i] = lambert(grid, [i, j, k], sun, g0);
    }
}

/// `(1 − w) + w · max(0, n̂ · L)` at point `p` (see the module documentation).
fn lambert(grid: &DensityGrid, p: [usize; 3], sun: DVec3, g0: f64) -> f64 {
    let dims = grid.dims();
    let spacing = grid.spacing().to_array();
    let gradient = DVec3::from(std::array::from_fn::<f64, 3, _>(|axis| {
        let n = dims[axis];
        let at = |c: usize| {
            let mut q = p;
            q[axis] = c;
            f64::from(grid.value(q[0], q[1], q[2]))
        };
        let c = p[axis];
        let (lo, hi) = (c.saturating_sub(1), (c + 1).min(n - 1));
        (at(hi) - at(lo)) * (1.0 / ((hi - lo) as f64 * spacing[axis]))
    }));
    lambert_term(gradient, sun, g0)
}

/// `(1 − w) + w · max(0, n̂ · L)` for the density gradient `gradient`, as
/// `(g0 + max(0, −∇f · L)) / (|∇f| + g0)`: with `w = |∇f| / (|∇f| + g0)` and
/// `n̂ · L = −∇f · L / |∇f|` the same value, in one division (exactly 1
/// where the gradient vanishes, as `g0 > 0`).
#[inline(always)]
fn lambert_term(gradient: DVec3, sun: DVec3, g0: f64) -> f64 {
    let lambert = (g0 + (-gradient.dot(sun)).max(0.0)) / (gradient.length() + g0);
    // Only a spacing so large that `g0` underflows, or so small that the
    // gradient overflows, gets to NaN.
    if lambert.is_nan() { 1.0 } else { lambert }
}

/// The axes of the shadow sweep: `a` along which it steps, `b` and `c`
/// spanning each slice, and a slice's points in the order `u + n_b · v`
/// (`u` along `b`, `v` along `c`).
struct SweepAxes {
    a: usize,
    b: usize,
    c: usize,
    /// Flat-index step along each grid axis.
    strides: [usize; 3],
    dims: [usize; 3],
}

impl SweepAxes {
    /// The axis along which the sun direction in index units is largest, and
    /// the other two in order.
    fn new(dims: [usize; 3], sun_in_index_units: [f64; 3]) -> Self {
        let d = sun_in_index_units;
        let a = (0..3)
            .max_by(|&x, &y| d[x].abs().total_cmp(&d[y].abs()))
            .unwrap_or(1);
        let (b, c) = match a {
            0 => (1, 2),
            1 => (0, 2),
            _ => (0, 1),
        };
        Self {
            a,
            b,
            c,
            strides: [1, dims[0], dims[0] * dims[1]],
            dims,
        }
    }

    /// The flat grid index of point `(u, v)` of slice `s`.
    fn index(&self, s: usize, u: usize, v: usize) -> usize {
        s * self.strides[self.a] + u * self.strides[self.b] + v * self.strides[self.c]
    }
}

/// Sweeps the optical depth τ toward the sun (module documentation) a slice
/// of the sweep axis at a time, from the sun's side, and calls
/// `visit(axes, slices, τ)` for each block of consecutive slices with τ at
/// their points (per slice in the slice's order, [`SweepAxes`]): one slice
/// per block, or up to [`SWEEP_BLOCK`] when the sweep goes along x (there a
/// slice's points are a row apart in the grid, and a block reads and writes
/// the points of a cache line together).
///
/// The slices' densities are copied into compact buffers first, so the
/// rows of a slice are contiguous whatever the axis; the points whose step
/// toward the sun lands inside the previous slice with all four bilinear
/// neighbours there (all but a few at the slice's edges) go through one
/// branch-free loop per row, compiled for the vector instructions the CPU
/// has (`pulp`'s runtime dispatch), the others through the same formulas
/// point by point with the neighbours clamped to the grid, or the side-face
/// exit. The same operations in the same order either way, so the values are
/// those of a point-by-point sweep bit for bit.
fn sweep_optical_depth(
    grid: &DensityGrid,
    sun: DVec3,
    sigma: f64,
    mut visit: impl FnMut(&SweepAxes, &[usize], &[f64]),
) {
    let dims = grid.dims();
    let values = grid.values();
    let d = (sun / grid.spacing()).to_array();
    let axes = SweepAxes::new(dims, d);
    let SweepAxes { a, b, c, .. } = axes;
    // Index-space step toward the sun (±1 along a) and its world length.
    let step = d.map(|x| x / d[a].abs());
    let ds = 1.0 / d[a].abs();
    let (na, nb, nc) = (dims[a], dims[b], dims[c]);
    let (lb, lc) = ((nb - 1) as f64, (nc - 1) as f64);
    // The bilinear stencil in the previous slice is the same for every point.
    let (floor_b, floor_c) = (step[b].floor(), step[c].floor());
    let stencil = Stencil {
        fb: step[b] - floor_b,
        fc: step[c] - floor_c,
        half_step: 0.5 * sigma * ds,
    };
    let (floor_b, floor_c) = (floor_b as isize, floor_c as isize);
    // The points u of a row whose step lands inside the previous slice along
    // b (an interval, the same in every row), and of those the ones whose
    // bilinear neighbours u0, u0 + 1 are both in it.
    let interval = |keep: &dyn Fn(usize) -> bool| {
        let first = (0..nb).find(|&u| keep(u));
        let last = (0..nb).rev().find(|&u| keep(u));
        match (first, last) {
            (Some(first), Some(last)) => first..last + 1,
            _ => 0..0,
        }
    };
    let inside_b = interval(&|u| (0.0..=lb).contains(&(u as f64 + step[b])));
    let vector_range = interval(&|u| {
        let u0 = u as isize + floor_b;
        inside_b.contains(&u) && u0 >= 0 && u0 + 1 < nb as isize
    });

    let slices: Vec<usize> = if step[a] > 0.0 {
        (0..na).rev().collect()
    } else {
        (0..na).collect()
    };
    // Where a slice's rows are not contiguous in the grid (sweeping along x)
    // it takes a block of slices to read and write whole cache lines.
    let points = nb * nc;
    let block = if axes.strides[b] == 1 {
        1
    } else {
        (SWEEP_BLOCK_BYTES / (12 * points)).clamp(1, SWEEP_BLOCK.min(na))
    };
    // Slot 0: the last slice of the previous block; then the block's, one
    // after another in one allocation, zeroed a piece at a time (tens of
    // megabytes when sweeping along x).
    let mut taus = filled_paced((block + 1) * points, 0.0f64);
    let mut densities = filled_paced((block + 1) * points, 0.0f32);
    let arch = pulp::Arch::new();
    for (block_index, block) in slices.chunks(block).enumerate() {
        // A row of slots per row of the grid's points: where the sweep goes
        // along x, a row `v` of the block reads the same few cache lines of
        // its grid rows for every slice.
        let stride_b = axes.strides[b];
        for v in 0..nc {
            for (k, &s) in block.iter().enumerate() {
                let slot = &mut densities[(k + 1) * points + nb * v..][..nb];
                let row = axes.index(s, 0, v);
                for (u, density) in slot.iter_mut().enumerate() {
                    *density = values[row + u * stride_b];
                }
            }
            pace();
        }
        for (k, &s) in block.iter().enumerate() {
            let (done, ahead) = taus.split_at_mut((k + 1) * points);
            let (tau_previous, tau_current) = (&done[k * points..], &mut ahead[..points]);
            let (f_previous, f_current) = (
                &densities[k * points..][..points],
                &densities[(k + 1) * points..][..points],
            );
            if block_index == 0 && k == 0 {
                // The sun-side slice: the ray leaves at once.
                tau_current.fill(0.0);
                continue;
            }
            for v in 0..nc {
                let qv = v as f64 + step[c];
                let row = &mut tau_current[nb * v..][..nb];
                if !(0.0..=lc).contains(&qv) {
                    // The whole row leaves through a side face.
                    for (u, tau) in row.iter_mut().enumerate() {
                        *tau =
                            side_exit(grid, &axes, step, [s, u, v], stencil.half_step).min(TAU_MAX);
                    }
                    continue;
                }
                let v0 = (v as isize + floor_c) as usize;
                let v1 = (v0 + 1).min(nc - 1);
                let previous =
                    [v0, v1].map(|v| (&tau_previous[nb * v..][..nb], &f_previous[nb * v..][..nb]));
                let own = &f_current[nb * v..][..nb];
                for u in (0..vector_range.start).chain(vector_range.end..nb) {
                    row[u] = if inside_b.contains(&u) {
                        let u0 = (u as isize + floor_b) as usize;
                        let u1 = (u0 + 1).min(nb - 1);
                        let corners = previous
                            .map(|(tau, f)| [[tau[u0], tau[u1]], [f[u0], f[u1]].map(f64::from)]);
                        stencil.tau(f64::from(own[u]), corners)
                    } else {
                        side_exit(grid, &axes, step, [s, u, v], stencil.half_step)
                    }
                    .min(TAU_MAX);
                }
                if !vector_range.is_empty() {
                    let u0 = (vector_range.start as isize + floor_b) as usize;
                    arch.dispatch(InteriorRow {
                        stencil,
                        previous: previous.map(|(tau, f)| (&tau[u0..], &f[u0..])),
                        own: &own[vector_range.clone()],
                        out: &mut row[vector_range.clone()],
                    });
                }
            }
            pace();
        }
        visit(&axes, block, &taus[points..(block.len() + 1) * points]);
        let last = block.len() * points;
        taus.copy_within(last..last + points, 0);
        densities.copy_within(last..last + points, 0);
    }
}

/// The trapezoid step of the sweep from the previous slice, bilinear there.
#[derive(Clone, Copy)]
struct Stencil {
    /// The step's fractions along `b` and `c` past the lower neighbours.
    fb: f64,
    fc: f64,
    /// `σ Δs / 2`.
    half_step: f64,
}

impl Stencil {
    /// τ at a point of density `own` whose step lands between the previous
    /// slice's points `corners[v][field][u]` (rows `v0`, `v1`; τ then f;
    /// columns `u0`, `u1`), before the cap.
    #[inline(always)]
    fn tau(&self, own: f64, corners: [[[f64; 2]; 2]; 2]) -> f64 {
        let bilinear = |field: usize| {
            let [lo, hi] = corners.map(|row| {
                let [at0, at1] = row[field];
                at0 + (at1 - at0) * self.fb
            });
            lo + (hi - lo) * self.fc
        };
        bilinear(0) + self.half_step * (own + bilinear(1))
    }
}

/// τ (before the cap) at point `(u, v)` of slice `s` whose step toward the
/// sun leaves the box through a side face after the fraction `t` of the
/// step, with f trilinear at the exit point.
fn side_exit(
    grid: &DensityGrid,
    axes: &SweepAxes,
    step: [f64; 3],
    [s, u, v]: [usize; 3],
    half_step: f64,
) -> f64 {
    let SweepAxes { a, b, c, dims, .. } = *axes;
    let (lb, lc) = ((dims[b] - 1) as f64, (dims[c] - 1) as f64);
    let (qu, qv) = (u as f64 + step[b], v as f64 + step[c]);
    let exit = |q: f64, p: usize, last: f64, delta: f64| {
        if q < 0.0 {
            p as f64 / -delta
        } else if q > last {
            (last - p as f64) / delta
        } else {
            1.0
        }
    };
    let t = exit(qu, u, lb, step[b]).min(exit(qv, v, lc, step[c]));
    let mut p = [0.0; 3];
    p[a] = s as f64;
    p[b] = u as f64;
    p[c] = v as f64;
    let e = DVec3::from(p) + DVec3::from(step) * t;
    let fp = f64::from(grid.values()[axes.index(s, u, v)]);
    half_step * t * (fp + grid.sample_grid(e))
}

/// τ along the run of a row whose bilinear neighbours are all inside the
/// previous slice, compiled for the vector instructions the CPU has:
/// `previous[v]` holds τ and f from the first point's `u0` on (rows `v0`,
/// `v1`), `own` the run's densities, `out` gets τ capped.
struct InteriorRow<'a> {
    stencil: Stencil,
    previous: [(&'a [f64], &'a [f32]); 2],
    own: &'a [f32],
    out: &'a mut [f64],
}

impl pulp::WithSimd for InteriorRow<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let n = self.out.len();
        let [(t0, f0), (t1, f1)] = self.previous.map(|(tau, f)| (&tau[..n + 1], &f[..n + 1]));
        // Each point's two neighbours along the row.
        fn pairs<T>(field: &[T]) -> impl Iterator<Item = (&T, &T)> {
            field.iter().zip(&field[1..])
        }
        let rows = pairs(t0).zip(pairs(f0)).zip(pairs(t1).zip(pairs(f1)));
        for ((out, &own), (((&t00, &t01), (&f00, &f01)), ((&t10, &t11), (&f10, &f11)))) in
            self.out.iter_mut().zip(self.own).zip(rows)
        {
            let f = |value: f32| f64::from(value);
            let corners = [
                [[t00, t01], [f(f00), f(f01)]],
                [[t10, t11], [f(f10), f(f11)]],
            ];
            *out = self.stencil.tau(f(own), corners).min(TAU_MAX);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::CloudNoise;
    use crate::test_support::{assert_mentions, error_message};

    fn uniform(dims: [usize; 3], spacing: DVec3, density: f32) -> DensityGrid {
        let n = dims.iter().product();
        DensityGrid::new(dims, spacing, DVec3::new(3.0, -2.0, 1.0), vec![density; n]).unwrap()
    }

    /// The default lighting with a shadow toward the sun.
    fn shadowed() -> CloudLighting {
        CloudLighting {
            shadow_extinction: 0.3,
            ..Default::default()
        }
    }

    fn cloud() -> DensityGrid {
        let noise = CloudNoise {
            seed: 5,
            wavelength: 20.0,
            coverage: 0.7,
            ..Default::default()
        };
        DensityGrid::cloud([25, 13, 19], DVec3::ONE, DVec3::ZERO, &noise, 0.0).unwrap()
    }

    /// World distance from `p` along the unit `sun` to the box's boundary.
    fn exit_distance(grid: &DensityGrid, p: DVec3, sun: DVec3) -> f64 {
        let (lo, hi) = (grid.origin(), grid.max_corner());
        (0..3)
            .filter(|&axis| sun[axis] != 0.0)
            .map(|axis| {
                let bound = if sun[axis] > 0.0 { hi[axis] } else { lo[axis] };
                (bound - p[axis]) / sun[axis]
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// Whether the sweep's domain of dependence from grid point `p` stays
    /// inside the box until the ray leaves through the sun-side face of the
    /// sweep axis: there the slab's optical depth is the same over every slice
    /// the sweep reads, and bilinear resampling is exact.
    fn clear_of_side_faces(grid: &DensityGrid, p: [usize; 3], sun: DVec3) -> bool {
        let dims = grid.dims();
        let d = (sun / grid.spacing()).to_array();
        let a = (0..3)
            .max_by(|&x, &y| d[x].abs().total_cmp(&d[y].abs()))
            .unwrap();
        let steps = if d[a] > 0.0 { dims[a] - 1 - p[a] } else { p[a] } as f64;
        (0..3).filter(|&axis| axis != a).all(|axis| {
            let delta = d[axis] / d[a].abs();
            let reach = |offset: f64| p[axis] as f64 + steps * offset;
            let (lo, hi) = (reach(delta.floor()), reach(delta.ceil()));
            lo >= 0.0 && hi <= (dims[axis] - 1) as f64
        })
    }

    /// Largest |γ − closed form| for a density slab f = 1 over the points
    /// [`clear_of_side_faces`], and their number.
    fn slab_error(dims: [usize; 3], spacing: DVec3, sun: DVec3, sigma: f32) -> (f64, usize) {
        let grid = uniform(dims, spacing, 1.0);
        let lighting = CloudLighting {
            ambient: 0.2,
            diffuse: 0.8,
            sun_direction: sun,
            shadow_extinction: sigma,
            lambert: true,
            ..CloudLighting::default()
        };
        let light = light_field(&grid, &lighting).unwrap();
        let sun = sun.normalize();
        let (mut largest, mut count) = (0.0f64, 0);
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    if !clear_of_side_faces(&grid, [i, j, k], sun) {
                        continue;
                    }
                    let p =
                        grid.origin() + DVec3::new(i as f64, j as f64, k as f64) * grid.spacing();
                    let transmittance = (-f64::from(sigma) * exit_distance(&grid, p, sun)).exp();
                    let expected = 0.2 + 0.8 * transmittance;
                    largest = largest.max((f64::from(light.value(i, j, k)) - expected).abs());
                    count += 1;
                }
            }
        }
        (largest, count)
    }

    /// The sweep of the module documentation point by point, straight from
    /// its formulas: τ at every grid index.
    fn pointwise_optical_depth(grid: &DensityGrid, sun: DVec3, sigma: f64) -> Vec<f64> {
        let dims = grid.dims();
        let axes = SweepAxes::new(dims, (sun / grid.spacing()).to_array());
        let SweepAxes { a, b, c, .. } = axes;
        let d = (sun / grid.spacing()).to_array();
        let step = d.map(|x| x / d[a].abs());
        let ds = 1.0 / d[a].abs();
        let half_step = 0.5 * sigma * ds;
        let (nb, nc) = (dims[b], dims[c]);
        let (lb, lc) = ((nb - 1) as f64, (nc - 1) as f64);
        let (floor_b, floor_c) = (step[b].floor(), step[c].floor());
        let (fb, fc) = (step[b] - floor_b, step[c] - floor_c);
        let f = |s: usize, u: usize, v: usize| f64::from(grid.values()[axes.index(s, u, v)]);
        let mut tau = vec![0.0; grid.values().len()];
        let slices: Vec<usize> = if step[a] > 0.0 {
            (0..dims[a]).rev().collect()
        } else {
            (0..dims[a]).collect()
        };
        for pair in slices.windows(2) {
            let (previous, s) = (pair[0], pair[1]);
            for v in 0..nc {
                for u in 0..nb {
                    let (qu, qv) = (u as f64 + step[b], v as f64 + step[c]);
                    let value = if (0.0..=lb).contains(&qu) && (0.0..=lc).contains(&qv) {
                        let u0 = (u as isize + floor_b as isize) as usize;
                        let v0 = (v as isize + floor_c as isize) as usize;
                        let (u1, v1) = ((u0 + 1).min(nb - 1), (v0 + 1).min(nc - 1));
                        let bilinear = |at: &dyn Fn(usize, usize) -> f64| {
                            let lo = at(u0, v0) + (at(u1, v0) - at(u0, v0)) * fb;
                            let hi = at(u0, v1) + (at(u1, v1) - at(u0, v1)) * fb;
                            lo + (hi - lo) * fc
                        };
                        let tau_q = bilinear(&|u, v| tau[axes.index(previous, u, v)]);
                        let f_q = bilinear(&|u, v| f(previous, u, v));
                        tau_q + half_step * (f(s, u, v) + f_q)
                    } else {
                        side_exit(grid, &axes, step, [s, u, v], half_step)
                    };
                    tau[axes.index(s, u, v)] = value.min(TAU_MAX);
                }
            }
        }
        tau
    }

    /// A grid `long` points along `long_axis` and `short` along the others,
    /// its values `levels` in a scrambled repeating order, with `spacing`.
    fn long_grid(
        long_axis: usize,
        long: usize,
        short: [usize; 2],
        levels: &[f32],
        spacing: [f64; 3],
    ) -> DensityGrid {
        let mut dims = [short[0], short[1], short[0]];
        dims[long_axis] = long;
        dims[(long_axis + 1) % 3] = short[1];
        let n: usize = dims.iter().product();
        let values = (0..n)
            .map(|i| levels[(i * 7 + i / 5) % levels.len()])
            .collect();
        DensityGrid::new(dims, DVec3::from(spacing), DVec3::ZERO, values).unwrap()
    }

    proptest::proptest! {
        /// Sweeps along each axis, either way, grazing and steep, over
        /// grids longer than a block of slices along x, with plateaus and
        /// steps: τ equals the point-by-point sweep bit for bit.
        #[test]
        fn the_sweep_equals_the_pointwise_sweep_bit_for_bit(
            long_axis in 0usize..3,
            long in 2usize..(SWEEP_BLOCK * 2 + 8),
            short in proptest::array::uniform2(2usize..6),
            levels in proptest::collection::vec(proptest::prop_oneof![proptest::strategy::Just(0.0f32), proptest::strategy::Just(0.5), 0.0f32..1.0], 64),
            spacing in proptest::array::uniform3(1e-2f64..50.0),
            sun in proptest::array::uniform3(-1.0f64..1.0),
            sigma in 1e-3f64..5.0,
        ) {
            let grid = long_grid(long_axis, long, short, &levels, spacing);
            let (dims, n) = (grid.dims(), grid.values().len());
            let sun = DVec3::from(sun).normalize_or(DVec3::Y);
            let expected = pointwise_optical_depth(&grid, sun, sigma);
            let mut swept = vec![f64::NAN; n];
            sweep_optical_depth(&grid, sun, sigma, |axes, slices, taus| {
                let points = axes.dims[axes.b] * axes.dims[axes.c];
                for (&s, taus) in slices.iter().zip(taus.chunks_exact(points)) {
                    for v in 0..axes.dims[axes.c] {
                        for u in 0..axes.dims[axes.b] {
                            swept[axes.index(s, u, v)] = taus[u + axes.dims[axes.b] * v];
                        }
                    }
                }
            });
            for (index, (tau, expected)) in swept.iter().zip(&expected).enumerate() {
                proptest::prop_assert_eq!(tau.to_bits(), expected.to_bits(), "point {} of {:?}", index, dims);
            }
        }

        /// The plain transmittance (no ambient, no Lambert term) of the whole
        /// light field, shaded through `exp_neg` a row or a block of slices
        /// at a time, is within one f32 step of `exp(−τ)` by the library on
        /// the point-by-point sweep's τ.
        #[test]
        fn the_transmittance_is_the_library_exponential_to_one_f32_step(
            long_axis in 0usize..3,
            long in 2usize..(SWEEP_BLOCK + 40),
            short in proptest::array::uniform2(2usize..6),
            levels in proptest::collection::vec(0.0f32..1.0, 64),
            spacing in proptest::array::uniform3(1e-2f64..50.0),
            sun in proptest::array::uniform3(-1.0f64..1.0),
            sigma in 1e-3f32..5.0,
        ) {
            let grid = long_grid(long_axis, long, short, &levels, spacing);
            let dims = grid.dims();
            let sun = DVec3::from(sun).normalize_or(DVec3::Y);
            let light = light_field(&grid, &CloudLighting::transmittance(sun, sigma)).unwrap();
            let taus = pointwise_optical_depth(&grid, sun.normalize(), f64::from(sigma));
            for (index, (&gamma, &tau)) in light.values().iter().zip(&taus).enumerate() {
                let expected = (-tau).exp() as f32;
                let steps = gamma.to_bits().abs_diff(expected.to_bits());
                proptest::prop_assert!(steps <= 1, "point {} of {:?}: {} against {}", index, dims, gamma, expected);
            }
        }

        /// Rows through the interior and along every face of small grids
        /// with plateaus (zero gradients) and steps, any spacing and sun.
        #[test]
        fn lambert_rows_equal_the_pointwise_lambert_term_bit_for_bit(
            dims in proptest::array::uniform3(2usize..7),
            levels in proptest::collection::vec(proptest::prop_oneof![proptest::strategy::Just(0.0f32), proptest::strategy::Just(0.5), 0.0f32..1.0], 216),
            spacing in proptest::array::uniform3(1e-3f64..50.0),
            sun in proptest::array::uniform3(-1.0f64..1.0),
            g0 in 1e-4f64..10.0,
        ) {
            let n: usize = dims.iter().product();
            let grid = DensityGrid::new(dims, DVec3::from(spacing), DVec3::ZERO, levels[..n].to_vec()).unwrap();
            let sun = DVec3::from(sun).normalize_or(DVec3::Y);
            let mut terms = vec![0.0; dims[0]];
            for k in 0..dims[2] {
                for j in 0..dims[1] {
                    lambert_row(&grid, j, k, sun, g0, &mut terms);
                    for (i, term) in terms.iter().enumerate() {
                        let expected = lambert(&grid, [i, j, k], sun, g0);
                        proptest::prop_assert_eq!(term.to_bits(), expected.to_bits(), "point ({}, {}, {})", i, j, k);
                    }
                }
            }
        }
    }

    #[test]
    fn ambient_only_is_constant() {
        let lighting = CloudLighting {
            ambient: 0.35,
            diffuse: 0.0,
            shadow_extinction: 0.8,
            ..Default::default()
        };
        let grid = cloud();
        let light = light_field(&grid, &lighting).unwrap();
        assert_eq!(light.dims(), grid.dims());
        assert_eq!(light.spacing(), grid.spacing());
        assert_eq!(light.origin(), grid.origin());
        assert!(light.values().iter().all(|&g| g == 0.35));
    }

    #[test]
    fn a_uniform_medium_without_shadow_is_fully_lit() {
        let lighting = CloudLighting {
            ambient: 0.2,
            diffuse: 0.5,
            ..Default::default()
        };
        let light = light_field(&uniform([5, 4, 6], DVec3::ONE, 0.6), &lighting).unwrap();
        assert!(light.values().iter().all(|&g| (g - 0.7).abs() < 1e-6));
    }

    #[test]
    fn slab_shadow_matches_the_closed_form() {
        // Sun straight up: T = exp(−σ (top − y)).
        let dims = [7, 21, 6];
        let grid = uniform(dims, DVec3::splat(0.5), 1.0);
        let lighting = CloudLighting {
            ambient: 0.2,
            diffuse: 0.8,
            sun_direction: DVec3::new(0.0, 3.0, 0.0),
            shadow_extinction: 0.4,
            lambert: true,
            ..CloudLighting::default()
        };
        let light = light_field(&grid, &lighting).unwrap();
        let top = grid.max_corner().y;
        for j in 0..dims[1] {
            let y = grid.origin().y + j as f64 * 0.5;
            let expected = 0.2 + 0.8 * (-0.4 * (top - y)).exp();
            for (i, k) in [(0, 0), (3, 2), (6, 5)] {
                let got = f64::from(light.value(i, j, k));
                assert!((got - expected).abs() < 1e-3, "j {j}: {got} vs {expected}");
            }
        }
        // Oblique sun through the top: the path is longer by 1 / cos θ. The box
        // is wide enough that no ray the sweep follows from column (0, ·, 24)
        // leaves through a side.
        let dims = [25, 21, 25];
        let grid = uniform(dims, DVec3::splat(0.5), 1.0);
        let top = grid.max_corner().y;
        let sun = DVec3::new(0.3, 1.0, -0.2).normalize();
        let light = light_field(
            &grid,
            &CloudLighting {
                sun_direction: sun,
                ..lighting
            },
        )
        .unwrap();
        for j in 0..dims[1] {
            let y = grid.origin().y + j as f64 * 0.5;
            let expected = 0.2 + 0.8 * (-0.4 * (top - y) / sun.y).exp();
            // x rises and z falls toward the sun.
            let got = f64::from(light.value(0, j, 24));
            assert!((got - expected).abs() < 1e-3, "j {j}: {got} vs {expected}");
        }
        let (error, count) = slab_error(dims, DVec3::splat(0.5), sun, 0.4);
        assert!(error < 1e-3 && count > 1000, "{error} over {count} points");
    }

    #[test]
    fn octaves_and_sky_occlusion_match_their_closed_forms_in_a_slab() {
        // Sun straight up: τ = σ (top − y) toward the sun and up the column.
        let dims = [6, 21, 5];
        let grid = uniform(dims, DVec3::new(0.7, 0.5, 1.3), 1.0);
        let top = grid.max_corner().y;
        for (octaves, sky_occlusion) in [(1, true), (3, false), (4, true), (8, true)] {
            let lighting = CloudLighting {
                ambient: 0.3,
                diffuse: 0.7,
                sun_direction: DVec3::Y,
                shadow_extinction: 0.4,
                scattering_octaves: octaves,
                sky_occlusion,
                ..CloudLighting::default()
            };
            let light = light_field_with_threads(&grid, &lighting, 2).unwrap();
            for j in 0..dims[1] {
                let tau = 0.4 * (top - (grid.origin().y + j as f64 * 0.5));
                // Σ_k 2^−k e^{−2^−k τ} / Σ_k 2^−k, written out.
                let (sum, norm) = (0..octaves).fold((0.0, 0.0), |(sum, norm), k| {
                    let b = 0.5f64.powi(k as i32);
                    (sum + b * (-b * tau).exp(), norm + b)
                });
                let sky = if sky_occlusion {
                    (-1.66 * tau).exp()
                } else {
                    1.0
                };
                let expected = 0.3 * sky + 0.7 * sum / norm;
                for (i, k) in [(0, 0), (3, 2), (5, 4)] {
                    let got = f64::from(light.value(i, j, k));
                    assert!(
                        (got - expected).abs() < 1e-3,
                        "{octaves} octaves, sky {sky_occlusion}, j {j}: {got} vs {expected}"
                    );
                }
            }
        }
        // An oblique sun through the top: the sun's path is longer by
        // 1 / cos θ, the sky's is still straight up. Column (0, ·, 24) sees
        // no side face toward the sun (as in the slab shadow test).
        let dims = [25, 21, 25];
        let grid = uniform(dims, DVec3::splat(0.5), 1.0);
        let top = grid.max_corner().y;
        let sun = DVec3::new(0.3, 1.0, -0.2).normalize();
        let lighting = CloudLighting {
            ambient: 0.3,
            diffuse: 0.7,
            sun_direction: sun,
            shadow_extinction: 0.4,
            scattering_octaves: 2,
            sky_occlusion: true,
            ..CloudLighting::default()
        };
        let light = light_field(&grid, &lighting).unwrap();
        for j in 0..dims[1] {
            let up = 0.4 * (top - (grid.origin().y + j as f64 * 0.5));
            let toward_sun = up / sun.y;
            let sun_light = ((-toward_sun).exp() + 0.5 * (-0.5 * toward_sun).exp()) / 1.5;
            let expected = 0.3 * (-1.66 * up).exp() + 0.7 * sun_light;
            let got = f64::from(light.value(0, j, 24));
            assert!((got - expected).abs() < 1e-3, "j {j}: {got} vs {expected}");
        }
        // A grid turned in the world: its zenith is its +x, the sun its +y.
        let dims = [9, 11, 5];
        let grid = uniform(dims, DVec3::splat(0.5), 1.0);
        let lighting = CloudLighting {
            sun_direction: DVec3::Y,
            sky_direction: DVec3::new(2.0, 0.0, 0.0),
            ..lighting
        };
        let light = light_field(&grid, &lighting).unwrap();
        let max = grid.max_corner();
        for (i, j, k) in [(0, 0, 0), (4, 7, 2), (8, 3, 4), (2, 10, 1)] {
            let p = grid.origin() + DVec3::new(i as f64, j as f64, k as f64) * 0.5;
            let (up, toward_sun) = (0.4 * (max.x - p.x), 0.4 * (max.y - p.y));
            let sun_light = ((-toward_sun).exp() + 0.5 * (-0.5 * toward_sun).exp()) / 1.5;
            let expected = 0.3 * (-1.66 * up).exp() + 0.7 * sun_light;
            let got = f64::from(light.value(i, j, k));
            assert!(
                (got - expected).abs() < 1e-3,
                "({i}, {j}, {k}): {got} vs {expected}"
            );
        }
    }

    #[test]
    fn more_octaves_light_deeper_and_the_cloud_above_darkens_the_sky() {
        let (grid, lighting) = (cloud(), shadowed());
        let light = |lighting: CloudLighting| light_field(&grid, &lighting).unwrap();
        let single = light(lighting);
        let multiple = light(CloudLighting {
            scattering_octaves: 4,
            ..lighting
        });
        let occluded = light(CloudLighting {
            sky_occlusion: true,
            ..lighting
        });
        let [nx, ny, nz] = grid.dims();
        let mut darker = 0;
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let [s, m, o] = [&single, &multiple, &occluded].map(|l| l.value(i, j, k));
                    assert!(m >= s, "octaves only add light: ({i}, {j}, {k})");
                    // The sun's share is rounded to f32 before the sky's is
                    // added: a unit in the last place.
                    let ulp = 1e-6;
                    assert!(
                        o <= s + ulp,
                        "the cloud above only dims the sky: ({i}, {j}, {k})"
                    );
                    if j == ny - 1 {
                        assert!((o - s).abs() <= ulp, "nothing above the top layer");
                    }
                    darker += usize::from(o < s - 0.05);
                }
            }
        }
        assert!(darker > 0, "some points lie under the cloud");
        // Threads do not change either.
        let both = CloudLighting {
            scattering_octaves: 3,
            sky_occlusion: true,
            ..lighting
        };
        let one = light_field_with_threads(&grid, &both, 1).unwrap();
        assert_eq!(one, light_field_with_threads(&grid, &both, 3).unwrap());
    }

    #[test]
    fn sun_from_below_reverses_the_shadow() {
        let dims = [5, 17, 5];
        let grid = uniform(dims, DVec3::ONE, 1.0);
        let lighting = CloudLighting {
            ambient: 0.1,
            diffuse: 0.9,
            sun_direction: DVec3::NEG_Y,
            shadow_extinction: 0.25,
            lambert: true,
            ..CloudLighting::default()
        };
        let light = light_field(&grid, &lighting).unwrap();
        for j in 0..dims[1] {
            let expected = 0.1 + 0.9 * (-0.25 * j as f64).exp();
            let got = f64::from(light.value(2, j, 2));
            assert!((got - expected).abs() < 1e-3, "j {j}: {got} vs {expected}");
        }
        assert!(light.value(2, 0, 2) > light.value(2, 16, 2));
    }

    #[test]
    fn anisotropic_spacing_matches_the_closed_form() {
        // Sweeps along each axis: the index-space direction d = L / spacing
        // decides, not the world direction.
        for (spacing, sun) in [
            (DVec3::new(2.0, 0.25, 1.0), DVec3::new(0.6, 0.5, 0.3)),
            (DVec3::new(0.25, 2.0, 1.0), DVec3::new(0.6, 0.5, 0.3)),
            (DVec3::new(1.5, 1.0, 0.2), DVec3::new(-0.4, 0.3, -0.5)),
            (DVec3::new(0.5, 0.75, 1.0), DVec3::new(0.0, 0.0, 1.0)),
        ] {
            let (error, count) = slab_error([25, 23, 21], spacing, sun, 0.3);
            assert!(
                error < 1e-3 && count > 500,
                "spacing {spacing}, sun {sun}: {error} over {count} points"
            );
        }
    }

    #[test]
    fn lambert_on_a_linear_ramp_matches_the_closed_form() {
        // f = 0.04 i with spacing 0.5 along x: |∇f| = 0.08 per world unit,
        // g0 = 0.05 / ∛(0.5 · 2 · 1) = 0.05, outward normal −x.
        let dims = [11, 4, 3];
        let spacing = DVec3::new(0.5, 2.0, 1.0);
        let mut values = Vec::new();
        for _k in 0..dims[2] {
            for _j in 0..dims[1] {
                for i in 0..dims[0] {
                    values.push(0.04 * i as f32);
                }
            }
        }
        let grid = DensityGrid::new(dims, spacing, DVec3::ZERO, values).unwrap();
        let w = 0.08 / (0.08 + 0.05);
        for (sun, lambert) in [
            (DVec3::NEG_X, 1.0),
            (DVec3::X, 1.0 - w),
            (DVec3::Y, 1.0 - w),
            (DVec3::new(-1.0, 1.0, 0.0), 1.0 - w + w * 0.5f64.sqrt()),
        ] {
            let lighting = CloudLighting {
                ambient: 0.1,
                diffuse: 0.8,
                sun_direction: sun,
                shadow_extinction: 0.0,
                lambert: true,
                ..CloudLighting::default()
            };
            let unshaded = light_field(
                &grid,
                &CloudLighting {
                    lambert: false,
                    ..lighting
                },
            )
            .unwrap();
            assert!(
                unshaded
                    .values()
                    .iter()
                    .all(|&g| (f64::from(g) - 0.9).abs() < 1e-6),
                "without the Lambert term the sun lights every point fully"
            );
            let light = light_field(&grid, &lighting).unwrap();
            let expected = 0.1 + 0.8 * lambert;
            assert!(
                light
                    .values()
                    .iter()
                    .all(|&g| (f64::from(g) - expected).abs() < 1e-5),
                "sun {sun}: expected {expected}, found {:?}",
                &light.values()[..3]
            );
        }
    }

    #[test]
    fn the_lit_side_of_a_ball_is_brighter() {
        let n = 33;
        let mut values = Vec::new();
        for k in 0..n {
            for j in 0..n {
                for i in 0..n {
                    let r = DVec3::new(i as f64, j as f64, k as f64).distance(DVec3::splat(16.0));
                    values.push(((12.0 - r) / 6.0).clamp(0.0, 1.0) as f32);
                }
            }
        }
        let grid = DensityGrid::new([n; 3], DVec3::splat(0.5), DVec3::ZERO, values).unwrap();
        let sun = DVec3::new(1.0, 0.3, 0.2).normalize();
        let center = DVec3::splat(8.0);
        for shadow_extinction in [0.0, 0.5] {
            let lighting = CloudLighting {
                sun_direction: sun,
                shadow_extinction,
                ..Default::default()
            };
            let light = light_field(&grid, &lighting).unwrap();
            let lit = light.sample(center + sun * 4.5);
            let far = light.sample(center - sun * 4.5);
            assert!(lit > far + 0.2, "σ {shadow_extinction}: {lit} vs {far}");
            let inside = light.sample(center);
            if shadow_extinction > 0.0 {
                assert!(lit > inside && inside > far, "{lit} {inside} {far}");
            }
        }
    }

    #[test]
    fn threads_do_not_change_the_result() {
        let (grid, lighting) = (cloud(), shadowed());
        let one = light_field_with_threads(&grid, &lighting, 1).unwrap();
        for threads in [0, 2, 3, 50] {
            assert_eq!(
                one,
                light_field_with_threads(&grid, &lighting, threads).unwrap()
            );
        }
        assert!(one.values().iter().all(|g| (0.3..=1.0).contains(g)));
        // A huge extinction: black shadows, no NaN.
        let dark = CloudLighting {
            shadow_extinction: f32::MAX,
            ..lighting
        };
        let light = light_field(&grid, &dark).unwrap();
        assert!(light.values().contains(&0.3));
    }

    #[test]
    fn bad_settings_are_refused_by_name() {
        let grid = uniform([3, 3, 3], DVec3::ONE, 0.5);
        let check = |lighting: CloudLighting, parameter: &str| {
            let message = error_message(light_field(&grid, &lighting));
            assert_mentions(&message, &["light_field", parameter]);
        };
        let ok = CloudLighting::default();
        for sun in [
            DVec3::ZERO,
            DVec3::new(f64::NAN, 1.0, 0.0),
            DVec3::new(0.0, f64::INFINITY, 0.0),
        ] {
            check(
                CloudLighting {
                    sun_direction: sun,
                    ..ok
                },
                "sun_direction",
            );
        }
        check(CloudLighting { ambient: 1.5, ..ok }, "ambient");
        let zenith = CloudLighting {
            sky_direction: DVec3::ZERO,
            ..ok
        };
        check(zenith, "sky_direction");
        for scattering_octaves in [0, 9] {
            let octaves = CloudLighting {
                scattering_octaves,
                ..ok
            };
            check(octaves, "scattering_octaves");
        }
        check(
            CloudLighting {
                ambient: f32::NAN,
                ..ok
            },
            "ambient",
        );
        check(
            CloudLighting {
                diffuse: -0.1,
                ..ok
            },
            "diffuse",
        );
        for sigma in [-1.0, f32::NAN, f32::INFINITY] {
            check(
                CloudLighting {
                    shadow_extinction: sigma,
                    ..ok
                },
                "shadow_extinction",
            );
        }
        // A direction with huge but finite components is still a direction.
        let far = CloudLighting {
            sun_direction: DVec3::new(0.0, 1e300, 0.0),
            shadow_extinction: 0.5,
            ..ok
        };
        assert_eq!(
            light_field(&grid, &far).unwrap(),
            light_field(
                &grid,
                &CloudLighting {
                    sun_direction: DVec3::Y,
                    ..far
                }
            )
            .unwrap()
        );
    }
}
