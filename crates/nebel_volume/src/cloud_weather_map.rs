//! A cloud's weather map from grayscale map assets.
//!
//! [`CloudWeatherMap`] on a [`CloudVolume`]'s entity names grayscale maps
//! (PNGs through the `AssetServer`, or maps built in memory) of coverage and
//! cloud type over the cloud's box (`nebel_core::field::WeatherMap`: black no
//! cloud or stratus, white full coverage or cumulus). Once they are loaded,
//! [`VolumePlugin`](crate::VolumePlugin) sets [`CloudVolume::weather_map`]
//! from them, and again whenever the component or a map changes; until
//! then the cloud waits (its status pending) rather than being drawn without
//! its weather. A map that fails to load, or holds values outside [0, 1],
//! fails the volume's status with the reason. Removing the component removes
//! the weather.

use std::sync::Arc;

use bevy::math::DVec2;
use bevy::prelude::*;
use nebel_core::field::{HeightField, WeatherMap};
use nebel_render::GrayscaleMap;

use crate::CloudVolume;
use crate::cloud::{CloudGeneration, WeatherState};
use crate::status::VolumeError;

/// Grayscale maps of coverage and cloud type over a [`CloudVolume`]'s box
/// (see the module docs); it replaces [`CloudVolume::weather_map`]. The
/// cloud waits until `coverage` (the default handle never loads) and `kind`
/// are loaded.
#[derive(Component, Clone, Debug, Reflect)]
#[reflect(Component, Default, Clone)]
pub struct CloudWeatherMap {
    /// Coverage: black no cloud, white the cloud's full coverage; the map's
    /// first column at the box's minimum x, its first row at its minimum z.
    pub coverage: Handle<GrayscaleMap>,
    /// Cloud type: black stratus, white cumulus; `None` is cumulus
    /// everywhere. Default `None`.
    pub kind: Option<Handle<GrayscaleMap>>,
    /// Top of a stratus column, a fraction of the box's height in (0, 1].
    /// Default 0.35.
    pub stratus_top: f32,
}

impl Default for CloudWeatherMap {
    fn default() -> Self {
        Self {
            coverage: Handle::default(),
            kind: None,
            stratus_top: 0.35,
        }
    }
}

impl CloudWeatherMap {
    /// The weather map once every map is loaded: `Ok(None)` while one loads.
    fn resolve(
        &self,
        maps: &Assets<GrayscaleMap>,
        asset_server: &AssetServer,
    ) -> Result<Option<WeatherMap>, VolumeError> {
        let field = |handle: &Handle<GrayscaleMap>| -> Result<Option<HeightField>, VolumeError> {
            if let Some((path, error)) = GrayscaleMap::load_failure(handle, asset_server) {
                return Err(VolumeError::WeatherMapNotLoaded { path, error });
            }
            let Some(map) = maps.get(handle) else {
                return Ok(None);
            };
            let dims = [map.dims.x as usize, map.dims.y as usize];
            let values = map.values.as_ref().clone();
            Ok(Some(HeightField::new(
                dims,
                DVec2::ONE,
                DVec2::ZERO,
                values,
            )?))
        };
        let Some(coverage) = field(&self.coverage)? else {
            return Ok(None);
        };
        let kind = match &self.kind {
            Some(handle) => match field(handle)? {
                Some(kind) => Some(kind),
                None => return Ok(None),
            },
            None => None,
        };
        Ok(Some(WeatherMap::new(coverage, kind, self.stratus_top)?))
    }

    /// Whether `id` is one of the maps.
    fn uses(&self, id: AssetId<GrayscaleMap>) -> bool {
        self.coverage.id() == id || self.kind.as_ref().is_some_and(|kind| kind.id() == id)
    }
}

