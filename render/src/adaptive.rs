//! Adaptive sampling to an error target: where the samples go, how many, and how wrong
//! the image still is.
//!
//! **Blocks.** The frame is cut into blocks of [`BLOCK`] × [`BLOCK`] pixels aligned to
//! its top-left corner. All pixels of a block take the same number of samples, a power
//! of two: [`BASE_SAMPLES`] first, then doublings. A block's statistics pool its
//! pixels, which is what makes them stable enough to decide on.
//!
//! **The estimate.** A pixel's n samples form four groups of n/4 consecutive samples
//! (each a well-spread net of the scrambled Sobol sequence; at the first level each of
//! the 4 samples is a group). The unbiased variance of the four group means, over 4,
//! is the error the mean would have if the groups were independent; summed over the
//! block's pixels it is the level's `spread`. Stratified samples do better than
//! independent ones, by a factor that depends on how fast the error falls with n
//! (a two-halves comparison over-reads it by 2^(2α) − 1 for error ∝ n^-α): measured
//! over the benchmark scenes and checked on others, [`STRATIFIED`] = 0.45 turns the
//! spread into the squared error of the mean. Per-block measurements of α from
//! successive levels proved too noisy to use (the estimate scattered by ×/÷ 2 around
//! the measurement); one calibrated factor is within ×/÷ 1.1. To that the estimate
//! adds what rounding to 8 bits adds to the comparison ([`rounding_excess`]), which
//! below a level is most of the measured error. The decay per doubling used to
//! predict a doubling's gain is [`PRIOR_RATIO`].
//!
//! **The allocation.** Doubling a block of squared error V is predicted to remove
//! V (1 − r) for about as many rays as the block has taken so far: its priority is that
//! gain per ray. For a threshold λ, every block doubles while its priority is above λ
//! (and it is under the cap, or under the minimum its sub-pixel geometry demands, see
//! [`Footprints`]). The thresholds form a fixed ladder (eight steps per factor of
//! two), walked from the top: the image for a target E is the first rung at which the
//! estimated RMS error of the frame is at most E. Each rung is a pure function of the
//! blocks, and a block's state is a pure function of the scene, the settings and its
//! coordinates: the same bytes for any tiling, thread count or machine, and a render
//! that stopped at one rung can go on to a lower one, or to a larger cap, and give what
//! a direct render would have given.
//!
//! **Sums.** A pixel's sum over n samples is the sum over its first n/2 plus the sum
//! over the next n/2 (each summed in sample order): the same additions whether the
//! samples were taken in one go or in several sessions.

pub use crate::footprint::Footprints;
use crate::image::Image;
use crate::rect::Rect;
use crate::settings::Sampling;
use crate::tracer::{to_byte, Tracer};
use crate::vec3::Vec3;

/// Side of a block, in pixels.
pub const BLOCK: u32 = 8;
/// Samples per pixel of a block's first level (fewer if the cap is lower).
pub const BASE_SAMPLES: u32 = 4;
/// The squared-error ratio per doubling assumed before a block has doubled: α = 3/4,
/// the rate of stratified samples at an edge.
pub const PRIOR_RATIO: f64 = 0.375;

/// The most samples an adaptive pixel may take with `aa` = n: the largest power of two
/// not above n².
pub fn sample_cap(aa: u32) -> u32 {
    let n2 = aa.saturating_mul(aa).max(1);
    1 << (31 - n2.leading_zeros())
}

/// Rungs of the threshold ladder per factor of two.
const RUNGS_PER_OCTAVE: u32 = 8;
/// The threshold of rung 1, as a power of two: above any block's priority (a block's
/// squared error is at most 255² per pixel).
const TOP_OCTAVE: i32 = 24;
/// The last rung: threshold 0, every block at its cap.
pub const LAST_RUNG: u32 = RUNGS_PER_OCTAVE * 88 + 1;

/// 2^(−j/8) for j = 0..8, written out so that every machine has the same bits.
const EIGHTHS: [f64; 8] = [
    1.0,
    0.917_004_043_204_671_2,
    0.840_896_415_253_714_5,
    0.771_105_412_703_970_4,
    std::f64::consts::FRAC_1_SQRT_2,
    0.648_419_777_325_504_8,
    0.594_603_557_501_360_6,
    0.545_253_866_332_628_8,
];

