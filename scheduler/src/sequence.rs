//! A sequence job: a range of frames of an animated scene, each rendered as a frame job
//! of its own (its tiles, checks, image and end, like any job).
//!
//! This machine decides which frames start and when, and what the sequence's state is.
//! Frames start lowest first, and only as many at a time as keep the workers busy: a
//! new frame starts when the tiles still waiting in the active frames would no longer
//! fill the workers' credit, so the farm works on one frame at a time except for its
//! tail, frames finish in order (a preview can play while the rest renders), and the
//! coordinator holds the pixels of a few frames however long the sequence. Per frame it
//! keeps a state and the id of the frame job that renders it: 16 bytes.

use std::collections::BTreeSet;

use protocol::{JobId, JobState};

/// The most frames of one sequence rendering at once, whatever the tiles: what a
/// coordinator holds of a sequence is at most this many frames' pixels, and what a
/// worker keeps of one is at most this many frames' scenes.
pub const MAX_ACTIVE_FRAMES: usize = protocol::MAX_ACTIVE_FRAMES;

/// Where one frame stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameState {
    /// Not started yet.
    Pending,
    /// Its frame job is being admitted and stored.
    Starting,
    /// Its frame job is queued or running.
    Active,
    Done,
    /// Its frame job failed: an operator may requeue it.
    Failed,
    /// Cancelled before it was done.
    Cancelled,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Slot {
    state: FrameState,
    /// The frame job that renders or rendered it (0 while none has been admitted).
    job: JobId,
}

/// Counts of frames by state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counts {
    pub pending: u32,
    pub active: u32,
    pub done: u32,
    pub failed: u32,
    pub cancelled: u32,
}

/// One sequence's frames.
#[derive(Clone, Debug)]
pub struct Sequence {
    first: u32,
    slots: Vec<Slot>,
    /// No frame before this index is pending.
    next: usize,
    counts: Counts,
    /// The indices of the frames `Starting` or `Active` (at most
    /// [`MAX_ACTIVE_FRAMES`], unless more were found active at a restart): what is
    /// looked at on every tile handed out, without a walk of every frame.
    running: BTreeSet<usize>,
    /// The frames done one after another from the first.
    prefix: usize,
    /// An operator cancelled it: a frame job admitted after is cancelled at once.
    cancelled: bool,
    paused: bool,
    /// Some frame has started (the sequence is running, not queued).
    started: bool,
}

impl Sequence {
    /// Frames `first..=last`, all pending. `first` is at least 1 and at most `last`.
    pub fn new(first: u32, last: u32) -> Sequence {
        assert!(first >= 1 && first <= last, "a sequence has frames");
        let n = (last - first) as usize + 1;
        Sequence {
            first,
            slots: vec![
                Slot {
                    state: FrameState::Pending,
                    job: 0,
                };
                n
            ],
            next: 0,
            counts: Counts {
                pending: n as u32,
                ..Counts::default()
            },
            running: BTreeSet::new(),
            prefix: 0,
            cancelled: false,
            paused: false,
            started: false,
        }
    }

    pub fn first(&self) -> u32 {
        self.first
    }

    pub fn last(&self) -> u32 {
        self.first + self.slots.len() as u32 - 1
    }

    pub fn len(&self) -> u32 {
        self.slots.len() as u32
    }

    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    pub fn counts(&self) -> Counts {
        self.counts
    }

    pub fn paused(&self) -> bool {
        self.paused
    }

    /// The state of `frame`, if the sequence has it.
    pub fn frame(&self, frame: u32) -> Option<FrameState> {
        self.index(frame).map(|i| self.slots[i].state)
    }

    /// The frame job that renders or rendered `frame`, once one was admitted.
    pub fn job(&self, frame: u32) -> Option<JobId> {
        self.index(frame)
            .map(|i| self.slots[i].job)
            .filter(|&j| j != 0)
    }

