//! What every effect plugin shares: the status of an effect's entity, its
//! diagnostics' registration, its failures logged once, and the error of a
//! setting out of its range.
//!
//! Each effect names its status after itself, e.g. `pub type AuroraStatus =
//! EffectStatus<SkyLayerError>`, so a game reads `AuroraStatus::Failed(error)`
//! and two effects on one entity keep separate statuses.

use std::fmt::Display;
use std::ops::DerefMut;

use bevy::diagnostic::{Diagnostic, DiagnosticPath, RegisterDiagnostic};
use bevy::prelude::*;
use bevy::reflect::{FromReflect, GetTypeRegistration, Typed};
use thiserror::Error;

/// Implements `PartialEq` for an effect's error by its message: two failures
/// are the same when they say the same (their sources are `Arc`s of errors
/// that have no `PartialEq`). [`EffectStatus::fail`] logs a failure only
/// when it differs from the last.
#[macro_export]
macro_rules! eq_by_message {
    ($error:ty) => {
        impl PartialEq for $error {
            fn eq(&self, other: &Self) -> bool {
                self.to_string() == other.to_string()
            }
        }
    };
}

/// A setting out of its range: its name, the value given and what it must
/// be. Each effect's error carries it.
#[derive(Clone, Copy, Debug, PartialEq, Error)]
#[error("{setting} = {value} is invalid: it must be {requirement}")]
pub struct InvalidSetting {
    /// The setting's name.
    pub setting: &'static str,
    /// The value given.
    pub value: f32,
    /// What it must be.
    pub requirement: &'static str,
}

impl InvalidSetting {
    /// `Err` of the setting unless `ok`.
    pub fn check(
        ok: bool,
        setting: &'static str,
        value: f32,
        requirement: &'static str,
    ) -> Result<(), Self> {
        if ok {
            return Ok(());
        }
        Err(Self {
            setting,
            value,
            requirement,
        })
    }
}

/// Whether an effect's entity is drawn, still waiting, or failed, and why.
/// Read it to show a loading screen or an error.
#[derive(Component, Clone, Debug, Default, PartialEq, Reflect)]
#[reflect(Component, Default, Clone)]
pub enum EffectStatus<E>
where
    E: Clone + Send + Sync + FromReflect + TypePath + Typed + GetTypeRegistration,
{
    /// Waiting for an asset, a build on the task pool or the first camera
    /// (the last result, if any, is drawn meanwhile).
    #[default]
    Pending,
    /// Built: drawn where the camera sees it, or nothing to draw (hidden,
    /// transparent, of no density).
    Ready,
    /// A setting, an asset or a build is unusable: why. Logged once per
    /// entity and reason; nothing is rebuilt until the entity, its settings
    /// or its assets change.
    Failed(E),
}

impl<E> EffectStatus<E>
where
    E: Clone
        + PartialEq
        + Display
        + Send
        + Sync
        + FromReflect
        + TypePath
        + Typed
        + GetTypeRegistration,
{
    /// Records a failure of the `effect` (its name in the log) on `entity`:
    /// one error line per entity and new reason. It writes `status` only
    /// for a new reason, so a `Mut` (pass `status.reborrow()`) is marked
    /// changed only when the status changes.
    pub fn fail(mut status: impl DerefMut<Target = Self>, effect: &str, entity: Entity, error: E) {
        if !matches!(&*status, Self::Failed(old) if *old == error) {
            error!("nebel: {effect} {entity} not drawn: {error}");
            *status = Self::Failed(error);
        }
    }
}

/// Registers an effect's diagnostics, each with its suffix (`" ms"` for
/// timings, `""` for counts).
pub fn register_diagnostics(app: &mut App, diagnostics: &[(DiagnosticPath, &'static str)]) {
    for (path, suffix) in diagnostics {
        app.register_diagnostic(Diagnostic::new(path.clone()).with_suffix(*suffix));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Clone, Debug, PartialEq, thiserror::Error, Reflect)]
    #[reflect(opaque, Clone, Debug, PartialEq)]
    #[error("bad {0}")]
    struct Bad(u32);

    #[test]
    fn a_failure_is_recorded_once_per_reason() {
        let entity = Entity::from_raw_u32(1).unwrap();
        let mut status = EffectStatus::<Bad>::default();
        assert_eq!(status, EffectStatus::Pending);
        EffectStatus::fail(&mut status, "test", entity, Bad(1));
        assert_eq!(status, EffectStatus::Failed(Bad(1)));
        EffectStatus::fail(&mut status, "test", entity, Bad(2));
        assert_eq!(status, EffectStatus::Failed(Bad(2)));
    }

    #[test]
    fn the_same_failure_again_leaves_the_status_unchanged() {
        let mut world = World::new();
        let entity = world.spawn(EffectStatus::<Bad>::Pending).id();
        let fail = |world: &mut World, error| {
            let mut status = world.get_mut::<EffectStatus<Bad>>(entity).unwrap();
            EffectStatus::fail(status.reborrow(), "test", entity, error);
        };
        let changed = |world: &World| {
            world
                .entity(entity)
                .get_ref::<EffectStatus<Bad>>()
                .unwrap()
                .is_changed()
        };
        fail(&mut world, Bad(1));
        world.clear_trackers();
        fail(&mut world, Bad(1));
        assert!(!changed(&world), "the same reason: not written");
        fail(&mut world, Bad(2));
        assert!(changed(&world), "a new reason: written");
    }
}
