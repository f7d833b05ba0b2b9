//! The terrain of a scene file: where its heights come from, how large it
//! is and how finely the quadtree C-LOD draws it (Röttger 2004 §3.5.3).
//!
//! ```ron
//! terrain: (
//!     source: Procedural((dims: 513,           // points per side, 2..=8193
//!                         kind: Fbm,           // or Ridged; default Fbm
//!                         seed: 7, octaves: 6, // defaults 0 and 6
//!                         wavelength: 2000.0,  // first octave, metres; default 2000
//!                         persistence: 0.5,    // amplitude ratio per octave; default 0.5
//!                         exponent: 1.5)),     // on the unit height, > 1 widens valleys; default 1
//!     // or Png((path: "heights.png")): an 8- or 16-bit grayscale PNG relative
//!     // to the scene file, columns along x, rows along z, black = 0, white = 1
//!     center: (0.0, 0.0, 0.0),   // the grid's centre at (x, z), height 0 at y; default origin
//!     spacing: 10.0,             // metres between grid points; default 10
//!     vertical_scale: 400.0,     // metres of a unit height (white); default 400
//!     accuracy: 300.0,           // c of f = l²/(d² max(c·d2, C)²); default 300
//!     // or pixel_error: 2.0,    // the most pixels a left-out detail moves (c from the camera)
//!     min_accuracy: 2.0,         // C, ≥ 1.6; default 2
//!     morph: true,               // geomorphing; default true
//!     debug_lod_colours: false,  // colour each quadtree level; default false
//!     debug_edges: false,        // darken triangle edges; default false
//!     color: Some((0.0, 0.0, 0.0)), // unlit in one colour; default none (lit, by height and slope)
//!     fog: (thickness: Valley((altitude: 60.0))), // ground fog; default none (see GroundFogDescription)
//! )
//! ```
//!
//! Procedural heights are [`HeightField::terrain`]: fractal Perlin noise
//! rescaled to [0, 1], so `vertical_scale` is the terrain's relief. A
//! height field whose sides are not `2^k + 1` points (or not square) is
//! padded by the terrain plugin at its high x and z ends, replicating the
//! edge (`nebel_lod::quadtree::pad_to_power_of_two_plus_one`); the centre is
//! the centre of the field as given. Validation checks the settings (and that
//! the procedural heights, padded heights and quadtree fit the memory
//! budget of `nebel_core::budget`); building
//! ([`TerrainDescription::unit_heights`]) generates or loads the heights and
//! reports a missing or unreadable PNG naming `terrain.source.Png.path`.

use std::path::Path;

use glam::{DMat4, DVec2};
use serde::{Deserialize, Serialize};

use super::{GroundFogDescription, InvalidField};
use nebel_core::field::{
    DEFAULT_TERRAIN_SPACING, DEFAULT_TERRAIN_VERTICAL_SCALE, HeightField, NoiseKind, TerrainNoise,
    power_of_two_plus_one,
};
use nebel_lod::TerrainHierarchy;
use nebel_lod::quadtree::{
    DEFAULT_ACCURACY, DEFAULT_MIN_RESOLUTION, MAX_TERRAIN_SIDE, accuracy_for_pixel_error,
};
use nebel_reference::ReferenceCamera;

