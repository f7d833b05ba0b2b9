//! The sun in ground fog: a sorted fog with a [`GroundFog::sun_color`] gets
//! the terrain's shadow and its own column above each point as a
//! [`CellFogSunlight`] beside its `CellBatch` (`nebel_core::fog_sunlight`
//! has the model, `nebel_render::fog_sunlight` draws it).
//!
//! The sun is the first `DirectionalLight` (none: the fog is unlit by it).
//! The map (ground, thickness and shadow height at up to
//! `FogSunMap::MAX_POINTS` points a side over the terrain) is built on the task
//! pool from the fog's map, transfer function, density and profile, again
//! when any of them changes, the terrain moves, or the sun turns (in the
//! terrain's frame) by more than [`SUN_STEP`], one build at a time; the fog
//! keeps the last map until the new one lands (the same frame under
//! `HeavyBuilds::Blocking`). The phase and the colour follow the sun every
//! frame; a sun with `shadow_maps_enabled` is also hidden by opaque meshes,
//! through Bevy's shadow map of it. A fog without a sun colour, unsorted,
//! or without cells has no map, no build and no `CellFogSunlight`: its
//! shader variant is the unlit one.

use std::sync::Arc;
use std::time::Instant;

use bevy::diagnostic::Diagnostics;
use bevy::math::DVec3;
use bevy::prelude::*;
use nebel_core::fog_sunlight::FogSunMap;
use nebel_core::optics::OpticalMode;
use nebel_render::camera::to_double_affine;
use nebel_render::{CellBatch, CellFogSunlight, HeavyBuild, HeavyBuilds};
use nebel_terrain::{TerrainLod, TerrainMapLod};

use crate::ground_fog::{GroundFog, GroundFogPlugin};

/// The angle, radians, by which the sun turns before the map is built again
/// (about 0.3°): a shadow edge 1 km from its ridge then steps by 5 m as the
/// sun turns about the vertical (between maps the shadow follows the sun's
/// elevation, `nebel_render::fog_sunlight`).
pub const SUN_STEP: f64 = 0.005;

/// What a fog's sun map was built from.
#[derive(Clone, Debug, PartialEq)]
struct SunKey {
    /// The mapped quadtree (by identity).
    quadtree: usize,
    /// The generation of the fog's [`SunSettings`].
    settings: u64,
    transform: GlobalTransform,
}

/// The fog's settings a sun map depends on: its transfer function (by
/// content), density and profile.
#[derive(Debug, PartialEq)]
struct SunSettings {
    transfer: u64,
    density: u32,
    profile: Vec<[f32; 2]>,
}

/// A fog's sun map, the build in flight and what each was built for.
#[derive(Component, Default)]
pub struct GroundFogSun {
    /// The fog's settings as last seen, and their generation (counted up
    /// when they change; looked at only when the `GroundFog` changed).
    settings: Option<(SunSettings, u64)>,
    built: Option<(SunKey, DVec3, Option<Arc<FogSunMap>>)>,
    building: Option<(SunKey, DVec3, HeavyBuild<(Option<FogSunMap>, f32)>)>,
}

