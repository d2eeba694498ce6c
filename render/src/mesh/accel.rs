//! What the tracer builds once per mesh geometry, whatever the number of objects that
//! show it: the hierarchy over its triangles in the file's own coordinates, and, for
//! smooth shading, the normals computed from its faces.
//!
//! Kept with the mesh's geometry ([`MeshGeometry`] caches it), not with the shapes that
//! trace it, so that the geometry a scene holds needs nothing above the generic
//! [`crate::hierarchy`]; [`crate::shapes`] walks it.

use std::sync::OnceLock;

use super::load::degenerate;
use super::{MeshData, MeshGeometry};
use crate::bounds::Bounds;
use crate::hierarchy::Hierarchy;
use crate::vec3::Vec3;

pub(crate) struct MeshAccel {
    /// Over the triangles that are not degenerate (degenerate ones are never hit).
    pub hierarchy: Hierarchy,
    /// Per vertex, the normalised sum of the cross products of the faces that share it
    /// (by index), or `None` where that sum is zero; computed for smooth shading only.
    computed_normals: OnceLock<Vec<Option<[f64; 3]>>>,
}

impl MeshAccel {
    pub fn of(geometry: &MeshGeometry) -> &MeshAccel {
        geometry
            .prepared
            .get_or_init(|| MeshAccel::build(&geometry.data))
    }

    fn build(mesh: &MeshData) -> MeshAccel {
        let live: Vec<u32> = (0..mesh.triangles.len() as u32)
            .filter(|&t| !degenerate(mesh, mesh.triangles[t as usize]))
            .collect();
        let boxes: Vec<Bounds> = live
            .iter()
            .map(|&t| {
                let [a, b, c] = mesh.triangles[t as usize].map(|i| vertex(mesh, i));
                let mut bounds = Bounds::of_point(a);
                bounds.grow(b);
                bounds.grow(c);
                bounds
            })
            .collect();
        let mut hierarchy = Hierarchy::build(&boxes);
        // Leaves name triangles of the file, not positions in `live`.
        for p in &mut hierarchy.order {
            *p = live[*p as usize];
        }
        MeshAccel {
            hierarchy,
            computed_normals: OnceLock::new(),
        }
    }

    /// The computed vertex normals (see [`MeshAccel::computed_normals`]).
    pub fn computed_normals(&self, mesh: &MeshData) -> &[Option<[f64; 3]>] {
        self.computed_normals.get_or_init(|| {
            let mut sums = vec![[0.0f64; 3]; mesh.positions.len()];
            for &tri in &mesh.triangles {
                let [a, b, c] = tri.map(|i| vertex(mesh, i));
                let n = (b - a).cross(c - a);
                for i in tri {
                    let s = &mut sums[i as usize];
                    s[0] += n.x;
                    s[1] += n.y;
                    s[2] += n.z;
                }
            }
            sums.into_iter()
                .map(|s| {
                    let v = Vec3::new(s[0], s[1], s[2]);
                    let len = v.length();
                    (len > 0.0 && len.is_finite()).then(|| {
                        let n = v / len;
                        [n.x, n.y, n.z]
                    })
                })
                .collect()
        })
    }
}

/// Vertex `i` of the mesh as a vector.
#[inline(always)]
pub(crate) fn vertex(mesh: &MeshData, i: u32) -> Vec3 {
    let p = mesh.positions[i as usize];
    Vec3::new(p[0], p[1], p[2])
}