/// The threshold (levels² per ray) of rung `k`: infinite at rung 0 (first levels and
/// forced doublings only), 2^(24 − (k − 1)/8) after, 0 at [`LAST_RUNG`].
pub fn threshold(k: u32) -> f64 {
    if k == 0 {
        return f64::INFINITY;
    }
    if k >= LAST_RUNG {
        return 0.0;
    }
    let step = k - 1;
    let octave = TOP_OCTAVE - (step / RUNGS_PER_OCTAVE) as i32;
    EIGHTHS[(step % RUNGS_PER_OCTAVE) as usize] * power_of_two(octave)
}

/// 2^e exactly, for the exponents of the ladder.
fn power_of_two(e: i32) -> f64 {
    f64::from_bits(((1023 + e) as u64) << 52)
}

/// One level of a block: its pixels at `count` samples each.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Level {
    pub count: u32,
    /// Σ over the block's pixels of the variance of the mean that the spread of its
    /// [`GROUPS`] sample groups gives if they were independent (unbiased variance of
    /// the group means over the group count), averaged over the 3 channels, in
    /// levels². NaN with one sample.
    pub spread: f64,
    /// Σ over pairs of neighbouring pixels inside the block of the squared difference
    /// of their colours at this level (averaged over channels, levels²).
    pub contrast: f64,
    /// Σ over the block's pixels of what rounding to 8 bits adds to the squared error
    /// of a pixel whose colour is off by its estimated error ([`rounding_excess`]).
    pub rounding: f64,
    /// Rays traced for the block up to and including this level.
    pub rays: u64,
    /// The block's pixels at this level, RGB8, rows top to bottom.
    pub rgb: Vec<u8>,
}

/// A block's levels so far and the sums needed to go on.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BlockState {
    pub rect: Rect,
    pub levels: Vec<Level>,
    /// Each pixel's sums of sample colours over the first and the second half of its
    /// samples at the last level.
    pub sums: Vec<[[f64; 3]; 2]>,
}

/// What a level is worth: its estimated squared error and the priority of doubling it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LevelEstimate {
    /// Estimated Σ over the block's pixels of the squared error (levels², averaged over
    /// channels). NaN when unknown (one sample).
    pub error_sq: f64,
    /// Predicted squared error removed per ray by doubling.
    pub priority: f64,
}

impl BlockState {
    /// The estimate of level `l`.
    pub fn estimate(&self, l: usize) -> LevelEstimate {
        let level = &self.levels[l];
        if level.count < 2 {
            return LevelEstimate {
                error_sq: f64::NAN,
                priority: 0.0,
            };
        }
        let error_sq = level.spread * STRATIFIED + level.rounding;
        let r = PRIOR_RATIO;
        LevelEstimate {
            error_sq,
            priority: error_sq * (1.0 - r) / level.rays.max(1) as f64,
        }
    }

    /// Whether level `l` doubles at threshold `lambda`.
    fn doubles(&self, l: usize, lambda: f64, cap: u32, min_count: u32) -> bool {
        let count = self.levels[l].count;
        count < cap && (count < min_count || self.estimate(l).priority > lambda)
    }

    /// The level this block stands at for rung `k`, if it has been rendered that far.
    pub fn level_at(&self, k: u32, cap: u32, min_count: u32) -> Option<usize> {
        let lambda = threshold(k);
        let mut l = 0;
        while self.doubles(l, lambda, cap, min_count) {
            l += 1;
            if l == self.levels.len() {
                return None;
            }
        }
        Some(l)
    }
}

/// Renders blocks: their first level, and doublings.
pub(crate) struct BlockRenderer<'t> {
    tracer: &'t Tracer,
    points: Vec<(f64, f64)>,
    colors: Vec<Vec3>,
}

impl<'t> BlockRenderer<'t> {
    pub fn new(tracer: &'t Tracer) -> Self {
        BlockRenderer {
            tracer,
            points: Vec::new(),
            colors: Vec::new(),
        }
    }

    /// A block's first level: min(cap, [`BASE_SAMPLES`]) samples per pixel.
    pub fn first(&mut self, rect: Rect, cap: u32) -> BlockState {
        let count = BASE_SAMPLES.min(cap);
        let pixels = rect.pixel_count() as usize;
        let mut block = BlockState {
            rect,
            levels: Vec::with_capacity(4),
            sums: vec![[[0.0; 3]; 2]; pixels],
        };
        let level = self.add_samples(&mut block, 0, count);
        block.levels.push(level);
        block
    }

