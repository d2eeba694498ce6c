//! Where adaptive sampling must not stop early: per square block of pixels, the fewest
//! samples a pixel should take before its samples' agreement is believed.
//!
//! Adaptive sampling calls a pixel converged when its first samples agree. That test is
//! blind to whatever all of those samples missed: a sphere a fraction of a pixel wide, or
//! checker squares so small that four samples land on one colour. Such a pixel looks
//! perfectly converged after four samples and is wrong. The scene tells in advance where
//! this can happen, from its geometry alone, so this module computes it once per frame
//! from the camera, the spheres and the checkerboard planes: one pass over the spheres
//! and a few analytic ray–plane intersections per block, no tracing of the image.
//!
//! The bounds are conservative: a block is constrained whenever it *may* show such
//! detail (occlusion is mostly ignored), never the other way round.
//!
//! Only +, −, ×, ÷ and square roots of `f64`, all correctly rounded by IEEE 754, and
//! integer operations are used (no `powf`, logarithms or trigonometry, whose results
//! differ between math libraries), and no state is shared, so the same scene gives the
//! same minima bit for bit on every machine: the farm's workers must agree on them,
//! since they decide how many samples a pixel takes.
//!
//! What is not covered: detail seen only in mirrors (a reflected checkerboard or small
//! sphere), small shadows, and the edges of large objects, where the sampler's own error
//! estimate is expected to do the work.

use crate::geometry::{PlaneGeom, SphereGeom};
use crate::scene::Material;
use crate::tracer::Tracer;
use crate::vec3::Vec3;

/// A sphere whose projection has a radius (lower bound) below this many pixels is
/// small enough for a pixel's first samples to miss it altogether.
const SMALL_SPHERE_PIXELS: f64 = 2.0;

/// A small sphere of projected radius r pixels asks for n ≥ this / r² samples per pixel.
/// A (0, m, 2)-net of n = 2^m points puts a point in every elementary square of side
/// about 1/√n of the pixel, and a disk of radius r contains a square of side r√2; with
/// n ≥ 4/r² that square holds a whole elementary square (with room to spare for its
/// alignment), so a pixel that shows part of the sphere is very unlikely to miss it.
const SPHERE_SAMPLES_TIMES_R2: f64 = 4.0;

/// The least minimum a small sphere imposes: the smallest count past the sampler's
/// first four samples, the ones whose agreement would otherwise end the pixel.
const SMALL_SPHERE_MIN: u32 = 4;

/// Pixels of margin around a small sphere's projection (beyond an upper bound of its
/// projected radius) in which blocks are constrained: a pixel that only touches the
/// silhouette's edge is the likeliest to miss it, and the margin absorbs any rounding.
const SPHERE_MARGIN_PIXELS: f64 = 1.0;

/// A checkerboard whose footprint exceeds this many squares per pixel (squares are one
/// unit) needs more than the first samples: squares of four pixels or less can put all
/// four first samples on one colour (aliasing) and look converged.
const CHECKER_FOOTPRINT_LIMIT: f64 = 0.25;

/// Such a block asks for n ≥ (this × footprint)² samples: with the footprint f squares
/// per pixel, a square of side 1/f pixels then holds about 16 samples of the net (4 per
/// side), enough that both colours of every pixel the pattern crosses are seen.
const CHECKER_SAMPLES_PER_FOOTPRINT: f64 = 4.0;

/// The least minimum a fine checkerboard imposes: (4 · ¼)² = 1 would not constrain
/// anything, and 16 samples in a (0, m, 2)-net already form a 4 × 4 stratification of
/// the pixel, the first count that resolves squares of a quarter to a whole pixel.
const CHECKER_MIN: u32 = 16;

/// Footprints above this many squares per pixel (and blocks the horizon crosses) ask
/// only for [`CHECKER_MIN`]: with two squares or more across a pixel, samples spread
/// over the pixel land on both colours and the sampler's own estimate sees the
/// pattern; forcing more there would spend the budget where the estimate already
/// works. The danger is the band between: squares of half a pixel to four pixels,
/// which a few samples can all miss in the same way.
const CHECKER_VISIBLE: f64 = 2.0;

