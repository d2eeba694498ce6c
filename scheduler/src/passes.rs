//! The passes of an adaptive job: which rung of the threshold ladder each pass takes
//! the tiles to, and when the job's image is found.
//!
//! An adaptive job's image for a target E is, by definition, the frame at the first
//! rung k* of the ladder whose estimated error meets E (the local walk goes rung after
//! rung from 0 and stops there). The farm cannot afford a round of the whole farm per
//! rung, so it renders in passes: pass p advances every tile to rung k_p, and when the
//! pass is complete the coordinator adds up the tiles' totals at each rung from the one
//! after the previous pass's rung up to k_p. If one of them meets the target, the first
//! such is k* and the job is done (every tile painted at k*: a tile's state at k_p holds
//! its levels at every rung below). Otherwise the next pass aims further.
//!
//! How far is a choice of cost, never of bytes: too short a jump costs a whole round of
//! the farm, too long one renders samples the image will not use. The estimate falls
//! about log-linearly in the rung (each halving of the error takes a roughly constant
//! number of rungs, [`PRIOR_RUNGS_PER_HALVING`] on the benchmark scenes), so the next
//! rung is predicted from the fall over the last two passes (the prior before there are
//! two), then aimed a little past it, since an undershoot costs more than an overshoot.
//!
//! **A time budget.** A job may also have a time limit. Time is an input here like the
//! totals: the coordinator passes how long the job has been rendering at the end of each
//! pass. A pass that ends at or past the limit ends the job at its own rung, the deepest
//! one rendered (the frame there is the best the budget bought, and its estimate is
//! reported). Before that, the next pass is aimed to fit the time left: its cost is
//! predicted from the samples (the frame's samples grow about exponentially in the rung,
//! and a pass's time with its new samples), so that the job overruns its limit by a
//! share of a pass at most rather than by a pass aimed at a target it cannot afford.
//!
//! A pure state machine: the coordinator computes the totals (it needs the renderer),
//! this decides. No clock, no I/O.

use std::ops::RangeInclusive;

/// Rungs per halving of the estimated error assumed before two passes have measured it.
pub const PRIOR_RUNGS_PER_HALVING: f64 = 28.0;

/// How far past the predicted rung the next pass aims, as a factor of the jump.
pub const OVERSHOOT: f64 = 1.15;

/// Rungs added to every jump: a prediction that lands just short still finishes.
pub const MARGIN: u32 = 2;

/// The fewest and most rungs per halving a measured fall may imply: a pass whose
/// estimate barely moved (or jumped) is not believed beyond these.
const PER_HALVING_RANGE: (f64, f64) = (4.0, 400.0);

/// What the totals of the tiles say at one rung.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RungCheck {
    pub rung: u32,
    /// The frame's estimated RMS error at the rung, in levels (NaN when unknown).
    pub estimate: f64,
    /// Whether the frame at this rung meets the target (or cannot go further).
    pub meets: bool,
}

/// Rungs per doubling of the frame's samples assumed before two passes have measured
/// it: an error falling as samples^(-1/2) halves for every two doublings.
pub const PRIOR_RUNGS_PER_DOUBLING: f64 = PRIOR_RUNGS_PER_HALVING / 2.0;

/// The fewest and most rungs per doubling of the samples a measurement may imply.
const PER_DOUBLING_RANGE: (f64, f64) = (2.0, 200.0);

/// What to do once a pass is complete.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Decision {
    /// The image is every tile at this rung: no more rendering.
    Finish { rung: u32 },
    /// The time limit is reached before any rung met the target: the image is every
    /// tile at this rung, the deepest rendered.
    OutOfTime { rung: u32 },
    /// Start the next pass, which takes the tiles to this rung.
    Next { rung: u32 },
}

/// An adaptive job's passes.
#[derive(Clone, Debug, PartialEq)]
pub struct Passes {
    target: f64,
    last_rung: u32,
    /// The pass under way: its number (never reused within the job, restarts included)
    /// and its rung.
    pass: u32,
    rung: u32,
    /// The rungs up to this one are known not to meet the target.
    checked: Option<u32>,
    /// (rung, estimate) at the end of each pass so far, the latest last.
    history: Vec<(u32, f64)>,
    /// The job's time limit in milliseconds of rendering, if any.
    time_limit_ms: Option<u64>,
    /// (rung, milliseconds of rendering, frame's samples) at the end of each pass.
    clock: Vec<(u32, u64, u64)>,
}

