//! The figures the coordinator reports of its jobs and workers, as functions of what
//! it has seen (time passed in): how they are estimated is decided here, and tested.

use std::collections::VecDeque;

use crate::db::Totals;

/// The image's estimated error in 8-bit levels: the root mean square of the per-pixel
/// estimates, once every pixel of the image has one (`pixels` of them), `None` before,
/// and always with one sample per pixel (`aa` 1: no spread to measure).
///
/// Not over the tiles in so far: those are whichever part of the image came first
/// (often a smooth sky), and read far better than the image will (0.003 levels at 6 of
/// 300 tiles, 1.309 at the end). An adaptive job's totals hold the whole frame's
/// estimate after each pass, so it has one from its first pass on.
pub fn image_error(aa: u32, totals: &Totals, pixels: u64) -> Option<f64> {
    (aa >= 2 && pixels > 0 && totals.error_pixels >= pixels)
        .then(|| (totals.error_sq_sum / totals.error_pixels as f64).sqrt())
}

/// The pace of a job's current run: when its recent tiles were done (Unix ms). A run
/// starts with the job's first tile out in this coordinator's life, or with its retry:
/// tiles kept from before, and the time before, are no measure of the farm now.
#[derive(Debug, Default)]
pub struct Pace {
    /// The times of the tiles done in the last [`PACE_WINDOW_MS`] before the newest,
    /// and at least the last [`PACE_TILES`] of them.
    done: VecDeque<u64>,
    /// Tiles done earlier were forgotten: the pace is over those kept.
    forgot: bool,
}

/// The time left of a job is estimated from the tiles done in about this last while
/// (and at least [`PACE_TILES`]): a farm whose workers come and go, or whose tiles get
/// cheaper or dearer down the image, is followed as it goes, not averaged since the
/// start.
pub const PACE_WINDOW_MS: u64 = 20_000;

/// The fewest tiles the pace is measured over, once the run has more.
pub const PACE_TILES: usize = 16;

impl Pace {
    /// A tile of the run was done at `at`.
    pub fn tile_done(&mut self, at: u64) {
        self.done.push_back(at);
        while self.done.len() > PACE_TILES
            && self
                .done
                .front()
                .is_some_and(|&t| at.saturating_sub(t) > PACE_WINDOW_MS)
        {
            self.done.pop_front();
            self.forgot = true;
        }
    }

    /// The time left, in ms, for `left` tiles at `now`, at the run's pace: the tiles
    /// done over the time they took, from the run's start (`since`) while all are
    /// kept, then from the oldest kept (which the count then leaves out). Every worker
    /// is in it: it is the farm's pace for this job, however many render it at once.
    /// `None` before the run's first tile.
    pub fn time_left(&self, since: u64, now: u64, left: u32) -> Option<u64> {
        let &first = self.done.front()?;
        let (from, tiles) = if self.forgot {
            (first, self.done.len() - 1)
        } else {
            (since.min(first), self.done.len())
        };
        let span = now.saturating_sub(from).max(1) as f64;
        (tiles > 0).then(|| (f64::from(left) * span / tiles as f64) as u64)
    }
}

/// A worker's rays per second while it renders: the rays of its `results` over the
/// time it spent rendering them, each result given as (when it arrived, how long its
/// tile took to render, both in µs, and its rays). The time is the union of the
/// results' rendering spans (a tile's ending as it arrived): tiles rendered at once on
/// its threads count once, and the time it sat idle not at all. So a worker that just
/// rendered a 37 M rays/s job shows 37 M, not that job's rays spread over a minute
/// mostly idle. 0 without results.
pub fn rendering_rate(results: impl IntoIterator<Item = (u64, u64, u64)>) -> f64 {
    let mut spans: Vec<(u64, u64)> = Vec::new();
    let mut rays = 0u64;
    for (arrived, render_us, r) in results {
        spans.push((arrived.saturating_sub(render_us), arrived));
        rays = rays.saturating_add(r);
    }
    spans.sort_unstable();
    let mut busy_us = 0u64;
    let mut current: Option<(u64, u64)> = None;
    for (start, end) in spans {
        current = match current {
            Some((s, e)) if start <= e => Some((s, e.max(end))),
            Some((s, e)) => {
                busy_us += e - s;
                Some((start, end))
            }
            None => Some((start, end)),
        };
    }
    if let Some((s, e)) = current {
        busy_us += e - s;
    }
    if busy_us == 0 {
        return 0.0;
    }
    rays as f64 / (busy_us as f64 / 1e6)
}

