//! Adaptive jobs on the farm: the tiles' block states the coordinator keeps between
//! passes, the checks of a worker's answer, and the end of a pass (the totals at each
//! rung, and the image once a rung meets the target), all computed off the state lock.
//!
//! The decisions are the pure [`scheduler::passes::Passes`]'s; the tiles of each pass
//! are handed out by the tile scheduler like any job's (the pass is a job to it, resumed
//! with the tiles that have no work at the new rung already done). Workers keep
//! nothing: every `Advance` carries the state the tile starts from, so a tile lost with
//! its worker is sent again from the same state and gives the same bytes.

use std::sync::Arc;

use protocol::{Settings, TileRect};
use render::adaptive::{meets, RungTotals};
use scheduler::farm::PassTile;
use scheduler::passes::{Passes, RungCheck};
use sha2::{Digest, Sha256};

use super::verification::Verifier;

/// What the coordinator holds of an adaptive job beside its record: the bytes. Where
/// its passes stand is the core's ([`scheduler::farm::PassRun`]).
pub struct AdaptiveJob {
    pub tiles: Vec<AdaptiveTile>,
    /// The totals of the pass just added up, until the core has ruled on them.
    pub evaluation: Option<Evaluation>,
    /// Rays traced for the job over all passes (the local walk would trace the rays of
    /// the final rung only; the farm's overshoot and checks cost more).
    pub rays: u64,
}

/// One tile's state between passes.
#[derive(Clone, Default)]
pub struct AdaptiveTile {
    /// Its blocks' state (compressed, as the worker sent it) and the rung it has
    /// reached; `None` before its first result (or after a quarantine took it back).
    pub state: Option<Arc<Vec<u8>>>,
    pub rung: Option<u32>,
    /// The SHA-256 of the state's encoded bytes: copies are compared by it.
    pub sha: [u8; 32],
    /// The state the pass under way started the tile from: what every `Advance` of the
    /// tile in this pass carries, and what its answers are checked against.
    pub previous: Option<Arc<Vec<u8>>>,
    /// The first rung after `rung` at which a block of the tile doubles (`Some(0)`
    /// without a state, `None` once every block is at its cap).
    pub next_work: Option<u32>,
    /// The machines whose answers the state was built from, pass after pass: a
    /// quarantine of any of them takes the tile back to nothing.
    pub machines: Vec<Arc<str>>,
}

impl AdaptiveTile {
    /// A tile with nothing rendered: all its work is ahead.
    pub fn unrendered() -> AdaptiveTile {
        AdaptiveTile {
            next_work: Some(0),
            ..AdaptiveTile::default()
        }
    }
}

/// The passes of an adaptive job with these settings, limited to `time_limit_ms` of
/// rendering if given; a refinement's from the rung its tiles' states have reached.
fn passes_for(settings: &Settings, time_limit_ms: Option<u64>, from: Option<u32>) -> Passes {
    let target = settings.sampling.target_error().unwrap_or(f64::INFINITY);
    let last = render::adaptive::LAST_RUNG;
    let passes = match from {
        Some(rung) => Passes::from_rung(target, last, rung),
        None => Passes::new(target, last),
    };
    passes.with_time_limit(time_limit_ms)
}

impl AdaptiveJob {
    /// A job of `tiles` tiles. A refinement's tiles start from `start` (checked by the
    /// caller: one valid state per tile): its first pass sends every tile from its
    /// state to the states' rung, where a larger cap may add samples, and looks at
    /// every rung up to it. Returns the job and its passes, for the core.
    pub fn new(
        settings: &Settings,
        tiles: usize,
        time_limit_ms: Option<u64>,
        start: Option<crate::store::TileStates>,
    ) -> (AdaptiveJob, Passes) {
        let (from, tiles) = match start {
            Some(start) if start.states.len() == tiles => (
                Some(start.rung),
                start
                    .states
                    .into_iter()
                    .map(|state| AdaptiveTile {
                        state: Some(Arc::clone(&state)),
                        previous: Some(state),
                        ..AdaptiveTile::unrendered()
                    })
                    .collect(),
            ),
            _ => (None, vec![AdaptiveTile::unrendered(); tiles]),
        };
        let job = AdaptiveJob {
            tiles,
            evaluation: None,
            rays: 0,
        };
        (job, passes_for(settings, time_limit_ms, from))
    }