/// A scene's terrain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TerrainDescription {
    /// Where the heights come from.
    pub source: TerrainHeightSource,
    /// World position of the grid's centre (x, z) and of height 0 (y),
    /// metres. Default `(0, 0, 0)`.
    #[serde(default)]
    pub center: [f32; 3],
    /// Horizontal distance between neighbouring grid points, metres, finite
    /// and > 0. Default 10.
    #[serde(default = "default_spacing")]
    pub spacing: f32,
    /// Height of a unit value (a white pixel, the highest procedural point),
    /// metres, finite and ≥ 0. Default 400.
    #[serde(default = "default_vertical_scale")]
    pub vertical_scale: f32,
    /// Global accuracy `c` of the quadtree, finite and > 0: larger draws
    /// more triangles. Default 300 ([`TerrainDescription::accuracy_for`]);
    /// not together with `pixel_error`.
    #[serde(default)]
    pub accuracy: Option<f32>,
    /// The most pixels a detail the mesh leaves out (of the ground and of
    /// its fog's top) may move, finite and > 0: the accuracy is derived
    /// from the camera's projection and the image size
    /// (`nebel_lod::quadtree::accuracy_for_pixel_error`). Default: none (the
    /// accuracy is used); not together with `accuracy`.
    #[serde(default)]
    pub pixel_error: Option<f32>,
    /// Minimum resolution `C`, finite and ≥ 1.6: a node is refined within
    /// `C` node sizes of the eye whatever its roughness. Default 2.
    #[serde(default = "default_min_accuracy")]
    pub min_accuracy: f32,
    /// Geomorphing of new vertices. Default true.
    #[serde(default = "default_morph")]
    pub morph: bool,
    /// Debug view: colour every triangle by its quadtree level. Default false.
    #[serde(default)]
    pub debug_lod_colours: bool,
    /// Debug view: darken every triangle's edges (wireframe-like). Default
    /// false.
    #[serde(default)]
    pub debug_edges: bool,
    /// Drawn unlit in this sRGB colour instead of lit in colours by height
    /// and slope (black: as the reference draws the terrain, whatever the
    /// lights). Default: none.
    #[serde(default)]
    pub color: Option<[f32; 3]>,
    /// Ground fog lying on the terrain, see [`GroundFogDescription`].
    /// Default: none.
    #[serde(default)]
    pub fog: Option<GroundFogDescription>,
}

fn default_spacing() -> f32 {
    DEFAULT_TERRAIN_SPACING
}

fn default_vertical_scale() -> f32 {
    DEFAULT_TERRAIN_VERTICAL_SCALE
}

fn default_min_accuracy() -> f32 {
    DEFAULT_MIN_RESOLUTION
}

fn default_morph() -> bool {
    true
}

/// Where a terrain's heights come from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum TerrainHeightSource {
    /// Seeded fractal noise, see [`HeightField::terrain`].
    Procedural(ProceduralTerrainSource),
    /// An 8- or 16-bit grayscale PNG.
    Png(PngTerrainSource),
}

/// Procedural terrain heights.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProceduralTerrainSource {
    /// Grid points per side, 2 to 8193; `2^k + 1` needs no padding.
    pub dims: usize,
    /// Fractal kind. Default `Fbm`.
    #[serde(default)]
    pub kind: NoiseKind,
    /// Seed. Default 0.
    #[serde(default)]
    pub seed: u32,
    /// Octaves, 1 to 32. Default 6.
    #[serde(default = "default_octaves")]
    pub octaves: usize,
    /// Wavelength of the first octave, metres, finite and > 0. Default 2000.
    #[serde(default = "default_wavelength")]
    pub wavelength: f64,
    /// Amplitude ratio between octaves, finite and > 0. Default 0.5.
    #[serde(default = "default_persistence")]
    pub persistence: f64,
    /// Exponent on the unit height, finite and > 0; above 1 widens the
    /// valleys. Default 1.
    #[serde(default = "default_exponent")]
    pub exponent: f64,
}

fn default_octaves() -> usize {
    TerrainNoise::default().octaves
}

fn default_wavelength() -> f64 {
    TerrainNoise::default().wavelength
}

fn default_persistence() -> f64 {
    TerrainNoise::default().persistence
}

fn default_exponent() -> f64 {
    TerrainNoise::default().exponent
}

impl ProceduralTerrainSource {
    /// The generator settings.
    pub fn noise(&self) -> TerrainNoise {
        TerrainNoise {
            kind: self.kind,
            seed: self.seed,
            octaves: self.octaves,
            wavelength: self.wavelength,
            persistence: self.persistence,
            exponent: self.exponent,
        }
    }
}

/// Terrain heights from a grayscale PNG.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PngTerrainSource {
    /// The PNG, relative to the scene file.
    pub path: String,
}

