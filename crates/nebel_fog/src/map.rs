//! Building a ground fog's map on the task pool: its thickness per grid
//! point of the terrain's quadtree and the quadtree with the thickness's
//! roughness added to d2 (Röttger and Ertl 2003 §6: the fog's thickness
//! enters the refinement with a weight).
//!
//! `build_ground_fog_maps` notices a new fog, a new terrain quadtree, a changed
//! thickness source or `roughness_weight` (compared bit for bit), and a fog
//! map that was added, loaded or modified, and starts the build on Bevy's
//! `AsyncComputeTaskPool` (one at a time per fog; at once under
//! `HeavyBuilds::Blocking`). Its result goes to the terrain as a
//! [`TerrainMapLod`], which the terrain's refinement then carries; a fog of
//! no thickness anywhere, no density or a transparent transfer function
//! gives none (the terrain refines alone, and nothing of the fog runs per
//! frame; the map is kept for when the fog can be seen again). Unless the
//! fog, its map or the terrain's quadtree changed, the system only reads the
//! fog's density and transfer function and compares pointers per fog: no
//! key is formatted and nothing is built.
//!
//! A sorted fog's prisms are ordered for the eye the terrain was last refined
//! for, so it keeps the terrain's update distance to at most half a grid
//! spacing ([`TerrainMapLod::max_update_distance`]); with the latency of a
//! build in the background the order is drawn for an eye up to about a
//! spacing away, which `nebel_lod`'s ground-fog tests hold to half an 8-bit
//! step in RMS. An unsorted fog needs no order and leaves the terrain's own.

use std::sync::Arc;
use std::time::Instant;

use bevy::diagnostic::Diagnostics;
use bevy::prelude::*;
use nebel_core::field::{FogNoise, ValleyFog};
use nebel_core::optics::OpticalMode;
use nebel_lod::TerrainHierarchy;
use nebel_lod::quadtree::TerrainMap;
use nebel_render::GrayscaleMap;
use nebel_render::{EffectiveQuality, HeavyBuild, HeavyBuilds, InvalidSetting};
use nebel_terrain::{MappedQuadtree, TerrainLod, TerrainMapLod};

use crate::error::GroundFogError;
use crate::ground_fog::{
    FogThickness, GroundFog, GroundFogPlugin, GroundFogStats, GroundFogStatus,
};

/// The most grid spacings the eye moves between the refinements of a sorted
/// fog's terrain (module docs).
const SORTED_UPDATE_DISTANCE: f32 = 0.5;

/// What a map is built from, bit for bit.
#[derive(Clone, Debug, PartialEq)]
struct MapKey {
    /// The terrain's quadtree (by identity).
    quadtree: usize,
    /// The thickness source as written (`Debug`), so a NaN setting compares
    /// equal to itself and is not rebuilt every frame.
    thickness: String,
    roughness_weight: u32,
}

/// Where a build takes the thickness from, owned.
enum ThicknessInput {
    Map {
        dims: [usize; 2],
        values: Arc<Vec<f32>>,
        scale: f32,
    },
    Noise(FogNoise),
    Valley(ValleyFog),
}

/// A finished map: `None` for a fog of no thickness anywhere.
struct BuiltMap {
    quadtree: Option<MappedQuadtree>,
    max_thickness: f32,
    build_ms: f32,
}

/// A ground fog's map and the build in flight.
#[derive(Component, Default)]
pub struct GroundFogMap {
    key: Option<MapKey>,
    build: Option<(MapKey, HeavyBuild<Result<BuiltMap, GroundFogError>>)>,
    /// The last map built, handed to the terrain while the fog can be
    /// seen.
    built: Option<MappedQuadtree>,
    /// The fog map changed while a build was in flight: build again when it
    /// lands.
    stale: bool,
}