    /// Tiles whose state has reached `rung`, the pass's: the progress of the pass.
    pub fn tiles_done(&self, rung: u32) -> u32 {
        self.tiles.iter().filter(|t| t.rung == Some(rung)).count() as u32
    }

    /// The tiles as the core weighs them: the rung each has reached and its next work.
    pub fn pass_tiles(&self) -> Vec<PassTile> {
        self.tiles
            .iter()
            .map(|t| PassTile {
                rung: t.rung,
                next_work: t.next_work,
            })
            .collect()
    }
}

/// What an answer is checked against, gathered under the lock.
#[derive(Clone)]
pub struct AdaptivePlan {
    pub pass: u32,
    pub rung: u32,
    pub previous: Option<Arc<Vec<u8>>>,
}

/// An answer that passed its checks: what the core keeps of it.
#[derive(Clone)]
pub struct Answer {
    pub pass: u32,
    pub state: Arc<Vec<u8>>,
    pub sha: [u8; 32],
    pub next_work: Option<u32>,
    pub samples: u64,
}

/// Checks an answer off the lock: its pixels and state decompress within their bounds,
/// the state is a valid state of the tile that has reached the rung, the pixels are
/// the state's at the rung, and (for a share of answers) one block chosen at random is
/// advanced here from the previous state and must give the same bits.
pub fn check_answer(
    verifier: &Verifier,
    tracer: &render::Tracer,
    settings: &Settings,
    rect: TileRect,
    plan: &AdaptivePlan,
    rgb: &[u8],
    state: Vec<u8>,
) -> Result<Answer, String> {
    let aa = settings.aa;
    let footprints = verifier.footprints(tracer);
    let raw = verify::adaptive::decompress_state(&state, rect, aa)?;
    let blocks = verify::adaptive::decode_state(&raw)?;
    let region = verify::adaptive::region(tracer, Arc::clone(&footprints), rect, blocks)?;
    let ours = verify::adaptive::pixels(&region, &footprints, aa, rect, plan.rung)
        .ok_or_else(|| format!("its blocks have not reached rung {}", plan.rung))?;
    if ours != rgb {
        return Err(format!(
            "its pixels are not those of its blocks at rung {}",
            plan.rung
        ));
    }
    if verifier.adaptive_check(region.blocks().len()) {
        let previous = plan
            .previous
            .as_ref()
            .map(|p| verify::adaptive::unpack_state(p, rect, aa))
            .transpose()?;
        verify::adaptive::check_block(
            tracer,
            &footprints,
            previous.as_deref(),
            region.blocks(),
            plan.rung,
            super::verification::random_u64(),
        )
        .map_err(|e| e.to_string())?;
    }
    let samples = region.totals(plan.rung).map_or(0, |t| t.samples);
    Ok(Answer {
        pass: plan.pass,
        next_work: verify::adaptive::next_work(&region, plan.rung),
        sha: Sha256::digest(&raw).into(),
        state: Arc::new(state),
        samples,
    })
}

