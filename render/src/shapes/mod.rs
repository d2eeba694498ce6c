//! The shapes of section 8 (triangles, boxes, meshes) and the top-level hierarchy that
//! holds them with the mesh instances and their transforms.
//!
//! Spheres and planes keep their own kernels and hierarchy (`crate::bvh`, the tracer's
//! lane code); a scene without section 8's shapes builds none of this and traces as
//! before. Each class here has its bounds and its intersection test in its own module
//! ([`triangle`], [`cuboid`]; a mesh's triangles take the triangle test, under the
//! hierarchy its shared geometry caches, [`crate::mesh::accel`]); [`Shapes`] joins them
//! under one hierarchy ([`crate::hierarchy`]) whose leaves are boxes, loose triangles and
//! mesh instances.
//!
//! A mesh is traced in the file's coordinates (its hierarchy is built once, whatever
//! the number of objects that show it), but every triangle test runs in world space on
//! the vertices mapped by [`Affine::point`], the same bits a mesh mapped at load would
//! have: so a mesh shown once and the same file shown by several objects give the same
//! image, and watertightness holds in world space. The ray taken into the file's
//! coordinates to walk its hierarchy is rounded, and so is the triangle test, so boxes
//! are widened by a bound on those errors ([`Shapes::instance_margin`]).

pub(crate) mod block;
pub(crate) mod cuboid;
pub(crate) mod packet;
pub(crate) mod triangle;

use std::collections::HashMap;
use std::sync::Arc;

use self::block::TriBlock;
use self::cuboid::BoxHit;
use self::triangle::ShearedRay;
use crate::bounds::{Bounds, SlabRay};
use crate::hierarchy::Hierarchy;
use crate::mesh::accel::{vertex, MeshAccel};
use crate::mesh::{MeshGeometry, NO_NORMAL};
use crate::scene::{Scene, Shape};
use crate::simd::{isa_dispatch, Isa};
use crate::transform::{map_normal, Affine};
use crate::vec3::{Vec3, F4, M4};

/// The factor of ε in the margins by which boxes are widened: each error bounded is a
/// few roundings of terms no larger than those the margins sum.
const MARGIN_ULPS: f64 = 64.0 * f64::EPSILON;

/// A ray leaves no triangle or face: no object has this index.
pub(crate) const NO_PRIM: u32 = u32::MAX;

/// Section 8's shapes of a scene, ready for tracing.
pub(crate) struct Shapes {
    /// The instruction set the single-ray searches run with.
    pub isa: Isa,
    items: Vec<Item>,
    top: Hierarchy,
    /// The largest coordinate of any shape's bounds: hits lie within it.
    reach: f64,
}

impl std::fmt::Debug for Shapes {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Shapes")
            .field("items", &self.items.len())
            .field("nodes", &self.top.nodes.len())
            .finish()
    }
}

enum Item {
    Box { object: u32, min: Vec3, max: Vec3 },
    Triangle { object: u32, v: [Vec3; 3] },
    Instance(Box<Instance>),
}

/// A mesh object: its shared geometry and where it goes.
struct Instance {
    object: u32,
    geometry: Arc<MeshGeometry>,
    transform: Affine,
    /// The map into the file's coordinates, for walking its hierarchy.
    inverse: Affine,
    identity: bool,
    /// The vertices mapped to world space once, when no other object shares the file.
    world: Option<Vec<[f64; 3]>>,
    /// Whether vertices are mapped as they are tested (a file several transformed
    /// objects share).
    mapped: bool,
    /// cof(A), which maps normals.
    normal_matrix: [[f64; 3]; 3],
    smooth: bool,
    /// ‖A‖∞·R + ‖t‖∞ (R the file's largest coordinate) and ‖A⁻¹‖∞, for margins.
    world_size: f64,
    inverse_norm: f64,
}

/// What a walk offers to test: a box, a loose triangle, or a leaf's triangles of a mesh
/// (each with its item's index).
enum Candidate<'a> {
    Box(u32, u32, Vec3, Vec3),
    Triangle(u32, u32, &'a [Vec3; 3]),
    Block(u32, &'a Instance, &'a TriBlock),
}

impl Instance {
    /// The triangles of leaf `leaf` of the file's hierarchy, in world space.
    #[inline(always)]
    fn block(&self, hierarchy: &Hierarchy, leaf: u32) -> TriBlock {
        let data = &self.geometry.data;
        let positions = self.world.as_deref().unwrap_or(&data.positions);
        let mut block = TriBlock::gather(hierarchy, leaf, &data.triangles, positions);
        if self.mapped {
            block.v = block.mapped(&self.transform);
        }
        block
    }
}