/// The thickness of `input` on `base`'s grid, and `base` with its roughness.
fn build_map(
    base: Arc<TerrainHierarchy>,
    input: ThicknessInput,
    roughness_weight: f32,
) -> Result<BuiltMap, GroundFogError> {
    let started = Instant::now();
    let valid = roughness_weight.is_finite() && roughness_weight >= 0.0;
    InvalidSetting::check(
        valid,
        "roughness_weight",
        roughness_weight,
        "finite and ≥ 0",
    )?;
    let side = base.size();
    let spacing = base.field().spacing().x;
    let map = match input {
        ThicknessInput::Map {
            dims,
            values,
            scale,
        } => {
            let valid = scale.is_finite() && scale >= 0.0;
            InvalidSetting::check(valid, "thickness.Map.scale", scale, "finite and ≥ 0")?;
            let metres: Vec<f32> = values.iter().map(|v| v * scale).collect();
            TerrainMap::resample(&metres, dims, side)?
        }
        ThicknessInput::Noise(noise) => TerrainMap::new(side, noise.thickness(side, spacing)?)?,
        ThicknessInput::Valley(valley) => TerrainMap::new(side, valley.thickness(base.field())?)?,
    };
    let max_thickness = map.max();
    let quadtree = if map.is_zero() {
        None
    } else {
        let mut hierarchy = (*base).clone();
        hierarchy.add_map_roughness(&map, roughness_weight)?;
        Some(MappedQuadtree {
            base,
            hierarchy: Arc::new(hierarchy),
            map: Arc::new(map),
        })
    };
    Ok(BuiltMap {
        quadtree,
        max_thickness,
        build_ms: started.elapsed().as_secs_f32() * 1e3,
    })
}

/// The thickness input of `fog`, `Ok(None)` while its map loads.
fn thickness_input(
    fog: &GroundFog,
    maps: &Assets<GrayscaleMap>,
    asset_server: &AssetServer,
) -> Result<Option<ThicknessInput>, GroundFogError> {
    Ok(Some(match &fog.thickness {
        FogThickness::Noise(noise) => ThicknessInput::Noise(*noise),
        FogThickness::Valley(valley) => ThicknessInput::Valley(*valley),
        FogThickness::Map { map, scale } => match maps.get(map) {
            Some(asset) => ThicknessInput::Map {
                dims: [asset.dims.x as usize, asset.dims.y as usize],
                values: asset.values.clone(),
                scale: *scale,
            },
            None => {
                return match GrayscaleMap::load_failure(map, asset_server) {
                    Some((path, error)) => Err(GroundFogError::MapNotLoaded { path, error }),
                    None => Ok(None),
                };
            }
        },
    }))
}

