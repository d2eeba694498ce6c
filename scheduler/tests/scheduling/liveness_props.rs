// Liveness when heartbeats lie: workers that keep talking but stop rendering, render
// only some tiles, deliver after their leases ran out, or are slow. A small farm in
// virtual time around the real scheduler: every worker heart-beats every second,
// renders its tiles one at a time in the order received, and the daemon's timer calls
// `Timeout` every 100 ms. Results of every third tile are held for confirmation by
// another machine (an audit, optional), the case where a hung machine used to keep
// a job waiting forever.

use std::collections::{BTreeMap, BTreeSet, VecDeque};

use proptest::prelude::*;
use protocol::{JobId, WorkerId};
use scheduler::{Action, Event, Millis, Policy, Scheduler};

const SCENE: [u8; 32] = [7; 32];
const JOB: JobId = 1;
const TICK: Millis = 100;

/// How a simulated worker behaves.
#[derive(Clone, Copy, Debug)]
enum Kind {
    /// Renders each tile in `tile` ms.
    Working { tile: Millis },
    /// Renders like `Working` until `at`, then its render thread hangs for good (its
    /// heartbeats go on).
    HangsAt { tile: Millis, at: Millis },
    /// Renders, but never returns a tile whose number is a multiple of `every`.
    Partial { tile: Millis, every: u32 },
}

impl Kind {
    fn tile_time(self) -> Millis {
        match self {
            Kind::Working { tile } | Kind::HangsAt { tile, .. } | Kind::Partial { tile, .. } => {
                tile
            }
        }
    }
}

struct SimWorker {
    kind: Kind,
    queue: VecDeque<u32>,
    /// The tile being rendered and when it is done.
    current: Option<(u32, Millis)>,
    /// Tiles rendered but kept (a partial worker's swallowed ones).
    swallowed: BTreeSet<u32>,
}

/// What a run did.
#[derive(Debug, Default)]
struct Run {
    done_at: Option<Millis>,
    failed: Option<String>,
    /// When each worker was marked unresponsive, and when it came back.
    marked: BTreeMap<WorkerId, Vec<Millis>>,
    back: BTreeMap<WorkerId, Vec<Millis>>,
    /// Tiles assigned to each worker while it was marked (must stay empty).
    assigned_while_marked: Vec<(WorkerId, u32)>,
}