    /// Doubles the block's last level.
    pub fn double(&mut self, block: &mut BlockState) {
        let last = block.levels.last().expect("a block has its first level");
        let (count, rays) = (last.count, last.rays);
        let mut level = self.add_samples(block, count, count);
        level.rays += rays;
        block.levels.push(level);
    }

    /// Takes samples `from .. from + count` of each pixel of the block, in
    /// [`GROUPS`] groups: with `from` = 0 (the first level, count = 4 or 1) each
    /// sample is a group; otherwise the old samples' two halves are the first two
    /// groups and the new samples' two halves the other two.
    fn add_samples(&mut self, block: &mut BlockState, from: u32, count: u32) -> Level {
        let sampling = Sampling::Adaptive { target_milli: 0 };
        let total = from + count;
        let scale = 1.0 / f64::from(total);
        let mut rays = 0;
        let mut spread = 0.0;
        let mut rounding = 0.0;
        let mut rgb = Vec::with_capacity(block.sums.len() * 3);
        let rect = block.rect;
        let mut p = 0;
        for j in rect.y..rect.y + rect.height {
            for i in rect.x..rect.x + rect.width {
                self.points.clear();
                let pattern = crate::sampling::pixel_points(sampling, i, j);
                self.points.extend((from..total).map(|k| {
                    let (sx, sy) = pattern(k);
                    (f64::from(i) + sx, f64::from(j) + sy)
                }));
                let n = self.points.len();
                if self.colors.len() < n {
                    self.colors.resize(n, Vec3::ZERO);
                }
                let colors = &mut self.colors[..n];
                self.tracer.samples(&self.points, colors, &mut rays);
                let v = |a: [f64; 3]| Vec3::new(a[0], a[1], a[2]);
                // The four groups' sums, each over total / 4 samples.
                let (groups, halves) = if from == 0 {
                    if n < GROUPS {
                        let s = sum(colors);
                        ([s; GROUPS], [s, Vec3::ZERO])
                    } else {
                        let q = n / GROUPS;
                        let g: [Vec3; GROUPS] =
                            std::array::from_fn(|k| sum(&colors[k * q..(k + 1) * q]));
                        (g, [g[0] + g[1], g[2] + g[3]])
                    }
                } else {
                    let old = block.sums[p];
                    let half = n / 2;
                    let (n1, n2) = (sum(&colors[..half]), sum(&colors[half..]));
                    let old_total = v(old[0]) + v(old[1]);
                    ([v(old[0]), v(old[1]), n1, n2], [old_total, n1 + n2])
                };
                let total_sum = halves[0] + halves[1];
                if total >= GROUPS as u32 {
                    let own = group_spread(&groups, total);
                    spread += own;
                    rounding += rounding_excess((own * STRATIFIED).sqrt());
                }
                let mean = total_sum * scale;
                rgb.extend_from_slice(&[to_byte(mean.x), to_byte(mean.y), to_byte(mean.z)]);
                block.sums[p] = [
                    [halves[0].x, halves[0].y, halves[0].z],
                    [halves[1].x, halves[1].y, halves[1].z],
                ];
                p += 1;
            }
        }
        let contrast = contrast(&rgb, rect.width as usize);
        Level {
            count: total,
            contrast,
            rounding,
            spread: if total >= GROUPS as u32 {
                spread
            } else {
                f64::NAN
            },
            rays,
            rgb,
        }
    }
}

/// Σ over horizontally and vertically neighbouring pixels of `rgb` (rows of `width`
/// pixels) of their squared difference, averaged over channels, in levels².
fn contrast(rgb: &[u8], width: usize) -> f64 {
    let px = |p: usize| &rgb[p * 3..p * 3 + 3];
    let d = |a: &[u8], b: &[u8]| -> u64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| u64::from(x.abs_diff(*y)).pow(2))
            .sum()
    };
    let n = rgb.len() / 3;
    let mut total = 0u64;
    for p in 0..n {
        if (p + 1) % width != 0 && p + 1 < n {
            total += d(px(p), px(p + 1));
        }
        if p + width < n {
            total += d(px(p), px(p + width));
        }
    }
    total as f64 / 3.0
}

