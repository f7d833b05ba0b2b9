//! The pre-integration tables of the cell projection (Röttger 2004 §9.1) on
//! the GPU, built off the frame.
//!
//! A table takes tens of milliseconds to build, so a transfer function no
//! table exists for is built on Bevy's [`AsyncComputeTaskPool`], one table
//! at a time, and uploaded in the first frame after it is done. Until then
//! a batch draws with the last table it drew (nothing, the first time), so a
//! transfer function that changes every frame (a day cycle) draws every
//! frame with a table at most a build behind. Under
//! [`HeavyBuilds::Blocking`] the frame waits for its tables instead, and
//! every batch draws with its own. Tables are shared by batches with the
//! same transfer function; up to [`SPARE_TABLES`] unused ones are kept for a
//! transfer function that comes back.

use std::collections::{HashMap, HashSet};
use std::fmt::Display;
use std::sync::Arc;
use std::sync::atomic::Ordering;

use bevy::prelude::*;
use bevy::render::Extract;
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderDevice, RenderQueue};
use bevy::tasks::AsyncComputeTaskPool;
use nebel_core::preintegration::{PreintegrationConfig, PreintegrationError, PreintegrationTable};
use nebel_core::transfer::TransferFunction;

use super::CellProjectionStats;
use super::resources::{ExtractedCellBatches, TableKey};
use crate::builds::{HeavyBuild, HeavyBuilds};

/// Samples along `s_f` and `s_b` of the GPU tables.
const TABLE_SCALAR_SIZE: u32 = 64;
/// Samples along the optical-depth axis `u = τ / (1 + τ)` of the GPU colour table.
const TABLE_DEPTH_SIZE: u32 = 128;

/// Unused tables kept for a batch that may need them again (a transfer
/// function that goes back and forth), most recently used first. Each
/// colour table is 8 MiB.
const SPARE_TABLES: usize = 2;

/// The GPU copy of one [`PreintegrationTable`].
pub struct GpuCellTable {
    pub(super) colour: TextureView,
    pub(super) emission: TextureView,
    pub(super) maximum: TextureView,
    pub(super) parameters: UniformBuffer<CellTablesUniform>,
}

/// Parameters of the tables, as the shader's `CellTables`.
#[derive(Clone, Copy, Default, ShaderType)]
pub struct CellTablesUniform {
    scalar_size: u32,
    depth_size: u32,
}

/// The pre-integration tables of this frame's batches, the build in flight
/// and which table each batch draws with (see the module docs).
#[derive(Resource, Default)]
pub struct GpuCellTables(TableCache<PreintegrationTable, GpuCellTable, PreintegrationError>);

impl GpuCellTables {
    /// The table the batch of `entity` draws with this frame, if any.
    pub(super) fn drawn(&self, entity: Entity) -> Option<&GpuCellTable> {
        self.0.drawn(entity)
    }
}

/// A table being built, and the batches that asked for it.
struct TableBuild<B, E> {
    key: TableKey,
    batches: Vec<Entity>,
    build: HeavyBuild<Result<B, E>>,
}

/// The bookkeeping of [`GpuCellTables`], apart from the GPU: tables `T` made
/// from builds of `B` that may fail with `E`.
struct TableCache<B, T, E> {
    tables: HashMap<TableKey, T>,
    /// The keys of the tables, most recently used first.
    recent: Vec<TableKey>,
    building: Option<TableBuild<B, E>>,
    /// The table each batch draws with: its own, or the last one it drew.
    drawn: HashMap<Entity, TableKey>,
    /// Keys whose build failed, not tried again while a batch asks for them.
    failed: HashSet<TableKey>,
}

impl<B, T, E> Default for TableCache<B, T, E> {
    fn default() -> Self {
        Self {
            tables: HashMap::new(),
            recent: Vec::new(),
            building: None,
            drawn: HashMap::new(),
            failed: HashSet::new(),
        }
    }
}

