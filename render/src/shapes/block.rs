//! A leaf's triangles side by side: the vertices of up to four triangles of a mesh in
//! structure-of-arrays form, one triangle a lane, so that one ray is tested against all
//! of them with four doubles at once.
//!
//! Each lane runs the operations of [`super::triangle::ShearedRay::hit`] in the same
//! order, so its hit has the bits the triangle's hit has when tested alone; a lane past
//! the leaf's count is never a hit. A block is read from world-space vertices (a mesh
//! shown once, mapped at load, or shown as it is in its file) or from the file's own (a
//! file several transformed objects share): these are mapped to world space lane by
//! lane with the operations of [`Affine::point`], giving the same bits as mapping them
//! one by one.

use super::packet::woop4;
use super::triangle::{ShearedRay, TriangleHit};
use crate::hierarchy::Hierarchy;
use crate::transform::Affine;
use crate::vec3::{Vec3, F4, LANES, M4, V4};

/// Up to four triangles of a hierarchy's leaf.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TriBlock {
    /// Vertex j of the triangle in lane k: `v[j].lane(k)`.
    pub v: [V4; 3],
    /// The triangles (their indices in the file); lanes past `count` repeat the last.
    pub tri: [u32; LANES],
    /// How many lanes hold a triangle of the leaf.
    pub count: u32,
}

impl TriBlock {
    /// The lanes that hold a triangle of the leaf.
    #[inline(always)]
    pub fn live(&self) -> M4 {
        M4::first(self.count as usize)
    }

    /// The triangles of leaf `leaf` of `hierarchy` (whose primitives are `triangles`,
    /// indices into `positions`), read from the mesh as they are tested: a copy per
    /// leaf would hold the vertices again four times over, in memory the traversal
    /// would then miss in the caches.
    #[inline(always)]
    pub fn gather(
        hierarchy: &Hierarchy,
        leaf: u32,
        triangles: &[[u32; 3]],
        positions: &[[f64; 3]],
    ) -> TriBlock {
        let tris = hierarchy.primitives(leaf);
        let count = tris.len();
        let mut block = TriBlock {
            v: [V4::splat(Vec3::ZERO); 3],
            tri: [0; LANES],
            count: count as u32,
        };
        for k in 0..LANES {
            let t = tris[k.min(count - 1)];
            block.tri[k] = t;
            let corners = triangles[t as usize];
            for j in 0..3 {
                let p = positions[corners[j] as usize];
                block.v[j].x.0[k] = p[0];
                block.v[j].y.0[k] = p[1];
                block.v[j].z.0[k] = p[2];
            }
        }
        block
    }

    /// The vertices mapped by `a`, lane by lane as [`Affine::point`] maps one.
    #[inline(always)]
    pub fn mapped(&self, a: &Affine) -> [V4; 3] {
        [map(&self.v[0], a), map(&self.v[1], a), map(&self.v[2], a)]
    }
}

/// Four points mapped by `a` (written out, without closures, so that it is compiled
/// with the instruction set of the code that calls it).
#[inline(always)]
fn map(p: &V4, a: &Affine) -> V4 {
    let m = &a.a;
    V4 {
        x: p.x * m[0][0] + p.y * m[0][1] + p.z * m[0][2] + a.t[0],
        y: p.x * m[1][0] + p.y * m[1][1] + p.z * m[1][2] + a.t[1],
        z: p.x * m[2][0] + p.y * m[2][1] + p.z * m[2][2] + a.t[2],
    }
}

impl ShearedRay {
    /// [`ShearedRay::hit`] of the four triangles with vertices `v` (lane k the
    /// triangle of lane k): the lanes that hit, and their distances and barycentric
    /// coordinates.
    #[inline(always)]
    pub fn hit4(&self, v: &[V4; 3], t_max: f64) -> (M4, F4, [F4; 3]) {
        let (a, b, c) = (self.frame4(v[0]), self.frame4(v[1]), self.frame4(v[2]));
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
