//! The statistics `nebel render --stats FILE.json` writes.
//!
//! ```json
//! {
//!   "adapter": { "name": "llvmpipe (LLVM 15.0.6, 256 bits)", "backend": "Vulkan", "device_type": "Cpu" },
//!   "frames_rendered": 8,
//!   "width": 320, "height": 240,
//!   "frame_wall_ms": { "median": 41.2, "mean": 60.3, "max": 380.5 },
//!   "warm_up_frames": 2,
//!   "warm_up_frame_wall_ms": { "median": 700.1, "mean": 955.2, "max": 1210.4 },
//!   "nebel_systems_cpu_ms": { "median": 0.01, "mean": 0.01, "max": 0.02 },
//!   "nebel_systems_wall_ms": { "median": 0.02, "mean": 0.02, "max": 0.05 },
//!   "nebel_builds_cpu_ms": { "median": 0.0, "mean": 1.2, "max": 9.8 },
//!   "per_frame_ms": { "wall": [41.2, 380.5, ...], "nebel_systems": [0.01, 0.02, ...], "nebel_systems_wall": [0.02, 0.05, ...] },
//!   "effects": { }
//! }
//! ```
//!
//! `frame_wall_ms` is the whole `App::update` plus waiting for the GPU, per
//! scene frame; `warm_up_frame_wall_ms` the same for the frames before the
//! first, until every pipeline compiled; `nebel_systems_cpu_ms` is the
//! diagnostic `nebel/systems_cpu_ms` of the scene frames (the CPU time of
//! nebel's systems) and `nebel_systems_wall_ms` the diagnostic
//! `nebel/systems_ms` (the wall time of their set, an upper bound);
//! `nebel_builds_cpu_ms` the diagnostic `nebel/builds_cpu_ms` (the CPU time of
//! the builds on the task pool that ended in each frame); under a build budget
//! (`--build-budget-ms`) `budgeted_builds_ms` summarises the diagnostic
//! `nebel/volume/budgeted_build_ms`, the work of the budgeted builds per
//! frame; `per_frame_ms` lists these per scene frame, in order; `effects` has one
//! object per effect present in the scene with the latest value of each of
//! its `nebel/<effect>/<counter>` diagnostics (and `_mean` and `_max` over the
//! history of each timing), none for an absent effect.

use std::collections::BTreeMap;
use std::time::Duration;

use serde::Serialize;

/// What the renderer ran on.
#[derive(Clone, Debug, Serialize, PartialEq, Eq)]
pub struct AdapterSummary {
    /// The adapter's name as the driver reports it.
    pub name: String,
    /// The graphics API: Vulkan, Gl, Metal, Dx12.
    pub backend: String,
    /// Cpu (a software driver such as lavapipe), `DiscreteGpu`, `IntegratedGpu`, ...
    pub device_type: String,
}

/// Median, mean and maximum of a per-frame time, milliseconds.
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct TimeSummary {
    /// Median over the frames, ms.
    pub median: f64,
    /// Mean over the frames, ms.
    pub mean: f64,
    /// Maximum over the frames, ms.
    pub max: f64,
}

impl TimeSummary {
    /// Summarises per-frame durations; zeros for an empty list.
    pub fn of(durations: &[Duration]) -> Self {
        let mut millis: Vec<f64> = durations.iter().map(|d| d.as_secs_f64() * 1e3).collect();
        millis.sort_by(f64::total_cmp);
        let Some(&max) = millis.last() else {
            return Self::default();
        };
        let middle = millis.len() / 2;
        let median = if millis.len() % 2 == 1 {
            millis[middle]
        } else {
            (millis[middle - 1] + millis[middle]) / 2.0
        };
        let mean = millis.iter().sum::<f64>() / millis.len() as f64;
        Self { median, mean, max }
    }
}

/// The times of every scene frame, milliseconds, in frame order.
#[derive(Clone, Debug, Default, Serialize, PartialEq)]
pub struct FrameTimes {
    /// Wall time of each frame, update plus GPU wait.
    pub wall: Vec<f64>,
    /// CPU time of nebel's systems in each frame.
    pub nebel_systems: Vec<f64>,
    /// Wall time of the `NebelSystems` set in each frame.
    pub nebel_systems_wall: Vec<f64>,
    /// Under a build budget, the CPU time the budgeted builds worked in
    /// each frame (empty, and not written, without one).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub budgeted_builds: Vec<f64>,
}

impl FrameTimes {
    /// The times in milliseconds.
    pub fn of(
        wall: &[Duration],
        nebel_systems: &[Duration],
        nebel_systems_wall: &[Duration],
        budgeted_builds: &[Duration],
    ) -> Self {
        let millis = |times: &[Duration]| times.iter().map(|d| d.as_secs_f64() * 1e3).collect();
        Self {
            wall: millis(wall),
            nebel_systems: millis(nebel_systems),
            nebel_systems_wall: millis(nebel_systems_wall),
            budgeted_builds: millis(budgeted_builds),
        }
    }
}

/// The statistics of one headless render.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct RenderStats {
    /// What the renderer ran on.
    pub adapter: AdapterSummary,
    /// Frames run (the image shows the last).
    pub frames_rendered: u32,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Wall time per frame, update plus GPU wait.
    pub frame_wall_ms: TimeSummary,
    /// Frames run before the first scene frame, with time standing still,
    /// until every pipeline compiled.
    pub warm_up_frames: u32,
    /// Wall time per warm-up frame (the first one includes the scene's
    /// setup and, with builds that wait, its first builds).
    pub warm_up_frame_wall_ms: TimeSummary,
    /// CPU time per frame of nebel's systems.
    pub nebel_systems_cpu_ms: TimeSummary,
    /// Wall time per frame of the `NebelSystems` set: an upper bound.
    pub nebel_systems_wall_ms: TimeSummary,
    /// CPU time of the builds on the task pool that ended in each frame.
    pub nebel_builds_cpu_ms: TimeSummary,
    /// Under a build budget (`--build-budget-ms`), the CPU time per frame
    /// the budgeted builds (an animated volume's keyframes and refinement
    /// steps) worked, on nebel's worker threads: the work a game gives that
    /// budget each frame.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub budgeted_builds_ms: Option<TimeSummary>,
    /// Both times of every scene frame, in frame order.
    pub per_frame_ms: FrameTimes,
    /// Counters per effect present in the scene.
    pub effects: BTreeMap<String, BTreeMap<String, f64>>,
}

impl RenderStats {
    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("render statistics always serialise")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_summary_of_even_odd_and_empty() {
        let ms = |v: u64| Duration::from_millis(v);
        assert_eq!(TimeSummary::of(&[]), TimeSummary::default());
        assert_eq!(
            TimeSummary::of(&[ms(3), ms(1), ms(2)]),
            TimeSummary {
                median: 2.0,
                mean: 2.0,
                max: 3.0
            }
        );
        assert_eq!(
            TimeSummary::of(&[ms(4), ms(1), ms(2), ms(8)]),
            TimeSummary {
                median: 3.0,
                mean: 3.75,
                max: 8.0
            }
        );
    }
}