/// Builds and hands over every sunlit fog's map (see the module docs).
pub(crate) fn update_fog_sunlight(
    mut commands: Commands,
    mut fogs: Query<(
        Entity,
        Ref<GroundFog>,
        &TerrainLod,
        Option<&TerrainMapLod>,
        &GlobalTransform,
        Has<CellBatch>,
        Option<&CellFogSunlight>,
        &mut GroundFogSun,
    )>,
    suns: Query<(&GlobalTransform, &DirectionalLight)>,
    mode: Res<HeavyBuilds>,
    mut diagnostics: Diagnostics,
) {
    let sun = suns.iter().next();
    let shadows = sun.is_some_and(|(_, light)| light.shadow_maps_enabled);
    let sun = sun.map(|(transform, _)| transform.back().as_vec3());
    for (entity, fog, lod, map, transform, has_batch, current, mut state) in &mut fogs {
        let colour = fog.sun_color.to_linear().to_vec3();
        let mapped = map.and_then(|map| map.quadtree.as_ref()).filter(|mapped| {
            lod.quadtree()
                .is_some_and(|own| Arc::ptr_eq(own, &mapped.base))
        });
        let wanted =
            has_batch && fog.drawn_mode() == OpticalMode::Sorted && colour.max_element() > 0.0;
        let (Some(sun), Some(mapped), true) = (sun, mapped, wanted) else {
            if state.built.is_some() || state.building.is_some() {
                *state = GroundFogSun::default();
            }
            if current.is_some() {
                commands.entity(entity).remove::<CellFogSunlight>();
            }
            continue;
        };
        let world_from_terrain = to_double_affine(transform);
        let terrain_from_world = world_from_terrain.inverse();
        let local_sun = terrain_from_world
            .transform_vector3(sun.as_dvec3())
            .normalize_or(DVec3::Y);
        if fog.is_changed() || state.settings.is_none() {
            let settings = SunSettings {
                transfer: fog.transfer_function.content_hash(),
                density: fog.density.to_bits(),
                profile: fog.profile.clone(),
            };
            if state.settings.as_ref().map(|(seen, _)| seen) != Some(&settings) {
                let generation = state.settings.as_ref().map_or(0, |(_, g)| g + 1);
                state.settings = Some((settings, generation));
            }
        }
        let key = SunKey {
            quadtree: Arc::as_ptr(&mapped.hierarchy) as usize,
            settings: state
                .settings
                .as_ref()
                .map_or(0, |(_, generation)| *generation),
            transform: *transform,
        };
        let fresh = |(built_key, built_sun): (&SunKey, DVec3)| {
            *built_key == key && built_sun.angle_between(local_sun) <= SUN_STEP
        };
        let up_to_date = state.built.as_ref().is_some_and(|(k, s, _)| fresh((k, *s)));
        // A build in flight lands before the next starts, so a sun that
        // turns faster than a build takes still gets a map per build.
        if !up_to_date && state.building.is_none() {
            let ground = mapped.base.clone();
            let thickness = mapped.map.clone();
            let (profile, density) = (fog.profile.clone(), fog.density);
            let transfer = fog.transfer_function.clone();
            let build = HeavyBuild::spawn(move || {
                let started = Instant::now();
                let map = transfer.scale_density(density).ok().and_then(|scaled| {
                    FogSunMap::of_fog(
                        ground.field(),
                        thickness.values(),
                        &profile,
                        &scaled,
                        local_sun,
                    )
                });
                (map, started.elapsed().as_secs_f32() * 1e3)
            });
            state.building = Some((key, local_sun, build));
        }
        if let Some((key, built_sun, build)) = state.building.as_mut()
            && let Some((map, ms)) = build.poll(*mode)
        {
            state.built = Some((key.clone(), *built_sun, map.map(Arc::new)));
            state.building = None;
            diagnostics.add_measurement(&GroundFogPlugin::SUN_MAP_MS, || f64::from(ms));
        }
        let Some(map) = state.built.as_ref().and_then(|(_, _, map)| map.clone()) else {
            if current.is_some() {
                commands.entity(entity).remove::<CellFogSunlight>();
            }
            continue;
        };
        let sunlight = CellFogSunlight {
            map,
            map_from_world: terrain_from_world,
            direction: sun,
            colour,
            asymmetry: fog.sun_asymmetry,
            shadows,
        };
        let same = current.is_some_and(|current| {
            Arc::ptr_eq(&current.map, &sunlight.map)
                && current.map_from_world == sunlight.map_from_world
                && (
                    current.direction,
                    current.colour,
                    current.asymmetry,
                    current.shadows,
                ) == (
                    sunlight.direction,
                    sunlight.colour,
                    sunlight.asymmetry,
                    sunlight.shadows,
                )
        });
        if !same {
            commands.entity(entity).insert(sunlight);
        }
    }
}