impl Passes {
    /// A job aiming for `target` levels on a ladder ending at `last_rung`: its first
    /// pass takes every tile to rung 0 (the first samples), whose estimate tells how far
    /// the second must go.
    pub fn new(target: f64, last_rung: u32) -> Passes {
        Passes {
            target,
            last_rung,
            pass: 0,
            rung: 0,
            checked: None,
            history: Vec::new(),
            time_limit_ms: None,
            clock: Vec::new(),
        }
    }

    /// A job whose tiles start from states that have already reached `rung` (a job
    /// refined from a finished one): its first pass takes every tile to that rung (a
    /// larger cap may add samples there), and every rung up to it is looked at, since
    /// the stored levels make the frame change at each of them.
    pub fn from_rung(target: f64, last_rung: u32, rung: u32) -> Passes {
        Passes {
            rung: rung.min(last_rung),
            ..Passes::new(target, last_rung)
        }
    }

    /// The same passes, stopping once the job has rendered for `limit_ms`.
    pub fn with_time_limit(mut self, limit_ms: Option<u64>) -> Passes {
        self.time_limit_ms = limit_ms;
        self
    }

    /// The pass under way.
    pub fn pass(&self) -> u32 {
        self.pass
    }

    /// The rung the pass under way takes the tiles to.
    pub fn rung(&self) -> u32 {
        self.rung
    }

    /// The estimate at the end of the last pass, if any.
    pub fn estimate(&self) -> Option<f64> {
        self.history.last().map(|&(_, e)| e)
    }

    /// The rungs whose totals must be looked at when the pass under way is complete:
    /// those not yet known to miss the target.
    pub fn to_check(&self) -> RangeInclusive<u32> {
        self.checked.map_or(0, |c| c + 1)..=self.rung
    }

    /// The pass under way is complete: `checks` are the totals' verdicts at the rungs of
    /// [`Passes::to_check`], in order, and `first_work` the first rung after the pass's
    /// at which any block doubles (`None` when every block is at its cap). The first
    /// rung that meets the target ends the job; otherwise the next pass starts.
    ///
    /// Up to `first_work` − 1 the frame cannot change, so its estimate there is the
    /// pass's: those rungs need no pass of their own (they do not meet the target
    /// either, being short of the last rung), and the fall is measured from there.
    ///
    /// # Panics
    ///
    /// If `checks` are not the rungs of `to_check`.
    pub fn pass_done(&mut self, checks: &[RungCheck], first_work: Option<u32>) -> Decision {
        self.pass_done_at(checks, first_work, 0, 0)
    }

    /// [`Passes::pass_done`] for a job that may have a time limit: `elapsed_ms` is how
    /// long the job has been rendering, `samples` the frame's samples at the pass's
    /// rung. At or past the limit the job ends at the pass's rung
    /// ([`Decision::OutOfTime`]) unless a rung met the target; before it, the next
    /// pass is aimed no further than the time left is predicted to reach.
    pub fn pass_done_at(
        &mut self,
        checks: &[RungCheck],
        first_work: Option<u32>,
        elapsed_ms: u64,
        samples: u64,
    ) -> Decision {
        let rungs: Vec<u32> = checks.iter().map(|c| c.rung).collect();
        assert_eq!(
            rungs,
            self.to_check().collect::<Vec<_>>(),
            "the checks of the pass's rungs"
        );
        if let Some(found) = checks.iter().find(|c| c.meets) {
            return Decision::Finish { rung: found.rung };
        }
        if self.time_limit_ms.is_some_and(|limit| elapsed_ms >= limit) {
            return Decision::OutOfTime { rung: self.rung };
        }
        self.clock.push((self.rung, elapsed_ms, samples));
        let estimate = checks.last().map_or(f64::NAN, |c| c.estimate);
        let unchanged = first_work
            .map_or(self.last_rung, |w| w.saturating_sub(1))
            .clamp(self.rung, self.last_rung.saturating_sub(1).max(self.rung));
        self.history.push((unchanged, estimate));
        self.checked = Some(unchanged);
        self.pass += 1;
        self.rung = if first_work.is_none() {
            self.last_rung
        } else {
            next_rung(&self.history, self.target, self.last_rung)
        };
        if let Some(limit) = self.time_limit_ms {
            let fits = fitting_rung(
                &self.clock,
                limit.saturating_sub(elapsed_ms),
                self.last_rung,
            );
            self.rung = self.rung.min(fits).max(unchanged + 1).min(self.last_rung);
        }
        Decision::Next { rung: self.rung }
    }

