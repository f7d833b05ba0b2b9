//! Fog layers against Bevy's own fogs in one run (`nebel bench-fog-layers`):
//! nebel's `FogLayers`, Bevy 0.19's `DistanceFog` with exponential and with
//! atmospheric falloff, and its `FogVolume` ray marcher covering the layers,
//! each scored against the exact reference of the fog layers and timed.
//!
//! - `DistanceFog` depends on the distance only, `α = 1 − e^{−k d}`, and is
//!   applied by the PBR shader of meshes (not to the sky). `k` is fitted to
//!   the exact opacity of the layers over the scene's opaque pixels (least
//!   squares, golden-section search on `ln k`); the atmospheric falloff gets
//!   the same coefficient for extinction and in-scattering, which over the
//!   reference's black surfaces is the best it can do too.
//! - `FogVolume` samples a density texture over a box: here the layers'
//!   profile over altitude on 64 texels, in a box over the scene's meshes,
//!   up to the altitude where the density falls below 1/1000 of its
//!   largest. It is lit by one directional light with `VolumetricLight`,
//!   whose colour is chosen so that a thin fog has the layers' colour
//!   (`L · exposure / 4π = c`; [`crate::fog_comparison`] gives Bevy's model);
//!   its self-shadowing factor `e^{−σ D s R}`, `R` half the box's diagonal,
//!   then darkens it, which the comparison measures.
//!
//! The command writes `DIR/fog_layer_peers.csv`, `DIR/fog_layer_peers.svg`
//! (frame time against RMSE) and every image.

use std::path::Path;

use bevy::camera::Exposure;
use bevy::pbr::{DistanceFog, FogFalloff};
use bevy::prelude::{Color, Vec3, default};
use glam::DVec3;
use nebel_core::field::DensityGrid;
use nebel_core::optics::OpticalMode;
use nebel_core::transfer::{TransferFunction, TransferPreset};
use nebel_reference::image_metrics::{compare, load_png_linear};
use nebel_scene::reference::{reference_image, save_reference};
use nebel_scene::{
    BuiltVolume, DirectionalLightDescription, LightDescription, MeshDescription, SceneDescription,
    SceneField,
};
use plotters::style::colors::BLACK;

use crate::error::CommandError;
use crate::fog_comparison::BevyFog;
use crate::headless::HeadlessOptions;
use crate::progress::reference_bar;
use crate::scene_setup::{BevyPeer, SceneSetupPlugin};
use crate::time_error_chart::{ChartSeries, time_error_chart};

/// Texels of the `FogVolume`'s density profile over altitude.
const PROFILE_TEXELS: usize = 64;

/// One renderer's figures.
#[derive(Clone, Debug, PartialEq)]
pub struct PeerResult {
    /// The renderer.
    pub renderer: &'static str,
    /// Its fog's parameters, for the record.
    pub parameters: String,
    /// Median and largest wall time of a frame, ms.
    pub frame_ms: (f64, f64),
    /// RMSE, largest error and PSNR against the exact reference.
    pub rmse: f64,
    /// Largest per-pixel error, linear RGB.
    pub max_abs: f64,
    /// PSNR, dB.
    pub psnr: f64,
}

