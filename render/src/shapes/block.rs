//! A leaf's triangles side by side: the vertices of up to four triangles of a mesh in
//! structure-of-arrays form, one triangle a lane, so that one ray is tested against all
//! of them with four doubles at once.
//!
//! Each lane runs the operations of [`super::triangle::ShearedRay::hit`] in the same
//! order, so its hit has the bits the triangle's hit has when tested alone; a lane past
//! the leaf's count is never a hit. A block holds world-space vertices (a mesh shown
//! once, or shown as it is in its file) or the file's own (a file several transformed
//! objects share): these are mapped to world space lane by lane with the operations of
//! [`Affine::point`], giving the same bits as mapping them one by one.

use super::packet::woop4;
use super::triangle::{ShearedRay, TriangleHit};
use crate::hierarchy::Hierarchy;
use crate::mesh::MeshData;
use crate::transform::Affine;
use crate::vec3::{Vec3, F4, LANES, M4, V4};

/// Up to four triangles of a hierarchy's leaf.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TriBlock {
    /// Vertex j of the triangle in lane k: `v[j].lane(k)`.
    pub v: [V4; 3],
    /// The triangles (their indices in the file); lanes past `live` repeat the first.
    pub tri: [u32; LANES],
    /// The lanes that hold a triangle of the leaf.
    pub live: M4,
}

impl TriBlock {
    /// One block per leaf of `hierarchy` (whose primitives are triangles of `mesh`), in
    /// leaf order, with each vertex `map`ped (or as it is in the file).
    pub fn of_leaves(
        hierarchy: &Hierarchy,
        mesh: &MeshData,
        map: impl Fn([f64; 3]) -> Vec3,
    ) -> Vec<TriBlock> {
        (0..hierarchy.leaves.len() as u32)
            .map(|leaf| {
                let tris = hierarchy.primitives(leaf);
                let tri: [u32; LANES] = std::array::from_fn(|k| tris[k.min(tris.len() - 1)]);
                let corners = tri
                    .map(|t| mesh.triangles[t as usize].map(|i| map(mesh.positions[i as usize])));
                let v = std::array::from_fn(|j| V4 {
                    x: F4(corners.map(|c| c[j].x)),
                    y: F4(corners.map(|c| c[j].y)),
                    z: F4(corners.map(|c| c[j].z)),
                });
                TriBlock {
                    v,
                    tri,
                    live: M4::first(tris.len()),
                }
            })
            .collect()
    }

    /// The vertices mapped by `a`, lane by lane as [`Affine::point`] maps one.
    #[inline(always)]
    pub fn mapped(&self, a: &Affine) -> [V4; 3] {
        self.v.map(|p| {
            let row = |r: usize| p.x * a.a[r][0] + p.y * a.a[r][1] + p.z * a.a[r][2] + a.t[r];
            V4 {
                x: row(0),
                y: row(1),
                z: row(2),
            }
        })
    }
}

impl ShearedRay {
    /// [`ShearedRay::hit`] of the four triangles with vertices `v` (lane k the
    /// triangle of lane k): the lanes that hit, and their distances and barycentric
    /// coordinates.
    #[inline(always)]
    pub fn hit4(&self, v: &[V4; 3], t_max: f64) -> (M4, F4, [F4; 3]) {
        let [a, b, c] = v.map(|p| self.frame4(p));
        woop4(a, b, c, F4::splat(self.shear().2), F4::splat(t_max))
    }

    /// The hit of lane `k` of [`ShearedRay::hit4`]'s answer.
    #[inline(always)]
    pub fn lane_hit(t: F4, b: &[F4; 3], k: usize) -> TriangleHit {
        TriangleHit {
            t: t.0[k],
            b: [b[0].0[k], b[1].0[k], b[2].0[k]],
        }
    }
}