impl<B: Send + 'static, T, E: Display + Send + 'static> TableCache<B, T, E> {
    /// Brings the tables up to this frame's `requests` (each batch's entity,
    /// its table's key and what the table is built from): takes a finished
    /// build through `finish`, starts the next missing table with `start`
    /// (waiting for each under [`HeavyBuilds::Blocking`]), assigns each batch
    /// its table and drops unused ones beyond the spares. Returns the tables
    /// finished.
    fn update<S>(
        &mut self,
        requests: &[(Entity, TableKey, S)],
        mode: HeavyBuilds,
        mut start: impl FnMut(&S) -> HeavyBuild<Result<B, E>>,
        mut finish: impl FnMut(B) -> T,
    ) -> u64 {
        let requested = |key: &TableKey| requests.iter().any(|(_, k, _)| k == key);
        self.drawn
            .retain(|entity, _| requests.iter().any(|(e, _, _)| e == entity));
        self.failed.retain(requested);
        let mut finished = 0;
        loop {
            if let Some(build) = &mut self.building {
                let Some(result) = build.build.poll(mode) else {
                    break;
                };
                let TableBuild { key, batches, .. } =
                    self.building.take().expect("polled just now");
                match result {
                    Ok(built) => {
                        self.tables.insert(key, finish(built));
                        self.recent.retain(|k| *k != key);
                        self.recent.insert(0, key);
                        finished += 1;
                        // The newest table built for each batch that asked.
                        for entity in batches {
                            self.drawn.insert(entity, key);
                        }
                    }
                    Err(error) => {
                        // Logged once per table: the same inputs fail the same way.
                        error!("nebel: cannot build the pre-integration table: {error}");
                        self.failed.insert(key);
                    }
                }
            }
            let next = requests
                .iter()
                .find(|(_, key, _)| !self.tables.contains_key(key) && !self.failed.contains(key));
            let Some((_, key, source)) = next else {
                break;
            };
            self.building = Some(TableBuild {
                key: *key,
                batches: requests
                    .iter()
                    .filter(|(_, k, _)| k == key)
                    .map(|(entity, _, _)| *entity)
                    .collect(),
                build: start(source),
            });
        }
        for (entity, key, _) in requests {
            if self.tables.contains_key(key) {
                self.drawn.insert(*entity, *key);
            }
        }
        // The tables drawn now first, then the others by recency, up to the spares.
        let drawn: HashSet<TableKey> = self.drawn.values().copied().collect();
        self.recent.sort_by_key(|key| !drawn.contains(key));
        let keep = if requests.is_empty() {
            0
        } else {
            drawn.len() + SPARE_TABLES
        };
        for key in self.recent.drain(keep.min(self.recent.len())..) {
            self.tables.remove(&key);
        }
        finished
    }

    /// The table the batch of `entity` draws with, if any.
    fn drawn(&self, entity: Entity) -> Option<&T> {
        self.tables.get(self.drawn.get(&entity)?)
    }
}

/// Whether the frame waits for heavy builds, as the main world says (the
/// default, [`HeavyBuilds::Background`], where it says nothing).
pub fn extract_heavy_builds(
    main: Extract<Option<Res<HeavyBuilds>>>,
    mut render: ResMut<HeavyBuilds>,
) {
    render.set_if_neq(main.as_deref().copied().unwrap_or_default());
}

/// Builds the tables this frame's batches need off the frame, uploads the
/// finished ones and chooses each batch's table (see the module docs).
pub fn prepare_cell_tables(
    extracted: Res<ExtractedCellBatches>,
    mut tables: ResMut<GpuCellTables>,
    mode: Res<HeavyBuilds>,
    device: Res<RenderDevice>,
    queue: Res<RenderQueue>,
    stats: Res<CellProjectionStats>,
) {
    let cache = &mut tables.0;
    if extracted.0.is_empty() && cache.tables.is_empty() && cache.building.is_none() {
        return;
    }
    let requests: Vec<(Entity, TableKey, Arc<TransferFunction>)> = extracted
        .0
        .iter()
        .map(|(entity, batch)| (*entity, batch.table_key, batch.transfer_function.clone()))
        .collect();
    let start = |transfer_function: &Arc<TransferFunction>| {
        let transfer_function = transfer_function.clone();
        // A frame that waits takes every core; otherwise as many threads as
        // Bevy gives its asynchronous compute.
        let threads = match *mode {
            HeavyBuilds::Blocking => std::thread::available_parallelism().map_or(1, usize::from),
            HeavyBuilds::Background | HeavyBuilds::Budgeted(_) => {
                AsyncComputeTaskPool::get().thread_num()
            }
        };
        HeavyBuild::spawn(move || {
            PreintegrationTable::build_with_threads(
                &transfer_function,
                PreintegrationConfig {
                    scalar_size: TABLE_SCALAR_SIZE,
                    depth_size: TABLE_DEPTH_SIZE,
                },
                threads,
            )
        })
    };
    let finished = cache.update(&requests, *mode, start, |table| {
        upload(&device, &queue, &table)
    });
    stats.0.tables_built.fetch_add(finished, Ordering::Relaxed);
}