    /// The frame jobs queued or running, with their frames.
    pub fn active(&self) -> impl Iterator<Item = (u32, JobId)> + '_ {
        self.running
            .iter()
            .map(|&i| (i, self.slots[i]))
            .filter(|(_, s)| s.state == FrameState::Active)
            .map(|(i, s)| (self.first + i as u32, s.job))
    }

    /// How many frames are being admitted (their jobs not yet stored).
    pub fn starting(&self) -> usize {
        self.running
            .iter()
            .filter(|&&i| self.slots[i].state == FrameState::Starting)
            .count()
    }

    /// The frames in `state`, lowest first, with their jobs.
    pub fn frames_in(&self, state: FrameState) -> impl Iterator<Item = (u32, JobId)> + '_ {
        self.slots
            .iter()
            .enumerate()
            .filter(move |(_, s)| s.state == state)
            .map(|(i, s)| (self.first + i as u32, s.job))
    }

    /// The frames done, lowest first, with their jobs.
    pub fn done(&self) -> impl Iterator<Item = (u32, JobId)> + '_ {
        self.frames_in(FrameState::Done)
    }

    /// The frames done one after another from the first: what a preview can play.
    pub fn done_prefix(&self) -> u32 {
        self.prefix as u32
    }

    fn index(&self, frame: u32) -> Option<usize> {
        let i = frame.checked_sub(self.first)? as usize;
        (i < self.slots.len()).then_some(i)
    }

    fn set(&mut self, i: usize, state: FrameState) {
        let old = self.slots[i].state;
        if old == state {
            return;
        }
        *self.count_mut(old) -= 1;
        *self.count_mut(state) += 1;
        if matches!(state, FrameState::Starting | FrameState::Active) {
            self.running.insert(i);
        } else {
            self.running.remove(&i);
        }
        if state == FrameState::Pending {
            self.next = self.next.min(i);
        }
        self.slots[i].state = state;
        if state != FrameState::Done {
            self.prefix = self.prefix.min(i);
        }
        while self.prefix < self.slots.len() && self.slots[self.prefix].state == FrameState::Done {
            self.prefix += 1;
        }
    }

    fn count_mut(&mut self, state: FrameState) -> &mut u32 {
        match state {
            FrameState::Pending => &mut self.counts.pending,
            FrameState::Starting | FrameState::Active => &mut self.counts.active,
            FrameState::Done => &mut self.counts.done,
            FrameState::Failed => &mut self.counts.failed,
            FrameState::Cancelled => &mut self.counts.cancelled,
        }
    }

    /// The frames to start now, lowest first, marked `Starting`: `waiting` is the tiles
    /// of the active frames not yet handed out, `credit` the tiles the workers may hold
    /// at once, `tiles` a frame's tiles. A frame starts when nothing runs, or when what
    /// waits would leave some credit idle; at most [`MAX_ACTIVE_FRAMES`] run.
    pub fn to_start(&mut self, mut waiting: u64, credit: u64, tiles: u64) -> Vec<u32> {
        let mut start = Vec::new();
        if self.cancelled || self.paused {
            return start;
        }
        while self.running.len() < MAX_ACTIVE_FRAMES
            && (self.running.is_empty() || waiting < credit.max(1))
        {
            while self.next < self.slots.len() && self.slots[self.next].state != FrameState::Pending
            {
                self.next += 1;
            }
            let Some(i) = (self.next < self.slots.len()).then_some(self.next) else {
                break;
            };
            self.set(i, FrameState::Starting);
            self.started = true;
            start.push(self.first + i as u32);
            waiting += tiles;
        }
        start
    }

    /// The frame job of a starting frame is stored as `job`. Returns whether it must be
    /// cancelled at once (the sequence was cancelled meanwhile).
    pub fn started(&mut self, frame: u32, job: JobId) -> bool {
        let Some(i) = self.index(frame) else {
            return true;
        };
        if self.slots[i].state != FrameState::Starting {
            return true;
        }
        self.slots[i].job = job;
        self.set(i, FrameState::Active);
        self.cancelled
    }

    /// A starting frame's job could not be admitted or stored: it waits again (or is
    /// cancelled, if the sequence was).
    pub fn start_failed(&mut self, frame: u32) {
        if let Some(i) = self.index(frame) {
            if self.slots[i].state == FrameState::Starting {
                let state = if self.cancelled {
                    FrameState::Cancelled
                } else {
                    FrameState::Pending
                };
                self.set(i, state);
            }
        }
    }

    /// The frame job `job` ended as `state`. Returns whether it was the frame's job
    /// (an older job of a requeued frame changes nothing).
    pub fn ended(&mut self, frame: u32, job: JobId, state: JobState) -> bool {
        let Some(i) = self.index(frame) else {
            return false;
        };
        if self.slots[i].job != job || self.slots[i].state != FrameState::Active {
            return false;
        }
        let new = match state {
            JobState::Done => FrameState::Done,
            JobState::Failed => FrameState::Failed,
            JobState::Cancelled => FrameState::Cancelled,
            JobState::Queued | JobState::Running | JobState::Waiting => return false,
        };
        self.set(i, new);
        true
    }

    /// A frame's state as found on disk at startup: its latest frame job and that
    /// job's state (`Queued`/`Running`: it is active and resumes).
    pub fn restore(&mut self, frame: u32, job: JobId, state: JobState) {
        let Some(i) = self.index(frame) else {
            return;
        };
        if job < self.slots[i].job {
            return;
        }
        self.slots[i].job = job;
        self.started = true;
        self.set(
            i,
            match state {
                JobState::Queued | JobState::Running | JobState::Waiting => FrameState::Active,
                JobState::Done => FrameState::Done,
                JobState::Failed => FrameState::Failed,
                JobState::Cancelled => FrameState::Cancelled,
            },
        );
    }

    /// An operator cancels the sequence: frames not started are cancelled; returns the
    /// frame jobs to cancel. A later [`Sequence::requeue`] renders a frame again.
    pub fn cancel(&mut self) -> Vec<JobId> {
        self.cancelled = true;
        for i in 0..self.slots.len() {
            if self.slots[i].state == FrameState::Pending {
                self.set(i, FrameState::Cancelled);
            }
        }
        self.active().map(|(_, job)| job).collect()
    }

    /// An operator pauses (no new frame starts; the frame jobs are paused by the
    /// daemon) or resumes the sequence.
    pub fn set_paused(&mut self, paused: bool) {
        self.paused = paused;
    }

    /// An operator has a failed, cancelled or done frame rendered again, alone: it is
    /// pending again, and goes before the later frames. Returns its old frame job, if
    /// any, which the new one replaces.
    pub fn requeue(&mut self, frame: u32) -> Result<Option<JobId>, String> {
        self.may_requeue(frame)?;
        let Some(i) = self.index(frame) else {
            return Ok(None);
        };
        let old = self.job(frame);
        self.slots[i].job = 0;
        self.set(i, FrameState::Pending);
        self.cancelled = false;
        Ok(old)
    }

    /// Whether [`Sequence::requeue`] would render `frame` again, and if not why.
    pub fn may_requeue(&self, frame: u32) -> Result<(), String> {
        let i = self.index(frame).ok_or_else(|| {
            format!(
                "the sequence has frames {} to {}: there is no frame {frame}",
                self.first,
                self.last()
            )
        })?;
        match self.slots[i].state {
            FrameState::Failed | FrameState::Cancelled | FrameState::Done => Ok(()),
            FrameState::Pending | FrameState::Starting | FrameState::Active => Err(format!(
                "frame {frame} is not rendered yet: only a done, failed or cancelled frame \
                 is requeued"
            )),
        }
    }

    /// What clients see: queued until a frame starts; running while frames are pending
    /// or active; then done (every frame), failed (some frame failed) or cancelled.
    pub fn state(&self) -> JobState {
        let c = self.counts;
        if c.pending + c.active > 0 {
            if self.started && !(self.cancelled && c.active == 0) {
                JobState::Running
            } else if self.cancelled {
                JobState::Cancelled
            } else {
                JobState::Queued
            }
        } else if c.failed > 0 {
            JobState::Failed
        } else if c.cancelled > 0 {
            JobState::Cancelled
        } else {
            JobState::Done
        }
    }

    /// The frames that failed, lowest first, with their jobs (no walk of the frames
    /// when none has).
    pub fn failed(&self) -> impl Iterator<Item = (u32, JobId)> + '_ {
        (self.counts.failed > 0)
            .then(|| self.frames_in(FrameState::Failed))
            .into_iter()
            .flatten()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run_all(s: &mut Sequence, next_job: &mut JobId) {
        // Start and finish frames one window at a time, checking the order.
        let mut last_done = 0;
        loop {
            let frames = s.to_start(0, 4, 10);
            if frames.is_empty() && s.active().count() == 0 {
                break;
            }
            for f in frames {
                *next_job += 1;
                assert!(!s.started(f, *next_job));
            }
            let (f, j) = s.active().next().unwrap();
            assert!(f > last_done, "frames finish in order");
            last_done = f;
            assert!(s.ended(f, j, JobState::Done));
        }
    }

    #[test]
    fn frames_start_lowest_first_only_as_many_as_fill_the_credit() {
        let mut s = Sequence::new(3, 12);
        assert_eq!(s.state(), JobState::Queued);
        // Nothing runs: one frame starts, then more only while what waits is below
        // the credit.
        assert_eq!(s.to_start(0, 25, 10), vec![3, 4, 5]);
        assert_eq!(s.state(), JobState::Running);
        for (f, j) in [(3, 100), (4, 101), (5, 102)] {
            assert!(!s.started(f, j));
        }
        // 30 tiles wait for a credit of 25: nothing more.
        assert!(s.to_start(30, 25, 10).is_empty());
        // A frame's tiles all out: the next starts.
        assert_eq!(s.to_start(20, 25, 10), vec![6]);
        // Never more than the cap, however small the frames.
        assert!(!s.started(6, 103));
        let more = s.to_start(0, 1000, 1);
        assert_eq!(more.len(), MAX_ACTIVE_FRAMES - 4);
        assert_eq!(more[0], 7);
    }

    #[test]
    fn a_whole_sequence_finishes_frame_after_frame_and_is_done() {
        let mut s = Sequence::new(1, 20);
        let mut job = 0;
        run_all(&mut s, &mut job);
        assert_eq!(s.state(), JobState::Done);
        assert_eq!(s.counts().done, 20);
        assert_eq!(s.done_prefix(), 20);
        assert_eq!(s.job(20), Some(job));
    }

    #[test]
    fn a_failed_frame_fails_the_sequence_until_it_is_requeued_alone() {
        let mut s = Sequence::new(1, 3);
        assert_eq!(s.to_start(0, 1, 10), vec![1]);
        s.started(1, 7);
        assert!(s.ended(1, 7, JobState::Failed));
        let mut job = 7;
        run_all(&mut s, &mut job);
        assert_eq!(s.state(), JobState::Failed);
        assert_eq!(s.failed().collect::<Vec<_>>(), vec![(1, 7)]);
        assert_eq!(s.done_prefix(), 0);
        // Only frame 1 runs again; an end of its old job changes nothing.
        assert_eq!(s.requeue(1), Ok(Some(7)));
        assert_eq!(s.state(), JobState::Running);
        assert_eq!(s.to_start(0, 100, 10), vec![1]);
        s.started(1, 20);
        assert!(!s.ended(1, 7, JobState::Done));
        assert!(s.ended(1, 20, JobState::Done));
        assert_eq!(s.state(), JobState::Done);
        assert_eq!(s.done_prefix(), 3);
        assert!(s.requeue(4).unwrap_err().contains("there is no frame 4"));
    }

    #[test]
    fn cancelling_stops_every_frame_and_a_late_admission_is_cancelled() {
        let mut s = Sequence::new(1, 10);
        assert_eq!(s.to_start(0, 25, 10), vec![1, 2, 3]);
        s.started(1, 1);
        s.started(2, 2);
        // Frame 3's job is still being stored when the cancel comes.
        assert_eq!(s.cancel(), vec![1, 2]);
        assert!(s.to_start(0, 100, 1).is_empty());
        assert!(s.started(3, 3), "admitted after the cancel: cancel it");
        assert_eq!(s.state(), JobState::Running);
        for j in 1..=3 {
            assert!(s.ended(j as u32, j, JobState::Cancelled));
        }
        assert_eq!(s.state(), JobState::Cancelled);
        assert_eq!(s.counts().cancelled, 10);
        // A cancelled frame can still be rendered alone.
        assert_eq!(s.requeue(5), Ok(None));
        assert_eq!(s.to_start(0, 100, 1), vec![5]);
    }

    #[test]
    fn a_cancel_before_any_frame_started_is_final_at_once() {
        let mut s = Sequence::new(1, 4);
        assert!(s.cancel().is_empty());
        assert_eq!(s.state(), JobState::Cancelled);
    }

    #[test]
    fn a_refused_admission_puts_the_frame_back_first_in_line() {
        let mut s = Sequence::new(1, 5);
        assert_eq!(s.to_start(0, 25, 10), vec![1, 2, 3]);
        s.start_failed(2);
        assert_eq!(s.frame(2), Some(FrameState::Pending));
        s.started(1, 1);
        s.started(3, 3);
        assert_eq!(s.to_start(20, 25, 10), vec![2]);
    }

    #[test]
    fn a_paused_sequence_starts_nothing() {
        let mut s = Sequence::new(1, 5);
        s.set_paused(true);
        assert!(s.to_start(0, 25, 10).is_empty());
        s.set_paused(false);
        assert_eq!(s.to_start(0, 5, 10), vec![1]);
    }

    #[test]
    fn a_restored_sequence_resumes_where_it_stood() {
        let mut s = Sequence::new(1, 6);
        s.restore(1, 10, JobState::Done);
        s.restore(2, 11, JobState::Failed);
        s.restore(2, 14, JobState::Done); // requeued later: the latest job counts
        s.restore(2, 9, JobState::Failed); // an older one does not
        s.restore(3, 12, JobState::Running);
        assert_eq!(s.counts().done, 2);
        assert_eq!(s.counts().active, 1);
        assert_eq!(s.job(2), Some(14));
        assert_eq!(s.state(), JobState::Running);
        assert_eq!(s.to_start(10, 1, 10), Vec::<u32>::new());
        assert!(s.ended(3, 12, JobState::Done));
        assert_eq!(s.to_start(0, 1, 10), vec![4]);
        assert_eq!(s.done_prefix(), 3);
    }

    #[test]
    fn a_requeue_of_a_frame_not_rendered_yet_is_refused() {
        let mut s = Sequence::new(1, 3);
        assert!(s.requeue(2).unwrap_err().contains("not rendered yet"));
    }

    /// Counts, the prefix and the running set as a walk of the frames finds them.
    fn check(s: &Sequence) {
        let mut c = Counts::default();
        let mut running = 0;
        for slot in &s.slots {
            match slot.state {
                FrameState::Pending => c.pending += 1,
                FrameState::Starting | FrameState::Active => {
                    c.active += 1;
                    running += 1
                }
                FrameState::Done => c.done += 1,
                FrameState::Failed => c.failed += 1,
                FrameState::Cancelled => c.cancelled += 1,
            }
        }
        assert_eq!(s.counts(), c);
        assert_eq!(s.running.len(), running);
        let prefix = s
            .slots
            .iter()
            .take_while(|x| x.state == FrameState::Done)
            .count();
        assert_eq!(s.done_prefix() as usize, prefix);
        assert!(s.slots[..s.next.min(s.slots.len())]
            .iter()
            .all(|x| x.state != FrameState::Pending));
    }

    proptest::proptest! {
        #[test]
        fn any_order_of_events_keeps_the_counts_and_the_order_of_starts(
            ops in proptest::collection::vec((0u8..7, 0u32..12, 0u64..40), 1..200),
        ) {
            let mut s = Sequence::new(1, 10);
            let mut next_job = 100;
            for (op, frame, n) in ops {
                match op {
                    0 => {
                        let before = s.running.len();
                        let started = s.to_start(n, 20, 5);
                        assert!(s.running.len() <= MAX_ACTIVE_FRAMES.max(before));
                        // Lowest first: no pending frame is left below one started.
                        if let Some(&last) = started.last() {
                            assert!((1..last).all(|f| s.frame(f) != Some(FrameState::Pending)));
                        }
                    }
                    1 => {
                        if s.frame(frame) == Some(FrameState::Starting) {
                            next_job += 1;
                            s.started(frame, next_job);
                        }
                    }
                    2 => s.start_failed(frame),
                    3 => {
                        if let Some(job) = s.job(frame) {
                            let state = [JobState::Done, JobState::Failed, JobState::Cancelled]
                                [(n % 3) as usize];
                            s.ended(frame, job, state);
                        }
                    }
                    4 => {
                        let _ = s.requeue(frame);
                    }
                    5 => {
                        if n % 5 == 0 {
                            s.cancel();
                        }
                    }
                    _ => s.set_paused(n % 2 == 0),
                }
                check(&s);
                // Final only when nothing is pending or active.
                let c = s.counts();
                assert_eq!(s.state().is_final(), c.pending + c.active == 0);
            }
        }
    }
}
