//! Building the hierarchy, once per scene: the binned surface area heuristic over the
//! sphere centres (at the median below a depth), splitting the child with the largest
//! box until a node has eight children, with subtrees built in parallel on the current
//! rayon pool. Its boxes of four lanes ([`Box4`]) and ranges of spheres ([`Part`]) are
//! the build's own: the traversals read only the nodes it writes.

use super::{down32, up32, Bvh, Node, EMPTY, LEAF_BIT, LEAF_SIZE, MAX_SCALE, WIDTH};
use crate::geometry::SphereGeom;
use crate::simd::Isa;

/// Split-plane candidates per axis in the surface area heuristic.
const BINS: usize = 16;
/// Below this binary depth the heuristic chooses splits; deeper, splits are at the
/// median, which halves the sphere count and so bounds the depth for any input.
const SAH_MAX_DEPTH: u32 = 40;
/// Subtrees with at least this many spheres are built in parallel with their siblings.
const PARALLEL_MIN: usize = 4096;
/// Most spheres: a leaf's first sphere is kept in 28 bits.
const MAX_SPHERES: usize = 1 << 28;

impl Bvh {
    /// Builds the hierarchy over `spheres` (object index, geometry), or `None` if the
    /// scene is too large in scale or count for the margin argument (then only brute
    /// force). Subtrees are built in parallel on the current rayon pool. The
    /// traversals run with `isa`, which must be available on this processor.
    pub fn build(spheres: &[(u32, SphereGeom)], isa: Isa) -> Option<Bvh> {
        let scale = spheres
            .iter()
            .map(|(_, s)| s.center.x.abs() + s.center.y.abs() + s.center.z.abs() + s.radius)
            .fold(0.0, f64::max);
        if spheres.is_empty() || spheres.len() > MAX_SPHERES || scale.is_nan() || scale > MAX_SCALE
        {
            return None;
        }
        use rayon::prelude::*;
        let parallel = rayon::current_num_threads() > 1;
        // Per sphere, in order: mapped in parallel when large (the order, so the
        // hierarchy, is the same).
        let mut prims: Vec<Prim> = if parallel && spheres.len() >= PARALLEL_MIN {
            spheres
                .par_iter()
                .enumerate()
                .map(|(i, (_, s))| Box4::prim(i as u32, s))
                .collect()
        } else {
            spheres
                .iter()
                .enumerate()
                .map(|(i, (_, s))| Box4::prim(i as u32, s))
                .collect()
        };
        let (bounds, centres) = prims.iter().fold((Box4::EMPTY, Box4::EMPTY), |(b, c), p| {
            (b.union(&p.bounds()), c.grow(p.centre2()))
        });
        let whole = Part {
            start: 0,
            len: prims.len(),
            bounds,
            centres,
            depth: 0,
        };
        let mut nodes = Vec::with_capacity(spheres.len() / 4 + 1);
        build_node(&mut prims, 0, whole, parallel, &mut nodes);
        let spheres = if parallel && prims.len() >= PARALLEL_MIN {
            prims
                .par_iter()
                .map(|p| spheres[p.index() as usize])
                .collect()
        } else {
            prims.iter().map(|p| spheres[p.index() as usize]).collect()
        };
        Some(Bvh {
            nodes,
            spheres,
            scale,
            isa,
        })
    }
}

impl Node {
    const EMPTY: Node = Node {
        bounds: [
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
            [f32::INFINITY; WIDTH],
            [f32::NEG_INFINITY; WIDTH],
        ],
        children: [EMPTY; WIDTH],
    };

    fn set(&mut self, k: usize, b: &Box4, child: u32) {
        for axis in 0..3 {
            self.bounds[2 * axis][k] = b.lo[axis];
            self.bounds[2 * axis + 1][k] = b.hi[axis];
        }
        self.children[k] = child;
    }
}

/// An axis-aligned box in single precision, in four lanes so that a union is two SIMD
/// operations: lane 3 is unused (a [`Prim`] keeps its sphere's position there).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
struct Box4 {
    lo: [f32; 4],
    hi: [f32; 4],
}

#[inline(always)]
fn min4(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    std::array::from_fn(|i| if a[i] < b[i] { a[i] } else { b[i] })
}

#[inline(always)]
fn max4(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    std::array::from_fn(|i| if a[i] > b[i] { a[i] } else { b[i] })
}

impl Box4 {
    const EMPTY: Box4 = Box4 {
        lo: [f32::INFINITY; 4],
        hi: [f32::NEG_INFINITY; 4],
    };

    #[inline(always)]
    fn union(&self, o: &Box4) -> Box4 {
        Box4 {
            lo: min4(self.lo, o.lo),
            hi: max4(self.hi, o.hi),
        }
    }

    #[inline(always)]
    fn grow(&self, p: [f32; 4]) -> Box4 {
        Box4 {
            lo: min4(self.lo, p),
            hi: max4(self.hi, p),
        }
    }