/// Runs the comparison (see the module docs).
pub fn run_fog_layer_peers(
    scene_path: &Path,
    mut scene: SceneDescription,
    out_dir: &Path,
    step_count: u32,
) -> Result<Vec<PeerResult>, CommandError> {
    let unsuitable = |reason: &str| CommandError::Unsuitable {
        path: scene_path.to_owned(),
        reason: reason.to_owned(),
    };
    let Some(layers) = scene.fog_layers.clone() else {
        return Err(unsuitable("bench-fog-layers needs a scene with fog_layers"));
    };
    if !scene.volumes.is_empty() || scene.terrain.is_some() {
        return Err(unsuitable(
            "bench-fog-layers compares fog layers alone: the scene may have meshes, no volumes or terrain",
        ));
    }
    scene.camera.tonemapping = false;
    scene.camera.msaa = 1;
    std::fs::create_dir_all(out_dir).map_err(CommandError::write(out_dir))?;

    let (bar, report) = reference_bar(true);
    let reference = reference_image(&scene, Vec::new(), Some(&report))?;
    bar.finish_and_clear();
    save_reference(&reference, &out_dir.join("reference.png"))?;

    let fog = layers
        .reference(
            scene
                .sun_direction()
                .map(|sun| (sun, scene.sun_casts_shadows())),
            Vec::new(),
            Vec::new(),
        )
        .map_err(|invalid| {
            unsuitable(&format!("fog_layers.{}: {}", invalid.field, invalid.reason))
        })?;
    let density = fitted_distance_density(&scene, &fog)?;
    let colour = Color::linear_rgb(layers.color[0], layers.color[1], layers.color[2]);
    let distance_fog = |falloff| DistanceFog {
        color: colour,
        falloff,
        ..default()
    };
    let without_layers = SceneDescription {
        fog_layers: None,
        ..scene.clone()
    };
    let (fog_volume_scene, fog_volume, fog_volume_field) =
        fog_volume_peer(&without_layers, &fog.fog, layers.color, step_count)
            .ok_or_else(|| unsuitable("the fog layers have no density over the scene's meshes"))?;

    let runs: Vec<(
        &'static str,
        String,
        SceneDescription,
        Vec<BuiltVolume>,
        Option<BevyPeer>,
    )> = vec![
        (
            "nebel_fog_layers",
            String::from("exact"),
            scene.clone(),
            Vec::new(),
            None,
        ),
        (
            "bevy_distance_fog_exponential",
            format!("density {density:.6e}/m"),
            without_layers.clone(),
            Vec::new(),
            Some(BevyPeer::DistanceFog(distance_fog(
                FogFalloff::Exponential {
                    density: density as f32,
                },
            ))),
        ),
        (
            "bevy_distance_fog_atmospheric",
            format!("extinction = inscattering {density:.6e}/m"),
            without_layers.clone(),
            Vec::new(),
            Some(BevyPeer::DistanceFog(distance_fog(
                FogFalloff::Atmospheric {
                    extinction: Vec3::splat(density as f32),
                    inscattering: Vec3::splat(density as f32),
                },
            ))),
        ),
        (
            "bevy_fog_volume",
            format!(
                "{step_count} steps, density factor {:.4e}, {PROFILE_TEXELS} texels over altitude",
                fog_volume.density_factor
            ),
            fog_volume_scene,
            vec![fog_volume_field],
            Some(BevyPeer::FogVolume(fog_volume)),
        ),
    ];
    let mut results = Vec::with_capacity(runs.len());
    for (renderer, parameters, run_scene, volumes, peer) in runs {
        let setup = SceneSetupPlugin {
            scene: run_scene,
            volumes,
            terrain: None,
            ground_fog: None,
            aurora: None,
            cloud_layer: None,
            peer,
        };
        let image_path = out_dir.join(format!("{renderer}.png"));
        let options = HeadlessOptions {
            progress: true,
            ..HeadlessOptions::default()
        };
        let stats = setup.render_headless(options, &image_path)?;
        let metrics = compare(&load_png_linear(&image_path)?, &reference)?;
        println!(
            "{renderer} ({parameters}): frame {:.1} ms (median); against the exact reference {metrics}",
            stats.frame_wall_ms.median
        );
        results.push(PeerResult {
            renderer,
            parameters,
            frame_ms: (stats.frame_wall_ms.median, stats.frame_wall_ms.max),
            rmse: metrics.rmse,
            max_abs: metrics.max_abs,
            psnr: metrics.psnr,
        });
    }

    let mut rows = vec![String::from(
        "renderer,parameters,frame_ms_median,frame_ms_max,rmse,max_abs,psnr_db",
    )];
    rows.extend(results.iter().map(|r| {
        format!(
            "{},\"{}\",{},{},{},{},{}",
            r.renderer, r.parameters, r.frame_ms.0, r.frame_ms.1, r.rmse, r.max_abs, r.psnr
        )
    }));
    let csv = out_dir.join("fog_layer_peers.csv");
    std::fs::write(&csv, rows.join("\n") + "\n").map_err(CommandError::write(&csv))?;
    let plot_path = out_dir.join("fog_layer_peers.svg");
    let svg = plot(&results).map_err(|reason| CommandError::Plot {
        path: plot_path.clone(),
        reason,
    })?;
    std::fs::write(&plot_path, svg).map_err(CommandError::write(&plot_path))?;
    eprintln!("nebel: wrote {} and {}", csv.display(), plot_path.display());
    Ok(results)
}