/// Which of two differing answers of a tile is wrong (both passed their own checks):
/// the blocks where their states differ, advanced here. `(first, second)` reasons.
pub fn arbitrate(
    verifier: &Verifier,
    tracer: &render::Tracer,
    settings: &Settings,
    rect: TileRect,
    plan: &AdaptivePlan,
    first: &[u8],
    second: &[u8],
) -> (Option<String>, Option<String>) {
    let aa = settings.aa;
    let footprints = verifier.footprints(tracer);
    let decode = |s: &[u8]| verify::adaptive::unpack_state(s, rect, aa);
    let previous = match plan.previous.as_ref().map(|p| decode(p)).transpose() {
        Ok(p) => p,
        Err(e) => return (Some(e.clone()), Some(e)),
    };
    let (a, b) = match (decode(first), decode(second)) {
        (Ok(a), Ok(b)) => (a, b),
        (a, b) => return (a.err(), b.err()),
    };
    let (x, y) =
        verify::adaptive::arbitrate(tracer, &footprints, previous.as_deref(), &a, &b, plan.rung);
    (x.map(|w| w.to_string()), y.map(|w| w.to_string()))
}

/// A pass's tiles as the end of the pass needs them, copied under the lock.
pub struct PassSnapshot {
    pub rungs: std::ops::RangeInclusive<u32>,
    pub settings: Settings,
    pub rects: Vec<TileRect>,
    pub states: Vec<Option<Arc<Vec<u8>>>>,
    /// Paint the pass's rung when none meets the target (a job with a time limit may
    /// end there).
    pub paint_last: bool,
}

/// The end of a pass, computed off the lock.
pub struct Evaluation {
    pub checks: Vec<RungCheck>,
    /// The frame's totals at the first rung that meets the target, else at the pass's
    /// rung.
    pub totals: RungTotals,
    /// The image at the first rung that meets the target, if one does (else at the
    /// pass's rung when asked for).
    pub image: Option<render::Image>,
}

/// Adds up the tiles' totals at each rung the pass must look at, and paints the image
/// at the first that meets the target. Tile by tile, so that only one tile's decoded
/// state is held at a time.
pub fn evaluate(
    verifier: &Verifier,
    tracer: &render::Tracer,
    snap: PassSnapshot,
) -> Result<Evaluation, String> {
    let footprints = verifier.footprints(tracer);
    let aa = snap.settings.aa;
    let rungs: Vec<u32> = snap.rungs.clone().collect();
    let mut sums = vec![RungTotals::default(); rungs.len()];
    let region = |t: usize| {
        let state = snap.states[t]
            .as_ref()
            .ok_or_else(|| format!("tile {t} has no state at the end of its pass"))?;
        let blocks = verify::adaptive::unpack_state(state, snap.rects[t], aa)?;
        verify::adaptive::region(tracer, Arc::clone(&footprints), snap.rects[t], blocks)
    };
    for t in 0..snap.rects.len() {
        let r = region(t)?;
        for (sum, &k) in sums.iter_mut().zip(&rungs) {
            let totals = r
                .totals(k)
                .ok_or_else(|| format!("tile {t} has not reached rung {k}"))?;
            sum.add(&totals);
        }
    }
    let target = snap
        .settings
        .sampling
        .target_error()
        .unwrap_or(f64::INFINITY);
    let checks: Vec<RungCheck> = rungs
        .iter()
        .zip(&sums)
        .map(|(&rung, t)| RungCheck {
            rung,
            estimate: t.estimated_error(),
            meets: meets(t, rung, target),
        })
        .collect();
    let found = checks.iter().position(|c| c.meets);
    let painted = found.or((snap.paint_last && !rungs.is_empty()).then(|| rungs.len() - 1));
    let image = match painted {
        Some(i) => {
            let k = rungs[i];
            let s = snap.settings;
            let mut image = render::Image::black(s.width, s.height);
            for t in 0..snap.rects.len() {
                let r = region(t)?;
                let rgb = verify::adaptive::pixels(&r, &footprints, aa, snap.rects[t], k)
                    .ok_or_else(|| format!("tile {t} has not reached rung {k}"))?;
                image.put_rect(verify::render_rect(snap.rects[t]), &rgb);
            }
            Some(image)
        }
        None => None,
    };
    let at = found.unwrap_or(rungs.len() - 1);
    Ok(Evaluation {
        checks,
        totals: sums[at],
        image,
    })
}
