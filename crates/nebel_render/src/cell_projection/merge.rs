//! Batches whose bounds intersect, merged per pixel: each member is drawn
//! alone into a layer of its own, with its span along each pixel's ray (the
//! first entry and the last exit of its segments, min-blended), and one
//! full-screen pass composites the members jointly under the accumulation
//! (`cell_merge.wgsl`, the GPU's copy of [`nebel_core::overlap`]).
//!
//! The merge is exact where the members are uniform over their spans and
//! wherever their spans do not overlap along a ray (then each member is
//! whole, in its order along that ray, not in the order of the batches'
//! centres); elsewhere each member's medium is spread evenly over its span.
//! Bounds that only touch do not merge. A group of more than
//! [`MAX_MERGED`] batches is merged in runs of that many, nearest first.
//! MIP batches take the maximum, which needs no order: they never merge.

use std::collections::HashMap;

use bevy::asset::load_embedded_asset;
use bevy::core_pipeline::FullscreenShader;
use bevy::prelude::*;
use bevy::render::render_resource::binding_types::texture_2d_array;
use bevy::render::render_resource::*;
use bevy::render::renderer::{RenderContext, RenderDevice};
use bevy::render::texture::{CachedTexture, TextureCache};
use bevy::shader::ShaderDefVal;
use nebel_core::optics::OpticalMode;

use super::pipeline::{cell_stencil, under_blend};
use super::resources::render_target;

/// The most batches one merge pass composites.
pub(super) const MAX_MERGED: usize = 8;

/// Where a span target is cleared: no segment, an entry beyond every exit.
const NO_SPAN: f64 = 3.0e38;

/// The format of the span targets: 32-bit float where the device can blend
/// it, 16-bit float otherwise.
pub(super) fn span_format(device: &RenderDevice) -> TextureFormat {
    if device.features().contains(WgpuFeatures::FLOAT32_BLENDABLE) {
        TextureFormat::Rg32Float
    } else {
        TextureFormat::Rg16Float
    }
}

/// The blend of the span targets: each channel's minimum (the entry, and the
/// negated exit).
pub(super) const SPAN_BLEND: BlendState = BlendState {
    color: BlendComponent {
        src_factor: BlendFactor::One,
        dst_factor: BlendFactor::One,
        operation: BlendOperation::Min,
    },
    alpha: BlendComponent {
        src_factor: BlendFactor::One,
        dst_factor: BlendFactor::One,
        operation: BlendOperation::Min,
    },
};

/// For each batch (its bounds, and whether it may merge), the group of
/// batches it overlaps, directly or through others: the group's smallest
/// index, or `None` for a batch that overlaps none.
pub(super) fn overlap_groups(batches: &[(Vec3, Vec3, bool)]) -> Vec<Option<usize>> {
    let mut parent: Vec<usize> = (0..batches.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let overlap = |(a_min, a_max, a): (Vec3, Vec3, bool), (b_min, b_max, b): (Vec3, Vec3, bool)| {
        a && b && a_min.cmplt(b_max).all() && b_min.cmplt(a_max).all()
    };
    for i in 0..batches.len() {
        for j in i + 1..batches.len() {
            if overlap(batches[i], batches[j]) {
                let (ri, rj) = (root(&mut parent, i), root(&mut parent, j));
                parent[ri.max(rj)] = ri.min(rj);
            }
        }
    }
    let roots: Vec<usize> = (0..batches.len()).map(|i| root(&mut parent, i)).collect();
    let mut members = vec![0_usize; batches.len()];
    for &r in &roots {
        members[r] += 1;
    }
    roots
        .iter()
        .map(|&r| (members[r] > 1).then_some(r))
        .collect()
}

/// Whether a batch of this mode may merge with others.
pub(super) fn merges(mode: OpticalMode) -> bool {
    mode != OpticalMode::Mip
}

/// One step of the drawing order: a batch alone, or a run of a group's
/// batches merged.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(super) struct Item {
    /// Indices into the draws, nearest first.
    pub(super) draws: Vec<usize>,
    pub(super) merged: bool,
}