/// Where a ray meets one of these shapes.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ShapeHit {
    pub t: f64,
    pub object: u32,
    /// The triangle of a mesh (in file order); 0 for a loose triangle or a box.
    pub prim: u32,
    item: u32,
    detail: Detail,
}

#[derive(Clone, Copy, Debug)]
enum Detail {
    Triangle([f64; 3]),
    Box(BoxHit),
}

/// The surface at a hit: the point, the geometric and shading normals (unit, not yet
/// turned to the ray), and what spawning rays from it needs.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SurfacePoint {
    pub p: Vec3,
    pub ng: Vec3,
    pub ns: Vec3,
    spawn: Spawn,
}

#[derive(Clone, Copy, Debug)]
enum Spawn {
    /// A triangle: the bound on the point's rounding errors.
    Triangle(Vec3),
    /// A box face.
    Box { min: Vec3, max: Vec3, hit: BoxHit },
}

impl SurfacePoint {
    /// The origin of a ray leaving the surface in direction `dir`: certainly on that
    /// side of it.
    pub fn origin(&self, dir: Vec3) -> Vec3 {
        match self.spawn {
            Spawn::Triangle(error) => triangle::spawn_origin(self.p, error, self.ng, dir),
            Spawn::Box { min, max, hit } => cuboid::on_face(min, max, &hit, self.p, dir).1,
        }
    }
}

/// Whether (t, object, prim) comes before `best` (equal distances go to the object
/// listed first, then to the triangle listed first).
#[inline(always)]
fn before(t: f64, object: u32, prim: u32, best: &(f64, u32, u32)) -> bool {
    t < best.0 || (t == best.0 && (object, prim) < (best.1, best.2))
}

impl Shapes {
    /// The section 8 shapes of `scene`, or `None` if it has none.
    pub fn new(scene: &Scene) -> Option<Shapes> {
        let mut uses: HashMap<*const MeshGeometry, usize> = HashMap::new();
        for object in &scene.objects {
            if let Shape::Mesh(m) = &object.shape {
                *uses.entry(Arc::as_ptr(&m.file.geometry)).or_default() += 1;
            }
        }
        let mut items = Vec::new();
        let mut boxes = Vec::new();
        for (index, object) in scene.objects.iter().enumerate() {
            let object_index = index as u32;
            match &object.shape {
                Shape::Sphere { .. } | Shape::Plane { .. } => continue,
                &Shape::Box { min, max } => {
                    let mut b = Bounds::of_point(min);
                    b.grow(max);
                    boxes.push(b);
                    items.push(Item::Box {
                        object: object_index,
                        min,
                        max,
                    });
                }
                &Shape::Triangle { vertices } => {
                    let e = (vertices[1] - vertices[0]).cross(vertices[2] - vertices[0]);
                    if e == Vec3::ZERO {
                        // Degenerate: never hit.
                        continue;
                    }
                    let mut b = Bounds::of_point(vertices[0]);
                    b.grow(vertices[1]);
                    b.grow(vertices[2]);
                    boxes.push(b);
                    items.push(Item::Triangle {
                        object: object_index,
                        v: vertices,
                    });
                }
                Shape::Mesh(m) => {
                    let geometry = m.file.geometry.clone();
                    let accel = MeshAccel::of(&geometry);
                    let Some(local) = accel.hierarchy.root_bounds() else {
                        continue;
                    };
                    let transform = m.transform;
                    let identity = transform.is_identity();
                    let shared = uses[&Arc::as_ptr(&geometry)] > 1;
                    // A file shown once is mapped to world space here, once; one several
                    // transformed objects show is mapped as it is tested.
                    let mapped = !identity && shared;
                    let world = (!identity && !shared).then(|| {
                        geometry
                            .data
                            .positions
                            .iter()
                            .map(|&p| {
                                let w = transform.point(p);
                                [w.x, w.y, w.z]
                            })
                            .collect()
                    });
                    let t_norm = transform.t.iter().fold(0.0f64, |m, x| m.max(x.abs()));
                    let world_size = transform.norm() * local.magnitude() + t_norm;
                    let mut b = Bounds::EMPTY;
                    for c in local.corners() {
                        b.grow(transform.point(c));
                    }
                    // The corners' own rounding, and that of the vertices inside.
                    boxes.push(b.widened(MARGIN_ULPS * world_size));
                    let inverse = transform.inverse();
                    items.push(Item::Instance(Box::new(Instance {
                        object: object_index,
                        geometry,
                        transform,
                        inverse,
                        identity,
                        world,
                        mapped,
                        normal_matrix: transform.normal_matrix(),
                        smooth: m.smooth,
                        world_size,
                        inverse_norm: inverse.norm(),
                    })));
                }
            }
        }
        if items.is_empty() {
            return None;
        }
        let top = Hierarchy::build(&boxes);
        let reach = top.root_bounds().map_or(0.0, |b| b.magnitude());
        Some(Shapes {
            isa: Isa::detect(),
            items,
            top,
            reach,
        })
    }