/// Runs one job of `tiles` tiles on workers of the given kinds (ids 1, 2, ...; each
/// its own machine) until it ends or `limit` ms pass.
fn run(policy: Policy, tiles: u32, kinds: &[Kind], limit: Millis) -> Run {
    let mut s = Scheduler::with_policy(policy);
    let mut workers: BTreeMap<WorkerId, SimWorker> = BTreeMap::new();
    let mut out = Run::default();
    let mut marked: BTreeSet<WorkerId> = BTreeSet::new();
    let mut actions = Vec::new();
    for (i, &kind) in kinds.iter().enumerate() {
        let id = i as WorkerId + 1;
        workers.insert(
            id,
            SimWorker {
                kind,
                queue: VecDeque::new(),
                current: None,
                swallowed: BTreeSet::new(),
            },
        );
        actions.extend(s.handle(
            0,
            Event::WorkerJoined {
                worker: id,
                threads: 1,
                machine: Some(format!("m{id}")),
            },
        ));
    }
    actions.extend(s.handle(
        0,
        Event::JobSubmitted {
            job: JOB,
            priority: 0,
            scene: SCENE,
            tiles,
        },
    ));
    let mut now = 0;
    loop {
        // Carry out what the scheduler asked.
        for action in std::mem::take(&mut actions) {
            match action {
                Action::Assign { worker, tile, .. } => {
                    if marked.contains(&worker) {
                        out.assigned_while_marked.push((worker, tile));
                    }
                    workers.get_mut(&worker).unwrap().queue.push_back(tile);
                }
                Action::CancelOnWorker { worker, .. } => {
                    let w = workers.get_mut(&worker).unwrap();
                    w.queue.clear();
                }
                Action::WorkerUnresponsive { worker, .. } => {
                    marked.insert(worker);
                    out.marked.entry(worker).or_default().push(now);
                }
                Action::WorkerResponsive { worker } => {
                    marked.remove(&worker);
                    out.back.entry(worker).or_default().push(now);
                }
                Action::JobDone { .. } => out.done_at = Some(now),
                Action::JobFailed { message, .. } => out.failed = Some(message),
                Action::DropWorker { worker } => panic!("worker {worker} dropped: it talks"),
                _ => {}
            }
        }
        if out.done_at.is_some() || out.failed.is_some() || now >= limit {
            return out;
        }
        now += TICK;
        // Renders due by now, in worker order; each result then the next tile.
        for (&id, w) in workers.iter_mut() {
            loop {
                if w.current.is_none() {
                    let hung = matches!(w.kind, Kind::HangsAt { at, .. } if now >= at);
                    if hung {
                        break;
                    }
                    let Some(tile) = w.queue.pop_front() else {
                        break;
                    };
                    w.current = Some((tile, now + w.kind.tile_time()));
                }
                let (tile, due) = w.current.expect("set above");
                if due > now {
                    break;
                }
                if matches!(w.kind, Kind::HangsAt { at, .. } if due > at) {
                    // The thread hung while rendering it.
                    break;
                }
                w.current = None;
                if matches!(w.kind, Kind::Partial { every, .. } if tile % every == 0) {
                    w.swallowed.insert(tile);
                    continue;
                }
                let event = if tile % 3 == 0 {
                    Event::TileToConfirm {
                        worker: id,
                        job: JOB,
                        tile,
                        required: false,
                    }
                } else {
                    Event::TileDone {
                        worker: id,
                        job: JOB,
                        tile,
                    }
                };
                actions.extend(s.handle(now, event));
            }
        }
        if now % 1_000 == 0 {
            for &id in workers.keys() {
                actions.extend(s.handle(now, Event::Heartbeat { worker: id }));
            }
        }
        actions.extend(s.handle(now, Event::Timeout));
    }
}