/// The drawing order of draws given nearest first with their groups: each
/// group where its nearest member is, in runs of at most [`MAX_MERGED`].
pub(super) fn items(groups: &[Option<usize>]) -> Vec<Item> {
    let mut items = Vec::new();
    let mut placed = Vec::new();
    for (draw, group) in groups.iter().enumerate() {
        match group {
            None => items.push(Item {
                draws: vec![draw],
                merged: false,
            }),
            Some(group) if !placed.contains(group) => {
                placed.push(*group);
                let members: Vec<usize> = (draw..groups.len())
                    .filter(|&other| groups[other] == Some(*group))
                    .collect();
                items.extend(members.chunks(MAX_MERGED).map(|run| Item {
                    draws: run.to_vec(),
                    merged: true,
                }));
            }
            Some(_) => {}
        }
    }
    items
}

/// The merge pass's layout and shader, and its pipelines (with and without
/// the stencil test).
#[derive(Resource)]
pub struct MergePipelines {
    layout: BindGroupLayoutDescriptor,
    shader: Handle<Shader>,
    fullscreen_vertex: VertexState,
    pipelines: HashMap<(bool, TextureFormat), CachedRenderPipelineId>,
}

/// Creates the merge pass's layout and loads its shader.
pub fn init_merge_pipelines(
    mut commands: Commands,
    asset_server: Res<AssetServer>,
    fullscreen_shader: Res<FullscreenShader>,
) {
    let unfilterable = TextureSampleType::Float { filterable: false };
    commands.insert_resource(MergePipelines {
        layout: BindGroupLayoutDescriptor::new(
            "nebel_cell_merge_layout",
            &BindGroupLayoutEntries::sequential(
                ShaderStages::FRAGMENT,
                (
                    texture_2d_array(unfilterable),
                    texture_2d_array(unfilterable),
                ),
            ),
        ),
        shader: load_embedded_asset!(asset_server.as_ref(), "cell_merge.wgsl"),
        fullscreen_vertex: fullscreen_shader.to_vertex_state(),
        pipelines: HashMap::new(),
    });
}

impl MergePipelines {
    /// The pipeline merging into an accumulation of `format`, tested against
    /// the stencil or not; queued the first time it is asked for.
    pub(super) fn get(
        &mut self,
        pipeline_cache: &PipelineCache,
        stencil: bool,
        format: TextureFormat,
    ) -> CachedRenderPipelineId {
        *self.pipelines.entry((stencil, format)).or_insert_with(|| {
            pipeline_cache.queue_render_pipeline(RenderPipelineDescriptor {
                label: Some("nebel_cell_merge_pipeline".into()),
                layout: vec![self.layout.clone()],
                vertex: self.fullscreen_vertex.clone(),
                fragment: Some(FragmentState {
                    shader: self.shader.clone(),
                    shader_defs: vec![
                        ShaderDefVal::UInt("MAX_MERGED".into(), MAX_MERGED as u32),
                        ShaderDefVal::UInt("MAX_ENDS".into(), 2 * MAX_MERGED as u32),
                    ],
                    targets: vec![Some(ColorTargetState {
                        format,
                        blend: Some(under_blend()),
                        write_mask: ColorWrites::ALL,
                    })],
                    ..default()
                }),
                depth_stencil: stencil.then(|| cell_stencil(OpticalMode::Sorted)),
                ..default()
            })
        })
    }
}

/// One round's layers of merged batches: a colour and transmittance layer
/// and a span layer per member.
pub(super) struct MergeTargets {
    colour: CachedTexture,
    span: CachedTexture,
    /// Per layer, its colour and span views.
    layers: Vec<(TextureView, TextureView)>,
    pub(super) pipeline: CachedRenderPipelineId,
}

impl MergeTargets {
    /// `layers` layers of `size` pixels, the colour in `format`.
    pub(super) fn new(
        texture_cache: &mut TextureCache,
        device: &RenderDevice,
        size: UVec2,
        layers: u32,
        (format, span_format): (TextureFormat, TextureFormat),
        pipeline: CachedRenderPipelineId,
    ) -> Self {
        let mut target =
            |label, format| render_target(texture_cache, device, label, size, layers, format);
        let colour = target("nebel_cell_merge_colour", format);
        let span = target("nebel_cell_merge_span", span_format);
        let layer = |texture: &CachedTexture, layer| {
            texture.texture.create_view(&TextureViewDescriptor {
                label: Some("nebel_cell_merge_layer"),
                dimension: Some(TextureViewDimension::D2),
                base_array_layer: layer,
                array_layer_count: Some(1),
                ..default()
            })
        };
        let layers = (0..layers)
            .map(|i| (layer(&colour, i), layer(&span, i)))
            .collect();
        Self {
            colour,
            span,
            layers,
            pipeline,
        }
    }