/// The GPU copy of `table`.
fn upload(device: &RenderDevice, queue: &RenderQueue, table: &PreintegrationTable) -> GpuCellTable {
    let texture =
        |label: &'static str, size: Extent3d, dimension: TextureDimension, data: &[[f32; 4]]| {
            device
                .create_texture_with_data(
                    queue,
                    &TextureDescriptor {
                        label: Some(label),
                        size,
                        mip_level_count: 1,
                        sample_count: 1,
                        dimension,
                        format: TextureFormat::Rgba32Float,
                        usage: TextureUsages::TEXTURE_BINDING,
                        view_formats: &[],
                    },
                    TextureDataOrder::LayerMajor,
                    bytemuck::cast_slice(data),
                )
                .create_view(&TextureViewDescriptor::default())
        };
    let pair = Extent3d {
        width: TABLE_SCALAR_SIZE,
        height: TABLE_SCALAR_SIZE,
        depth_or_array_layers: 1,
    };
    let volume = Extent3d {
        depth_or_array_layers: TABLE_DEPTH_SIZE,
        ..pair
    };
    let mut parameters = UniformBuffer::from(CellTablesUniform {
        scalar_size: TABLE_SCALAR_SIZE,
        depth_size: TABLE_DEPTH_SIZE,
    });
    parameters.set_label(Some("nebel_cell_tables"));
    parameters.write_buffer(device, queue);
    GpuCellTable {
        colour: texture(
            "nebel_colour_table",
            volume,
            TextureDimension::D3,
            table.colour(),
        ),
        emission: texture(
            "nebel_emission_table",
            pair,
            TextureDimension::D2,
            table.emission(),
        ),
        maximum: texture(
            "nebel_maximum_table",
            pair,
            TextureDimension::D2,
            table.maximum(),
        ),
        parameters,
    }
}

#[cfg(test)]
mod tests {
    use std::sync::mpsc::{Receiver, channel};
    use std::time::Duration;

    use bevy::tasks::TaskPool;

    use super::*;

    /// Tables that are their key's hash, built from that hash.
    type Cache = TableCache<u64, u64, String>;

    fn key(hash: u64) -> TableKey {
        TableKey {
            transfer_hash: hash,
        }
    }

    fn request(entity: Entity, hash: u64) -> (Entity, TableKey, u64) {
        (entity, key(hash), hash)
    }

    /// One frame in `mode`, every build done at once.
    fn frame(cache: &mut Cache, requests: &[(Entity, TableKey, u64)], mode: HeavyBuilds) -> u64 {
        cache.update(
            requests,
            mode,
            |&hash| HeavyBuild::spawn(move || Ok(hash)),
            |table| table,
        )
    }

    /// One frame in the background whose builds wait for `gate`.
    fn gated_frame(
        cache: &mut Cache,
        requests: &[(Entity, TableKey, u64)],
        gate: &mut Option<Receiver<()>>,
    ) {
        cache.update(
            requests,
            HeavyBuilds::Background,
            |&hash| {
                let gate = gate.take().expect("one build per gate");
                HeavyBuild::spawn(move || {
                    gate.recv().ok();
                    Ok(hash)
                })
            },
            |table| table,
        );
    }

    /// Runs background frames of `requests` until `done` holds (a bounded
    /// number of frames a millisecond apart: a guard against a hang).
    fn frames_until(
        cache: &mut Cache,
        requests: &[(Entity, TableKey, u64)],
        done: impl Fn(&Cache) -> bool,
    ) {
        for _ in 0..10_000 {
            if done(cache) {
                return;
            }
            frame(cache, requests, HeavyBuilds::Background);
            std::thread::sleep(Duration::from_millis(1));
        }
        panic!("never done");
    }

    #[test]
    fn a_new_table_is_built_off_the_frame_while_the_last_one_draws() {
        AsyncComputeTaskPool::get_or_init(TaskPool::new);
        let mut cache = Cache::default();
        let batch = Entity::from_raw_u32(1).unwrap();
        let (open, gate) = channel();
        let mut gate = Some(gate);
        gated_frame(&mut cache, &[request(batch, 10)], &mut gate);
        assert_eq!(cache.drawn(batch), None, "nothing to draw the first time");
        open.send(()).unwrap();
        frames_until(&mut cache, &[request(batch, 10)], |cache| {
            cache.drawn(batch).is_some()
        });
        assert_eq!(cache.drawn(batch), Some(&10));

        let (open, gate) = channel();
        let mut gate = Some(gate);
        for _ in 0..3 {
            gated_frame(&mut cache, &[request(batch, 20)], &mut gate);
            assert_eq!(cache.drawn(batch), Some(&10), "the last table meanwhile");
        }
        open.send(()).unwrap();
        frames_until(&mut cache, &[request(batch, 20)], |cache| {
            cache.drawn(batch) == Some(&20)
        });
        assert!(cache.tables.contains_key(&key(10)), "kept as a spare");
    }

