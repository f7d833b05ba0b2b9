//! A point light whose intensity flickers like firelight.
//!
//! [`FlickeringLight`] scales its entity's [`PointLight::intensity`] every
//! frame by `1 + amplitude · n(t)`, where `n(t)` is a fixed sum of three sines
//! with incommensurate frequencies (2.9, 7.3 and 13.1 Hz), normalised to
//! [−1, 1]: deterministic, so headless renders are repeatable, and never
//! periodic to the eye. The campfire scene uses it for the fire's light.

use bevy::prelude::*;

/// Makes a [`PointLight`] flicker around `base_intensity`.
#[derive(Component, Clone, Copy, Debug, Reflect)]
#[reflect(Component, Default, Clone)]
#[require(PointLight)]
pub struct FlickeringLight {
    /// The mean luminous power, lumens. Default 100 000.
    pub base_intensity: f32,
    /// Relative amplitude of the flicker, in [0, 1]. Default 0.3.
    pub amplitude: f32,
}

impl Default for FlickeringLight {
    fn default() -> Self {
        Self {
            base_intensity: 100_000.0,
            amplitude: 0.3,
        }
    }
}

impl FlickeringLight {
    /// The intensity at `time` seconds.
    pub fn intensity_at(&self, time: f32) -> f32 {
        let factor = nebel_core::local_light::flicker(f64::from(self.amplitude), f64::from(time));
        self.base_intensity * factor as f32
    }
}

/// Animates every [`FlickeringLight`].
#[derive(Default)]
pub struct FlickeringLightPlugin;

impl Plugin for FlickeringLightPlugin {
    fn build(&self, app: &mut App) {
        app.register_type::<FlickeringLight>().add_systems(
            Update,
            nebel_render::cpu_timed(flicker).in_set(nebel_render::NebelSystems),
        );
    }
}

fn flicker(time: Res<Time>, mut lights: Query<(&FlickeringLight, &mut PointLight)>) {
    for (flickering, mut light) in &mut lights {
        light.intensity = flickering.intensity_at(time.elapsed_secs());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flicker_stays_within_its_amplitude_and_varies() {
        let light = FlickeringLight {
            base_intensity: 1000.0,
            amplitude: 0.4,
        };
        let samples: Vec<f32> = (0..500)
            .map(|i| light.intensity_at(i as f32 / 97.0))
            .collect();
        assert!(samples.iter().all(|i| (600.0..=1400.0).contains(i)));
        let spread = samples.iter().copied().fold(f32::MIN, f32::max)
            - samples.iter().copied().fold(f32::MAX, f32::min);
        assert!(spread > 400.0, "spread {spread}");
        assert_eq!(light.intensity_at(0.25), light.intensity_at(0.25));
    }

    #[test]
    fn the_system_drives_the_light() {
        let mut app = App::new();
        app.add_plugins((MinimalPlugins, FlickeringLightPlugin));
        let light = app
            .world_mut()
            .spawn(FlickeringLight {
                base_intensity: 500.0,
                amplitude: 0.0,
            })
            .id();
        app.update();
        assert_eq!(
            app.world().get::<PointLight>(light).unwrap().intensity,
            500.0
        );
    }
}