    /// Results the pass under way depends on were taken back (a machine was caught
    /// returning wrong pixels): the pass starts again under a new number, at the same
    /// rung, and every rung is looked at again at its end, since the totals that ruled
    /// the earlier rungs out included the taken-back results. Returns the new number.
    pub fn restart_pass(&mut self) -> u32 {
        self.checked = None;
        self.pass += 1;
        self.pass
    }
}

/// The rung the next pass should reach, from the (rung, estimate) at the end of each
/// pass so far (none of which met `target`), on a ladder ending at `last_rung`.
pub fn next_rung(history: &[(u32, f64)], target: f64, last_rung: u32) -> u32 {
    let Some(&(rung, estimate)) = history.last() else {
        return 0;
    };
    if rung >= last_rung {
        return last_rung;
    }
    // No estimate (one sample per pixel): only the last rung can end the job.
    if !(estimate.is_finite() && estimate > 0.0 && target > 0.0) {
        return last_rung;
    }
    let halvings = (estimate / target).log2().max(0.0);
    let measured = history.len().checked_sub(2).and_then(|i| {
        let (k0, e0) = history[i];
        let fall = (e0 / estimate).log2();
        (fall.is_finite() && fall > 0.0 && rung > k0).then(|| f64::from(rung - k0) / fall)
    });
    let per_halving = measured
        .unwrap_or(PRIOR_RUNGS_PER_HALVING)
        .clamp(PER_HALVING_RANGE.0, PER_HALVING_RANGE.1);
    let jump = (halvings * per_halving * OVERSHOOT).ceil();
    let jump = if jump.is_finite() {
        jump.min(f64::from(last_rung)) as u32
    } else {
        last_rung
    };
    rung.saturating_add(jump.saturating_add(MARGIN))
        .min(last_rung)
}

/// The deepest rung a pass can be predicted to reach in `remaining_ms`, from the
/// (rung, milliseconds of rendering, samples) at the end of each pass so far: the time
/// per sample of the last pass (of the first, from the start), and the rungs per
/// doubling of the samples measured over the last two passes (the prior before).
pub fn fitting_rung(clock: &[(u32, u64, u64)], remaining_ms: u64, last_rung: u32) -> u32 {
    let Some(&(rung, elapsed, samples)) = clock.last() else {
        return 0;
    };
    let (r0, e0, s0) = clock.len().checked_sub(2).map_or((0, 0, 0), |i| clock[i]);
    if samples <= s0 || elapsed <= e0 || samples == 0 {
        return rung.saturating_add(1).min(last_rung);
    }
    let ms_per_sample = (elapsed - e0) as f64 / (samples - s0) as f64;
    let per_doubling = (s0 > 0 && rung > r0)
        .then(|| f64::from(rung - r0) / (samples as f64 / s0 as f64).log2())
        .filter(|d| d.is_finite() && *d > 0.0)
        .unwrap_or(PRIOR_RUNGS_PER_DOUBLING)
        .clamp(PER_DOUBLING_RANGE.0, PER_DOUBLING_RANGE.1);
    let affordable = samples as f64 + remaining_ms as f64 / ms_per_sample;
    let jump = (per_doubling * (affordable / samples as f64).log2()).floor();
    let jump = if jump.is_finite() && jump >= 1.0 {
        jump.min(f64::from(last_rung)) as u32
    } else {
        1
    };
    rung.saturating_add(jump).min(last_rung)
}