impl TerrainDescription {
    /// The unit heights (values in [0, 1]; `vertical_scale` multiplies them),
    /// `spacing` apart, origin (0, 0): generated, or loaded from the PNG
    /// (relative to `scene_dir`). Errors name the field (relative to
    /// `terrain`) and the reason.
    pub fn unit_heights(&self, scene_dir: &Path) -> Result<HeightField, InvalidField> {
        let spacing = f64::from(self.spacing);
        match &self.source {
            TerrainHeightSource::Procedural(procedural) => HeightField::terrain(
                [procedural.dims; 2],
                spacing,
                &procedural.noise(),
            )
            .map_err(|error| InvalidField::new("source.Procedural", error.to_string())),
            TerrainHeightSource::Png(png) => {
                HeightField::load_png(scene_dir.join(&png.path), DVec2::splat(spacing), DVec2::ZERO, 1.0)
                    .map_err(|error| InvalidField::new("source.Png.path", error.to_string()))
                    .and_then(|field| {
                        let [nx, nz] = field.dims();
                        if nx.max(nz) > MAX_TERRAIN_SIDE {
                            return Err(InvalidField::new(
                                "source.Png.path",
                                format!(
                                    "{}: {nx}×{nz} points, more than the largest terrain side {MAX_TERRAIN_SIDE}",
                                    png.path
                                ),
                            ));
                        }
                        Ok(field)
                    })
            }
        }
    }

    /// The heights in world space: `center.y + vertical_scale · unit` at
    /// horizontal positions centred on `center` (the field as given, without
    /// padding), from [`TerrainDescription::unit_heights`].
    pub fn world_heights(&self, unit: &HeightField) -> HeightField {
        let [nx, nz] = unit.dims();
        let spacing = unit.spacing();
        let half = DVec2::new((nx - 1) as f64, (nz - 1) as f64) * spacing / 2.0;
        let center = DVec2::new(f64::from(self.center[0]), f64::from(self.center[2]));
        let (base, scale) = (f64::from(self.center[1]), f64::from(self.vertical_scale));
        let heights = unit
            .heights()
            .iter()
            .map(|&u| (base + scale * f64::from(u)) as f32)
            .collect();
        HeightField::new(unit.dims(), spacing, center - half, heights)
            .expect("a validated terrain scales to finite heights")
    }

    /// The accuracy `c` given, or the default (300) when neither it nor a
    /// pixel error is.
    pub fn accuracy(&self) -> f32 {
        self.accuracy.unwrap_or(DEFAULT_ACCURACY)
    }

    /// The accuracy `c` the quadtree refines with for `camera` (a
    /// perspective one, as every scene camera is): [`Self::accuracy`], or
    /// the one the pixel error gives for the camera's field of view and image
    /// size.
    pub fn accuracy_for(&self, camera: &ReferenceCamera) -> Result<f32, InvalidField> {
        let Some(pixel_error) = self.pixel_error else {
            return Ok(self.accuracy());
        };
        let aspect = f64::from(camera.width) / f64::from(camera.height.max(1));
        let clip_from_view =
            DMat4::perspective_infinite_reverse_rh(camera.vertical_fov, aspect, camera.near);
        accuracy_for_pixel_error(
            f64::from(pixel_error),
            clip_from_view,
            [camera.width, camera.height],
            self.min_accuracy,
        )
        .map(|accuracy| accuracy as f32)
        .map_err(|error| InvalidField::new("pixel_error", error.to_string()))
    }

