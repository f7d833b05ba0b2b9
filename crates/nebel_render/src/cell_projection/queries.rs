//! The cell projection's GPU counters: the GPU time from the first cell pass
//! to the composite (two timestamps per view, where the device has
//! `TIMESTAMP_QUERY`) and, behind the debug setting [`CountCellFragments`],
//! the fragments the cell shader runs.
//!
//! The fragments are counted by the shader itself, one atomic addition per
//! invocation, because pipeline-statistics queries do not count the same
//! thing everywhere: lavapipe counts every rasterized fragment, also those
//! the early stencil test then rejects, so early termination would not show.
//! The counter costs GPU time, so it is off unless asked for; timings are
//! taken without it. Fragments per pixel are a frame's cell fragments over
//! the pixels of its views' viewports at their full resolution: the work of
//! the exact fragment shader per pixel, the same figure on every machine.
//! Where the device cannot force early tests (`SHADER_EARLY_DEPTH_TEST`),
//! the counter's atomic makes the shader run before the stencil test, so
//! there the figure includes the fragments early termination would reject
//! without the counter.
//!
//! The results come back a frame or two later through a small ring of
//! read-back buffers, so reading them never waits for the GPU.

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};

use bevy::prelude::*;
use bevy::render::extract_resource::ExtractResource;
use bevy::render::renderer::{PendingCommandBuffers, RenderDevice, RenderQueue};
use wgpu::{
    Buffer, BufferBinding, BufferDescriptor, BufferUsages, CommandEncoderDescriptor, Features,
    MapMode, QUERY_RESOLVE_BUFFER_ALIGNMENT, QuerySet, QuerySetDescriptor, QueryType,
    RenderPassTimestampWrites,
};

use super::{CellProjectionStats, FrameMeasurement};

/// Counts the fragments the cell shader runs, for the diagnostic
/// `nebel/cell_projection/fragments_per_pixel` (see the module docs). A
/// debug setting: every fragment adds to one atomic counter, which costs GPU
/// time. Default off.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq, Eq, Reflect, ExtractResource)]
#[reflect(Resource, Default, Debug, Clone)]
pub struct CountCellFragments(pub bool);

/// Timestamp queries per frame: two per view.
const TIMESTAMP_QUERIES: u32 = 16;
/// Frames whose results may be on their way back at once.
const RING: usize = 4;
/// Where the timestamps sit in the read-back buffer, after the counter.
const TIMESTAMP_OFFSET: u64 = QUERY_RESOLVE_BUFFER_ALIGNMENT;
const BUFFER_BYTES: u64 = TIMESTAMP_OFFSET + 8 * TIMESTAMP_QUERIES as u64;

/// The read-back buffer is on its way back.
const WAITING: u8 = 0;
/// The read-back buffer is mapped and can be read.
const MAPPED: u8 = 1;
/// The mapping failed: the frame's results are lost and its slot is freed.
const FAILED: u8 = 2;

/// The counters of one frame and the buffers their results come back in.
struct QueryFrame {
    timestamps: Option<QuerySet>,
    /// The fragment counter the cell shader adds to (one `u32`).
    fragments: Buffer,
    resolve: Buffer,
    read_back: Buffer,
    /// Timestamp pairs written this frame.
    views_timed: u32,
    /// Pixels of the views that drew cells this frame.
    pixels: u64,
    /// The shader counted fragments this frame.
    counted: bool,
    /// Where the read-back stands, set by the map callback: [`WAITING`],
    /// [`MAPPED`] or [`FAILED`].
    read_back_state: Arc<AtomicU8>,
    /// Between `map_async` and the read.
    in_flight: bool,
}