    /// The margin of the top level's boxes (and of meshes in world coordinates) for a
    /// ray from `origin`: every hit lies within `reach` of the origin's magnitude, and
    /// the triangle test's rounding moves a hit by a few ε of that distance.
    #[inline(always)]
    fn world_margin(&self, origin: Vec3) -> f64 {
        let o = origin.x.abs().max(origin.y.abs()).max(origin.z.abs());
        MARGIN_ULPS * 2.0 * (o + self.reach)
    }

    /// The margin of a transformed mesh's boxes, in the file's coordinates, for a ray
    /// from `origin` (unit `dir`) that leaves the mesh's world box at `exit`: the
    /// rounding of the ray taken into the file's coordinates, of the vertices mapped to
    /// world space and of the triangle test, all mapped back by A⁻¹.
    #[inline(always)]
    fn instance_margin(&self, instance: &Instance, origin: Vec3, exit: f64) -> f64 {
        let o = origin.x.abs().max(origin.y.abs()).max(origin.z.abs());
        MARGIN_ULPS
            * instance.inverse_norm
            * (instance.world_size + 2.0 * (o + self.reach) + exit.min(2.0 * (o + self.reach)))
    }

    /// Vertex `i` of an instance in world space.
    #[inline(always)]
    fn world_vertex(instance: &Instance, i: u32) -> Vec3 {
        if let Some(w) = &instance.world {
            let p = w[i as usize];
            Vec3::new(p[0], p[1], p[2])
        } else if instance.identity {
            vertex(&instance.geometry.data, i)
        } else {
            instance
                .transform
                .point(instance.geometry.data.positions[i as usize])
        }
    }

    fn triangle_vertices(instance: &Instance, tri: u32) -> [Vec3; 3] {
        let [a, b, c] = instance.geometry.data.triangles[tri as usize];
        [
            Self::world_vertex(instance, a),
            Self::world_vertex(instance, b),
            Self::world_vertex(instance, c),
        ]
    }