/// What rounding to 8 bits adds, on average, to the squared difference between a
/// pixel whose value is off by a random error of `sigma` levels and the converged
/// pixel, both rounded: about 0.8 σ for small errors (the chance that one of them
/// crosses a rounding boundary the other does not), 1/6 level² for large ones (two
/// independent roundings), joined smoothly. Images are compared in 8 bits, so at
/// errors below a level this is most of what a comparison measures.
pub fn rounding_excess(sigma: f64) -> f64 {
    const SMALL: f64 = 0.8;
    const LARGE: f64 = 1.0 / 6.0;
    let a = SMALL * sigma;
    if a > 0.0 {
        a * LARGE / (a * a + LARGE * LARGE).sqrt()
    } else {
        0.0
    }
}

/// Sample groups per pixel and level.
pub const GROUPS: usize = 4;

/// How much smaller the squared error of a stratified mean is than the variance the
/// groups' spread gives for independent groups.
pub const STRATIFIED: f64 = 0.45;

/// The variance of the mean of `total` samples that the spread of four equal groups
/// (sums `groups`) gives for independent groups, averaged over channels, in levels².
fn group_spread(groups: &[Vec3; GROUPS], total: u32) -> f64 {
    let per_group = f64::from(total) / GROUPS as f64;
    let m: [Vec3; GROUPS] = std::array::from_fn(|k| groups[k] * (1.0 / per_group));
    let mean = (m[0] + m[1] + m[2] + m[3]) * 0.25;
    let mut ss = 0.0;
    for g in m {
        let d = g - mean;
        ss += d.x * d.x + d.y * d.y + d.z * d.z;
    }
    // Unbiased variance of a group mean (3 degrees of freedom), over 4 groups, over 3
    // channels, in levels².
    ss / 3.0 / GROUPS as f64 / 3.0 * (255.0 * 255.0)
}

/// The sum of colours in order.
fn sum(colors: &[Vec3]) -> Vec3 {
    colors.iter().fold(Vec3::ZERO, |s, &c| s + c)
}

/// Units of [`RungTotals::error_sq`] per level².
const FIXED_POINT_UNITS: f64 = 16_777_216.0;

/// A block's squared error as a whole number of 2⁻²⁴ levels², so that sums over blocks
/// are exact and do not depend on the order in which tiles arrive.
fn fixed_point(error_sq: f64) -> u128 {
    if error_sq.is_finite() && error_sq > 0.0 {
        (error_sq * FIXED_POINT_UNITS).round() as u128
    } else {
        0
    }
}

/// Running totals of a set of blocks at one rung: what the frame's estimate is made of.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RungTotals {
    /// Σ of the blocks' estimated squared error, in 2⁻²⁴ levels² (exact).
    pub error_sq: u128,
    pub pixels: u64,
    pub samples: u64,
    pub rays: u64,
    /// Whether some block has one sample per pixel (no estimate).
    pub unknown: bool,
}

impl RungTotals {
    pub fn add(&mut self, other: &RungTotals) {
        self.error_sq += other.error_sq;
        self.pixels += other.pixels;
        self.samples += other.samples;
        self.rays += other.rays;
        self.unknown |= other.unknown;
    }

    /// The blocks' summed estimated squared error, in levels².
    pub fn error_sq_levels(&self) -> f64 {
        self.error_sq as f64 / FIXED_POINT_UNITS
    }

    /// The RMS estimated error in levels; NaN when unknown.
    pub fn estimated_error(&self) -> f64 {
        if self.unknown || self.pixels == 0 {
            return f64::NAN;
        }
        (self.error_sq_levels() / self.pixels as f64).sqrt()
    }
}

/// The blocks of a rectangle of the frame (the whole frame, or a tile whose corners
/// lie on block boundaries or the frame's edge), walked down the threshold ladder.
pub struct Region<'t> {
    tracer: &'t Tracer,
    cap: u32,
    footprints: std::sync::Arc<Footprints>,
    blocks: Vec<BlockState>,
}

/// Why a region cannot be set up.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RegionError {
    /// The rectangle's corners are not on block boundaries (or it is not inside the
    /// frame).
    #[error("tile {0:?} is not cut on the {BLOCK}-pixel blocks of adaptive sampling")]
    Misaligned(Rect),
    /// A previous state that cannot be the state of this rectangle: it came from
    /// elsewhere, or was damaged.
    #[error("the saved samples of tile {rect:?} are not valid: {why}")]
    BadState { rect: Rect, why: String },
}

