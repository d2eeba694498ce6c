//! Where the samples of a pixel go, and what the spread of their colours says about the
//! pixel's error.
//!
//! Three samplers share one budget, `aa` = n: at most n × n camera samples per pixel.
//!
//! - [`Sampling::Grid`]: the scene format's n × n centred grid (section 3), the default
//!   and the reference. Its bytes, and its rays, are those of [`Tracer::pixel`]: it runs
//!   the tracer's own pixel loop, which hands over each sample's colour as it sums it,
//!   and divides the same way.
//! - [`Sampling::Jittered`]: the first n × n points of the pixel's Owen-scrambled
//!   Sobol sequence ([`owen_sobol`]): one point in each of the n × n cells when n is a
//!   power of two, and a well-spread set for any n.
//! - [`Sampling::Adaptive`]: samples to an error target over the whole frame, in
//!   power-of-two levels of 8 × 8 blocks ([`crate::adaptive`]). Its points are the
//!   same scrambled Sobol sequence, every power-of-two prefix of which is well spread,
//!   so a block can stop after any level and go on later.
//!
//! Nothing here uses a global generator or shared state: each pixel's samples, and
//! hence its bytes, depend only on the scene, the settings and its coordinates, so a
//! tile is the same in any tiling, on any thread or worker (architecture, invariant 1).
//! Only integer operations and +, −, ×, ÷, √ are used, which every machine computes
//! alike.
//!
//! **The error estimate** of the grid and jittered samplers. For a pixel of k ≥ 2 samples whose clipped colours have the
//! unbiased variance s² in a channel, the standard error of their mean is
//! 255 · √(s² / k) levels; the pixel's estimate is the largest over its 3 channels.
//! With one sample (aa = 1) there is no spread to measure: the estimate is unknown, and
//! such pixels add nothing to a tile's [`error_sq_sum`](crate::TileImage::error_sq_sum).
//! The estimate measures noise as if the samples were independent: for these
//! stratified patterns it is an upper bound (1.1 to 4.4 times the measured error in
//! `tessera-bench`), and a feature smaller than the spacing of the samples that none of
//! them hit leaves no trace in it. Adaptive sampling's calibrated estimate is in
//! [`crate::adaptive`].

use crate::settings::RenderSettings;
// The choice of sampler is a setting, below the scene that holds it; it is named here
// too, beside the samplers that carry it out.
pub use crate::settings::{
    InvalidTarget, Sampler, Sampling, SamplingChoiceError, MAX_TARGET_MILLI, MIN_TARGET_MILLI,
};
use crate::tracer::{to_byte, GridSink, Tracer};
use crate::vec3::{Divisor, Vec3, F4, M4, V4};

/// One pixel's result: its colour, the samples it took and its estimated error.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PixelResult {
    pub rgb: [u8; 3],
    pub samples: u32,
    /// The square of the estimated error, in levels²; 0 when unknown (one sample).
    /// Only squares are ever summed (a tile's and a frame's estimate is their root mean
    /// square), so no pixel pays for a square root.
    pub error_sq: f64,
}

/// Renders the pixels of one tile, one after the other, reusing its buffers.
pub(crate) struct PixelSampler<'t> {
    tracer: &'t Tracer,
    /// The image points of the samples being traced, and their colours.
    points: Vec<(f64, f64)>,
    colors: Vec<Vec3>,
    /// The grid sampler's traced pixels of a row, waiting for their results.
    traced: Vec<PixelSums>,
}

impl<'t> PixelSampler<'t> {
    pub fn new(tracer: &'t Tracer) -> Self {
        PixelSampler {
            tracer,
            points: Vec::new(),
            colors: Vec::new(),
            traced: Vec::new(),
        }
    }

    pub fn settings(&self) -> &RenderSettings {
        self.tracer.settings()
    }