/// Takes finished map builds and starts new ones (see the module docs).
pub(crate) fn build_ground_fog_maps(
    mut commands: Commands,
    mut fogs: Query<(
        Entity,
        Ref<GroundFog>,
        Option<&TerrainLod>,
        Option<&mut TerrainMapLod>,
        &mut GroundFogMap,
        &mut GroundFogStatus,
        &mut GroundFogStats,
    )>,
    maps: Res<Assets<GrayscaleMap>>,
    mut map_events: MessageReader<AssetEvent<GrayscaleMap>>,
    asset_server: Res<AssetServer>,
    mode: Res<HeavyBuilds>,
    quality: Option<Res<EffectiveQuality>>,
    mut diagnostics: Diagnostics,
) {
    let changed = GrayscaleMap::changed(&mut map_events);
    let prisms = quality.is_none_or(|quality| quality.ground_fog_prisms());
    for (entity, fog, lod, map_lod, mut state, mut status, mut stats) in &mut fogs {
        let Some(lod) = lod else {
            GroundFogStatus::fail(
                status.reborrow(),
                "ground fog",
                entity,
                GroundFogError::NoTerrain,
            );
            continue;
        };
        let max_update_distance =
            (fog.mode == OpticalMode::Sorted).then_some(SORTED_UPDATE_DISTANCE);
        let state = &mut *state;
        // A density out of range is a failure; fixed, the fog is what its
        // map makes it again.
        let density_valid = fog.density.is_finite() && fog.density >= 0.0;
        let density_failed = matches!(&*status, GroundFogStatus::Failed(GroundFogError::InvalidSetting(invalid)) if invalid.setting == "density");
        if !density_valid {
            GroundFogStatus::fail(
                status.reborrow(),
                "ground fog",
                entity,
                GroundFogError::InvalidSetting(InvalidSetting {
                    setting: "density",
                    value: fog.density,
                    requirement: "finite and ≥ 0",
                }),
            );
        } else if density_failed {
            *status = if state.key.is_some() && state.build.is_none() {
                GroundFogStatus::Ready
            } else {
                GroundFogStatus::Pending
            };
        }
        // A fog that draws nothing (no density, a transparent transfer
        // function, a quality that leaves it to the fog layers) leaves the
        // terrain refining alone.
        let drawn = prisms
            && density_valid
            && fog.density > 0.0
            && !fog.transfer_function.is_transparent(0.0, 1.0);
        if let Some(mut map_lod) = map_lod {
            if map_lod.max_update_distance != max_update_distance {
                map_lod.max_update_distance = max_update_distance;
            }
            let wanted = state.built.as_ref().filter(|_| drawn);
            let current = map_lod.quadtree.as_ref();
            let same = match (wanted, current) {
                (Some(a), Some(b)) => Arc::ptr_eq(&a.hierarchy, &b.hierarchy),
                (None, None) => true,
                _ => false,
            };
            if !same {
                map_lod.quadtree = wanted.cloned();
            }
        }
        let mut land = |state: &mut GroundFogMap, status: &mut GroundFogStatus| {
            let Some((key, build)) = state.build.as_mut() else {
                return;
            };
            let Some(result) = build.poll(*mode) else {
                return;
            };
            state.key = Some(key.clone());
            state.build = None;
            match result {
                Ok(built) => {
                    stats.build_ms = built.build_ms;
                    stats.max_thickness = built.max_thickness;
                    diagnostics
                        .add_measurement(&GroundFogPlugin::BUILD_MS, || f64::from(built.build_ms));
                    commands.entity(entity).insert(TerrainMapLod {
                        quadtree: built.quadtree.clone().filter(|_| drawn),
                        max_update_distance,
                    });
                    state.built = built.quadtree;
                    if density_valid {
                        *status = GroundFogStatus::Ready;
                    }
                }
                Err(error) => {
                    state.built = None;
                    commands.entity(entity).remove::<TerrainMapLod>();
                    GroundFogStatus::fail(&mut *status, "ground fog", entity, error);
                }
            }
        };
        let map_changed = matches!(&fog.thickness,
            FogThickness::Map { map, .. } if changed.contains(&map.id()));
        land(state, &mut status);
        if state.build.is_some() {
            state.stale |= map_changed;
            continue;
        }
        let Some(base) = lod.quadtree() else {
            // The terrain is loading, or failed (its status says why).
            *status = GroundFogStatus::Pending;
            continue;
        };
        let quadtree = Arc::as_ptr(base) as usize;
        let rebuild = map_changed || state.stale;
        let same_quadtree = state
            .key
            .as_ref()
            .is_some_and(|key| key.quadtree == quadtree);
        if !rebuild && same_quadtree && !fog.is_changed() {
            continue;
        }
        let key = MapKey {
            quadtree,
            thickness: format!("{:?}", fog.thickness),
            roughness_weight: fog.roughness_weight.to_bits(),
        };
        if !rebuild && state.key.as_ref() == Some(&key) {
            continue;
        }
        state.stale = false;
        match thickness_input(&fog, &maps, &asset_server) {
            Ok(None) => *status = GroundFogStatus::Pending,
            Ok(Some(input)) => {
                let (base, weight) = (base.clone(), fog.roughness_weight);
                state.build = Some((
                    key,
                    HeavyBuild::spawn(move || build_map(base, input, weight)),
                ));
                land(state, &mut status);
            }
            Err(error) => {
                state.key = Some(key);
                state.built = None;
                commands.entity(entity).remove::<TerrainMapLod>();
                GroundFogStatus::fail(status.reborrow(), "ground fog", entity, error);
            }
        }
    }
}