/// The `DistanceFog` density that fits the layers' exact opacity over the
/// scene's opaque pixels best (least squares).
fn fitted_distance_density(
    scene: &SceneDescription,
    fog: &nebel_reference::ReferenceFog,
) -> Result<f64, CommandError> {
    let camera = scene.reference_camera();
    let depth = scene
        .opaque_depth(&camera)
        .map_err(nebel_reference::ReferenceError::from)?
        .unwrap_or_default();
    let samples: Vec<(f64, f64)> = depth
        .iter()
        .enumerate()
        .filter(|(_, depth)| depth.is_finite())
        .map(|(index, depth)| {
            let (x, y) = (index as u32 % camera.width, index as u32 / camera.width);
            let (ray, depth_to_distance) = camera.pixel_ray(x, y);
            let distance = f64::from(*depth) / depth_to_distance;
            (distance, fog.segment(&ray, 0.0, distance).w)
        })
        .collect();
    let error = |ln_k: f64| {
        let k = ln_k.exp();
        samples
            .iter()
            .map(|(d, alpha)| (alpha + (-k * d).exp_m1()).powi(2))
            .sum::<f64>()
    };
    // Golden-section search on ln k over [1e-7, 10] per metre.
    let (mut a, mut b) = (1e-7f64.ln(), 10f64.ln());
    let ratio = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..100 {
        let (c, d) = (b - ratio * (b - a), a + ratio * (b - a));
        if error(c) < error(d) {
            b = d;
        } else {
            a = c;
        }
    }
    Ok((0.5 * (a + b)).exp())
}

/// The scene with one directional light that gives Bevy's fog the layers'
/// colour, the `FogVolume` settings and the density profile as a grid over
/// the meshes' box; `None` when the layers have no density there.
fn fog_volume_peer(
    scene: &SceneDescription,
    fog: &nebel_core::height_fog::HeightFog,
    colour: [f32; 3],
    step_count: u32,
) -> Option<(SceneDescription, BevyFog, BuiltVolume)> {
    // The meshes' horizontal extent and the fog's altitudes.
    let (mut min, mut max) = (DVec3::INFINITY, DVec3::NEG_INFINITY);
    for mesh in &scene.meshes {
        let (center, half) = match mesh {
            MeshDescription::Plane(plane) => (
                plane.center,
                [plane.size[0] / 2.0, 0.0, plane.size[1] / 2.0],
            ),
            MeshDescription::Box(cuboid) => (cuboid.center, cuboid.size.map(|s| s / 2.0)),
            MeshDescription::Sphere(sphere) => (sphere.center, [sphere.radius; 3]),
        };
        let (center, half) = (
            DVec3::from(center.map(f64::from)),
            DVec3::from(half.map(f64::from)),
        );
        min = min.min(center - half);
        max = max.max(center + half);
    }
    if !(min.is_finite() && max.is_finite()) {
        return None;
    }
    let ground = min.y;
    let densest = (0..=1000)
        .map(|i| fog.density(ground + f64::from(i)))
        .fold(0.0, f64::max);
    if densest <= 0.0 {
        return None;
    }
    let top = (1..=100_000)
        .map(|i| ground + f64::from(i))
        .find(|h| (0..100).all(|j| fog.density(h + f64::from(j)) < 1e-3 * densest))
        .unwrap_or(ground + 100_000.0);
    let spacing = DVec3::new(
        max.x - min.x,
        (top - ground) / (PROFILE_TEXELS - 1) as f64,
        max.z - min.z,
    );
    // Constant over x and z: two points per side, x fastest, then y, z.
    let profile: Vec<f32> = (0..PROFILE_TEXELS)
        .map(|j| (fog.density(ground + j as f64 * spacing.y) / densest) as f32)
        .collect();
    let values = (0..2)
        .flat_map(|_| profile.iter().flat_map(|value| [*value; 2]))
        .collect();
    let grid = DensityGrid::new(
        [2, PROFILE_TEXELS, 2],
        spacing,
        DVec3::new(min.x, ground, min.z),
        values,
    )
    .ok()?;
    let bevy_fog = BevyFog {
        scattering: 1.0,
        density_factor: densest as f32,
        step_count,
    };
    // L · exposure / 4π = c: a white light of illuminance 4π max(c) /
    // exposure, tinted by c, level, so it lights no horizontal surface (the
    // reference's meshes are black; Bevy's fog is isotropic here).
    let brightest = colour.iter().copied().fold(0.0f32, f32::max).max(1e-6);
    let tint = Color::linear_rgb(
        colour[0] / brightest,
        colour[1] / brightest,
        colour[2] / brightest,
    )
    .to_srgba();
    let sun = LightDescription::Directional(DirectionalLightDescription {
        direction: [1.0, 0.0, 0.0],
        color: [tint.red, tint.green, tint.blue],
        illuminance: 4.0 * std::f32::consts::PI * brightest / Exposure::default().exposure(),
        shadows: false,
        turn: None,
    });
    let mut lit = scene.clone();
    lit.lights
        .retain(|light| !matches!(light, LightDescription::Directional(_)));
    lit.lights.push(sun);
    let volume = BuiltVolume {
        field: SceneField::Grid(grid),
        transfer_function: TransferFunction::preset(TransferPreset::Cloud),
        mode: OpticalMode::Sorted,
        lod: None,
        lighting: None,
        projected_cells: false,
        ends_where_fog_layers_begin: false,
        fog_sunlight: None,
        light_response: Default::default(),
    };
    Some((lit, bevy_fog, volume))
}