    /// Renders the pixels `columns` of row `j` with the grid sampler, left to right,
    /// handing each one's result to `add` and adding the rays traced to `rays`. The
    /// tracer's own pixel loop hands over each colour as it sums it: no points to
    /// generate and no colours to store, and the bytes are [`Tracer::pixel`]'s.
    ///
    /// Each pixel's mean, bytes and error estimate are worked out once the whole row
    /// is traced: that arithmetic is a long chain of dependent operations (a division
    /// at its end), which between two packets would stall the processor, and in a loop
    /// of its own overlaps from one pixel to the next.
    pub fn render_grid_row(
        &mut self,
        j: u32,
        columns: std::ops::Range<u32>,
        rays: &mut u64,
        add: &mut impl FnMut(PixelResult),
    ) {
        debug_assert_eq!(self.settings().sampling, Sampling::Grid);
        self.traced.clear();
        let spread = self.settings().aa > 1;
        if spread {
            self.traced.reserve(columns.len());
        }
        let mut sink = GridPixels {
            tracer: self.tracer,
            moments: Moments::default(),
            spread,
            traced: &mut self.traced,
            add: &mut *add,
        };
        self.tracer.grid_span(j, columns, rays, &mut sink);
        for pixel in &self.traced {
            add(pixel.result(self.tracer));
        }
    }

    /// Renders pixel (`i`, `j`) with the jittered sampler: all n × n samples, adding the
    /// rays traced to `rays`.
    pub fn render_jittered(&mut self, i: u32, j: u32, rays: &mut u64) -> PixelResult {
        let settings = *self.tracer.settings();
        let n = settings.aa;
        debug_assert_eq!(settings.sampling, Sampling::Jittered);
        let pattern = Points::new(settings.sampling, n, i, j);
        let mut moments = Moments::default();
        // All at once, in sample order: traced four at a time like the tracer's own
        // pixels, and summed in the same order.
        self.trace(&pattern, i, j, 0..n * n, &mut moments, rays);
        moments.sums().result(self.tracer)
    }

    /// Traces samples `range` of pixel (`i`, `j`) and adds their colours, in order.
    fn trace(
        &mut self,
        pattern: &Points,
        i: u32,
        j: u32,
        range: std::ops::Range<u32>,
        moments: &mut Moments,
        rays: &mut u64,
    ) {
        self.points.clear();
        self.points.extend(range.map(|k| {
            let (sx, sy) = pattern.offset(k);
            (f64::from(i) + sx, f64::from(j) + sy)
        }));
        let count = self.points.len();
        if self.colors.len() < count {
            self.colors.resize(count, Vec3::ZERO);
        }
        let colors = &mut self.colors[..count];
        self.tracer.samples(&self.points, colors, rays);
        for &color in colors.iter() {
            moments.add(color);
        }
    }
}

/// The grid sampler's statistics of the pixels of a span, as the tracer hands over
/// their colours.
struct GridPixels<'t, 'a, F> {
    tracer: &'t Tracer,
    /// The pixel being traced.
    moments: Moments,
    /// Whether pixels have several samples: with one (aa = 1) there is no error
    /// estimate, only the samples are counted, and each pixel's result, a short
    /// computation, goes to `add` at once.
    spread: bool,
    /// The span's pixels traced so far, when they have an estimate to work out.
    traced: &'a mut Vec<PixelSums>,
    add: &'a mut F,
}

impl<F: FnMut(PixelResult)> GridSink for GridPixels<'_, '_, F> {
    #[inline(always)]
    fn samples(&mut self, colors: &V4, count: usize) {
        if self.spread {
            self.moments.add_spread(colors, count);
        } else {
            self.moments.count += count as u32;
        }
    }

    #[inline(always)]
    fn pixel(&mut self, sum: Vec3) {
        self.moments.sum = sum;
        if self.spread {
            self.traced.push(self.moments.sums());
        } else {
            (self.add)(PixelSums::of_one(&self.moments).result(self.tracer));
        }
        // The next pixel's first samples start the sums afresh (`add_spread`).
        self.moments.count = 0;
    }
}

/// The offsets in [0, 1)² inside pixel (`i`, `j`) of its first `count` samples (at most
/// the budget `aa` × `aa`), in the order they are taken. Adaptive sampling uses a prefix
/// of this sequence, as long as the pixel needs. For tests and for documentation of the
/// patterns.
pub fn sample_offsets(sampling: Sampling, aa: u32, i: u32, j: u32, count: u32) -> Vec<(f64, f64)> {
    let points = Points::new(sampling, aa, i, j);
    (0..count.min(aa * aa)).map(|k| points.offset(k)).collect()
}