    /// Checks every setting against its documented range; loading the PNG
    /// waits for [`TerrainDescription::unit_heights`].
    pub(super) fn validate(&self) -> Result<(), InvalidField> {
        if let Some(value) = self.center.iter().find(|c| !c.is_finite()) {
            return Err(InvalidField::new(
                "center",
                format!("must be finite, got {value}"),
            ));
        }
        if self.accuracy.is_some() && self.pixel_error.is_some() {
            return Err(InvalidField::new(
                "pixel_error",
                "give either accuracy or pixel_error, not both",
            ));
        }
        let pixel_error = self.pixel_error.unwrap_or(1.0);
        let checks: [(&str, f32, bool, &str); 5] = [
            ("pixel_error", pixel_error, pixel_error > 0.0, "> 0"),
            ("spacing", self.spacing, self.spacing > 0.0, "> 0"),
            (
                "vertical_scale",
                self.vertical_scale,
                self.vertical_scale >= 0.0,
                ">= 0",
            ),
            ("accuracy", self.accuracy(), self.accuracy() > 0.0, "> 0"),
            (
                "min_accuracy",
                self.min_accuracy,
                self.min_accuracy >= 1.6,
                ">= 1.6 (the one-level rule of the quadtree needs C > √10/2)",
            ),
        ];
        InvalidField::check_finite(checks)?;
        if let Some(color) = self.color {
            crate::colour("color", color)?;
        }
        match &self.source {
            TerrainHeightSource::Procedural(procedural) => {
                let field = "source.Procedural";
                if !(2..=MAX_TERRAIN_SIDE).contains(&procedural.dims) {
                    return Err(InvalidField::new(
                        format!("{field}.dims"),
                        format!(
                            "must be in [2, {MAX_TERRAIN_SIDE}], got {}",
                            procedural.dims
                        ),
                    ));
                }
                // The heights, the square they are padded to, the quadtree.
                let side = power_of_two_plus_one(procedural.dims).max(3);
                HeightField::check_budget([procedural.dims; 2])
                    .and_then(|_| HeightField::check_budget([side; 2]))
                    .and_then(|_| TerrainHierarchy::check_budget(side))
                    .map_err(|error| {
                        InvalidField::new(format!("{field}.dims"), error.to_string())
                    })?;
                if !(1..=32).contains(&procedural.octaves) {
                    return Err(InvalidField::new(
                        format!("{field}.octaves"),
                        format!("must be in [1, 32], got {}", procedural.octaves),
                    ));
                }
                for (name, value) in [
                    ("wavelength", procedural.wavelength),
                    ("persistence", procedural.persistence),
                    ("exponent", procedural.exponent),
                ] {
                    if !(value.is_finite() && value > 0.0) {
                        return Err(InvalidField::new(
                            format!("{field}.{name}"),
                            format!("must be finite and > 0, got {value}"),
                        ));
                    }
                }
            }
            TerrainHeightSource::Png(png) => {
                if png.path.trim().is_empty() {
                    return Err(InvalidField::new(
                        "source.Png.path",
                        "must name a PNG file (relative to the scene file)",
                    ));
                }
            }
        }
        if let Some(fog) = &self.fog {
            fog.validate().map_err(|invalid| invalid.within("fog"))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::SceneDescription;
    use glam::DVec3;

    const SCENE: &str = "(version: 1, camera: (view: Pose((position: (0.0, 500.0, 900.0), look_at: (0.0, 0.0, 0.0)))), terrain: TERRAIN)";

    fn parse(terrain: &str) -> Result<SceneDescription, String> {
        SceneDescription::from_ron(
            &SCENE.replace("TERRAIN", terrain),
            Path::new("scenes/t.ron"),
        )
        .map_err(|error| error.to_string())
    }

    #[test]
    fn a_pixel_error_gives_the_accuracy_for_the_camera() {
        let camera = ReferenceCamera {
            vertical_fov: 60f64.to_radians(),
            width: 1920,
            height: 1080,
            ..ReferenceCamera::default()
        };
        let given = parse("(source: Procedural((dims: 9)), accuracy: 120.0)").unwrap();
        assert_eq!(given.terrain.unwrap().accuracy_for(&camera).unwrap(), 120.0);
        let scene = parse("(source: Procedural((dims: 9)), pixel_error: 2.0)").unwrap();
        let terrain = scene.terrain.unwrap();
        let accuracy = terrain.accuracy_for(&camera).unwrap();
        assert!((735.0..750.0).contains(&accuracy), "{accuracy}");
        let half = ReferenceCamera {
            width: 960,
            height: 540,
            ..camera
        };
        let halved = terrain.accuracy_for(&half).unwrap();
        assert!(
            (halved - accuracy / 2.0).abs() < 1e-3 * accuracy,
            "{halved}"
        );
    }

    #[test]
    fn defaults_and_both_spellings_of_the_option() {
        for text in [
            "(source: Procedural((dims: 33)))",
            "Some((source: Procedural((dims: 33))))",
        ] {
            let scene = parse(text).unwrap();
            let terrain = scene.terrain.expect("a terrain");
            assert_eq!(terrain.spacing, 10.0);
            assert_eq!(terrain.vertical_scale, 400.0);
            assert_eq!((terrain.accuracy(), terrain.min_accuracy), (300.0, 2.0));
            assert_eq!(terrain.pixel_error, None);
            assert!(terrain.morph && !terrain.debug_lod_colours && !terrain.debug_edges);
            assert_eq!(terrain.center, [0.0; 3]);
            let TerrainHeightSource::Procedural(source) = &terrain.source else {
                panic!("procedural");
            };
            assert_eq!(source.noise(), TerrainNoise::default());
        }
        let scene = SceneDescription::from_ron(
            &SCENE.replace(", terrain: TERRAIN", ""),
            Path::new("scenes/t.ron"),
        )
        .unwrap();
        assert!(scene.terrain.is_none());
    }

    #[test]
    fn every_range_check_names_its_field() {
        let cases = [
            (
                "(source: Procedural((dims: 1)))",
                "field terrain.source.Procedural.dims: must be in [2, 8193], got 1",
            ),
            (
                "(source: Procedural((dims: 9000)))",
                "field terrain.source.Procedural.dims: must be in [2, 8193], got 9000",
            ),
            (
                "(source: Procedural((dims: 9, octaves: 0)))",
                "field terrain.source.Procedural.octaves: must be in [1, 32], got 0",
            ),
            (
                "(source: Procedural((dims: 9, wavelength: -1.0)))",
                "field terrain.source.Procedural.wavelength: must be finite and > 0, got -1",
            ),
            (
                "(source: Procedural((dims: 9, exponent: 0.0)))",
                "field terrain.source.Procedural.exponent: must be finite and > 0, got 0",
            ),
            (
                "(source: Procedural((dims: 9)), spacing: 0.0)",
                "field terrain.spacing: must be finite and > 0, got 0",
            ),
            (
                "(source: Procedural((dims: 9)), vertical_scale: inf)",
                "field terrain.vertical_scale: must be finite and >= 0, got inf",
            ),
            (
                "(source: Procedural((dims: 9)), accuracy: NaN)",
                "field terrain.accuracy: must be finite and > 0, got NaN",
            ),
            (
                "(source: Procedural((dims: 9)), pixel_error: 0.0)",
                "field terrain.pixel_error: must be finite and > 0, got 0",
            ),
            (
                "(source: Procedural((dims: 9)), accuracy: 300.0, pixel_error: 2.0)",
                "field terrain.pixel_error: give either accuracy or pixel_error, not both",
            ),
            (
                "(source: Procedural((dims: 9)), min_accuracy: 1.5)",
                "field terrain.min_accuracy: must be finite and >= 1.6",
            ),
            (
                "(source: Procedural((dims: 9)), center: (0.0, NaN, 0.0))",
                "field terrain.center: must be finite, got NaN",
            ),
            (
                "(source: Png((path: \" \")))",
                "field terrain.source.Png.path: must name a PNG file",
            ),
            (
                "(source: Procedural((dims: 9)), fog: (thickness: Valley((altitude: 4.0)), saturate: true))",
                "field terrain.fog.saturate: saturates unsorted emissive fog: needs mode Emissive, got Sorted",
            ),
            (
                "(source: Procedural((dims: 9)), fog: (thickness: Valley((altitude: 4.0)), sun_color: (1.0, NaN, 0.0)))",
                "field terrain.fog.sun_color: colour components must be finite and >= 0, got NaN",
            ),
            (
                "(source: Procedural((dims: 9)), fog: (thickness: Valley((altitude: 4.0)), sun_asymmetry: 1.0))",
                "field terrain.fog.sun_asymmetry: must be in (−1, 1), got 1",
            ),
        ];
        for (terrain, expected) in cases {
            let message = parse(terrain).expect_err(terrain);
            assert!(
                message.starts_with(&format!("scenes/t.ron: {expected}")),
                "{message}"
            );
        }
        let message = parse("(source: Procedural((dims: 9, colour: 1)))").unwrap_err();
        assert!(message.contains("colour"), "{message}");
    }

    /// A sorted fog with a sun colour under a directional light is lit in
    /// the reference by the map the plugin builds, in the terrain's frame;
    /// without the light, the colour or the sorted mode it is not.
    #[test]
    fn a_sunlit_fog_s_reference_carries_its_sun_map() {
        let terrain = "(source: Procedural((dims: 17)), vertical_scale: 40.0, center: (30.0, 0.0, -20.0), fog: (thickness: Valley((altitude: 10.0)), sun_color: (1.0, 0.5, 0.25), sun_asymmetry: 0.4MODE))";
        let sunlit = |terrain: &str, sun: bool| {
            let mut text = SCENE.replace("TERRAIN", terrain);
            if sun {
                text = text.replace(
                    "(version: 1,",
                    "(version: 1, lights: [Directional((direction: (-0.6, -0.64, -0.48)))],",
                );
            }
            let scene = SceneDescription::from_ron(&text, Path::new("scenes/t.ron")).unwrap();
            let unit = scene
                .terrain
                .as_ref()
                .unwrap()
                .unit_heights(Path::new("."))
                .unwrap();
            let built = scene
                .build_ground_fog(Path::new("scenes/t.ron"))
                .unwrap()
                .unwrap();
            let reference = scene
                .build_fog_reference(Path::new("scenes/t.ron"), &unit, &built)
                .unwrap()
                .unwrap();
            reference.volume.and_then(|volume| volume.fog_sunlight)
        };
        let lit = sunlit(&terrain.replace("MODE", ""), true).expect("lit by the sun");
        let toward = DVec3::new(0.6, 0.64, 0.48).normalize();
        assert!(lit.direction.distance(toward) < 1e-6);
        assert_eq!(
            (lit.colour, lit.asymmetry),
            (DVec3::new(1.0, 0.5, 0.25), 0.4_f32 as f64)
        );
        // The map's frame is the terrain's, centred on its `center`.
        let origin = lit
            .map_from_world
            .transform_point3(DVec3::new(30.0, 0.0, -20.0));
        assert!(origin.length() < 1e-12);
        assert!(lit.map.thickness.heights().iter().any(|h| *h > 0.0));
        assert!(sunlit(&terrain.replace("MODE", ""), false).is_none());
        assert!(sunlit(&terrain.replace("MODE", ", mode: Emissive"), true).is_none());
        assert!(
            sunlit(
                &terrain
                    .replace("sun_color: (1.0, 0.5, 0.25), ", "")
                    .replace("MODE", ""),
                true
            )
            .is_none()
        );
    }

    #[test]
    fn heights_are_generated_or_loaded_and_placed_around_the_centre() {
        let scene = parse(
            "(source: Procedural((dims: 17, wavelength: 50.0)), center: (100.0, -5.0, 200.0), spacing: 2.0, vertical_scale: 10.0)",
        )
        .unwrap();
        let terrain = scene.terrain.unwrap();
        let unit = terrain.unit_heights(Path::new(".")).unwrap();
        assert_eq!(unit.dims(), [17, 17]);
        let world = terrain.world_heights(&unit);
        assert_eq!(world.origin(), DVec2::new(84.0, 184.0));
        let low = world
            .heights()
            .iter()
            .copied()
            .fold(f32::INFINITY, f32::min);
        let high = world
            .heights()
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        assert_eq!((low, high), (-5.0, 5.0));

        let dir = std::env::temp_dir().join(format!("nebel-scene-terrain-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let values: Vec<u16> = (0..15).map(|v| v * 4369).collect();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(5, 3, values)
            .unwrap()
            .save(dir.join("h.png"))
            .unwrap();
        let png = TerrainDescription {
            source: TerrainHeightSource::Png(PngTerrainSource {
                path: String::from("h.png"),
            }),
            ..terrain.clone()
        };
        let unit = png.unit_heights(&dir).unwrap();
        assert_eq!(unit.dims(), [5, 3]);
        assert!((unit.height(4, 2) - 14.0 * 4369.0 / 65535.0).abs() < 1e-6);
        let missing = TerrainDescription {
            source: TerrainHeightSource::Png(PngTerrainSource {
                path: String::from("nope.png"),
            }),
            ..terrain
        };
        let error = missing.unit_heights(&dir).unwrap_err();
        assert_eq!(error.field, "source.Png.path");
        assert!(error.reason.contains("nope.png"), "{}", error.reason);

        let scene = parse("(source: Png((path: \"nope.png\")))").unwrap();
        let message = scene
            .build_terrain(&dir.join("t.ron"))
            .unwrap_err()
            .to_string();
        assert!(
            message.contains("t.ron: field terrain.source.Png.path: cannot read")
                && message.contains("nope.png"),
            "{message}"
        );
        assert!(
            parse("(source: Procedural((dims: 9)))")
                .unwrap()
                .build_terrain(Path::new("a.ron"))
                .unwrap()
                .is_some()
        );
    }
}
