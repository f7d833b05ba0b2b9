//! How the terrain looks: the default material, vertex colours by height
//! and slope, the debug views, and the copy of a [`TerrainMesh`] into a Bevy
//! [`Mesh`] that reuses the mesh's buffers, with UVs over the terrain.
//!
//! # Default material
//!
//! A white `StandardMaterial` (perceptual roughness 0.95, reflectance 0.2:
//! dry ground) whose base colour is multiplied by per-vertex colours
//! (linear RGB):
//!
//! - grass from dark green at the lowest point to olive at 60 % of the
//!   terrain's height range,
//! - rock where the slope is steep: weight `smoothstep(0.92, 0.72, n_y)`
//!   (`n_y` the normal's up component: from about 23° to 44°),
//! - snow above 72 % of the height range on slopes gentler than about 40°:
//!   weight `smoothstep(0.72, 0.86, h) · smoothstep(0.70, 0.85, n_y)`.
//!
//! Heights and normals are the morphed ones, so the colours blend in with
//! the geometry and never pop. The height range is the terrain's own
//! (lowest to highest grid point), whatever its vertical scale.
//!
//! # Debug views
//!
//! Level colours: every triangle belongs to the fan of one quadtree node;
//! the node's level is read from the grid indices of the fan's vertices (the
//! fan's centre and edge midpoints have odd multiples of the node's half
//! size, its corners even ones), and levels get hues from blue (root) over
//! green to red (finest). Edges: every triangle becomes an inner triangle,
//! shrunk to 85 % toward its centroid, and a border of three quads whose
//! outer vertices are darkened to 20 %; the surface stays where it was.

use bevy::asset::RenderAssetUsages;
use bevy::mesh::{Indices, PrimitiveTopology, VertexAttributeValues};
use bevy::prelude::*;
use nebel_lod::TerrainMesh;

use crate::terrain::TerrainDebug;

/// Inner triangle size in the edge view, relative to the triangle.
const EDGE_INNER: f32 = 0.85;
/// Brightness of the outer border vertices in the edge view.
const EDGE_DARK: f32 = 0.2;

/// The default terrain material (see the module docs).
pub(crate) fn default_material() -> StandardMaterial {
    StandardMaterial {
        base_color: Color::WHITE,
        perceptual_roughness: 0.95,
        reflectance: 0.2,
        ..default()
    }
}

fn linear(r: f32, g: f32, b: f32) -> [f32; 3] {
    let c = Color::srgb(r, g, b).to_linear();
    [c.red, c.green, c.blue]
}

fn smoothstep(edge0: f32, edge1: f32, x: f32) -> f32 {
    let t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    std::array::from_fn(|i| a[i] + (b[i] - a[i]) * t)
}

/// The palette of the default material, linear RGB.
pub(crate) struct Palette {
    grass_low: [f32; 3],
    grass_high: [f32; 3],
    rock: [f32; 3],
    snow: [f32; 3],
}

impl Default for Palette {
    fn default() -> Self {
        Self {
            grass_low: linear(0.26, 0.38, 0.15),
            grass_high: linear(0.47, 0.48, 0.27),
            rock: linear(0.46, 0.43, 0.39),
            snow: linear(0.93, 0.94, 0.97),
        }
    }
}

impl Palette {
    /// Colour at unit height `h` (0 lowest, 1 highest) with normal up
    /// component `n_y`.
    pub fn colour(&self, h: f32, n_y: f32) -> [f32; 3] {
        let grass = mix(self.grass_low, self.grass_high, smoothstep(0.0, 0.6, h));
        let rocky = mix(grass, self.rock, smoothstep(0.92, 0.72, n_y));
        let snow = smoothstep(0.72, 0.86, h) * smoothstep(0.70, 0.85, n_y);
        mix(rocky, self.snow, snow)
    }
}

/// The colour of quadtree level `level` of `levels` (hue from blue at the
/// root to red at the finest level), linear RGB.
pub(crate) fn level_colour(level: u32, levels: u32) -> [f32; 3] {
    let t = level as f32 / (levels.max(2) - 1) as f32;
    let c = Color::hsl(240.0 * (1.0 - t.clamp(0.0, 1.0)), 0.85, 0.5).to_linear();
    [c.red, c.green, c.blue]
}