/// The offsets of pixel (`i`, `j`)'s samples with `sampling` (not the grid): sample
/// `k` at `points(k)`. For the adaptive sampler's blocks.
pub(crate) fn pixel_points(sampling: Sampling, i: u32, j: u32) -> impl Fn(u32) -> (f64, f64) {
    let points = Points::new(sampling, 1, i, j);
    move |k| points.offset(k)
}

/// A pixel's sample pattern.
enum Points {
    /// (a + ½)/n on both axes, row by row: the tracer's own offsets.
    Grid { n: u32 },
    /// The first two Sobol dimensions, Owen-scrambled with seeds drawn from the pixel's
    /// coordinates ([`owen_sobol`]).
    Sobol { seed_x: u32, seed_y: u32 },
}

impl Points {
    fn new(sampling: Sampling, n: u32, i: u32, j: u32) -> Self {
        match sampling {
            Sampling::Grid => Points::Grid { n },
            Sampling::Jittered | Sampling::Adaptive { .. } => {
                let h = hash3(i, j, SCRAMBLE_STREAM);
                Points::Sobol {
                    seed_x: (h >> 32) as u32,
                    seed_y: h as u32,
                }
            }
        }
    }

    /// The offset of sample `k` inside the pixel.
    fn offset(&self, k: u32) -> (f64, f64) {
        match *self {
            Points::Grid { n } => {
                let nf = f64::from(n);
                let (a, b) = (k % n, k / n);
                ((f64::from(a) + 0.5) / nf, (f64::from(b) + 0.5) / nf)
            }
            Points::Sobol { seed_x, seed_y } => {
                let (x, y) = owen_sobol(k, seed_x, seed_y);
                (unit(x), unit(y))
            }
        }
    }
}

/// Point `k` of the two-dimensional Sobol sequence, each coordinate Owen-scrambled
/// (nested uniform scrambling) with its own seed, as 32-bit binary fractions.
///
/// Why this pattern: every prefix of 2ᵐ points is a (0, m, 2)-net (one point in each
/// elementary interval of area 2⁻ᵐ), so adaptive sampling can stop after any power of
/// two, resume later, or split a pixel's samples between machines, and the samples
/// taken so far are always well spread. Owen's scrambling keeps that property while
/// making the points of each pixel an independent random net, which is what makes the
/// error fall like N^-0.75 at edges (N^-0.5 for independent random points) and keeps
/// the two halves of a prefix statistically alike. Only integer operations: the same
/// bits on every processor.
pub fn owen_sobol(k: u32, seed_x: u32, seed_y: u32) -> (u32, u32) {
    (
        owen_scramble(k.reverse_bits(), seed_x),
        owen_scramble(sobol_second(k), seed_y),
    )
}

/// Nested uniform (Owen) scrambling of a 32-bit binary fraction: each digit is flipped
/// or not by a hash of the seed and of all the digits before it, so that points that
/// share their first d digits still share them after scrambling (the net property).
/// On the bit-reversed value "the digits before" are the lower bits, and each step
/// below changes a bit only as a function of the bits under it: adding the seed (carries
/// go up) and xoring with a multiple by an even constant (a product's bit b depends on
/// the factor's bits below b). Each step is a bijection.
fn owen_scramble(x: u32, seed: u32) -> u32 {
    let mut v = x.reverse_bits();
    v = v.wrapping_add(seed);
    v ^= v.wrapping_mul(0x2545_F492);
    v ^= v.wrapping_mul(0x9E37_79BA);
    v = v.wrapping_add(seed.rotate_left(16) & !1);
    v ^= v.wrapping_mul(0xA54F_F53A);
    v ^= v.wrapping_mul(0x510E_527E);
    v.reverse_bits()
}

/// The hash stream of a pixel's scrambling seeds.
const SCRAMBLE_STREAM: u32 = u32::MAX;

/// `bits` / 2³², exactly: a number in [0, 1).
fn unit(bits: u32) -> f64 {
    f64::from(bits) * (1.0 / 4_294_967_296.0)
}