/// Sets each cloud's weather map from its [`CloudWeatherMap`] when the
/// component or one of its maps changed, or while it waits for them; clears
/// the weather of a cloud whose component was removed.
pub(crate) fn apply_weather_maps(
    mut clouds: Query<(Ref<CloudWeatherMap>, &mut CloudVolume, &mut CloudGeneration)>,
    mut unmapped: Query<(&mut CloudVolume, &mut CloudGeneration), Without<CloudWeatherMap>>,
    mut removed: RemovedComponents<CloudWeatherMap>,
    mut events: MessageReader<AssetEvent<GrayscaleMap>>,
    maps: Res<Assets<GrayscaleMap>>,
    asset_server: Res<AssetServer>,
) {
    let changed = GrayscaleMap::changed(&mut events);
    for (weather, mut cloud, mut generation) in &mut clouds {
        let waiting = matches!(generation.weather, WeatherState::Loading);
        if !(weather.is_changed() || waiting || changed.iter().any(|id| weather.uses(*id))) {
            continue;
        }
        generation.weather = match weather.resolve(&maps, &asset_server) {
            Ok(Some(map)) => {
                cloud.weather_map = Some(Arc::new(map));
                WeatherState::Ready
            }
            Ok(None) => WeatherState::Loading,
            Err(error) => WeatherState::Failed(error),
        };
    }
    for entity in removed.read() {
        if let Ok((mut cloud, mut generation)) = unmapped.get_mut(entity) {
            cloud.weather_map = None;
            generation.weather = WeatherState::Ready;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::volume_grid;
    use crate::{VolumePlugin, VolumeStatus};
    use nebel_render::headless::headless_app;

    fn map(app: &mut App, values: impl Fn(u32) -> f32) -> Handle<GrayscaleMap> {
        let values = (0..16).map(|n| values(n % 4)).collect();
        app.world_mut()
            .resource_mut::<Assets<GrayscaleMap>>()
            .add(GrayscaleMap {
                dims: UVec2::splat(4),
                values: Arc::new(values),
            })
    }

    #[test]
    fn a_clouds_weather_comes_from_its_maps() {
        let mut app = headless_app(None);
        app.add_plugins(VolumePlugin);
        // Clear on the left half of the box, full coverage on the right.
        let coverage = map(&mut app, |x| if x < 2 { 0.0 } else { 1.0 });
        let cloud = app
            .world_mut()
            .spawn((
                CloudVolume {
                    dims: UVec3::new(13, 5, 13),
                    noise: nebel_core::field::CloudNoise {
                        coverage: 1.0,
                        side_fade: 0.0,
                        wavelength: 8.0,
                        ..default()
                    },
                    ..default()
                },
                CloudWeatherMap {
                    coverage,
                    ..default()
                },
                InheritedVisibility::VISIBLE,
            ))
            .id();
        let has_weather = |app: &App| {
            app.world()
                .get::<CloudVolume>(cloud)
                .unwrap()
                .weather_map
                .is_some()
        };
        app.update();
        assert!(has_weather(&app));
        let grid = volume_grid(&app, cloud).expect("generated under its weather");
        let [nx, ny, nz] = grid.dims();
        for k in 0..nz {
            for j in 0..ny {
                assert_eq!(grid.value(0, j, k), 0.0, "the clear side");
            }
        }
        assert!((0..nz).any(|k| (0..ny).any(|j| grid.value(nx - 1, j, k) > 0.0)));

        // A map outside [0, 1] fails the cloud, naming it.
        let bad = map(&mut app, |_| 1.5);
        app.world_mut()
            .get_mut::<CloudWeatherMap>(cloud)
            .unwrap()
            .kind = Some(bad);
        app.update();
        match app.world().get::<VolumeStatus>(cloud).unwrap() {
            VolumeStatus::Failed(error) => {
                let message = error.to_string();
                assert!(
                    message.contains("kind") && message.contains("1.5"),
                    "{message}"
                );
            }
            status => panic!("failed, not {status:?}"),
        }

        // Without the component, no weather.
        app.world_mut()
            .entity_mut(cloud)
            .remove::<CloudWeatherMap>();
        app.update();
        assert!(!has_weather(&app));
        assert!(!matches!(
            app.world().get::<VolumeStatus>(cloud).unwrap(),
            VolumeStatus::Failed(_)
        ));
    }
}