    /// Half the surface area (the heuristic only compares areas); 0 for an empty box.
    #[inline(always)]
    fn area(&self) -> f32 {
        let e: [f32; 3] = std::array::from_fn(|a| (self.hi[a] - self.lo[a]).max(0.0));
        e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
    }
}

/// A sphere during the build: its box, rounded outward to `f32`, with the sphere's
/// position in the input in lane 3 of `lo` (as bits).
type Prim = Box4;

impl Box4 {
    fn prim(index: u32, s: &SphereGeom) -> Prim {
        let c = [s.center.x, s.center.y, s.center.z];
        Box4 {
            lo: [
                down32(c[0] - s.radius),
                down32(c[1] - s.radius),
                down32(c[2] - s.radius),
                f32::from_bits(index),
            ],
            hi: [
                up32(c[0] + s.radius),
                up32(c[1] + s.radius),
                up32(c[2] + s.radius),
                0.0,
            ],
        }
    }

    /// The prim's sphere's position in the input.
    fn index(&self) -> u32 {
        self.lo[3].to_bits()
    }

    /// The prim's box without the index.
    #[inline(always)]
    fn bounds(&self) -> Box4 {
        Box4 {
            lo: [self.lo[0], self.lo[1], self.lo[2], 0.0],
            hi: self.hi,
        }
    }

    /// Twice the prim's centre (only compared), lane 3 zero.
    #[inline(always)]
    fn centre2(&self) -> [f32; 4] {
        [
            self.lo[0] + self.hi[0],
            self.lo[1] + self.hi[1],
            self.lo[2] + self.hi[2],
            0.0,
        ]
    }
}

/// A range of prims that becomes one child of a node: its box, the box of its doubled
/// centres, and its binary depth.
#[derive(Clone, Copy, Debug)]
struct Part {
    start: usize,
    len: usize,
    bounds: Box4,
    centres: Box4,
    depth: u32,
}

/// Builds the node over the prims of `whole` and its subtree into `out`, reordering
/// the prims so that each leaf's are contiguous; `offset` is the position of `prims`
/// in the whole array. Returns the node's index.
fn build_node(
    prims: &mut [Prim],
    offset: usize,
    whole: Part,
    parallel: bool,
    out: &mut Vec<Node>,
) -> u32 {
    // Split the child with the largest box until there are eight.
    let mut parts = [whole; WIDTH];
    let mut count = 1;
    while count < WIDTH {
        let widest = (0..count)
            .filter(|&i| parts[i].len > LEAF_SIZE)
            .max_by(|&a, &b| parts[a].bounds.area().total_cmp(&parts[b].bounds.area()));
        let Some(i) = widest else { break };
        let p = parts[i];
        let (left, right) = split(&mut prims[p.start..p.start + p.len], &p);
        parts.copy_within(i + 1..count, i + 2);
        parts[i] = left;
        parts[i + 1] = right;
        count += 1;
    }
    let index = out.len();
    out.push(Node::EMPTY);
    let parts = &parts[..count];
    for (k, p) in parts.iter().enumerate() {
        if p.len <= LEAF_SIZE {
            let first = u32::try_from(offset + p.start).expect("at most 2²⁸ spheres");
            out[index].set(k, &p.bounds, LEAF_BIT | ((p.len as u32 - 1) << 28) | first);
        }
    }
    if parallel && prims.len() >= PARALLEL_MIN {
        // The inner children's subtrees, each into its own array, then appended.
        use rayon::prelude::*;
        let mut jobs = Vec::new();
        let mut rest = prims;
        for (k, p) in parts.iter().enumerate() {
            let (mine, tail) = std::mem::take(&mut rest).split_at_mut(p.len);
            rest = tail;
            if p.len > LEAF_SIZE {
                jobs.push((k, mine, *p));
            }
        }
        let built: Vec<(usize, Vec<Node>)> = jobs
            .into_par_iter()
            .map(|(k, mine, p)| {
                let mut sub = Vec::with_capacity(p.len / 4);
                let whole = Part { start: 0, ..p };
                build_node(
                    mine,
                    offset + p.start,
                    whole,
                    p.len >= PARALLEL_MIN,
                    &mut sub,
                );
                (k, sub)
            })
            .collect();
        for (k, sub) in built {
            let base = u32::try_from(out.len()).expect("node count fits in u32");
            out.extend(sub.into_iter().map(|mut node| {
                for c in &mut node.children {
                    if *c & LEAF_BIT == 0 {
                        *c += base;
                    }
                }
                node
            }));
            out[index].set(k, &parts[k].bounds, base);
        }
    } else {
        for (k, p) in parts.iter().enumerate() {
            if p.len > LEAF_SIZE {
                let whole = Part { start: 0, ..*p };
                let child = build_node(
                    &mut prims[p.start..p.start + p.len],
                    offset + p.start,
                    whole,
                    false,
                    out,
                );
                out[index].set(k, &p.bounds, child);
            }
        }
    }
    u32::try_from(index).expect("node count fits in u32")
}