/// The fraction of a sphere's squared radius within which a corner's ray must pass for
/// the corner to count as covered by that sphere in the occlusion test: a hair inside
/// the silhouette, so that rounding at the rim never hides a plane that shows.
const HIDDEN_RADIUS2_FRACTION: f64 = 1.0 - 1e-6;

/// The fraction of its radius by which a sphere's centre must be off a plane for the
/// sphere to count as lying on one side of it: a sphere resting on the board (centre
/// exactly one radius above it, up to the rounding of the scene's numbers) qualifies;
/// one sunk by 1e-9 of its radius shows the board through a disk of radius ~5e-5 of
/// its own, too small to matter.
const TANGENT_TOLERANCE: f64 = 1.0 - 1e-9;

/// Per-block minimum samples per pixel that sub-pixel geometry demands.
///
/// Blocks are `block` × `block` pixels aligned to the image's top-left corner; the last
/// column and row of blocks may be partial.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Footprints {
    blocks_x: u32,
    blocks_y: u32,
    block: u32,
    /// Row by row, `blocks_x` per row: powers of two in 1..=cap.
    mins: Vec<u32>,
}

impl Footprints {
    /// The minima of the frame `tracer` renders, in blocks of `block` pixels. `cap` is
    /// the most samples a pixel may take; no minimum exceeds it.
    ///
    /// # Panics
    ///
    /// If `block` is 0 or `cap` is not a power of two.
    pub fn new(tracer: &Tracer, block: u32, cap: u32) -> Footprints {
        assert!(block > 0, "blocks have at least one pixel");
        assert!(cap.is_power_of_two(), "the cap {cap} is a power of two");
        let settings = tracer.settings();
        let view = View::new(tracer);
        let blocks_x = settings.width.div_ceil(block);
        let blocks_y = settings.height.div_ceil(block);
        let mut footprints = Footprints {
            blocks_x,
            blocks_y,
            block,
            mins: vec![1; blocks_x as usize * blocks_y as usize],
        };
        if cap > 1 {
            footprints.small_spheres(&view, tracer.spheres(), cap);
            for &(index, plane) in tracer.planes() {
                if tracer.material(index as usize) == Material::Checker {
                    footprints.checker_plane(tracer, &view, &plane, cap);
                }
            }
        }
        footprints
    }

    /// The minimum for the block whose top-left pixel is (`bx` · block, `by` · block): a
    /// power of two in 1..=cap, 1 meaning no constraint.
    ///
    /// # Panics
    ///
    /// If the block lies outside the image.
    pub fn min_samples(&self, bx: u32, by: u32) -> u32 {
        assert!(
            bx < self.blocks_x && by < self.blocks_y,
            "block ({bx}, {by}) outside {} × {}",
            self.blocks_x,
            self.blocks_y
        );
        self.mins[by as usize * self.blocks_x as usize + bx as usize]
    }

    /// The side of a block in pixels.
    pub fn block(&self) -> u32 {
        self.block
    }

    /// Blocks per row of the image.
    pub fn blocks_x(&self) -> u32 {
        self.blocks_x
    }

    /// Rows of blocks.
    pub fn blocks_y(&self) -> u32 {
        self.blocks_y
    }

    /// Raises the minimum of block (`bx`, `by`) to `n`.
    fn raise(&mut self, bx: u32, by: u32, n: u32) {
        let k = by as usize * self.blocks_x as usize + bx as usize;
        self.mins[k] = self.mins[k].max(n);
    }