    #[test]
    fn blocking_draws_every_batch_with_its_own_table_in_its_frame() {
        AsyncComputeTaskPool::get_or_init(TaskPool::new);
        let mut cache = Cache::default();
        let [a, b, c] = [1, 2, 3].map(|i| Entity::from_raw_u32(i).unwrap());
        let requests = [request(a, 5), request(b, 6), request(c, 5)];
        assert_eq!(frame(&mut cache, &requests, HeavyBuilds::Blocking), 2);
        assert_eq!(cache.drawn(a), Some(&5));
        assert_eq!(cache.drawn(b), Some(&6));
        assert_eq!(cache.drawn(c), Some(&5), "shared with the same transfer");
        assert_eq!(frame(&mut cache, &requests, HeavyBuilds::Blocking), 0);
    }

    #[test]
    fn a_transfer_function_changing_every_frame_draws_every_frame() {
        AsyncComputeTaskPool::get_or_init(TaskPool::new);
        let mut cache = Cache::default();
        let batch = Entity::from_raw_u32(1).unwrap();
        let mut started = 0;
        let mut last_drawn = 0;
        for hash in 1..=200_u64 {
            cache.update(
                &[request(batch, hash)],
                HeavyBuilds::Background,
                |&hash| {
                    started += 1;
                    HeavyBuild::spawn(move || {
                        std::thread::sleep(Duration::from_millis(2));
                        Ok(hash)
                    })
                },
                |table| table,
            );
            if let Some(&drawn) = cache.drawn(batch) {
                assert!(drawn >= last_drawn, "{drawn} after {last_drawn}");
                assert!(drawn <= hash);
                last_drawn = drawn;
            } else {
                assert_eq!(last_drawn, 0, "drawn every frame once it has a table");
            }
            std::thread::sleep(Duration::from_millis(1));
        }
        assert!(last_drawn > 0, "a table arrived");
        assert!(started < 200, "one build at a time, not one a frame");
        assert!(cache.tables.len() <= 1 + SPARE_TABLES);
        // When the transfer function stops changing, its own table comes.
        frames_until(&mut cache, &[request(batch, 200)], |cache| {
            cache.drawn(batch) == Some(&200)
        });
    }

    #[test]
    fn a_failed_build_is_not_tried_again_and_the_batch_keeps_its_table() {
        AsyncComputeTaskPool::get_or_init(TaskPool::new);
        let mut cache = Cache::default();
        let batch = Entity::from_raw_u32(1).unwrap();
        frame(&mut cache, &[request(batch, 1)], HeavyBuilds::Blocking);
        let mut tries = 0;
        for _ in 0..3 {
            cache.update(
                &[request(batch, 2)],
                HeavyBuilds::Blocking,
                |_| {
                    tries += 1;
                    HeavyBuild::spawn(|| Err("too large".to_owned()))
                },
                |table| table,
            );
            assert_eq!(cache.drawn(batch), Some(&1));
        }
        assert_eq!(tries, 1);
    }

    #[test]
    fn unused_tables_beyond_the_spares_are_dropped() {
        AsyncComputeTaskPool::get_or_init(TaskPool::new);
        let mut cache = Cache::default();
        let [a, b] = [1, 2].map(|i| Entity::from_raw_u32(i).unwrap());
        for hash in 1..=6 {
            frame(
                &mut cache,
                &[request(a, hash), request(b, 100)],
                HeavyBuilds::Blocking,
            );
            assert!(cache.tables.len() <= 2 + SPARE_TABLES);
            assert_eq!(cache.drawn(b), Some(&100), "a table drawn is kept");
        }
        let kept: HashSet<u64> = cache.tables.keys().map(|k| k.transfer_hash).collect();
        assert_eq!(
            kept,
            HashSet::from([6, 100, 5, 4]),
            "the most recent spares"
        );
        frame(&mut cache, &[], HeavyBuilds::Blocking);
        assert!(cache.tables.is_empty() && cache.drawn.is_empty());
    }
}