/// Checks that `blocks` can be the state of the blocks `rects` with first levels of
/// `base` samples: the right rectangles, levels that double from the base, pixels and
/// sums of the right lengths, finite numbers. `Ok(false)`: a valid state whose first
/// level has another count (a render with one sample per pixel, or refined from
/// one), which cannot be continued and is started over.
fn check_state(blocks: &[BlockState], rects: &[Rect], base: u32) -> Result<bool, String> {
    if blocks.len() != rects.len() {
        return Err(format!(
            "{} blocks for {} places",
            blocks.len(),
            rects.len()
        ));
    }
    let mut same_base = true;
    for (b, r) in blocks.iter().zip(rects) {
        if b.rect != *r {
            return Err(format!("block {:?} where {r:?} was expected", b.rect));
        }
        let pixels = r.pixel_count() as usize;
        let first = b.levels.first().ok_or("a block without samples")?.count;
        if first != 1 && first != BASE_SAMPLES {
            return Err(format!("a first level of {first} samples"));
        }
        same_base &= first == base;
        let mut rays = 0;
        for (l, level) in b.levels.iter().enumerate() {
            let expected = first.checked_shl(l as u32).filter(|&c| c <= 1 << 16);
            if Some(level.count) != expected || level.rgb.len() != pixels * 3 {
                return Err(format!("level {l} of block {r:?} is malformed"));
            }
            let spread_ok = if level.count >= GROUPS as u32 {
                level.spread.is_finite() && level.spread >= 0.0
            } else {
                level.spread.is_nan()
            };
            let stats_ok = spread_ok
                && [level.contrast, level.rounding]
                    .iter()
                    .all(|v| v.is_finite() && *v >= 0.0);
            if !stats_ok || level.rays < rays {
                return Err(format!(
                    "level {l} of block {r:?} has impossible statistics"
                ));
            }
            rays = level.rays;
        }
        if b.sums.len() != pixels || b.sums.iter().flatten().flatten().any(|v| !v.is_finite()) {
            return Err(format!("the sums of block {r:?} are malformed"));
        }
    }
    Ok(same_base)
}

impl<'t> Region<'t> {
    /// The blocks of `rect`, with no samples yet (or those of `blocks`, a previous
    /// state of the same rectangle with the same scene).
    pub fn new(
        tracer: &'t Tracer,
        footprints: std::sync::Arc<Footprints>,
        rect: Rect,
        blocks: Option<Vec<BlockState>>,
    ) -> Result<Self, RegionError> {
        let s = tracer.settings();
        let aligned = |start: u32, len: u32, side: u32| {
            start.is_multiple_of(BLOCK)
                && ((start + len).is_multiple_of(BLOCK) || start + len == side)
        };
        if rect.check_inside(s).is_err()
            || !aligned(rect.x, rect.width, s.width)
            || !aligned(rect.y, rect.height, s.height)
        {
            return Err(RegionError::Misaligned(rect));
        }
        let cap = sample_cap(s.aa);
        let rects = block_rects(rect, s.width, s.height);
        let base = BASE_SAMPLES.min(cap);
        let blocks = match blocks {
            Some(b) => match check_state(&b, &rects, base) {
                Ok(true) => Some(b),
                Ok(false) => None,
                Err(why) => return Err(RegionError::BadState { rect, why }),
            },
            None => None,
        };
        let blocks = blocks.unwrap_or_else(|| {
            use rayon::prelude::*;
            rects
                .into_par_iter()
                .map_init(|| BlockRenderer::new(tracer), |r, rect| r.first(rect, cap))
                .collect()
        });
        Ok(Region {
            tracer,
            cap,
            footprints,
            blocks,
        })
    }

    /// The frame's footprints for `tracer` (computed once per frame and shared by its
    /// regions).
    pub fn footprints(tracer: &Tracer) -> std::sync::Arc<Footprints> {
        std::sync::Arc::new(Footprints::new(
            tracer,
            BLOCK,
            sample_cap(tracer.settings().aa),
        ))
    }

    pub fn blocks(&self) -> &[BlockState] {
        &self.blocks
    }

    pub fn into_blocks(self) -> Vec<BlockState> {
        self.blocks
    }

    fn min_count(&self, block: &BlockState) -> u32 {
        self.footprints
            .min_samples(block.rect.x / BLOCK, block.rect.y / BLOCK)
    }

