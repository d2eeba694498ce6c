//! The real decision core, metered: the time each kind of input takes in it and the
//! heap it holds, as the report gives them. Measuring wraps the core without changing
//! what it is fed or returns, so it stands apart from the engine that feeds it.

use std::time::{Duration, Instant};

use protocol::JobId;

use super::{live_bytes, EventCost};
use crate::farm::{Effect, Farm, Input, TilePlan};
use crate::lifecycle;
use crate::tiles::{Action, Event, Millis};

pub(super) const EVENT_KINDS: [&str; 24] = [
    "Timeout",
    "WorkerJoined",
    "Heartbeat",
    "WorkerLeft",
    "WorkerDraining",
    "JobSubmitted",
    "TileDone",
    "TileFailed",
    "CancelJob",
    "StorageUnavailable",
    "StorageAvailable",
    "TileToConfirm",
    "Quarantine",
    "WorkerPace",
    "PauseJob",
    "ResumeJob",
    "SetPriority",
    "DisableMachine",
    "EnableMachine",
    "RequeueTiles",
    "Interactive",
    "Continue",
    "RequireTags",
    "WorkerTags",
];

fn kind_of(event: &Event) -> usize {
    match event {
        Event::Timeout => 0,
        Event::WorkerJoined { .. } => 1,
        Event::Heartbeat { .. } => 2,
        Event::WorkerLeft { .. } => 3,
        Event::WorkerDraining { .. } => 4,
        Event::JobSubmitted { .. } => 5,
        Event::TileDone { .. } => 6,
        Event::TileFailed { .. } => 7,
        Event::CancelJob { .. } => 8,
        Event::StorageUnavailable => 9,
        Event::StorageAvailable => 10,
        Event::TileToConfirm { .. } => 11,
        Event::Quarantine { .. } => 12,
        Event::WorkerPace { .. } => 13,
        Event::PauseJob { .. } => 14,
        Event::ResumeJob { .. } => 15,
        Event::SetPriority { .. } => 16,
        Event::DisableMachine { .. } => 17,
        Event::EnableMachine { .. } => 18,
        Event::RequeueTiles { .. } => 19,
        Event::Interactive { .. } => 20,
        Event::Continue => 21,
        Event::RequireTags { .. } => 22,
        Event::WorkerTags { .. } => 23,
    }
}

/// Heap bytes of the effects returned: the caller's, not the core's.
fn heap_of(effects: &Vec<Effect>) -> i64 {
    let strings: usize = effects
        .iter()
        .map(|e| match e {
            Effect::Tiles(Action::JobFailed { message, .. })
            | Effect::Job(lifecycle::Action::RefuseStored { message, .. }) => message.capacity(),
            Effect::Job(lifecycle::Action::RecordEnd { error, .. }) => {
                error.as_ref().map_or(0, String::capacity)
            }
            Effect::Job(lifecycle::Action::Reply { result: Err(r), .. }) => r.message.capacity(),
            _ => 0,
        })
        .sum();
    (effects.capacity() * std::mem::size_of::<Effect>() + strings) as i64
}

#[derive(Clone, Copy, Default)]
pub(super) struct Cost {
    pub(super) count: u64,
    total: Duration,
    max: Duration,
}

impl Cost {
    fn add(&mut self, took: Duration) {
        self.count += 1;
        self.total += took;
        self.max = self.max.max(took);
    }

    pub(super) fn report(&self, kind: &str) -> EventCost {
        EventCost {
            kind: kind.to_string(),
            count: self.count,
            total: self.total,
            max: self.max,
        }
    }
}

/// The real decision core, with the time spent in it per kind of input and the heap
/// it holds.
pub(super) struct Metered {
    pub(super) core: Farm,
    pub(super) bytes: i64,
    pub(super) peak: i64,
    /// Per kind of input about tiles and workers; the time (`Input::Timeout`) counts
    /// as `Timeout`.
    pub(super) costs: [Cost; EVENT_KINDS.len()],
    pub(super) admit: Cost,
    /// Per kind of input about jobs, in the order first seen, named after the variant
    /// (storage's reports among them).
    pub(super) job_costs: Vec<(String, Cost)>,
}

impl Metered {
    pub(super) fn handle(&mut self, now: Millis, input: Input) -> Vec<Effect> {
        let tiles_kind = match &input {
            Input::Tiles(event) => Some(kind_of(event)),
            Input::Timeout => Some(0),
            Input::Job(_)
            | Input::Storage(_)
            | Input::Pass(_)
            | Input::Sequence(_)
            | Input::Duplicate(_)
            | Input::Quarantine { .. } => None,
        };
        let job_kind = match &input {
            Input::Job(event) => Some(self.job_kind(&format!("{event:?}"))),
            Input::Pass(input) => Some(self.job_kind(&format!("{input:?}"))),
            Input::Sequence(input) => Some(self.job_kind(&format!("{input:?}"))),
            Input::Quarantine { .. } => Some(self.job_kind("Quarantine")),
            Input::Duplicate(_) => Some(self.job_kind("Duplicate")),
            Input::Storage(Ok(())) => Some(self.job_kind("StorageAvailable")),
            Input::Storage(Err(_)) => Some(self.job_kind("StorageUnavailable")),
            Input::Tiles(_) | Input::Timeout => None,
        };
        let before = live_bytes();
        let start = Instant::now();
        let effects = self.core.handle(now, input);
        let took = start.elapsed();
        self.bytes += live_bytes() - before - heap_of(&effects);
        self.peak = self.peak.max(self.bytes);
        if let Some(kind) = tiles_kind {
            self.costs[kind].add(took);
        }
        if let Some(kind) = job_kind {
            self.job_costs[kind].1.add(took);
        }
        effects
    }

    pub(super) fn admit(
        &mut self,
        now: Millis,
        request: &lifecycle::Request,
        plan: TilePlan,
    ) -> Result<JobId, protocol::Refusal> {
        let start = Instant::now();
        let result = self.core.admit(now, request, plan);
        self.admit.add(start.elapsed());
        result
    }

    /// The index in `job_costs` of the input named first in `debug` (its variant).
    fn job_kind(&mut self, debug: &str) -> usize {
        let name: String = debug
            .chars()
            .take_while(char::is_ascii_alphanumeric)
            .collect();
        match self.job_costs.iter().position(|(k, _)| *k == name) {
            Some(index) => index,
            None => {
                self.job_costs.push((name, Cost::default()));
                self.job_costs.len() - 1
            }
        }
    }

    /// Calls about jobs, the admissions included.
    pub(super) fn job_calls(&self) -> u64 {
        self.admit.count + self.job_costs.iter().map(|(_, c)| c.count).sum::<u64>()
    }
}