/// The quadtree level of the node whose fan holds a triangle with vertices
/// at grid points `points` (see the module docs), for a quadtree of
/// `levels` levels.
pub(crate) fn fan_level(points: [[u32; 2]; 3], levels: u32) -> u32 {
    let half = points
        .iter()
        .flat_map(|p| p.iter().map(|c| c.trailing_zeros()))
        .min()
        .unwrap_or(0);
    levels.saturating_sub(1).saturating_sub(half)
}

/// How to colour the vertices.
pub(crate) struct Colouring<'a> {
    /// The default material's palette, with the terrain's height range;
    /// `None`: white (a custom material, or a debug view without it).
    pub palette: Option<(&'a Palette, [f32; 2])>,
    /// The debug views.
    pub debug: TerrainDebug,
    /// Levels of the quadtree (for level colours).
    pub levels: u32,
}

impl Colouring<'_> {
    /// Whether the mesh carries vertex colours at all.
    pub fn has_colours(&self) -> bool {
        self.palette.is_some() || self.debug.lod_colours || self.debug.edges
    }
}

/// A new, empty terrain mesh (triangle list, kept in the main world so its
/// buffers can be refilled).
pub(crate) fn empty_mesh() -> Mesh {
    Mesh::new(
        PrimitiveTopology::TriangleList,
        RenderAssetUsages::default(),
    )
    .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, Vec::<[f32; 3]>::new())
    .with_inserted_attribute(Mesh::ATTRIBUTE_NORMAL, Vec::<[f32; 3]>::new())
    .with_inserted_attribute(Mesh::ATTRIBUTE_UV_0, Vec::<[f32; 2]>::new())
    .with_inserted_indices(Indices::U32(Vec::new()))
}

/// Takes a vertex attribute's buffer out of `mesh` (emptied, capacity kept),
/// or a new one.
fn take3(mesh: &mut Mesh, attribute: bevy::mesh::MeshVertexAttribute) -> Vec<[f32; 3]> {
    match mesh.try_remove_attribute(attribute) {
        Ok(VertexAttributeValues::Float32x3(mut values)) => {
            values.clear();
            values
        }
        _ => Vec::new(),
    }
}

fn take4(mesh: &mut Mesh, attribute: bevy::mesh::MeshVertexAttribute) -> Vec<[f32; 4]> {
    match mesh.try_remove_attribute(attribute) {
        Ok(VertexAttributeValues::Float32x4(mut values)) => {
            values.clear();
            values
        }
        _ => Vec::new(),
    }
}