/// A job's elapsed time and queue wait at `end` (now, or its end), in ms: those of its
/// current run, which starts at its submission or, once retried, at its last retry. A
/// retry starts a new run: the time the job sat cancelled or failed before it, and its
/// earlier runs, are not in its elapsed time (a job cancelled twice around a retry
/// showed 305 s, mostly of waiting). The wait is from the run's start to its first
/// tile out (`started`, if that is of this run); `None` before.
pub fn run_times(
    submitted: u64,
    retried: Option<u64>,
    started: Option<u64>,
    end: u64,
) -> (u64, Option<u64>) {
    let from = retried.map_or(submitted, |r| r.max(submitted));
    let queued = started.filter(|&s| s >= from).map(|s| s - from);
    (end.saturating_sub(from), queued)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn totals(error_sq_sum: f64, error_pixels: u64) -> Totals {
        Totals {
            error_sq_sum,
            error_pixels,
            ..Totals::default()
        }
    }

    #[test]
    fn the_error_is_reported_once_it_covers_the_whole_image() {
        let pixels = 300 * 256;
        // 6 tiles of sky in: no estimate yet, not one that reads too good.
        assert_eq!(
            image_error(2, &totals(0.0001 * 6.0 * 256.0, 6 * 256), pixels),
            None
        );
        assert_eq!(image_error(2, &totals(0.0, 0), pixels), None);
        let whole = image_error(2, &totals(1.309 * 1.309 * pixels as f64, pixels), pixels);
        assert!((whole.unwrap() - 1.309).abs() < 1e-9, "{whole:?}");
        // One sample per pixel: nothing to measure, even with every pixel in.
        assert_eq!(image_error(1, &totals(1.0, pixels), pixels), None);
    }
    /// A recorded schedule: one worker, a tile a second, for 30 s, then four workers,
    /// four tiles a second, to the 300th tile.
    fn schedule(since: u64) -> Vec<u64> {
        let mut done: Vec<u64> = (1..=30).map(|s| since + s * 1000).collect();
        while done.len() < 300 {
            done.push(done.last().unwrap() + 250);
        }
        done
    }

    #[test]
    fn the_time_left_follows_the_farms_pace_now_not_since_the_start() {
        let since = 1_000_000;
        let done = schedule(since);
        let mut pace = Pace::default();
        let mut fed = 0;
        for now in [40_000, 55_000, 70_000].map(|ms| since + ms) {
            while done[fed] <= now {
                pace.tile_done(done[fed]);
                fed += 1;
            }
            let left = (done.len() - fed) as u32;
            let actual = done.last().unwrap() - now;
            let estimate = pace.time_left(since, now, left).unwrap();
            // The pace since the start of the run, as it was estimated, reads long.
            let since_start = (now - since) * u64::from(left) / fed as u64;
            assert!(
                since_start > actual * 4 / 3,
                "{since_start} ms for {actual} ms"
            );
            if now >= since + 55_000 {
                // 20 s past the change, every tile measured is at the pace of four.
                assert!(
                    estimate.abs_diff(actual) * 10 <= actual,
                    "{estimate} ms estimated for {actual} ms left"
                );
            } else {
                assert!(estimate < since_start, "{estimate} ms, {since_start} ms");
            }
        }
    }

    #[test]
    fn a_new_run_is_timed_from_its_own_start_and_tiles() {
        let mut pace = Pace::default();
        // Retried (or the coordinator restarted) with 394 of 1200 tiles kept: none is
        // in the pace, nor the time before the run.
        assert_eq!(pace.time_left(10_000, 10_500, 806), None);
        pace.tile_done(12_000);
        pace.tile_done(12_000);
        // Two tiles in 2 s of this run: a second each for the 804 left.
        assert_eq!(pace.time_left(10_000, 12_000, 804), Some(804_000));
    }
    #[test]
    fn a_workers_rate_is_over_the_time_it_spent_rendering() {
        // A 5 s job on two threads, tiles of a second two at a time, 37 M rays a
        // second in all: 37 M, whatever idle time follows.
        let results: Vec<(u64, u64, u64)> = (1..=5)
            .flat_map(|s| [(s * 1_000_000, 1_000_000, 18_500_000); 2])
            .collect();
        let rate = rendering_rate(results.iter().copied());
        assert!((rate - 37e6).abs() < 1.0, "{rate}");
        // Two results apart, with idle time between: the idle time is not in it.
        let apart = [
            (2_000_000, 1_000_000, 1_000_000),
            (60_000_000, 1_000_000, 1_000_000),
        ];
        assert!((rendering_rate(apart) - 1e6).abs() < 1.0);
        // Overlapping spans count once.
        let overlapping = [(2_000_000, 2_000_000, 3_000_000), (3_000_000, 2_000_000, 0)];
        assert!((rendering_rate(overlapping) - 1e6).abs() < 1.0);
        assert_eq!(rendering_rate([]), 0.0);
        // A tile of no measurable time says nothing of the rate.
        assert_eq!(rendering_rate([(5, 0, 100)]), 0.0);
    }
    #[test]
    fn a_retry_starts_a_new_run_that_elapsed_time_and_the_wait_count_from() {
        // Submitted at 0, first tile out at 2 s, still running at 20 s.
        assert_eq!(
            run_times(0, None, Some(2_000), 20_000),
            (20_000, Some(2_000))
        );
        // Not started: all of it waiting, no wait known yet.
        assert_eq!(run_times(0, None, None, 5_000), (5_000, None));
        // Cancelled at 20 s, retried at 300 s: at 301 s, its run is 1 s old and has not
        // started (the first run's start is not this run's).
        assert_eq!(
            run_times(0, Some(300_000), Some(2_000), 301_000),
            (1_000, None)
        );
        // Its first tile out at 303 s, done at 305 s: 5 s, 3 of them waiting.
        assert_eq!(
            run_times(0, Some(300_000), Some(303_000), 305_000),
            (5_000, Some(3_000))
        );
    }
}