    /// Rule 1, small spheres seen directly. For each sphere wholly in front of the
    /// camera, a lower bound r of its projected radius decides the count (4/r², so a
    /// sphere is never under-sampled because its size was overestimated) and an upper
    /// bound decides which pixels it may cover (so no pixel it shows in is missed).
    ///
    /// The lower bound is m·R/D with D the distance to the centre: the rays within the
    /// angle asin(R/D) of the centre's direction all meet the sphere, and the image
    /// plane (at distance 1 from the eye, m pixels per unit) is never closer than its
    /// angular distance, so the disk of radius R/D around the projected centre lies
    /// inside the silhouette. The upper bound: a point c + e of the sphere (|e| ≤ R)
    /// projects at most R·(z + ρ)/(z·(z − R)) from the centre's projection, with z the
    /// centre's depth and ρ its distance from the optical axis.
    ///
    /// A sphere that crosses the camera's plane (depth of its centre minus its radius
    /// not positive) is skipped: it has no bounded projection, and it is either near the
    /// eye, hence large, or far to the side, hence outside the frame.
    fn small_spheres(&mut self, view: &View, spheres: &[(u32, SphereGeom)], cap: u32) {
        for &(_, sphere) in spheres {
            let d = sphere.center - view.eye;
            let depth = d.dot(view.forward);
            let near = depth - sphere.radius;
            if near.is_nan() || near <= 0.0 {
                continue;
            }
            let radius = view.short_side * sphere.radius / d.length();
            if radius.is_nan() || radius >= SMALL_SPHERE_PIXELS {
                continue;
            }
            let x = d.dot(view.right);
            let y = d.dot(view.up);
            let off_axis = (x * x + y * y).sqrt();
            let reach = view.short_side * sphere.radius * (depth + off_axis) / (depth * near)
                + SPHERE_MARGIN_PIXELS;
            let cx = view.half_width + view.short_side * x / depth;
            let cy = view.half_height - view.short_side * y / depth;
            let (Some((i0, i1)), Some((j0, j1))) = (
                pixel_span(cx - reach, cx + reach, view.width),
                pixel_span(cy - reach, cy + reach, view.height),
            ) else {
                continue;
            };
            let n = power_of_two_at_least(
                SPHERE_SAMPLES_TIMES_R2 / (radius * radius),
                SMALL_SPHERE_MIN,
                cap,
            );
            for by in j0 / self.block..=j1 / self.block {
                for bx in i0 / self.block..=i1 / self.block {
                    self.raise(bx, by, n);
                }
            }
        }
    }

    /// Rule 2, a checkerboard plane seen directly. The camera rays through each block's
    /// four corners are intersected with the plane analytically. The ray's direction is
    /// affine in the image point, so the sign of n̂·direction, hence whether the ray
    /// meets the plane ahead, is that of an affine function: when no corner hits, no
    /// point of the block does, and when only some do, the horizon crosses the block and
    /// the squares there shrink to nothing (the cap). When all four hit, the footprint f
    /// of a pixel in squares is the larger of
    /// - the distance between the hit points of adjacent corners over the block's side
    ///   (the mean footprint along each edge, in x and in y), and
    /// - the exact footprint at each corner, |∂p/∂x| and |∂p/∂y| per pixel, which also
    ///   catches the growth of the footprint toward the horizon inside the block.
    ///
    /// Distances are in 3-D; for a plane that is not horizontal they may overstate the
    /// change in (x, z), which only makes the bound more conservative.
    fn checker_plane(&mut self, tracer: &Tracer, view: &View, plane: &PlaneGeom, cap: u32) {
        let num = plane.distance - plane.normal.dot(view.eye);
        if !(num != 0.0) {
            // The eye lies in the plane: seen edge-on, it covers no pixel.
            return;
        }
        let (block, blocks_x) = (self.block, self.blocks_x);
        let corner_x = |bx: u32| f64::from((bx * block).min(view.width_px));
        let corner_y = |by: u32| f64::from((by * block).min(view.height_px));
        let row = |by: u32| -> Vec<Option<CornerHit>> {
            (0..=blocks_x)
                .map(|bx| CornerHit::new(view, plane, num, corner_x(bx), corner_y(by)))
                .collect()
        };
        let mut top = row(0);
        for by in 0..self.blocks_y {
            let bottom = row(by + 1);
            let height = corner_y(by + 1) - corner_y(by);
            for bx in 0..self.blocks_x {
                let (x0, x1) = (bx as usize, bx as usize + 1);
                let corners = [top[x0], top[x1], bottom[x0], bottom[x1]];
                let hits = corners.iter().flatten().count();
                let n = match corners {
                    _ if hits == 0 => continue,
                    [Some(a), Some(b), Some(c), Some(d)] => {
                        let width = corner_x(bx + 1) - corner_x(bx);
                        let across = (a.point - b.point)
                            .length()
                            .max((c.point - d.point).length())
                            / width;
                        let down = (a.point - c.point)
                            .length()
                            .max((b.point - d.point).length())
                            / height;
                        let f = [a, b, c, d]
                            .iter()
                            .fold(across.max(down), |f, corner| f.max(corner.footprint));
                        // A footprint that is not a number (overflow) counts as
                        // infinite, hence gets the cap.
                        if f <= CHECKER_FOOTPRINT_LIMIT {
                            continue;
                        }
                        if f <= CHECKER_VISIBLE {
                            let s = CHECKER_SAMPLES_PER_FOOTPRINT * f;
                            power_of_two_at_least(s * s, CHECKER_MIN, cap)
                        } else {
                            CHECKER_MIN.min(cap)
                        }
                    }
                    _ => CHECKER_MIN.min(cap),
                };
                if n > self.min_samples(bx, by)
                    && !hidden(
                        tracer,
                        view,
                        plane,
                        corner_points(bx, by, &corner_x, &corner_y),
                    )
                {
                    self.raise(bx, by, n);
                }
            }
            top = bottom;
        }
    }
}