    /// The colour attachments of member `layer`, cleared: colour 0,
    /// transmittance 1, no span.
    pub(super) fn attachments(&self, layer: usize) -> [Option<RenderPassColorAttachment<'_>>; 2] {
        let (colour, span) = &self.layers[layer];
        let attachment = |view, clear| {
            Some(RenderPassColorAttachment {
                view,
                depth_slice: None,
                resolve_target: None,
                ops: Operations {
                    load: LoadOp::Clear(clear),
                    store: StoreOp::Store,
                },
            })
        };
        [
            attachment(colour, LinearRgba::BLACK.into()),
            attachment(
                span,
                wgpu::Color {
                    r: NO_SPAN,
                    g: NO_SPAN,
                    b: NO_SPAN,
                    a: NO_SPAN,
                },
            ),
        ]
    }

    /// The merge pass's bind group over the first `members` layers.
    pub(super) fn bind_group(
        &self,
        ctx: &RenderContext,
        pipeline_cache: &PipelineCache,
        merge: &MergePipelines,
        members: u32,
    ) -> BindGroup {
        let array = |texture: &CachedTexture| {
            texture.texture.create_view(&TextureViewDescriptor {
                label: Some("nebel_cell_merge_layers"),
                dimension: Some(TextureViewDimension::D2Array),
                base_array_layer: 0,
                array_layer_count: Some(members),
                ..default()
            })
        };
        ctx.render_device().create_bind_group(
            "nebel_cell_merge_bind_group",
            &pipeline_cache.get_bind_group_layout(&merge.layout),
            &BindGroupEntries::sequential((&array(&self.colour), &array(&self.span))),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn boxed(min: [f32; 3], max: [f32; 3]) -> (Vec3, Vec3, bool) {
        (Vec3::from(min), Vec3::from(max), true)
    }

    #[test]
    fn overlapping_bounds_group_through_each_other() {
        let batches = [
            boxed([0.0; 3], [1.0; 3]),
            // Overlaps the first.
            boxed([0.5; 3], [2.0; 3]),
            // Apart from all.
            boxed([5.0; 3], [6.0; 3]),
            // Overlaps the second only: joins the first's group.
            boxed([1.5; 3], [3.0; 3]),
            // Touches the third only: no overlap.
            boxed([6.0, 5.0, 5.0], [7.0, 6.0, 6.0]),
            // Overlaps the third, but may not merge (MIP).
            (Vec3::splat(5.5), Vec3::splat(5.8), false),
        ];
        assert_eq!(
            overlap_groups(&batches),
            [Some(0), Some(0), None, Some(0), None, None]
        );
        assert_eq!(overlap_groups(&[]), []);
    }

    #[test]
    fn items_place_each_group_at_its_nearest_member() {
        let groups = [None, Some(3), None, Some(7), Some(3), None, Some(7)];
        assert_eq!(
            items(&groups),
            [
                Item {
                    draws: vec![0],
                    merged: false
                },
                Item {
                    draws: vec![1, 4],
                    merged: true
                },
                Item {
                    draws: vec![2],
                    merged: false
                },
                Item {
                    draws: vec![3, 6],
                    merged: true
                },
                Item {
                    draws: vec![5],
                    merged: false
                },
            ]
        );
        // A large group goes in runs of at most MAX_MERGED, each draw once.
        let groups = vec![Some(0); 2 * MAX_MERGED + 1];
        let items = items(&groups);
        assert_eq!(items.len(), 3);
        assert!(items.iter().all(|item| item.merged));
        let all: Vec<usize> = items.iter().flat_map(|item| item.draws.clone()).collect();
        assert_eq!(all, (0..groups.len()).collect::<Vec<_>>());
    }
}