/// Writes `lod` (positions relative to the quadtree origin, which lies at
/// `offset` in the entity's frame) into `mesh`, reusing its buffers, with
/// UVs from 0 to 1 over `extent` (the heights' sides along x and z in the
/// entity's units) from the quadtree's origin.
pub(crate) fn write_mesh(
    mesh: &mut Mesh,
    lod: &TerrainMesh,
    offset: Vec3,
    extent: Vec2,
    colouring: &Colouring,
) {
    let mut positions = take3(mesh, Mesh::ATTRIBUTE_POSITION);
    let mut normals = take3(mesh, Mesh::ATTRIBUTE_NORMAL);
    let mut uvs = match mesh.try_remove_attribute(Mesh::ATTRIBUTE_UV_0) {
        Ok(VertexAttributeValues::Float32x2(mut values)) => {
            values.clear();
            values
        }
        _ => Vec::new(),
    };
    let mut colours = take4(mesh, Mesh::ATTRIBUTE_COLOR);
    let mut indices = match mesh.try_remove_indices() {
        Ok(Some(Indices::U32(mut indices))) => {
            indices.clear();
            indices
        }
        _ => Vec::new(),
    };
    let at = |p: [f32; 3]| [p[0] + offset.x, p[1] + offset.y, p[2] + offset.z];
    let normal = |v: usize| lod.normals.get(v).copied().unwrap_or([0.0, 1.0, 0.0]);
    // Per-vertex base colour: palette or white, then level colours on top.
    let mut base: Vec<[f32; 3]> = Vec::new();
    if colouring.has_colours() {
        base.reserve(lod.positions.len());
        for (v, p) in lod.positions.iter().enumerate() {
            base.push(match colouring.palette {
                Some((palette, [low, high])) => {
                    let h = if high > low {
                        (p[1] - low) / (high - low)
                    } else {
                        0.0
                    };
                    palette.colour(h, normal(v)[1])
                }
                None => [1.0; 3],
            });
        }
        if colouring.debug.lod_colours && lod.grid_points.len() == lod.positions.len() {
            for triangle in lod.indices.chunks_exact(3) {
                let points = [0, 1, 2].map(|k| lod.grid_points[triangle[k] as usize]);
                let colour = level_colour(fan_level(points, colouring.levels), colouring.levels);
                for &v in triangle {
                    base[v as usize] = colour;
                }
            }
        }
    }
    let rgba = |c: [f32; 3], k: f32| [c[0] * k, c[1] * k, c[2] * k, 1.0];
    if colouring.debug.edges {
        // Six vertices and seven triangles per triangle (see the module docs).
        let count = lod.triangle_count();
        positions.reserve(6 * count);
        normals.reserve(6 * count);
        colours.reserve(6 * count);
        indices.reserve(21 * count);
        for triangle in lod.indices.chunks_exact(3) {
            let v = [0, 1, 2].map(|k| triangle[k] as usize);
            let p = v.map(|i| Vec3::from(at(lod.positions[i])));
            let n = v.map(|i| Vec3::from(normal(i)));
            let centroid = (p[0] + p[1] + p[2]) / 3.0;
            let n_mean = (n[0] + n[1] + n[2]) / 3.0;
            let first = positions.len() as u32;
            for k in 0..3 {
                positions.push(p[k].to_array());
                normals.push(n[k].to_array());
                colours.push(rgba(base[v[k]], EDGE_DARK));
            }
            for k in 0..3 {
                positions.push(centroid.lerp(p[k], EDGE_INNER).to_array());
                normals.push(
                    n_mean
                        .lerp(n[k], EDGE_INNER)
                        .normalize_or(Vec3::Y)
                        .to_array(),
                );
                colours.push(rgba(base[v[k]], 1.0));
            }
            let (o, i) = (first, first + 3);
            indices.extend_from_slice(&[i, i + 1, i + 2]);
            for k in 0..3 {
                let next = (k + 1) % 3;
                indices.extend_from_slice(&[o + k, o + next, i + next]);
                indices.extend_from_slice(&[o + k, i + next, i + k]);
            }
        }
    } else {
        positions.extend(lod.positions.iter().map(|&p| at(p)));
        normals.extend((0..lod.positions.len()).map(normal));
        if colouring.has_colours() {
            colours.extend(base.iter().map(|&c| rgba(c, 1.0)));
        }
        indices.extend_from_slice(&lod.indices);
    }
    // Geomorphing moves a vertex only along y, so its UV never changes.
    uvs.extend(
        positions
            .iter()
            .map(|p| [(p[0] - offset.x) / extent.x, (p[2] - offset.z) / extent.y]),
    );
    mesh.insert_attribute(Mesh::ATTRIBUTE_POSITION, positions);
    mesh.insert_attribute(Mesh::ATTRIBUTE_NORMAL, normals);
    mesh.insert_attribute(Mesh::ATTRIBUTE_UV_0, uvs);
    if colouring.has_colours() {
        mesh.insert_attribute(Mesh::ATTRIBUTE_COLOR, colours);
    }
    mesh.insert_indices(Indices::U32(indices));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fan_levels_follow_the_grid_indices() {
        // A 17 × 17 grid has 4 levels; node half sizes 8, 4, 2, 1.
        let levels = 4;
        // The root's fan: centre (8, 8), corner (16, 16), midpoint (16, 8).
        assert_eq!(fan_level([[8, 8], [16, 16], [16, 8]], levels), 0);
        // A finest node: centre (1, 1), corner (2, 2), midpoint (2, 1).
        assert_eq!(fan_level([[1, 1], [2, 2], [2, 1]], levels), 3);
        assert_eq!(fan_level([[5, 3], [6, 4], [4, 4]], levels), 3);
        // Level 1: centre (12, 4), corners (8, 0) and (16, 0).
        assert_eq!(fan_level([[12, 4], [8, 0], [16, 0]], levels), 1);
        // The unrefined root's two triangles (corners only) count as level 0.
        assert_eq!(fan_level([[0, 0], [16, 16], [16, 0]], levels), 0);
        assert_ne!(level_colour(0, 4), level_colour(3, 4));
    }

    #[test]
    fn the_palette_goes_from_grass_over_rock_to_snow() {
        let palette = Palette::default();
        let grass = palette.colour(0.1, 1.0);
        let rock = palette.colour(0.3, 0.5);
        let snow = palette.colour(0.95, 1.0);
        assert!(grass[1] > grass[0] && grass[1] > grass[2], "{grass:?}");
        assert_eq!(rock, palette.rock);
        assert_eq!(snow, palette.snow);
        // A steep slope high up stays rock.
        assert_eq!(palette.colour(0.95, 0.5), palette.rock);
    }

    #[test]
    fn the_bevy_mesh_reuses_its_buffers_and_shows_edges() {
        let lod = TerrainMesh {
            positions: vec![[0.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 3.0, 1.0]],
            normals: vec![[0.0, 1.0, 0.0]; 3],
            grid_points: vec![[0, 0], [1, 0], [0, 1]],
            indices: vec![0, 2, 1],
            ..TerrainMesh::default()
        };
        let mut mesh = empty_mesh();
        let palette = Palette::default();
        let colouring = Colouring {
            palette: Some((&palette, [1.0, 3.0])),
            debug: TerrainDebug::default(),
            levels: 1,
        };
        write_mesh(
            &mut mesh,
            &lod,
            Vec3::new(10.0, 0.0, -5.0),
            Vec2::new(2.0, 4.0),
            &colouring,
        );
        let Some(VertexAttributeValues::Float32x3(positions)) =
            mesh.attribute(Mesh::ATTRIBUTE_POSITION)
        else {
            panic!("positions");
        };
        assert_eq!(positions[2], [10.0, 3.0, -4.0]);
        let capacity = positions.capacity();
        // UVs over the extent, from the quadtree's origin.
        let Some(VertexAttributeValues::Float32x2(uvs)) = mesh.attribute(Mesh::ATTRIBUTE_UV_0)
        else {
            panic!("uvs");
        };
        assert_eq!(uvs, &vec![[0.0, 0.0], [0.5, 0.0], [0.0, 0.25]]);
        assert!(mesh.attribute(Mesh::ATTRIBUTE_COLOR).is_some());
        write_mesh(&mut mesh, &lod, Vec3::ZERO, Vec2::ONE, &colouring);
        let Some(VertexAttributeValues::Float32x3(positions)) =
            mesh.attribute(Mesh::ATTRIBUTE_POSITION)
        else {
            panic!("positions");
        };
        assert_eq!(positions.capacity(), capacity, "the buffer was reused");

        let edges = Colouring {
            palette: None,
            debug: TerrainDebug {
                lod_colours: false,
                edges: true,
            },
            levels: 1,
        };
        write_mesh(&mut mesh, &lod, Vec3::ZERO, Vec2::ONE, &edges);
        assert_eq!(mesh.count_vertices(), 6);
        assert_eq!(mesh.indices().unwrap().len(), 21);
        let Some(VertexAttributeValues::Float32x4(colours)) = mesh.attribute(Mesh::ATTRIBUTE_COLOR)
        else {
            panic!("colours");
        };
        assert_eq!(colours[0], [EDGE_DARK, EDGE_DARK, EDGE_DARK, 1.0]);
        assert_eq!(colours[3], [1.0; 4]);

        // A custom material without debug views: no colours.
        let plain = Colouring {
            palette: None,
            debug: TerrainDebug::default(),
            levels: 1,
        };
        write_mesh(&mut mesh, &lod, Vec3::ZERO, Vec2::ONE, &plain);
        assert!(mesh.attribute(Mesh::ATTRIBUTE_COLOR).is_none());
        assert_eq!(mesh.count_vertices(), 3);
    }
}