    /// Visits every primitive the ray may meet before `limit()`, a leaf's triangles of
    /// a mesh together; `visit` returns `true` to stop.
    #[inline(always)]
    fn walk(
        &self,
        origin: Vec3,
        dir: Vec3,
        limit: impl Fn() -> f64,
        mut visit: impl FnMut(Candidate<'_>) -> bool,
    ) {
        let ray = SlabRay::new(origin, dir);
        let margin = self.world_margin(origin);
        self.top.walk(
            &ray,
            margin,
            &limit,
            #[inline(always)]
            |leaf| {
                for &i in self.top.primitives(leaf) {
                    match &self.items[i as usize] {
                        Item::Box { object, min, max } => {
                            if visit(Candidate::Box(i, *object, *min, *max)) {
                                return true;
                            }
                        }
                        Item::Triangle { object, v } => {
                            if visit(Candidate::Triangle(i, *object, v)) {
                                return true;
                            }
                        }
                        Item::Instance(instance) => {
                            let accel = MeshAccel::of(&instance.geometry);
                            let (local, margin) = if instance.identity {
                                (ray, margin)
                            } else {
                                let o = instance.inverse.point([origin.x, origin.y, origin.z]);
                                let d = instance.inverse.vector(dir);
                                (
                                    SlabRay::new(o, d),
                                    self.instance_margin(instance, origin, f64::INFINITY),
                                )
                            };
                            let mut stop = false;
                            accel.hierarchy.walk(
                                &local,
                                margin,
                                &limit,
                                #[inline(always)]
                                |leaf| {
                                    let block = instance.block(&accel.hierarchy, leaf);
                                    stop = visit(Candidate::Block(i, instance, &block));
                                    stop
                                },
                            );
                            if stop {
                                return true;
                            }
                        }
                    }
                }
                false
            },
        );
    }

    isa_dispatch! {
        /// The nearest hit before `best` = (t, object, prim) of a ray leaving object
        /// `from` (its triangle `from_prim`), if one comes before it.
        pub fn nearest / nearest_avx2(
            &self,
            origin: Vec3,
            dir: Vec3,
            from: u32,
            from_prim: u32,
            best: (f64, u32, u32),
        ) -> Option<ShapeHit> {
            self.nearest_lanes(origin, dir, from, from_prim, best)
        }
    }

    isa_dispatch! {
        /// Whether the ray leaving object `from` (triangle `from_prim`) meets a shape at
        /// a distance in (0, `limit`).
        pub fn occluded / occluded_avx2(
            &self,
            origin: Vec3,
            dir: Vec3,
            from: u32,
            from_prim: u32,
            limit: f64,
        ) -> bool {
            self.occluded_lanes(origin, dir, from, from_prim, limit)
        }
    }

    #[inline(always)]
    fn nearest_lanes(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        from_prim: u32,
        best: (f64, u32, u32),
    ) -> Option<ShapeHit> {
        let sheared = ShearedRay::new(origin, dir);
        let best = std::cell::Cell::new(best);
        let mut found: Option<ShapeHit> = None;
        let limit = || best.get().0;
        let mut consider = |item: u32, t: f64, object: u32, prim: u32, detail: Detail| {
            let b = best.get();
            if before(t, object, prim, &b) {
                best.set((t, object, prim));
                found = Some(ShapeHit {
                    t,
                    object,
                    prim,
                    item,
                    detail,
                });
            }
        };
        self.walk(
            origin,
            dir,
            limit,
            #[inline(always)]
            |candidate| {
                let t_max = best.get().0;
                match candidate {
                    Candidate::Box(i, object, min, max) => {
                        if let Some(h) = cuboid::hit(min, max, origin, dir, t_max) {
                            consider(i, h.t, object, 0, Detail::Box(h));
                        }
                    }
                    Candidate::Triangle(i, object, v) => {
                        if object != from {
                            if let Some(h) = sheared.hit(v[0], v[1], v[2], t_max) {
                                consider(i, h.t, object, 0, Detail::Triangle(h.b));
                            }
                        }
                    }
                    Candidate::Block(i, instance, block) => {
                        let lanes = Self::lanes_not_from(instance, block, from, from_prim);
                        let (hit, t, b) = sheared.hit4(&block.v, t_max);
                        let mut bits = hit.and(lanes).bitmask();
                        while bits != 0 {
                            let k = bits.trailing_zeros() as usize;
                            bits &= bits - 1;
                            let h = ShearedRay::lane_hit(t, &b, k);
                            let detail = Detail::Triangle(h.b);
                            consider(i, h.t, instance.object, block.tri[k], detail);
                        }
                    }
                }
                false
            },
        );
        found
    }

    #[inline(always)]
    fn occluded_lanes(
        &self,
        origin: Vec3,
        dir: Vec3,
        from: u32,
        from_prim: u32,
        limit: f64,
    ) -> bool {
        let sheared = ShearedRay::new(origin, dir);
        let mut blocked = false;
        let reach = || limit;
        self.walk(
            origin,
            dir,
            reach,
            #[inline(always)]
            |candidate| {
                blocked = match candidate {
                    Candidate::Box(_, _, min, max) => {
                        cuboid::hit(min, max, origin, dir, limit).is_some_and(|h| h.t < limit)
                    }
                    Candidate::Triangle(_, object, v) => {
                        object != from
                            && sheared
                                .hit(v[0], v[1], v[2], limit)
                                .is_some_and(|h| h.t < limit)
                    }
                    Candidate::Block(_, instance, block) => {
                        let lanes = Self::lanes_not_from(instance, block, from, from_prim);
                        let (hit, t, _) = sheared.hit4(&block.v, limit);
                        hit.and(lanes).and(t.lt(F4::splat(limit))).any()
                    }
                };
                blocked
            },
        );
        blocked
    }

    /// The live lanes of `block` other than the triangle `from_prim` of object `from`.
    #[inline(always)]
    fn lanes_not_from(instance: &Instance, block: &TriBlock, from: u32, from_prim: u32) -> M4 {
        if instance.object != from {
            return block.live();
        }
        block
            .live()
            .and_not(M4::from_fn(|k| block.tri[k] == from_prim))
    }

    /// Every triangle or box hit of the ray at t > 0, through the hierarchies (for
    /// tests: the watertightness of the whole path, culling included).
    #[cfg(test)]
    pub fn all_hits(&self, origin: Vec3, dir: Vec3) -> Vec<(f64, u32, u32)> {
        let sheared = ShearedRay::new(origin, dir);
        let mut hits = Vec::new();
        let limit = || f64::INFINITY;
        self.walk(
            origin,
            dir,
            limit,
            #[inline(always)]
            |candidate| {
                match candidate {
                    Candidate::Box(_, object, min, max) => {
                        if let Some(h) = cuboid::hit(min, max, origin, dir, f64::INFINITY) {
                            hits.push((h.t, object, 0));
                        }
                    }
                    Candidate::Triangle(_, object, v) => {
                        if let Some(h) = sheared.hit(v[0], v[1], v[2], f64::INFINITY) {
                            hits.push((h.t, object, 0));
                        }
                    }
                    Candidate::Block(_, instance, block) => {
                        let (hit, t, _) = sheared.hit4(&block.v, f64::INFINITY);
                        let mut bits = hit.and(block.live()).bitmask();
                        while bits != 0 {
                            let k = bits.trailing_zeros() as usize;
                            bits &= bits - 1;
                            hits.push((t.0[k], instance.object, block.tri[k]));
                        }
                    }
                }
                false
            },
        );
        hits
    }

    /// The surface where `hit` meets the ray `origin + t·dir`.
    pub fn surface(&self, hit: &ShapeHit, origin: Vec3, dir: Vec3) -> SurfacePoint {
        match (&self.items[hit.item as usize], hit.detail) {
            (&Item::Box { min, max, .. }, Detail::Box(b)) => {
                let (p, _) = cuboid::on_face(min, max, &b, origin + dir * hit.t, dir);
                let mut n = [0.0; 3];
                n[b.axis] = b.outward;
                let ng = Vec3::new(n[0], n[1], n[2]);
                SurfacePoint {
                    p,
                    ng,
                    ns: ng,
                    spawn: Spawn::Box { min, max, hit: b },
                }
            }
            (Item::Triangle { v, .. }, Detail::Triangle(b)) => Self::flat(*v, b),
            (Item::Instance(instance), Detail::Triangle(b)) => {
                let v = Self::triangle_vertices(instance, hit.prim);
                let mut s = Self::flat(v, b);
                if instance.smooth {
                    s.ns = Self::smooth_normal(instance, hit.prim, b, s.ng);
                }
                s
            }
            _ => unreachable!("a hit's detail matches its item"),
        }
    }

    fn flat(v: [Vec3; 3], b: [f64; 3]) -> SurfacePoint {
        let (p, error) = triangle::point_at(v, b);
        let cross = (v[1] - v[0]).cross(v[2] - v[0]);
        let len = cross.length();
        let ng = if len > 0.0 && len.is_finite() {
            cross / len
        } else {
            // Too small or large to normalise as is: scaled first.
            let m = cross.x.abs().max(cross.y.abs()).max(cross.z.abs());
            (cross / m).normalize()
        };
        SurfacePoint {
            p,
            ng,
            ns: ng,
            spawn: Spawn::Triangle(error),
        }
    }

    /// Section 8's Ns: the interpolated vertex normals, normalised, on Ng's side.
    fn smooth_normal(instance: &Instance, tri: u32, b: [f64; 3], ng: Vec3) -> Vec3 {
        let data = &instance.geometry.data;
        let corners = data.triangles[tri as usize];
        let file = data
            .corner_normals
            .get(tri as usize)
            .copied()
            .unwrap_or([NO_NORMAL; 3]);
        let mut computed = None;
        let mut n = [Vec3::ZERO; 3];
        for k in 0..3 {
            let source = if file[k] != NO_NORMAL {
                data.normals.get(file[k] as usize).copied()
            } else {
                let normals = *computed.get_or_insert_with(|| {
                    MeshAccel::of(&instance.geometry).computed_normals(data)
                });
                normals[corners[k] as usize]
            };
            n[k] = source
                .and_then(|s| map_normal(&instance.normal_matrix, s))
                .unwrap_or(ng);
        }
        let sum = n[0] * b[0] + n[1] * b[1] + n[2] * b[2];
        let len = sum.length();
        let ns = if len > 0.0 && len.is_finite() {
            sum / len
        } else {
            ng
        };
        if ns.dot(ng) < 0.0 {
            -ns
        } else {
            ns
        }
    }
}

#[cfg(test)]
mod tests;