impl QueryFrame {
    fn new(device: &RenderDevice, timestamps: bool) -> Self {
        let wgpu = device.wgpu_device();
        let buffer = |label, size, usage| {
            wgpu.create_buffer(&BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        Self {
            timestamps: timestamps.then(|| {
                wgpu.create_query_set(&QuerySetDescriptor {
                    label: Some("nebel_cell_timestamps"),
                    ty: QueryType::Timestamp,
                    count: TIMESTAMP_QUERIES,
                })
            }),
            fragments: buffer(
                "nebel_cell_fragment_counter",
                4,
                BufferUsages::STORAGE | BufferUsages::COPY_SRC | BufferUsages::COPY_DST,
            ),
            resolve: buffer(
                "nebel_cell_query_resolve",
                BUFFER_BYTES,
                BufferUsages::QUERY_RESOLVE | BufferUsages::COPY_SRC | BufferUsages::COPY_DST,
            ),
            read_back: buffer(
                "nebel_cell_query_read_back",
                BUFFER_BYTES,
                BufferUsages::MAP_READ | BufferUsages::COPY_DST,
            ),
            views_timed: 0,
            pixels: 0,
            counted: false,
            read_back_state: Arc::default(),
            in_flight: false,
        }
    }

    fn is_used(&self) -> bool {
        self.counted || self.views_timed > 0
    }

    /// Frees the slot for a new frame.
    fn free(&mut self) {
        self.views_timed = 0;
        self.pixels = 0;
        self.counted = false;
        self.in_flight = false;
    }
}

/// The GPU counters of the cell projection (see the module docs).
#[derive(Resource)]
pub struct CellQueries {
    frames: Vec<QueryFrame>,
    /// The frame being recorded.
    current: usize,
    timestamp_period_ns: f32,
    /// A counter for frames whose slot is still on its way back: bound but
    /// never read.
    spare_counter: Buffer,
}

impl FromWorld for CellQueries {
    fn from_world(world: &mut World) -> Self {
        let device = world.resource::<RenderDevice>();
        let timestamps = device.features().contains(Features::TIMESTAMP_QUERY);
        Self {
            frames: (0..RING)
                .map(|_| QueryFrame::new(device, timestamps))
                .collect(),
            current: 0,
            timestamp_period_ns: world.resource::<RenderQueue>().get_timestamp_period(),
            spare_counter: device.wgpu_device().create_buffer(&BufferDescriptor {
                label: Some("nebel_cell_spare_fragment_counter"),
                size: 4,
                usage: BufferUsages::STORAGE,
                mapped_at_creation: false,
            }),
        }
    }
}

/// The counters of one view's cell passes this frame.
pub struct ViewQueries<'a> {
    frame: Option<&'a mut QueryFrame>,
    spare_counter: &'a Buffer,
}

impl CellQueries {
    /// The counters of a view of `pixels` pixels that draws cells, counting
    /// fragments if `count_fragments`; counts nothing while the frame's slot
    /// is still on its way back.
    pub fn view(&mut self, pixels: u64, count_fragments: bool) -> ViewQueries<'_> {
        let frame = &mut self.frames[self.current];
        let frame = (!frame.in_flight).then(|| {
            frame.pixels += pixels;
            frame.counted |= count_fragments;
            frame
        });
        ViewQueries {
            frame,
            spare_counter: &self.spare_counter,
        }
    }
}

impl ViewQueries<'_> {
    /// The timestamp writes of the view's first (`end` false) or last
    /// (`end` true) pass.
    pub fn timestamp(&self, end: bool) -> Option<RenderPassTimestampWrites<'_>> {
        let frame = self.frame.as_deref()?;
        let set = frame.timestamps.as_ref()?;
        if frame.views_timed * 2 + 2 > TIMESTAMP_QUERIES {
            return None;
        }
        let index = frame.views_timed * 2 + u32::from(end);
        Some(RenderPassTimestampWrites {
            query_set: set,
            beginning_of_pass_write_index: (!end).then_some(index),
            end_of_pass_write_index: end.then_some(index),
        })
    }

    /// Marks the view's timestamp pair as written.
    pub fn timed(&mut self) {
        if let Some(frame) = self.frame.as_deref_mut()
            && frame.timestamps.is_some()
            && frame.views_timed * 2 + 2 <= TIMESTAMP_QUERIES
        {
            frame.views_timed += 1;
        }
    }

    /// The fragment counter to bind.
    pub fn fragment_counter(&self) -> BufferBinding<'_> {
        self.frame
            .as_deref()
            .map_or(self.spare_counter, |frame| &frame.fragments)
            .as_entire_buffer_binding()
    }
}