    /// Brings every block to rung `k` (never back: a block only gains samples).
    pub fn advance_to(&mut self, k: u32) {
        use rayon::prelude::*;
        let lambda = threshold(k);
        let cap = self.cap;
        let footprints = &*self.footprints;
        let tracer = self.tracer;
        self.blocks.par_iter_mut().for_each_init(
            || BlockRenderer::new(tracer),
            |r, block| {
                let min = footprints.min_samples(block.rect.x / BLOCK, block.rect.y / BLOCK);
                while block.doubles(block.levels.len() - 1, lambda, cap, min) {
                    r.double(block);
                }
            },
        );
    }

    /// The totals at rung `k`, if every block has been rendered that far.
    pub fn totals(&self, k: u32) -> Option<RungTotals> {
        let mut t = RungTotals::default();
        for block in &self.blocks {
            let l = block.level_at(k, self.cap, self.min_count(block))?;
            let level = &block.levels[l];
            let est = block.estimate(l).error_sq;
            t.add(&RungTotals {
                error_sq: fixed_point(est),
                pixels: block.rect.pixel_count(),
                samples: u64::from(level.count) * block.rect.pixel_count(),
                rays: level.rays,
                unknown: est.is_nan(),
            });
        }
        Some(t)
    }

    /// Copies the pixels at rung `k` (which must have been reached) into `image`.
    pub fn paint(&self, k: u32, image: &mut Image) {
        for block in &self.blocks {
            let l = block
                .level_at(k, self.cap, self.min_count(block))
                .expect("the rung has been reached");
            image.put_rect(block.rect, &block.levels[l].rgb);
        }
    }

    /// The estimated squared error per pixel of each block at rung `k`, in levels²,
    /// with the block's rectangle: an error heat map.
    pub fn heat(&self, k: u32) -> Vec<(Rect, f64)> {
        self.blocks
            .iter()
            .filter_map(|b| {
                let l = b.level_at(k, self.cap, self.min_count(b))?;
                Some((b.rect, b.estimate(l).error_sq / b.rect.pixel_count() as f64))
            })
            .collect()
    }
}

/// The block rectangles of `rect`, row by row.
fn block_rects(rect: Rect, width: u32, height: u32) -> Vec<Rect> {
    let mut out = Vec::new();
    for y in (rect.y..rect.y + rect.height).step_by(BLOCK as usize) {
        for x in (rect.x..rect.x + rect.width).step_by(BLOCK as usize) {
            out.push(Rect {
                x,
                y,
                width: BLOCK.min(width - x).min(rect.x + rect.width - x),
                height: BLOCK.min(height - y).min(rect.y + rect.height - y),
            });
        }
    }
    out
}

/// A frame at one rung of the ladder.
#[derive(Clone, Debug)]
pub struct RungFrame {
    pub image: Image,
    pub rung: u32,
    pub totals: RungTotals,
}

impl RungFrame {
    pub fn estimated_error(&self) -> f64 {
        self.totals.estimated_error()
    }
}

/// Whether a frame whose totals are `t` meets `target`: its estimate is at most the
/// target, or it cannot go further (the last rung).
pub fn meets(t: &RungTotals, k: u32, target: f64) -> bool {
    k >= LAST_RUNG || t.estimated_error() <= target
}

/// Renders a whole frame adaptively to `target` levels: rung after rung until the
/// estimate meets the target. Stops early, at the last rung reached, if `keep_going`
/// says so before a rung (a time limit).
pub fn render_to_target<'t>(
    tracer: &'t Tracer,
    region: Option<Region<'t>>,
    target: f64,
    keep_going: &mut dyn FnMut(u32, &RungTotals) -> bool,
) -> (Region<'t>, RungFrame) {
    let s = *tracer.settings();
    let full = Rect {
        x: 0,
        y: 0,
        width: s.width,
        height: s.height,
    };
    let mut region = region.unwrap_or_else(|| {
        Region::new(tracer, Region::footprints(tracer), full, None)
            .expect("the frame is cut on blocks")
    });
    let mut k = 0;
    region.advance_to(0);
    let mut totals = region.totals(0).expect("advanced");
    while !meets(&totals, k, target) && keep_going(k, &totals) {
        k += 1;
        region.advance_to(k);
        totals = region.totals(k).expect("advanced");
    }
    let mut image = Image::black(s.width, s.height);
    region.paint(k, &mut image);
    (
        region,
        RungFrame {
            image,
            rung: k,
            totals,
        },
    )
}

#[cfg(test)]
mod tests;