/// Per axis, the bin of doubled centres `c` for bins from `lo` with `scale` per unit.
#[inline(always)]
fn bins_of(c: [f32; 4], lo: [f32; 4], scale: [f32; 4], last: i32) -> [usize; 3] {
    let b: [i32; 4] = std::array::from_fn(|a| ((c[a] - lo[a]) * scale[a]) as i32);
    std::array::from_fn(|a| (b[a].clamp(0, last)) as usize)
}

/// Splits the prims of `whole` (`prims`, more than one) in two by the binned surface
/// area heuristic over their centres, or at the median below [`SAH_MAX_DEPTH`];
/// returns the two parts.
fn split(prims: &mut [Prim], whole: &Part) -> (Part, Part) {
    let cb = whole.centres;
    let extent: [f32; 4] = std::array::from_fn(|a| cb.hi[a] - cb.lo[a]);
    let part = |start, len, bounds, centres| Part {
        start: whole.start + start,
        len,
        bounds,
        centres,
        depth: whole.depth + 1,
    };
    if whole.depth < SAH_MAX_DEPTH {
        // Fewer bins for few prims, where sweeping the bins would cost more than
        // binning. `scale` maps a centre to its bin (to bin 0 on an axis without
        // spread).
        let bins = (prims.len() / 2).clamp(4, BINS);
        let last = bins as i32 - 1;
        let scale: [f32; 4] = std::array::from_fn(|a| {
            if a < 3 && extent[a] > 0.0 {
                bins as f32 * 0.999_99 / extent[a]
            } else {
                0.0
            }
        });
        let mut boxes = [[Box4::EMPTY; BINS]; 3];
        let mut counts = [[0u32; BINS]; 3];
        for p in prims.iter() {
            let b = bins_of(p.centre2(), cb.lo, scale, last);
            for a in 0..3 {
                counts[a][b[a]] += 1;
                boxes[a][b[a]] = boxes[a][b[a]].union(p);
            }
        }
        // (cost, axis, first bin of the right part, left box, right box)
        let mut best: Option<(f32, usize, usize, Box4, Box4)> = None;
        for a in 0..3 {
            if extent[a] <= 0.0 {
                continue;
            }
            let mut left = [(Box4::EMPTY, 0u32); BINS];
            let (mut acc, mut m) = (Box4::EMPTY, 0);
            for b in 0..bins - 1 {
                acc = acc.union(&boxes[a][b]);
                m += counts[a][b];
                left[b] = (acc, m);
            }
            let (mut acc, mut m) = (Box4::EMPTY, 0);
            for b in (1..bins).rev() {
                acc = acc.union(&boxes[a][b]);
                m += counts[a][b];
                let (lb, ln) = left[b - 1];
                if ln == 0 || m == 0 {
                    continue;
                }
                let cost = lb.area() * ln as f32 + acc.area() * m as f32;
                if best.as_ref().is_none_or(|x| cost < x.0) {
                    best = Some((cost, a, b, lb, acc));
                }
            }
        }
        if let Some((_, a, b, lb, rb)) = best {
            // Hoare partition, gathering each side's centre bounds on the way.
            let (lo, per) = (cb.lo[a], scale[a]);
            let goes_left =
                |p: &Prim| ((((p.lo[a] + p.hi[a]) - lo) * per) as i32).clamp(0, last) < b as i32;
            let (mut lc, mut rc) = (Box4::EMPTY, Box4::EMPTY);
            let (mut i, mut j) = (0, prims.len());
            loop {
                while i < j && goes_left(&prims[i]) {
                    lc = lc.grow(prims[i].centre2());
                    i += 1;
                }
                while i < j && !goes_left(&prims[j - 1]) {
                    rc = rc.grow(prims[j - 1].centre2());
                    j -= 1;
                }
                if i >= j {
                    break;
                }
                prims.swap(i, j - 1);
            }
            let n = prims.len();
            return (part(0, i, lb.bounds(), lc), part(i, n - i, rb.bounds(), rc));
        }
    }
    // The median centre along the widest axis (any halving if the centres coincide).
    let axis = (0..3)
        .max_by(|&a, &b| extent[a].total_cmp(&extent[b]))
        .unwrap_or(0);
    let mid = prims.len() / 2;
    if extent[axis] > 0.0 {
        prims.select_nth_unstable_by(mid, |a, b| a.centre2()[axis].total_cmp(&b.centre2()[axis]));
    }
    let side = |ps: &[Prim]| {
        ps.iter().fold((Box4::EMPTY, Box4::EMPTY), |(b, c), p| {
            (b.union(&p.bounds()), c.grow(p.centre2()))
        })
    };
    let (lb, lc) = side(&prims[..mid]);
    let (rb, rc) = side(&prims[mid..]);
    (part(0, mid, lb, lc), part(mid, prims.len() - mid, rb, rc))
}