/// SplitMix64's output function: a bijection of u64 in which every output bit depends
/// on every input bit, so that neighbouring pixels and samples get unrelated offsets.
fn mix(z: u64) -> u64 {
    let mut z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A 64-bit hash of (pixel column, pixel row, sample index or stream).
fn hash3(i: u32, j: u32, k: u32) -> u64 {
    mix(mix((u64::from(i) << 32) | u64::from(j)) ^ u64::from(k))
}

/// The second dimension of the Sobol sequence (the first is the van der Corput sequence,
/// `k.reverse_bits()`), as 32 bits of a binary fraction. Its direction numbers are
/// v₁ = 1/2 and vᵢ₊₁ = vᵢ ⊕ vᵢ/2 (the primitive polynomial x + 1): together the two
/// dimensions form a (0, 2)-sequence, so each block of 2ᵐ consecutive points (from a
/// multiple of 2ᵐ) puts one point in every elementary interval of area 2⁻ᵐ. The XOR
/// shift keeps that property.
fn sobol_second(k: u32) -> u32 {
    let mut v = 1u32 << 31;
    let mut out = 0;
    let mut k = k;
    while k != 0 {
        if k & 1 == 1 {
            out ^= v;
        }
        v ^= v >> 1;
        k >>= 1;
    }
    out
}

/// Running sums of a pixel's sample colours: the plain sum for the mean (in sample
/// order, like the tracer's grid), and sums of differences from the first sample for the
/// variance, which stay exact for a constant colour and lose no precision to
/// cancellation. The differences are summed lane by lane as samples arrive, four at a
/// time in the tracer's structure-of-arrays form, and the lanes only at the end of the
/// pixel: each group of samples costs a dozen SIMD operations and no shuffles.
#[derive(Clone, Copy)]
pub(crate) struct Moments {
    count: u32,
    sum: Vec3,
    /// The first sample's colour in every lane.
    first: V4,
    diff: V4,
    diff_sq: V4,
}

impl Default for Moments {
    fn default() -> Self {
        Moments {
            count: 0,
            sum: Vec3::ZERO,
            first: V4::splat(Vec3::ZERO),
            diff: V4::splat(Vec3::ZERO),
            diff_sq: V4::splat(Vec3::ZERO),
        }
    }
}

impl Moments {
    fn add(&mut self, c: Vec3) {
        self.sum += c;
        self.add_spread(&V4::splat(c), 1);
    }

    /// Counts the `count` samples in lanes `0..count` of `colors` and adds them to the
    /// sums of differences, not to `sum` (which the caller keeps).
    #[inline(always)]
    fn add_spread(&mut self, colors: &V4, count: usize) {
        // The first group of a pixel starts the sums afresh, so that a finished pixel's
        // sums need no clearing, only its count.
        let fresh = self.count == 0;
        if fresh {
            self.first = V4::splat(colors.lane(0));
        }
        self.count += count as u32;
        let d = M4::first(count).select3(*colors - self.first, V4::splat(Vec3::ZERO));
        let d_sq = d.hadamard(d);
        if fresh {
            (self.diff, self.diff_sq) = (d, d_sq);
        } else {
            self.diff = self.diff + d;
            self.diff_sq = self.diff_sq + d_sq;
        }
    }

    /// The pixel's sums with the lanes added up.
    #[inline(always)]
    fn sums(&self) -> PixelSums {
        let lanes = |v: F4| (v.0[0] + v.0[1]) + (v.0[2] + v.0[3]);
        let channels = |v: &V4| F4([lanes(v.x), lanes(v.y), lanes(v.z), 0.0]);
        PixelSums {
            count: self.count,
            sum: self.sum,
            diff: channels(&self.diff),
            diff_sq: channels(&self.diff_sq),
        }
    }
}

/// A traced pixel's sums, small enough to keep a row of them until the row is done:
/// the sample count, the colours' sum, and per channel (lanes 0 to 2) the sums of the
/// differences from the first sample and of their squares.
#[derive(Clone, Copy)]
pub(crate) struct PixelSums {
    count: u32,
    sum: Vec3,
    diff: F4,
    diff_sq: F4,
}

impl PixelSums {
    /// A pixel whose samples were only counted: no estimate, as with one sample.
    #[inline(always)]
    fn of_one(moments: &Moments) -> PixelSums {
        PixelSums {
            count: moments.count,
            sum: moments.sum,
            diff: F4::splat(0.0),
            diff_sq: F4::splat(0.0),
        }
    }

    /// The pixel's bytes (the grid's mean: the sum divided by n²), samples and squared
    /// estimate.
    #[inline(always)]
    fn result(&self, tracer: &Tracer) -> PixelResult {
        let mean = tracer.grid_mean(self.sum);
        PixelResult {
            rgb: [to_byte(mean.x), to_byte(mean.y), to_byte(mean.z)],
            samples: self.count,
            error_sq: self.error_sq(),
        }
    }

    /// The square of the standard error of the mean in 8-bit levels, for the largest
    /// of the 3 channels: 255² · s²/k with s² the unbiased variance. 0 for fewer than 2
    /// samples (no estimate).
    ///
    /// Every pixel pays this, so it is one scalar division: the channel with the
    /// largest sum of squared deviations is the one with the largest variance, since
    /// all three share the divisor k(k − 1).
    #[inline(always)]
    fn error_sq(&self) -> f64 {
        if self.count < 2 {
            return 0.0;
        }
        // Division by k is a multiplication when k is a power of two (same bits).
        let ss = self.diff_sq - Divisor::count(self.count).divide4(self.diff * self.diff);
        let worst = ss.0[..3].iter().fold(0.0, |w: f64, &v| w.max(v));
        let k = f64::from(self.count);
        255.0 * 255.0 * worst / (k * (k - 1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sobol_points_fill_every_quadrant_of_each_group_of_four() {
        for shift in [(0, 0), (0xDEAD_BEEF, 0x1234_5678)] {
            let p = Points::Sobol {
                seed_x: shift.0,
                seed_y: shift.1,
            };
            for group in 0..16 {
                let mut quadrants: Vec<(u32, u32)> = (group * 4..group * 4 + 4)
                    .map(|k| {
                        let (x, y) = p.offset(k);
                        ((x * 2.0) as u32, (y * 2.0) as u32)
                    })
                    .collect();
                quadrants.sort();
                assert_eq!(quadrants, [(0, 0), (0, 1), (1, 0), (1, 1)], "{group}");
            }
            // And the first 16 one in each cell of a 4 × 4 grid.
            let mut cells: Vec<(u32, u32)> = (0..16)
                .map(|k| {
                    let (x, y) = p.offset(k);
                    ((x * 4.0) as u32, (y * 4.0) as u32)
                })
                .collect();
            cells.sort();
            cells.dedup();
            assert_eq!(cells.len(), 16);
        }
    }

    #[test]
    fn the_second_sobol_dimension_has_its_known_start() {
        // Sobol's second dimension in binary (not Gray-code) order: each block of 2^m
        // points is the same set as in Bratley and Fox's Gray-code order.
        let expected = [0.0, 0.5, 0.75, 0.25, 0.625, 0.125, 0.375, 0.875];
        for (k, want) in expected.iter().enumerate() {
            assert_eq!(unit(sobol_second(k as u32)), *want, "point {k}");
        }
    }

    #[test]
    fn the_error_of_a_constant_colour_is_zero_and_of_a_known_spread_is_known() {
        let mut m = Moments::default();
        for _ in 0..9 {
            m.add(Vec3::new(0.3, 0.7, 0.1));
        }
        assert_eq!(m.sums().error_sq(), 0.0);
        // Samples 0 and 1 in one channel: s² = 1/2, k = 2: 255 · √(1/4) = 127.5.
        let mut m = Moments::default();
        m.add(Vec3::new(0.0, 0.5, 0.5));
        m.add(Vec3::new(1.0, 0.5, 0.5));
        assert_eq!(m.sums().error_sq(), 127.5 * 127.5);
        let mut one = Moments::default();
        one.add(Vec3::new(1.0, 0.0, 0.0));
        assert_eq!(one.sums().error_sq(), 0.0);
    }
}
