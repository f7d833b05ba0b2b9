//! Stars on the night sky for the examples and scene files: one mesh of
//! small unlit quads, seeded over the whole sphere (`nebel_scene`'s
//! [`StarsDescription`]), [`STAR_DISTANCE`] away from where it is spawned,
//! so far that a camera moving tens of kilometres shifts them by well under
//! a pixel and everything else in a scene lies in front of them.

use bevy::asset::RenderAssetUsages;
use bevy::mesh::{Indices, PrimitiveTopology};
use bevy::prelude::*;
use nebel_scene::StarsDescription;

/// The distance of the stars from their centre, metres.
pub const STAR_DISTANCE: f32 = 1e7;

/// The stars' mesh: one quad per star facing the centre, `angular_size`
/// radians across, its vertex colour the star's brightness.
pub fn star_mesh(stars: &StarsDescription, angular_size: f32) -> Mesh {
    let half = 0.5 * angular_size * STAR_DISTANCE;
    let list = stars.stars();
    let mut positions = Vec::with_capacity(4 * list.len());
    let mut colours = Vec::with_capacity(4 * list.len());
    let mut indices = Vec::with_capacity(6 * list.len());
    for (direction, brightness) in list {
        let direction = Vec3::from(direction);
        let across = direction.any_orthonormal_vector();
        let up = direction.cross(across);
        let centre = direction * STAR_DISTANCE;
        let first = positions.len() as u32;
        for (a, b) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
            positions.push((centre + half * (a * across + b * up)).to_array());
            let value = brightness * stars.brightness;
            // A slightly blue-white.
            colours.push([value * 0.9, value * 0.95, value, 1.0]);
        }
        indices.extend([0, 1, 2, 0, 2, 3].map(|k| first + k));
    }
    Mesh::new(
        PrimitiveTopology::TriangleList,
        RenderAssetUsages::default(),
    )
    .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, positions)
    .with_inserted_attribute(Mesh::ATTRIBUTE_COLOR, colours)
    .with_inserted_indices(Indices::U32(indices))
}

/// Spawns the stars centred on `centre`, each about `angular_size` radians
/// across (unlit, seen from both sides).
pub fn spawn_stars(
    commands: &mut Commands,
    meshes: &mut Assets<Mesh>,
    materials: &mut Assets<StandardMaterial>,
    stars: &StarsDescription,
    angular_size: f32,
    centre: Vec3,
) {
    if stars.count == 0 {
        return;
    }
    commands.spawn((
        Mesh3d(meshes.add(star_mesh(stars, angular_size))),
        MeshMaterial3d(materials.add(StandardMaterial {
            base_color: Color::WHITE,
            unlit: true,
            cull_mode: None,
            ..default()
        })),
        Transform::from_translation(centre),
    ));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_star_is_a_quad_at_the_star_distance() {
        let stars = StarsDescription {
            count: 50,
            ..default()
        };
        let mesh = star_mesh(&stars, 0.004);
        let Some(positions) = mesh
            .attribute(Mesh::ATTRIBUTE_POSITION)
            .and_then(|values| values.as_float3())
        else {
            panic!("positions");
        };
        assert_eq!(positions.len(), 200);
        for corner in positions {
            let distance = Vec3::from(*corner).length();
            assert!((distance / STAR_DISTANCE - 1.0).abs() < 1e-4, "{distance}");
        }
        assert_eq!(mesh.indices().map(Indices::len), Some(300));
    }
}