/// Copies this frame's counter and resolves its timestamps into its
/// read-back buffer, in an encoder of its own submitted after the frame's
/// passes.
pub fn resolve_cell_queries(
    mut queries: ResMut<CellQueries>,
    device: Res<RenderDevice>,
    mut pending: ResMut<PendingCommandBuffers>,
) {
    let current = queries.current;
    let frame = &mut queries.frames[current];
    if frame.in_flight || !frame.is_used() {
        return;
    }
    let mut encoder = device
        .wgpu_device()
        .create_command_encoder(&CommandEncoderDescriptor {
            label: Some("nebel_cell_query_resolve"),
        });
    if let Some(set) = &frame.timestamps
        && frame.views_timed > 0
    {
        encoder.resolve_query_set(
            set,
            0..frame.views_timed * 2,
            &frame.resolve,
            TIMESTAMP_OFFSET,
        );
    }
    encoder.copy_buffer_to_buffer(&frame.fragments, 0, &frame.resolve, 0, 4);
    encoder.clear_buffer(&frame.fragments, 0, None);
    encoder.copy_buffer_to_buffer(&frame.resolve, 0, &frame.read_back, 0, BUFFER_BYTES);
    pending.push_encoder(encoder);
}

/// After the frame's submission: maps its read-back buffer and moves on to
/// the next slot of the ring.
pub fn map_cell_queries(mut queries: ResMut<CellQueries>) {
    let current = queries.current;
    let frame = &mut queries.frames[current];
    if frame.in_flight {
        return;
    }
    if !frame.is_used() {
        // Nothing measured: the pixels do not carry over to the next frame.
        frame.pixels = 0;
        return;
    }
    frame.in_flight = true;
    let state = frame.read_back_state.clone();
    frame
        .read_back
        .slice(..)
        .map_async(MapMode::Read, move |result| {
            state.store(
                if result.is_ok() { MAPPED } else { FAILED },
                Ordering::Release,
            );
        });
    queries.current = (current + 1) % RING;
}

/// Before a frame: reads the frames whose results came back into the
/// [`CellProjectionStats`] and frees their slots; a slot whose mapping
/// failed is freed without a measurement.
pub fn collect_cell_queries(mut queries: ResMut<CellQueries>, stats: Res<CellProjectionStats>) {
    let period_ns = f64::from(queries.timestamp_period_ns);
    for frame in &mut queries.frames {
        if !frame.in_flight {
            continue;
        }
        match frame.read_back_state.swap(WAITING, Ordering::Acquire) {
            MAPPED => {}
            FAILED => {
                frame.free();
                continue;
            }
            _ => continue,
        }
        let (fragments, timestamps): (u32, Vec<u64>) = {
            let data = frame.read_back.slice(..).get_mapped_range();
            let offset = TIMESTAMP_OFFSET as usize;
            let timestamps = &data[offset..offset + 16 * frame.views_timed as usize];
            (
                bytemuck::pod_read_unaligned(&data[..4]),
                bytemuck::pod_collect_to_vec(timestamps),
            )
        };
        frame.read_back.unmap();
        let fragments_per_pixel =
            (frame.counted && frame.pixels > 0).then(|| f64::from(fragments) / frame.pixels as f64);
        let gpu_ms = (frame.views_timed > 0).then(|| {
            timestamps
                .chunks_exact(2)
                .map(|pair| pair[1].saturating_sub(pair[0]) as f64 * period_ns / 1e6)
                .sum()
        });
        stats.record(FrameMeasurement {
            fragments_per_pixel,
            gpu_ms,
        });
        frame.free();
    }
}