/// The default policy but a short progress timeout, as a test farm sets it.
fn policy(progress_timeout: Millis) -> Policy {
    Policy {
        progress_timeout,
        ..Policy::default()
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// A worker that heart-beats and never returns a tile again, from the start or once
    /// it has rendered a few: the job is done on the working one, within its own
    /// rendering time plus the hung worker's allowance and a lease (leases given before
    /// the job's first tile was measured end by then too); the hung worker is marked
    /// unresponsive and given nothing after.
    #[test]
    fn a_worker_that_talks_but_never_renders_again_delays_a_job_by_a_bounded_time(
        tiles in 12..120u32,
        tile in 20..400 as Millis,
        hang_after in 0..4u64,
        progress_timeout in 1_000..30_000 as Millis,
    ) {
        let kinds = [
            Kind::Working { tile },
            Kind::HangsAt { tile, at: hang_after * 3 * (tile + TICK) },
        ];
        let alone = u64::from(tiles) * (tile + TICK);
        // The allowance is at most 16 times the slowest tile the job measured (a tile
        // waits behind the worker's credit: at most a few tile times).
        let allowance = progress_timeout.max(16 * 8 * (tile + TICK));
        let lease = (3 * 8 * (tile + TICK)).max(1_000);
        let limit = alone + allowance + lease + 10 * (tile + TICK);
        let r = run(policy(progress_timeout), tiles, &kinds, 10 * limit);
        prop_assert!(r.failed.is_none(), "{r:?}");
        let done = r.done_at.expect("the job ends");
        prop_assert!(done <= limit, "done at {done} ms, bound {limit} ms: {r:?}");
        prop_assert!(r.assigned_while_marked.is_empty(), "{r:?}");
        prop_assert!(!r.marked.contains_key(&1), "the working worker was marked: {r:?}");
    }

    /// A worker that swallows some tiles (a render thread stuck on some inputs, the
    /// others fine) is never marked while its other results come, and the job ends.
    #[test]
    fn a_worker_returning_only_some_tiles_is_worked_around(
        tiles in 12..120u32,
        tile in 20..200 as Millis,
        every in 2..6u32,
    ) {
        let kinds = [Kind::Working { tile }, Kind::Partial { tile, every }];
        let r = run(policy(3_000), tiles, &kinds, 3_600_000);
        prop_assert!(r.failed.is_none(), "{r:?}");
        prop_assert!(r.done_at.is_some(), "{r:?}");
        prop_assert!(r.assigned_while_marked.is_empty(), "{r:?}");
    }

    /// Slow workers that make progress (up to ten times slower than the others, their
    /// tiles outlasting the leases the fast one's tiles set) are never marked.
    #[test]
    fn a_slow_worker_making_progress_is_never_marked(
        tiles in 12..120u32,
        tile in 20..400 as Millis,
        slower in 2..10u64,
        progress_timeout in 1_000..30_000 as Millis,
    ) {
        let kinds = [Kind::Working { tile }, Kind::Working { tile: tile * slower }];
        let r = run(policy(progress_timeout), tiles, &kinds, 3_600_000);
        prop_assert!(r.failed.is_none(), "{r:?}");
        prop_assert!(r.done_at.is_some(), "{r:?}");
        prop_assert!(r.marked.is_empty(), "a slow worker was marked: {r:?}");
    }
}

/// The case of the report: every result of the working worker is to be confirmed by
/// another machine (optional audits), and the only other machine's render thread hangs
/// from the start while it heart-beats. Without copies of stragglers, its leases run
/// out at the initial lease (60 s); it is marked unresponsive then, the held
/// results are accepted (no other machine may confirm them) and the job ends. Its first
/// result, a late one, makes it responsive again.
#[test]
fn a_hung_worker_is_marked_and_responsive_again_with_its_first_late_result() {
    let mut s = Scheduler::with_policy(Policy {
        speculate: false,
        ..policy(5_000)
    });
    let mut assigned: BTreeMap<WorkerId, Vec<u32>> = BTreeMap::new();
    let record = |actions: Vec<Action>, assigned: &mut BTreeMap<WorkerId, Vec<u32>>| {
        let mut other = Vec::new();
        for a in actions {
            match a {
                Action::Assign { worker, tile, .. } => {
                    assigned.entry(worker).or_default().push(tile)
                }
                a => other.push(a),
            }
        }
        other
    };
    for worker in [1, 2] {
        record(
            s.handle(
                0,
                Event::WorkerJoined {
                    worker,
                    threads: 1,
                    machine: Some(format!("m{worker}")),
                },
            ),
            &mut assigned,
        );
    }
    record(
        s.handle(
            0,
            Event::JobSubmitted {
                job: JOB,
                priority: 0,
                scene: SCENE,
                tiles: 40,
            },
        ),
        &mut assigned,
    );
    // Worker 1 renders a tile every 100 ms; worker 2 never returns anything.
    let mut now = 0;
    let mut marked_at = None;
    let mut done_at = None;
    while done_at.is_none() && now < 120_000 {
        now += 100;
        let next = assigned.get_mut(&1).and_then(|q| {
            if q.is_empty() {
                None
            } else {
                Some(q.remove(0))
            }
        });
        let mut actions = Vec::new();
        if let Some(tile) = next {
            actions.extend(s.handle(
                now,
                Event::TileToConfirm {
                    worker: 1,
                    job: JOB,
                    tile,
                    required: false,
                },
            ));
        }
        if now % 1_000 == 0 {
            actions.extend(s.handle(now, Event::Heartbeat { worker: 1 }));
            actions.extend(s.handle(now, Event::Heartbeat { worker: 2 }));
        }
        actions.extend(s.handle(now, Event::Timeout));
        for a in record(actions, &mut assigned) {
            match a {
                Action::WorkerUnresponsive { worker, silent } => {
                    assert_eq!(worker, 2);
                    assert!(silent > 5_000, "{silent}");
                    marked_at.get_or_insert(now);
                    assert!(s.is_unresponsive(2));
                }
                Action::JobDone { .. } => done_at = Some(now),
                Action::DropWorker { .. } | Action::JobFailed { .. } => panic!("{a:?}"),
                _ => {}
            }
        }
    }
    let marked_at = marked_at.expect("worker 2 was marked");
    let done_at = done_at.expect("the job ended");
    // Its leases, given before any tile was measured, ran out at the initial lease
    // (60 s); it had been silent for longer than 5 s by then.
    assert!(
        (60_000..=61_000).contains(&marked_at),
        "marked at {marked_at}"
    );
    assert!(
        (marked_at..=marked_at + 1_000).contains(&done_at),
        "done at {done_at}, marked at {marked_at}"
    );
    let held = assigned[&2].clone();
    assert!(!held.is_empty(), "worker 2 was given tiles before it hung");
    // The job is over: a second one, and worker 2's late result of the first makes it
    // responsive again, and it takes tiles of the second.
    s.handle(
        now,
        Event::JobSubmitted {
            job: 2,
            priority: 0,
            scene: SCENE,
            tiles: 4,
        },
    );
    let actions = s.handle(
        now + 100,
        Event::TileDone {
            worker: 2,
            job: JOB,
            tile: held[0],
        },
    );
    assert!(
        actions.contains(&Action::WorkerResponsive { worker: 2 }),
        "{actions:?}"
    );
    assert!(!s.is_unresponsive(2));
}

/// Full verification with two machines, one of them hung: no machine may confirm the
/// working one's results, so the job fails after the stall timeout, and its message
/// names the hung machine apart, as unresponsive, rather than saying no other machine
/// is connected.
#[test]
fn a_job_only_an_unresponsive_machine_could_confirm_fails_naming_it() {
    let mut s = Scheduler::with_policy(Policy {
        speculate: false,
        ..policy(5_000)
    });
    let mut given: Vec<(WorkerId, u32)> = Vec::new();
    let take = |actions: Vec<Action>, given: &mut Vec<(WorkerId, u32)>| -> Vec<Action> {
        let mut rest = Vec::new();
        for a in actions {
            match a {
                Action::Assign { worker, tile, .. } => given.push((worker, tile)),
                a => rest.push(a),
            }
        }
        rest
    };
    take(
        s.handle(
            0,
            Event::JobSubmitted {
                job: JOB,
                priority: 0,
                scene: SCENE,
                tiles: 4,
            },
        ),
        &mut given,
    );
    for worker in [2, 1] {
        take(
            s.handle(
                0,
                Event::WorkerJoined {
                    worker,
                    threads: 1,
                    machine: Some(format!("m{worker}")),
                },
            ),
            &mut given,
        );
    }
    let mut failed = None;
    let mut now = 0;
    while failed.is_none() && now < 200_000 {
        now += 100;
        let mut actions = Vec::new();
        // Worker 1 returns what it is given at once, each result to be confirmed.
        for (worker, tile) in std::mem::take(&mut given) {
            if worker == 1 {
                actions.extend(s.handle(
                    now,
                    Event::TileToConfirm {
                        worker,
                        job: JOB,
                        tile,
                        required: true,
                    },
                ));
            }
        }
        if now % 1_000 == 0 {
            actions.extend(s.handle(now, Event::Heartbeat { worker: 1 }));
            actions.extend(s.handle(now, Event::Heartbeat { worker: 2 }));
        }
        actions.extend(s.handle(now, Event::Timeout));
        for a in take(actions, &mut given) {
            if let Action::JobFailed { message, .. } = a {
                failed = Some((now, message));
            }
        }
    }
    let (at, message) = failed.expect("the job failed");
    assert!(s.is_unresponsive(2));
    assert!(
        message.contains("awaits confirmation by another machine")
            && message
                .ends_with("; not counted, unresponsive (leases ran out without a result): m2"),
        "{message}"
    );
    // Its leases ran out at 60 s (no tile measured: every result is held), it was
    // marked then, and the stall ran its 30 s.
    assert!((90_000..=92_000).contains(&at), "failed at {at}");
}