/// The tiles a pass to `rung` sends: those with work at it. `next_work[t]` is the first
/// rung at which some block of tile t doubles (`Some(0)` for a tile without a state
/// yet, `None` for one whose blocks are all at their cap).
pub fn tiles_with_work(next_work: &[Option<u32>], rung: u32) -> Vec<u32> {
    next_work
        .iter()
        .enumerate()
        .filter(|(_, w)| w.is_some_and(|w| w <= rung))
        .map(|(t, _)| t as u32)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame whose estimate halves every `per_halving` rungs from `start` at rung 0.
    fn checks(
        range: RangeInclusive<u32>,
        start: f64,
        per_halving: f64,
        target: f64,
    ) -> Vec<RungCheck> {
        range
            .map(|rung| {
                let estimate = start * (-(f64::from(rung)) / per_halving).exp2();
                RungCheck {
                    rung,
                    estimate,
                    meets: rung >= 705 || estimate <= target,
                }
            })
            .collect()
    }

    /// Runs a job's passes on the model frame: (passes, final rung, rungs rendered past
    /// the final one).
    fn run(start: f64, per_halving: f64, target: f64) -> (u32, u32, u32) {
        let mut p = Passes::new(target, 705);
        let mut passes = 1;
        loop {
            let c = checks(p.to_check(), start, per_halving, target);
            let reached = p.rung();
            match p.pass_done(&c, Some(reached + 1)) {
                Decision::Finish { rung } | Decision::OutOfTime { rung } => {
                    return (passes, rung, reached - rung)
                }
                Decision::Next { rung } => {
                    assert!(rung > reached, "every pass goes further");
                    passes += 1;
                }
            }
        }
    }

    #[test]
    fn the_first_rung_that_meets_the_target_ends_the_job() {
        for (start, per_halving, target) in
            [(40.0, 28.0, 1.0), (10.0, 20.0, 2.0), (60.0, 35.0, 0.5)]
        {
            let (passes, rung, past) = run(start, per_halving, target);
            // The walk's own answer: the first rung whose estimate meets the target.
            let walk = checks(0..=705, start, per_halving, target)
                .into_iter()
                .find(|c| c.meets)
                .unwrap()
                .rung;
            assert_eq!(rung, walk, "{start} {per_halving} {target}");
            assert!(passes <= 4, "{passes} passes");
            // The overshoot stays a share of the walk (most of it the prior's miss on a
            // frame whose error falls faster than it assumes).
            assert!(
                f64::from(past) <= 0.7 * f64::from(walk) + 4.0,
                "{past} past {walk}"
            );
        }
    }

    #[test]
    fn a_target_met_at_once_takes_one_pass_and_no_estimate_goes_to_the_last_rung() {
        assert_eq!(run(0.5, 28.0, 1.0), (1, 0, 0));
        let mut p = Passes::new(1.0, 705);
        let unknown = [RungCheck {
            rung: 0,
            estimate: f64::NAN,
            meets: false,
        }];
        assert_eq!(p.pass_done(&unknown, Some(1)), Decision::Next { rung: 705 });
        assert_eq!(p.to_check(), 1..=705);
    }

    #[test]
    fn the_prediction_follows_the_measured_fall() {
        // Prior: 28 rungs per halving, 4 halvings to go.
        assert_eq!(
            next_rung(&[(0, 16.0)], 1.0, 705),
            (4.0 * 28.0 * OVERSHOOT).ceil() as u32 + MARGIN
        );
        // Measured: 10 rungs per halving between the passes, 2 halvings to go.
        let next = next_rung(&[(0, 16.0), (20, 4.0)], 1.0, 705);
        assert_eq!(next, 20 + (20.0 * OVERSHOOT).ceil() as u32 + MARGIN);
        // An estimate that rose is not believed: the prior again.
        let next = next_rung(&[(0, 4.0), (20, 8.0)], 1.0, 705);
        assert_eq!(next, 20 + (3.0 * 28.0 * OVERSHOOT).ceil() as u32 + MARGIN);
        assert_eq!(next_rung(&[(700, 8.0)], 1.0, 705), 705);
    }

    #[test]
    fn a_restarted_pass_checks_every_rung_again() {
        let mut p = Passes::new(1.0, 705);
        let first = checks(0..=0, 16.0, 28.0, 1.0);
        let Decision::Next { rung } = p.pass_done(&first, Some(1)) else {
            panic!("16 levels do not meet 1");
        };
        assert_eq!((p.pass(), p.to_check()), (1, 1..=rung));
        assert_eq!(p.restart_pass(), 2);
        assert_eq!((p.rung(), p.to_check()), (rung, 0..=rung));
    }

    #[test]
    fn rungs_where_nothing_changes_are_skipped() {
        // Nothing doubles before rung 130: the estimate of rung 0 holds up to 129, and
        // the next pass aims from there.
        let mut p = Passes::new(1.0, 705);
        let first = checks(0..=0, 16.0, 28.0, 1.0);
        assert_eq!(
            p.pass_done(&first, Some(130)),
            Decision::Next {
                rung: 129 + (4.0 * 28.0 * OVERSHOOT).ceil() as u32 + MARGIN
            }
        );
        assert_eq!(*p.to_check().start(), 130);
        // Every block at its cap: only the last rung is left.
        let mut p = Passes::new(1.0, 705);
        assert_eq!(p.pass_done(&first, None), Decision::Next { rung: 705 });
    }

    #[test]
    fn a_pass_ending_past_the_time_limit_ends_the_job_at_its_rung() {
        let mut p = Passes::new(0.001, 705).with_time_limit(Some(1000));
        let first = checks(0..=0, 16.0, 28.0, 0.001);
        // 100 ms for the first samples: the next pass is aimed to fit the 900 left.
        let Decision::Next { rung } = p.pass_done_at(&first, Some(1), 100, 1000) else {
            panic!("time is left");
        };
        // Ten times the time affords about 3.3 doublings of the samples, at the prior's
        // 14 rungs each.
        assert_eq!(rung, (14.0 * 10f64.log2()).floor() as u32);
        let second = checks(p.to_check(), 16.0, 28.0, 0.001);
        assert_eq!(
            p.pass_done_at(&second, Some(rung + 1), 1000, 10_000),
            Decision::OutOfTime { rung }
        );
        // A rung that meets the target still wins, whatever the time.
        let mut p = Passes::new(20.0, 705).with_time_limit(Some(10));
        let first = checks(0..=0, 16.0, 28.0, 20.0);
        assert_eq!(
            p.pass_done_at(&first, Some(1), 50, 10),
            Decision::Finish { rung: 0 }
        );
        // Without a limit the time does not matter.
        let mut p = Passes::new(1.0, 705);
        let first = checks(0..=0, 16.0, 28.0, 1.0);
        assert!(matches!(
            p.pass_done_at(&first, Some(1), u64::MAX, 10),
            Decision::Next { .. }
        ));
    }

    #[test]
    fn the_next_pass_fits_the_time_left() {
        // The last pass took 1 s for 3000 new samples over 14 rungs (one doubling).
        let clock = [(14, 1000, 3000), (28, 2000, 6000)];
        // 2 s more buys 6000 samples more: one doubling, 14 rungs.
        assert_eq!(fitting_rung(&clock, 2000, 705), 42);
        // No time left: one rung still, so that every pass goes further.
        assert_eq!(fitting_rung(&clock, 0, 705), 29);
        assert_eq!(fitting_rung(&clock, u64::MAX / 4, 705), 705);
        // A passes' ladder with a time limit never aims past what fits.
        let mut p = Passes::new(0.001, 705).with_time_limit(Some(2000));
        let first = checks(0..=0, 16.0, 28.0, 0.001);
        assert_eq!(
            p.pass_done_at(&first, Some(1), 1000, 1000),
            Decision::Next { rung: 14 }
        );
    }

    #[test]
    fn a_refined_job_checks_every_rung_up_to_its_states() {
        let p = Passes::from_rung(1.0, 705, 90);
        assert_eq!((p.pass(), p.rung(), p.to_check()), (0, 90, 0..=90));
    }

    #[test]
    fn tiles_without_work_at_the_rung_stay_home() {
        let work = [Some(0), None, Some(30), Some(31)];
        assert_eq!(tiles_with_work(&work, 30), [0, 2]);
        assert_eq!(tiles_with_work(&work, 705), [0, 2, 3]);
    }
}