/// The four corners of block (`bx`, `by`) in pixel coordinates: top left, top right,
/// bottom left, bottom right.
fn corner_points(
    bx: u32,
    by: u32,
    corner_x: &dyn Fn(u32) -> f64,
    corner_y: &dyn Fn(u32) -> f64,
) -> [(f64, f64); 4] {
    let (x0, x1, y0, y1) = (
        corner_x(bx),
        corner_x(bx + 1),
        corner_y(by),
        corner_y(by + 1),
    );
    [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
}

/// Whether the plane is certainly hidden in the block with these corners: the rays
/// through all four corners pass inside one matte sphere that lies wholly in front of
/// the camera and on the eye's side of the plane (touching it is allowed: a sphere
/// resting on the board still hides it). The sphere's silhouette is then convex and
/// contains the block, and along every ray of the block the sphere comes before the
/// plane. A mirror sphere hides nothing: it shows the board again, smaller, so its
/// reflection needs the samples at least as much. The candidate is the nearest object at
/// the first corner; other occluders (planes, several spheres together) are not
/// considered, which can only leave a constraint in place.
fn hidden(tracer: &Tracer, view: &View, plane: &PlaneGeom, corners: [(f64, f64); 4]) -> bool {
    let dirs = corners.map(|(px, py)| view.ray(px, py).normalize());
    let Some(hit) = tracer.nearest_hit(view.eye, dirs[0], None) else {
        return false;
    };
    let spheres = tracer.spheres();
    let Ok(k) = spheres.binary_search_by_key(&hit.object, |&(index, _)| index as usize) else {
        return false;
    };
    let sphere = spheres[k].1;
    if tracer.material(hit.object) != Material::Matte {
        return false;
    }
    let d = sphere.center - view.eye;
    let near = d.dot(view.forward) - sphere.radius;
    if near.is_nan() || near <= 0.0 {
        return false;
    }
    let eye_side = plane.normal.dot(view.eye) - plane.distance;
    let centre_side = plane.normal.dot(sphere.center) - plane.distance;
    // On the eye's side up to a rounding of the tangency of a sphere resting on it.
    let clearance = sphere.radius * TANGENT_TOLERANCE;
    let apart = if eye_side > 0.0 {
        centre_side >= clearance
    } else {
        -centre_side >= clearance
    };
    let inner = sphere.radius2 * HIDDEN_RADIUS2_FRACTION;
    apart
        && dirs.iter().all(|&dir| {
            let closest = d - dir * d.dot(dir);
            closest.dot(closest) < inner
        })
}

/// Where a corner's camera ray meets a plane ahead, and the footprint of a pixel there.
#[derive(Clone, Copy, Debug)]
struct CornerHit {
    point: Vec3,
    /// The larger of |∂p/∂x| and |∂p/∂y|, the hit point's motion per pixel.
    footprint: f64,
}

impl CornerHit {
    /// With the unnormalised direction v = f + x·r + y·u of section 2, s = n̂·v and
    /// t = (distance − n̂·eye)/s, the hit is p = eye + t·v and, since ∂v/∂x = r/m,
    /// ∂p/∂x = (t/m)·(r − v·(n̂·r)/s) (likewise with −u for y, rows growing downward).
    fn new(view: &View, plane: &PlaneGeom, num: f64, px: f64, py: f64) -> Option<CornerHit> {
        let v = view.ray(px, py);
        let s = plane.normal.dot(v);
        if s == 0.0 {
            return None;
        }
        let t = num / s;
        if !(t > 0.0 && t.is_finite()) {
            return None;
        }
        let scale = t / view.short_side;
        let along_x = (view.right - v * (plane.normal.dot(view.right) / s)) * scale;
        let along_y = (view.up - v * (plane.normal.dot(view.up) / s)) * scale;
        Some(CornerHit {
            point: view.eye + v * t,
            footprint: along_x.length().max(along_y.length()),
        })
    }
}

/// The camera of section 2 in pixel terms.
struct View {
    eye: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    width_px: u32,
    height_px: u32,
    width: f64,
    height: f64,
    half_width: f64,
    half_height: f64,
    /// m = min(W, H): pixels per unit of the image plane at distance 1.
    short_side: f64,
}

impl View {
    fn new(tracer: &Tracer) -> View {
        let settings = tracer.settings();
        let camera = tracer.camera();
        let (forward, right, up) = camera.basis();
        let width = f64::from(settings.width);
        let height = f64::from(settings.height);
        View {
            eye: camera.position(),
            forward,
            right,
            up,
            width_px: settings.width,
            height_px: settings.height,
            width,
            height,
            half_width: width / 2.0,
            half_height: height / 2.0,
            short_side: width.min(height),
        }
    }

    /// The unnormalised direction f + x·r + y·u through the pixel coordinates
    /// (`px`, `py`).
    fn ray(&self, px: f64, py: f64) -> Vec3 {
        let x = (px - self.half_width) / self.short_side;
        let y = (self.half_height - py) / self.short_side;
        self.forward + self.right * x + self.up * y
    }
}

/// The first and last of the pixels 0..side whose extent [i, i + 1) meets the interval
/// [`lo`, `hi`], or `None` if none does (or the bounds are not numbers).
fn pixel_span(lo: f64, hi: f64, side: f64) -> Option<(u32, u32)> {
    if !(hi >= 0.0 && lo < side) {
        return None;
    }
    // Casts saturate and truncate toward zero, which is floor for these non-negative
    // values.
    let first = lo.max(0.0) as u32;
    let last = (hi.min(side - 1.0) as u32).max(first);
    Some((first, last))
}

/// The smallest power of two that is at least `need` and at least `floor`, but no more
/// than `cap` (`floor` and `cap` powers of two); `cap` if `need` is not a number.
fn power_of_two_at_least(need: f64, floor: u32, cap: u32) -> u32 {
    let mut n = floor.min(cap);
    while n < cap && (need.is_nan() || f64::from(n) < need) {
        n *= 2;
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::parse_scene;
    use serde_json::{json, Value};

    fn footprints(scene: &Value, block: u32, cap: u32) -> Footprints {
        let scene = parse_scene(&scene.to_string()).expect("test scene loads");
        Footprints::new(&Tracer::new(&scene, scene.settings), block, cap)
    }

    fn all_mins(f: &Footprints) -> Vec<(u32, u32, u32)> {
        (0..f.blocks_y())
            .flat_map(|by| (0..f.blocks_x()).map(move |bx| (bx, by)))
            .map(|(bx, by)| (bx, by, f.min_samples(bx, by)))
            .collect()
    }

    /// A camera at (0, 0, −6) looking along +z at a 600 × 400 frame, with `objects`.
    fn facing(objects: Value) -> Value {
        json!({
            "camera": { "position": [0, 0, -6], "look_at": [0, 0, 2] },
            "image": { "width": 600, "height": 400 },
            "lights": [ { "position": [0, 6, -8], "color": [1, 1, 1] } ],
            "objects": objects
        })
    }

    /// A camera 1 above the checkerboard y = 0, looking slightly down toward +z, with
    /// `extra` objects.
    fn checker_to_horizon(extra: &[Value]) -> Value {
        let mut objects = vec![json!({
            "type": "plane", "normal": [0, 1, 0], "distance": 0.0, "color": [0, 0, 0, 2]
        })];
        objects.extend_from_slice(extra);
        json!({
            "camera": { "position": [0, 1, 0], "look_at": [0.5, 0.8, 10] },
            "image": { "width": 600, "height": 400 },
            "lights": [ { "position": [3, 20, 5], "color": [1, 1, 1] } ],
            "objects": objects
        })
    }

    #[test]
    fn a_tiny_sphere_constrains_only_the_blocks_around_its_projection() {
        // Depth 8, centre at (0.5, 0.3)/8 of the image plane: pixel (325, 185), projected
        // radius 400 · 0.01 / 8.02 ≈ 0.499 px, so 4/r² ≈ 16.1 and the minimum is 32.
        let scene = facing(json!([
            { "type": "sphere", "center": [0.5, 0.3, 2], "radius": 0.01, "color": [1, 1, 1, 0] },
            { "type": "plane", "normal": [0, 0, -1], "distance": -6, "color": [0.9, 0.8, 0.7, 0] }
        ]));
        let f = footprints(&scene, 8, 64);
        assert_eq!((f.blocks_x(), f.blocks_y(), f.block()), (75, 50, 8));
        assert_eq!(f.min_samples(325 / 8, 185 / 8), 32);
        for (bx, by, n) in all_mins(&f) {
            let near = bx.abs_diff(325 / 8) <= 1 && by.abs_diff(185 / 8) <= 1;
            assert!(n == 1 || (near && n == 32), "block ({bx}, {by}): {n}");
        }
        // The cap bounds it.
        assert_eq!(footprints(&scene, 8, 16).min_samples(40, 23), 16);
    }

    #[test]
    fn a_sphere_on_the_axis_gets_exactly_four_over_r_squared() {
        // Radius 0.01 at distance 8: r = 0.5 px exactly, 4/r² = 16.
        let scene = facing(json!([
            { "type": "sphere", "center": [0, 0, 2], "radius": 0.01, "color": [1, 1, 1, 0] }
        ]));
        let f = footprints(&scene, 8, 4096);
        assert_eq!(f.min_samples(300 / 8, 200 / 8), 16);
        // A sphere of 1.9 px still gets the floor of 4.
        let scene = facing(json!([
            { "type": "sphere", "center": [0, 0, 2], "radius": 0.038, "color": [1, 1, 1, 0] }
        ]));
        assert_eq!(footprints(&scene, 8, 4096).min_samples(300 / 8, 200 / 8), 4);
    }

    #[test]
    fn large_spheres_and_spheres_out_of_sight_constrain_nothing() {
        let scene = facing(json!([
            { "type": "sphere", "center": [0, 0, 2], "radius": 1, "color": [1, 1, 1, 0] },
            { "type": "sphere", "center": [0, 0, -8], "radius": 0.01, "color": [1, 1, 1, 0] },
            { "type": "sphere", "center": [30, 0, 2], "radius": 0.01, "color": [1, 1, 1, 0] },
            { "type": "sphere", "center": [3, 0, -6], "radius": 0.01, "color": [1, 1, 1, 0] }
        ]));
        let f = footprints(&scene, 8, 64);
        assert!(all_mins(&f).iter().all(|&(_, _, n)| n == 1));
    }

    #[test]
    fn a_checkerboard_to_the_horizon_gets_the_cap_where_squares_are_pixel_sized() {
        let f = footprints(&checker_to_horizon(&[]), 8, 64);
        for bx in 0..f.blocks_x() {
            let column: Vec<u32> = (0..f.blocks_y()).map(|by| f.min_samples(bx, by)).collect();
            // Above the horizon: sky. At the horizon, many squares per pixel: the
            // samples see them, a floor of 16. Then squares of about a pixel: the cap.
            // Then fewer and fewer toward the camera.
            let horizon = column.iter().position(|&n| n > 1).expect("a horizon");
            assert!(horizon > 0, "column {bx}: {column:?}");
            assert_eq!(column[horizon], CHECKER_MIN, "column {bx}: {column:?}");
            let peak = (horizon..column.len())
                .max_by_key(|&by| (column[by], std::cmp::Reverse(by)))
                .unwrap();
            assert_eq!(column[peak], 64, "column {bx}: {column:?}");
            assert!(column[peak..].windows(2).all(|w| w[0] >= w[1]));
            assert_eq!(*column.last().unwrap(), 1, "column {bx}: {column:?}");
            assert!(column[peak..].iter().any(|&n| n > 1 && n < 64));
        }
    }

    #[test]
    fn a_sphere_in_front_of_the_horizon_hides_it() {
        // The sphere sits above the board, straddling the horizon around the middle
        // column; blocks wholly inside its silhouette see no checkerboard.
        let sphere = json!({
            "type": "sphere", "center": [0.5, 2.4, 10], "radius": 2, "color": [1, 1, 1, 0]
        });
        let open = footprints(&checker_to_horizon(&[]), 8, 64);
        let hidden = footprints(&checker_to_horizon(&[sphere]), 8, 64);
        let mid = open.blocks_x() / 2;
        let horizon = (0..open.blocks_y())
            .position(|by| open.min_samples(mid, by) > 1)
            .unwrap() as u32;
        assert_eq!(hidden.min_samples(mid, horizon), 1);
        assert_eq!(hidden.min_samples(0, horizon), CHECKER_MIN);
        // Hiding only ever lowers a minimum.
        for (bx, by, n) in all_mins(&hidden) {
            assert!(n <= open.min_samples(bx, by));
        }
        // A mirror hides nothing, nor does a sphere that dips into the board; one that
        // rests on it does.
        for (sphere, hides) in [
            (
                json!({ "center": [0.5, 2.4, 10], "radius": 2, "color": [1, 1, 1, 0.5] }),
                false,
            ),
            (
                json!({ "center": [0.5, 1.9, 10], "radius": 2, "color": [1, 1, 1, 0] }),
                false,
            ),
            (
                json!({ "center": [0.5, 2, 10], "radius": 2, "color": [1, 1, 1, 0] }),
                true,
            ),
        ] {
            let mut sphere = sphere;
            sphere["type"] = json!("sphere");
            let f = footprints(&checker_to_horizon(&[sphere]), 8, 64);
            assert_eq!(
                f.min_samples(mid, horizon),
                if hides { 1 } else { CHECKER_MIN }
            );
        }
    }

    #[test]
    fn minima_are_powers_of_two_within_the_cap_and_a_cap_of_one_disables_them() {
        let scenes = [
            checker_to_horizon(&[
                json!({ "type": "sphere", "center": [0, 0.5, 3], "radius": 0.004, "color": [1, 1, 1, 0] }),
                json!({ "type": "sphere", "center": [1, 1.5, 30], "radius": 0.05, "color": [1, 1, 1, 0] }),
            ]),
            facing(json!([
                { "type": "sphere", "center": [0.5, 0.3, 2], "radius": 0.001, "color": [1, 1, 1, 0] },
                { "type": "plane", "normal": [0, 0, -1], "distance": -6, "color": [0, 0, 0, 2] }
            ])),
        ];
        for scene in &scenes {
            for block in [1, 7, 8, 16] {
                for cap in [1, 2, 4, 16, 64, 4096] {
                    let f = footprints(scene, block, cap);
                    for (bx, by, n) in all_mins(&f) {
                        assert!(n.is_power_of_two() && n <= cap, "({bx}, {by}): {n}");
                        if cap == 1 {
                            assert_eq!(n, 1);
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn partial_blocks_cover_the_image_edges() {
        let mut scene = checker_to_horizon(&[]);
        scene["image"] = json!({ "width": 61, "height": 37 });
        let f = footprints(&scene, 8, 64);
        assert_eq!((f.blocks_x(), f.blocks_y()), (8, 5));
        assert!(all_mins(&f).iter().any(|&(_, _, n)| n >= CHECKER_MIN));
    }

    #[test]
    fn power_of_two_rounding() {
        assert_eq!(power_of_two_at_least(16.0, 4, 64), 16);
        assert_eq!(power_of_two_at_least(16.000_001, 4, 64), 32);
        assert_eq!(power_of_two_at_least(0.5, 4, 64), 4);
        assert_eq!(power_of_two_at_least(1e300, 16, 64), 64);
        assert_eq!(power_of_two_at_least(f64::INFINITY, 16, 8), 8);
        assert_eq!(power_of_two_at_least(f64::NAN, 16, 64), 64);
    }
}