/// Frame time against RMSE, one labelled dot per renderer.
fn plot(results: &[PeerResult]) -> Result<String, String> {
    time_error_chart(
        "Fog layers against Bevy's fogs",
        "RMSE against the exact reference (linear RGB)",
        &[ChartSeries {
            legend: None,
            points: results
                .iter()
                .map(|r| (r.frame_ms.0, r.rmse, Some(r.renderer.to_owned())))
                .collect(),
            line: false,
            colour: BLACK,
            radius: 4,
        }],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(layers: &str) -> SceneDescription {
        SceneDescription::from_ron(
            &format!(
                "(version: 1, output: (width: 32, height: 20),
                  camera: (view: Pose((position: (0.0, 8.0, 0.0), look_at: (0.0, 2.0, -100.0)))),
                  meshes: [Plane((center: (0.0, 0.0, 0.0), size: (4000.0, 4000.0), color: (0.0, 0.0, 0.0)))],
                  fog_layers: (layers: [{layers}]))"
            ),
            Path::new("test.ron"),
        )
        .unwrap()
    }

    #[test]
    fn a_fog_of_one_density_everywhere_fits_that_density() {
        let scene = scene("Constant(bottom: -1000.0, top: 1000.0, density: 0.02)");
        let fog = scene
            .fog_layers
            .as_ref()
            .unwrap()
            .reference(None, Vec::new(), Vec::new())
            .unwrap();
        let k = fitted_distance_density(&scene, &fog).unwrap();
        assert!((k - 0.02).abs() < 1e-6, "{k}");
    }

    #[test]
    fn the_fog_volume_profile_follows_the_layers_up_to_their_top() {
        let scene = scene("Exponential(base: 0.0, density: 0.01, falloff: 0.05)");
        let fog = scene.fog_layers.as_ref().unwrap().height_fog().unwrap();
        let (lit, bevy_fog, volume) = fog_volume_peer(&scene, &fog, [0.5, 0.6, 0.7], 64).unwrap();
        assert_eq!(bevy_fog.density_factor, 0.01);
        let SceneField::Grid(grid) = volume.field else {
            panic!("a grid");
        };
        // 1 at the ground, e^{−0.05 h} above, below 1/1000 at the top
        // (ln 1000 / 0.05 ≈ 138 m).
        assert_eq!(grid.value(0, 0, 0), 1.0);
        let top = grid.origin().y + grid.spacing().y * (PROFILE_TEXELS - 1) as f64;
        assert!((138.0..=240.0).contains(&top), "{top}");
        let at = |j: usize| f64::from(grid.value(1, j, 1));
        let h = grid.spacing().y * 10.0;
        assert!((at(10) - (-0.05 * h).exp()).abs() < 1e-3);
        // One level light, tinted by the fog's colour.
        let suns: Vec<_> = lit
            .lights
            .iter()
            .filter(|light| matches!(light, LightDescription::Directional(_)))
            .collect();
        assert_eq!(suns.len(), 1);
        // No meshes: nothing to cover.
        let mut bare = scene.clone();
        bare.meshes.clear();
        assert!(fog_volume_peer(&bare, &fog, [0.5, 0.6, 0.7], 64).is_none());
    }
}
