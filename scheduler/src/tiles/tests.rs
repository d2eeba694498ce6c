//! The tile scheduler's policy rule by rule: scripted events on a virtual clock, and
//! the actions each must give.

use super::*;

const SCENE_A: SceneHash = [1; 32];
const SCENE_B: SceneHash = [2; 32];

fn assigns(actions: &[Action]) -> Vec<(WorkerId, JobId, u32)> {
    actions
        .iter()
        .filter_map(|a| match *a {
            Action::Assign { worker, job, tile } => Some((worker, job, tile)),
            _ => None,
        })
        .collect()
}

fn failure(actions: &[Action], job: JobId) -> Option<&str> {
    actions.iter().find_map(|a| match a {
        Action::JobFailed { job: j, message } if *j == job => Some(message.as_str()),
        _ => None,
    })
}

fn submit(
    s: &mut Scheduler,
    job: JobId,
    priority: i32,
    scene: SceneHash,
    tiles: u32,
) -> Vec<Action> {
    s.handle(
        0,
        Event::JobSubmitted {
            job,
            priority,
            scene,
            tiles,
        },
    )
}

fn join_at(
    s: &mut Scheduler,
    now: Millis,
    worker: WorkerId,
    threads: u32,
    name: Option<&str>,
) -> Vec<Action> {
    s.handle(
        now,
        Event::WorkerJoined {
            worker,
            threads,
            machine: name.map(str::to_string),
        },
    )
}

fn join(s: &mut Scheduler, worker: WorkerId, threads: u32) -> Vec<Action> {
    join_at(s, 0, worker, threads, None)
}

fn fail(s: &mut Scheduler, now: Millis, worker: WorkerId, job: JobId, tile: u32) -> Vec<Action> {
    s.handle(
        now,
        Event::TileFailed {
            worker,
            job,
            tile,
            message: "boom".into(),
        },
    )
}

/// A machine that reports failures on a job's tiles is blocked from the job, also
/// when it comes back under the same name (a service restarted by its supervisor),
/// and never gets the tiles it failed on; a machine of another name gets them.
#[test]
fn reported_failures_block_the_machine_name_across_reconnections() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 6);
    let first = join_at(&mut s, 0, 1, 1, Some("flaky"));
    assert_eq!(assigns(&first), vec![(1, 1, 0), (1, 1, 1)]);
    fail(&mut s, 0, 1, 1, 0);
    fail(&mut s, 0, 1, 1, 1);
    s.handle(0, Event::WorkerLeft { worker: 1 });
    let second = join_at(&mut s, 0, 2, 1, Some("flaky"));
    assert!(
        assigns(&second).is_empty(),
        "blocked after 2 failures: {second:?}"
    );
    // A healthy machine gets the tiles put back first: tile 2, which "flaky" held
    // when it left, then the failed ones.
    let healthy = join_at(&mut s, 0, 3, 1, Some("healthy"));
    assert_eq!(assigns(&healthy), vec![(3, 1, 2), (3, 1, 1)]);
    // Unnamed workers are each their own machine.
    let anon = join(&mut s, 4, 1);
    assert_eq!(assigns(&anon), vec![(4, 1, 0), (4, 1, 3)]);
}

/// Losing a connection is not proof a worker is bad: a worker killed while holding
/// tiles and restarted under its name, again and again, is never blocked, gets its
/// lost tiles back, and the job finishes. With one worker and with two.
#[test]
fn a_worker_killed_and_rejoining_under_its_name_5_times_finishes_the_job() {
    for workers in [1, 2] {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 12);
        let names = ["a", "b"];
        let mut next_id = 1;
        let mut ids = Vec::new();
        for name in &names[..workers] {
            join_at(&mut s, 0, next_id, 1, Some(name));
            ids.push(next_id);
            next_id += 1;
        }
        let mut now = 0;
        for _kill in 0..5 {
            now += 100;
            for i in 0..workers {
                assert_eq!(s.held_by(ids[i]), 2, "{workers} workers");
                let left = s.handle(now, Event::WorkerLeft { worker: ids[i] });
                assert!(failure(&left, 1).is_none(), "{left:?}");
                let back = join_at(&mut s, now, next_id, 1, Some(names[i]));
                assert_eq!(assigns(&back).len(), 2, "not blocked: {back:?}");
                ids[i] = next_id;
                next_id += 1;
            }
        }
        // Now they render everything.
        let mut done = false;
        while !done {
            now += 100;
            for &worker in &ids {
                let held: Vec<(JobId, u32)> = s.workers[&worker].holding.iter().copied().collect();
                for (job, tile) in held {
                    let actions = s.handle(now, Event::TileDone { worker, job, tile });
                    done |= actions.contains(&Action::JobDone { job: 1 });
                }
            }
        }
        assert!(!s.is_active(1));
    }
}

/// A tile that takes down every worker it reaches is lost with each one; at
/// `max_losses` its job fails with a message that says so.
#[test]
fn a_tile_lost_with_its_worker_max_losses_times_fails_its_job() {
    let max = Policy::default().max_losses;
    let mut s = Scheduler::with_policy(Policy {
        speculate: false,
        ..Policy::default()
    });
    submit(&mut s, 1, 0, SCENE_A, 1);
    for worker in 1..max as WorkerId {
        assert_eq!(assigns(&join(&mut s, worker, 1)), vec![(worker, 1, 0)]);
        let left = s.handle(0, Event::WorkerLeft { worker });
        assert!(failure(&left, 1).is_none(), "loss {worker}: {left:?}");
    }
    join(&mut s, max as WorkerId, 1);
    let left = s.handle(
        0,
        Event::WorkerLeft {
            worker: max as WorkerId,
        },
    );
    assert_eq!(
        failure(&left, 1),
        Some(
            "tile 0 was lost with its worker 8 times (a tile that crashes workers, or \
             workers that keep losing their connection)"
        )
    );
    assert!(!s.is_active(1));
}

/// A worker dropped for silence loses its tiles the same way: one loss each, no
/// block, no attempt; the same name gets the tiles back when it rejoins.
#[test]
fn a_network_cut_past_the_heartbeat_timeout_blocks_nobody() {
    let policy = Policy::default();
    let mut s = Scheduler::with_policy(policy);
    submit(&mut s, 1, 0, SCENE_A, 2);
    join_at(&mut s, 0, 1, 1, Some("far"));
    let mut now = 0;
    let dropped = loop {
        now += policy.wake_interval;
        let actions = s.handle(now, Event::Timeout);
        if !actions.is_empty() {
            break actions;
        }
    };
    assert_eq!(dropped, vec![Action::DropWorker { worker: 1 }]);
    assert_eq!(now, 6_000);
    let job = &s.jobs[&1];
    assert!(job.failures.is_empty() && job.blocked.is_empty());
    assert_eq!(job.losses, BTreeMap::from([(0, 1), (1, 1)]));
    let back = join_at(&mut s, now, 2, 1, Some("far"));
    assert_eq!(assigns(&back), vec![(2, 1, 1), (2, 1, 0)]);
}

/// The coordinator stopped for 7 s (no heartbeat read meanwhile) drops nobody: the
/// gap counts as one wake interval, and the heartbeats waiting in the sockets are
/// read before anyone comes near the timeout. Leases do not run out either.
#[test]
fn a_pause_of_7_s_drops_nobody() {
    let policy = Policy {
        initial_lease: 6_000,
        ..Policy::default()
    };
    let mut s = Scheduler::with_policy(policy);
    submit(&mut s, 1, 0, SCENE_A, 4);
    join(&mut s, 1, 1);
    join(&mut s, 2, 1);
    for now in [1_000, 2_000, 3_000] {
        for worker in [1, 2] {
            s.handle(now, Event::Heartbeat { worker });
        }
        assert!(s.handle(now, Event::Timeout).is_empty());
    }
    // Stopped at 3 s, running again at 10 s: the timer fires first.
    let woken = s.handle(10_000, Event::Timeout);
    assert!(woken.is_empty(), "{woken:?}");
    assert_eq!(s.counters(), Counters::default());
    for worker in [1, 2] {
        s.handle(10_000, Event::Heartbeat { worker });
        assert_eq!(s.held_by(worker), 2);
    }
    // The clock goes on from there: silence counts again.
    assert_eq!(s.next_deadline(), Some(11_000));
    assert!(s.handle(11_000, Event::Timeout).is_empty());
    // A real silence is still caught: 1 s counted for the pause, then 4 s of timeouts.
    let mut dropped = Vec::new();
    for now in (12_000..=20_000).step_by(1_000) {
        s.handle(now, Event::Heartbeat { worker: 2 });
        dropped.extend(s.handle(now, Event::Timeout));
    }
    assert_eq!(dropped.first(), Some(&Action::DropWorker { worker: 1 }));
}

/// The same pause without the coordinator's regular wake-ups would look the same to
/// it: a gap is a pause only beyond the threshold, and at most a wake interval of
/// it counts.
#[test]
fn only_gaps_beyond_the_pause_threshold_are_pauses() {
    let policy = Policy::default();
    let mut s = Scheduler::with_policy(policy);
    join(&mut s, 1, 1);
    // Gaps up to the threshold count in full: 5 s of them, then one more ms.
    s.handle(2_000, Event::Timeout);
    s.handle(4_000, Event::Timeout);
    assert!(s.handle(5_000, Event::Timeout).is_empty());
    assert_eq!(
        s.handle(5_001, Event::Timeout),
        vec![Action::DropWorker { worker: 1 }]
    );
    // A time from before is taken as the last one.
    let mut s = Scheduler::with_policy(policy);
    join_at(&mut s, 0, 1, 1, None);
    s.handle(4_000, Event::Heartbeat { worker: 1 });
    s.handle(3_000, Event::Timeout);
    assert_eq!(s.next_deadline(), Some(5_000));
}

/// While a worker is connected the daemon is told to call at least every wake
/// interval, earlier for a heartbeat timeout or a lease deadline; with none,
/// nothing waits on time.
#[test]
fn next_deadline_is_the_earliest_thing_that_waits_on_time() {
    let policy = Policy {
        initial_lease: 1_500,
        ..Policy::default()
    };
    let mut s = Scheduler::with_policy(policy);
    assert_eq!(s.next_deadline(), None);
    submit(&mut s, 1, 0, SCENE_A, 1);
    assert_eq!(s.next_deadline(), None, "a job without workers just waits");
    join_at(&mut s, 100, 1, 1, None);
    assert_eq!(
        s.next_deadline(),
        Some(1_000),
        "a wake interval after the first call"
    );
    s.handle(1_000, Event::Timeout);
    assert_eq!(s.next_deadline(), Some(1_600), "the lease of tile 0");
    s.handle(1_600, Event::Timeout);
    assert_eq!(s.next_deadline(), Some(2_600));
    // Messages more often than the wake interval do not put the timeout off.
    for now in (1_800..=2_400).step_by(200) {
        s.handle(now, Event::Heartbeat { worker: 1 });
        assert_eq!(s.next_deadline(), Some(2_600), "after a heartbeat at {now}");
    }
    s.handle(2_600, Event::Heartbeat { worker: 1 });
    s.handle(2_600, Event::WorkerLeft { worker: 1 });
    assert_eq!(s.next_deadline(), None);
    // A heartbeat timeout shorter than the wake interval.
    let mut s = Scheduler::with_policy(Policy {
        heartbeat_timeout: 300,
        ..policy
    });
    join_at(&mut s, 0, 1, 1, None);
    assert_eq!(s.next_deadline(), Some(301));
    assert_eq!(
        s.handle(301, Event::Timeout),
        vec![Action::DropWorker { worker: 1 }]
    );
    assert_eq!(s.next_deadline(), None);
}

/// A job whose waiting tiles failed on every connected machine fails after the
/// stall timeout, with a message naming the tile and the machines; a job without
/// any worker connected just waits; a new machine ends the stall.
#[test]
fn a_job_no_connected_worker_may_take_fails_after_the_stall_timeout() {
    let policy = Policy {
        speculate: false,
        ..Policy::default()
    };
    let mut s = Scheduler::with_policy(policy);
    submit(&mut s, 1, 0, SCENE_A, 1);
    join_at(&mut s, 0, 1, 1, Some("a"));
    fail(&mut s, 0, 1, 1, 0);
    join_at(&mut s, 0, 2, 1, Some("b"));
    fail(&mut s, 0, 2, 1, 0);
    // Nobody may take tile 0 now. The stall starts at the first timeout.
    let heartbeat = |s: &mut Scheduler, now| {
        for worker in [1, 2] {
            s.handle(now, Event::Heartbeat { worker });
        }
    };
    let mut now = 0;
    let failed = loop {
        now += 1_000;
        heartbeat(&mut s, now);
        let actions = s.handle(now, Event::Timeout);
        if !actions.is_empty() {
            break actions;
        }
    };
    assert_eq!(now, 1_000 + policy.stall_timeout);
    assert_eq!(
        failed,
        vec![
            Action::ForgetScene {
                worker: 1,
                scene: SCENE_A
            },
            Action::ForgetScene {
                worker: 2,
                scene: SCENE_A
            },
            Action::JobFailed {
                job: 1,
                message: "no connected worker may render tile 0: it failed on every one \
                          of them (a, b)"
                    .into()
            },
        ]
    );

    // Without any worker, the same job waits, however long.
    let mut s = Scheduler::with_policy(policy);
    submit(&mut s, 1, 0, SCENE_A, 1);
    join_at(&mut s, 0, 1, 1, Some("a"));
    fail(&mut s, 0, 1, 1, 0);
    s.handle(10, Event::Timeout);
    assert!(s.jobs[&1].stalled_since.is_some());
    s.handle(20, Event::WorkerLeft { worker: 1 });
    assert_eq!(s.jobs[&1].stalled_since, None);
    assert_eq!(s.next_deadline(), None);
    assert!(s.handle(100_000, Event::Timeout).is_empty());
    assert!(s.is_active(1));
    // The stall counts again from when a worker that may not take it is back...
    join_at(&mut s, 100_000, 2, 1, Some("a"));
    s.handle(101_000, Event::Timeout);
    assert!(s.jobs[&1].stalled_since.is_some());
    // ...and ends when a machine that may take it joins: it gets the tile.
    let fresh = join_at(&mut s, 101_500, 3, 1, Some("b"));
    assert_eq!(assigns(&fresh), vec![(3, 1, 0)]);
    s.handle(101_500, Event::Heartbeat { worker: 2 });
    s.handle(102_000, Event::Timeout);
    assert_eq!(s.jobs[&1].stalled_since, None);
}

/// Machines blocked from a job (too many of its tiles failed on them) stall it
/// too, and the message says so.
#[test]
fn a_job_every_connected_machine_is_blocked_from_fails_with_the_reason() {
    let policy = Policy {
        speculate: false,
        stall_timeout: 0,
        ..Policy::default()
    };
    let done = |s: &mut Scheduler, worker, tile| {
        s.handle(
            0,
            Event::TileDone {
                worker,
                job: 1,
                tile,
            },
        )
    };
    // "a" fails tiles 0 and 1 and is blocked; it leaves with tile 2, which goes
    // back to the head of the queue, and comes back.
    let mut s = Scheduler::with_policy(policy);
    submit(&mut s, 1, 0, SCENE_A, 4);
    join_at(&mut s, 0, 1, 1, Some("a"));
    assert_eq!(assigns(&fail(&mut s, 0, 1, 1, 0)), vec![(1, 1, 2)]);
    assert!(assigns(&fail(&mut s, 0, 1, 1, 1)).is_empty());
    s.handle(0, Event::WorkerLeft { worker: 1 });
    assert!(assigns(&join_at(&mut s, 0, 2, 1, Some("a"))).is_empty());
    let timeout = s.handle(0, Event::Timeout);
    assert_eq!(
        failure(&timeout, 1),
        Some(
            "no connected worker may render tile 2: every one of them is blocked from \
             the job after failing 2 of its tiles (a)"
        )
    );

    // Tile 3 failed on "b", and the other machine (unnamed, so named by its
    // connection) is blocked.
    let mut s = Scheduler::with_policy(policy);
    submit(&mut s, 1, 0, SCENE_A, 4);
    join(&mut s, 1, 1);
    assert_eq!(assigns(&fail(&mut s, 0, 1, 1, 0)), vec![(1, 1, 2)]);
    assert!(assigns(&fail(&mut s, 0, 1, 1, 1)).is_empty());
    assert!(assigns(&done(&mut s, 1, 2)).is_empty());
    let b = join_at(&mut s, 0, 2, 1, Some("b"));
    assert_eq!(assigns(&b), vec![(2, 1, 1), (2, 1, 0)]);
    assert_eq!(assigns(&done(&mut s, 2, 1)), vec![(2, 1, 3)]);
    assert!(assigns(&fail(&mut s, 0, 2, 1, 3)).is_empty());
    let timeout = s.handle(0, Event::Timeout);
    assert_eq!(
        failure(&timeout, 1),
        Some(
            "no connected worker may render tile 3: it failed on some of them (b) and \
             the others are blocked from the job after failing 2 of its tiles (worker 1)"
        )
    );
    assert!(timeout.contains(&Action::CancelOnWorker { worker: 2, job: 1 }));
}

/// However many machines, and whatever their names hold, the message is one line.
#[test]
fn a_stall_message_stays_on_one_line() {
    let mut s = Scheduler::with_policy(Policy {
        speculate: false,
        stall_timeout: 0,
        max_attempts: 20,
        ..Policy::default()
    });
    submit(&mut s, 1, 0, SCENE_A, 1);
    for worker in 0..10 {
        let name = format!("m\n{worker}");
        assert_eq!(
            assigns(&join_at(&mut s, 0, worker, 1, Some(&name))),
            vec![(worker, 1, 0)]
        );
        fail(&mut s, 0, worker, 1, 0);
    }
    let timeout = s.handle(0, Event::Timeout);
    assert_eq!(
        failure(&timeout, 1),
        Some(
            "no connected worker may render tile 0: it failed on every one of them (m?0, \
             m?1, m?2, m?3, m?4, m?5, m?6, m?7, and 2 more)"
        )
    );
}

/// While storage cannot record results no tile goes out, results of tiles out are
/// still accepted, and once it can every worker is filled again.
#[test]
fn storage_unavailable_assigns_nothing_and_resumes() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 6);
    join(&mut s, 1, 1);
    assert!(s.handle(0, Event::StorageUnavailable).is_empty());
    let done = s.handle(
        10,
        Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        },
    );
    assert_eq!(done, vec![Action::AcceptTile { job: 1, tile: 0 }]);
    assert!(assigns(&join(&mut s, 2, 1)).is_empty());
    assert!(assigns(&submit(&mut s, 2, 0, SCENE_B, 2)).is_empty());
    assert!(assigns(&s.handle(1_000, Event::Timeout)).is_empty());
    // No straggler copies either.
    assert_eq!((s.held_by(1), s.held_by(2)), (1, 0));
    // Tile 1's lease, given under the initial lease, ended at its start plus the
    // lease measured with tile 0 (the least, 1 s): it ran out at the timeout and
    // waits at the head of job 1's queue.
    let back = s.handle(1_500, Event::StorageAvailable);
    assert_eq!(
        assigns(&back),
        vec![(1, 2, 0), (2, 1, 1), (2, 1, 2)],
        "{back:?}"
    );
}

#[test]
fn a_worker_holds_its_credit_and_gets_the_next_tile_when_it_returns_one() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 10);
    let joined = join(&mut s, 7, 1);
    assert_eq!(joined[0], Action::SendScene { worker: 7, job: 1 });
    assert_eq!(assigns(&joined), vec![(7, 1, 0), (7, 1, 1)]);
    let done = s.handle(
        0,
        Event::TileDone {
            worker: 7,
            job: 1,
            tile: 0,
        },
    );
    assert_eq!(done[0], Action::AcceptTile { job: 1, tile: 0 });
    assert_eq!(assigns(&done), vec![(7, 1, 2)]);
    assert_eq!(s.held_by(7), 2);
}

fn without_speculation() -> Scheduler {
    Scheduler::with_policy(Policy {
        speculate: false,
        ..Policy::default()
    })
}

#[test]
fn interactive_jobs_go_first_but_batch_jobs_get_one_tile_in_five() {
    let mut s = without_speculation();
    // A batch job of the highest priority, and an interactive one of the lowest.
    submit(&mut s, 1, i32::MAX, SCENE_A, 20);
    submit(&mut s, 2, i32::MIN, SCENE_B, 20);
    s.handle(0, Event::Interactive { job: 2 });
    s.handle(0, Event::Interactive { job: 99 }); // not active: nothing to mark
                                                 // The tiles in the order they are handed out, each result freeing a slot.
    let mut out: std::collections::VecDeque<_> = assigns(&join(&mut s, 1, 1)).into();
    let mut order: Vec<JobId> = out.iter().map(|a| a.1).collect();
    while let Some((worker, job, tile)) = out.pop_front() {
        let next = assigns(&s.handle(0, Event::TileDone { worker, job, tile }));
        order.extend(next.iter().map(|a| a.1));
        out.extend(next);
    }
    assert_eq!(order.len(), 40, "{order:?}");
    let run = INTERACTIVE_RUN as usize;
    // The worker's credit is filled first, then every slot: count from the first
    // batch tile on, runs of `run` interactive tiles between single batch tiles.
    let first_batch = order.iter().position(|&j| j == 1).unwrap();
    assert!(order[..first_batch].iter().all(|&j| j == 2), "{order:?}");
    for window in order[first_batch..]
        .chunks(run + 1)
        .filter(|w| w.len() == run + 1)
    {
        if !window.contains(&2) {
            break; // the interactive job is done
        }
        assert_eq!(
            window.iter().filter(|&&j| j == 1).count(),
            1,
            "one batch tile in every {}: {order:?}",
            run + 1
        );
    }
}

#[test]
fn results_are_accepted_once_and_only_from_the_holder() {
    let mut s = without_speculation();
    submit(&mut s, 1, 0, SCENE_A, 3);
    join(&mut s, 1, 1);
    join(&mut s, 2, 1);
    let done = |s: &mut Scheduler, worker| {
        s.handle(
            0,
            Event::TileDone {
                worker,
                job: 1,
                tile: 0,
            },
        )
    };
    // Tile 0 is worker 1's: worker 2's result for it is dropped.
    let stray = done(&mut s, 2);
    assert!(!stray.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
    let first = done(&mut s, 1);
    assert!(first.contains(&Action::AcceptTile { job: 1, tile: 0 }));
    let again = done(&mut s, 1);
    assert!(!again.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
}

#[test]
fn a_leaving_worker_s_tiles_go_to_another_and_the_job_finishes() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 4);
    join(&mut s, 1, 1);
    let joined = join(&mut s, 2, 1);
    assert_eq!(assigns(&joined), vec![(2, 1, 2), (2, 1, 3)]);
    let left = s.handle(0, Event::WorkerLeft { worker: 1 });
    assert!(assigns(&left).is_empty(), "worker 2 is at its credit");
    let mut actions = Vec::new();
    for tile in [2, 3, 0, 1] {
        actions.extend(s.handle(
            0,
            Event::TileDone {
                worker: 2,
                job: 1,
                tile,
            },
        ));
    }
    assert!(actions.contains(&Action::JobDone { job: 1 }));
    assert!(!s.is_active(1));
}

#[test]
fn equal_priorities_share_the_farm_and_higher_priority_goes_first() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 100);
    submit(&mut s, 2, 0, SCENE_A, 4);
    let joined = join(&mut s, 1, 2);
    // Fewest tiles in flight first: the two jobs alternate.
    assert_eq!(
        assigns(&joined),
        vec![(1, 1, 0), (1, 2, 0), (1, 1, 1), (1, 2, 1)]
    );
    let urgent = submit(&mut s, 3, 5, SCENE_B, 2);
    assert!(assigns(&urgent).is_empty(), "the worker is at its credit");
    let next = s.handle(
        0,
        Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        },
    );
    assert_eq!(assigns(&next), vec![(1, 3, 0)]);
    assert!(next.contains(&Action::SendScene { worker: 1, job: 3 }));
}

#[test]
fn a_paused_job_gets_no_tile_keeps_those_out_and_resumes() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 10);
    let joined = join(&mut s, 1, 1);
    let out = assigns(&joined);
    assert!(!out.is_empty());
    assert!(s.handle(0, Event::PauseJob { job: 1 }).is_empty());
    // A tile already out counts, and frees a slot that stays empty.
    let (_, _, tile) = out[0];
    let done = s.handle(
        0,
        Event::TileDone {
            worker: 1,
            job: 1,
            tile,
        },
    );
    assert!(assigns(&done).is_empty(), "a paused job hands out nothing");
    // A paused job with no worker able to take its tiles does not fail.
    let later = s.handle(10 * 60 * 1000, Event::Timeout);
    assert_eq!(failure(&later, 1), None);
    let resumed = s.handle(10 * 60 * 1000, Event::ResumeJob { job: 1 });
    assert!(
        !assigns(&resumed).is_empty(),
        "resuming hands tiles out again"
    );
}

#[test]
fn a_job_that_ends_while_paused_leaves_no_pause_behind() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 1);
    let joined = join(&mut s, 1, 1);
    assert_eq!(assigns(&joined), vec![(1, 1, 0)]);
    s.handle(0, Event::PauseJob { job: 1 });
    assert!(s.is_paused(1));
    let done = s.handle(
        0,
        Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        },
    );
    assert!(done.contains(&Action::JobDone { job: 1 }));
    assert!(!s.is_paused(1), "a finished job's pause is forgotten");
    // Failed while paused: the tile out fails for good.
    let mut s = Scheduler::with_policy(Policy {
        max_attempts: 1,
        ..Policy::default()
    });
    submit(&mut s, 2, 0, SCENE_A, 2);
    join(&mut s, 1, 1);
    s.handle(0, Event::PauseJob { job: 2 });
    let failed = s.handle(
        0,
        Event::TileFailed {
            worker: 1,
            job: 2,
            tile: 0,
            message: "broken".into(),
        },
    );
    assert!(failure(&failed, 2).is_some(), "{failed:?}");
    assert!(!s.is_paused(2), "a failed job's pause is forgotten");
    // Taken back with every tile done, or with none to render.
    s.handle(0, Event::PauseJob { job: 3 });
    let resumed = s.resume_job(0, 3, 0, SCENE_A, 1, &[0]);
    assert!(resumed.contains(&Action::JobDone { job: 3 }));
    assert!(!s.is_paused(3));
    s.handle(0, Event::PauseJob { job: 4 });
    submit(&mut s, 4, 0, SCENE_A, 0);
    assert!(!s.is_paused(4));
    // A pause before submission still holds once the job is in.
    s.handle(0, Event::PauseJob { job: 5 });
    submit(&mut s, 5, 0, SCENE_A, 3);
    assert!(s.is_paused(5));
}

#[test]
fn requeued_tiles_are_taken_back_from_wherever_they_are() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 3);
    let out = assigns(&join(&mut s, 1, 4));
    assert_eq!(out.len(), 3, "{out:?}");
    // Tile 0 done, tile 1 still out, tile 2 out.
    let done = s.handle(
        0,
        Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        },
    );
    assert!(done.contains(&Action::AcceptTile { job: 1, tile: 0 }));
    let again = s.handle(
        0,
        Event::RequeueTiles {
            job: 1,
            tiles: vec![0, 1, 99],
        },
    );
    // Both go out again at once (the worker has free slots).
    let mut again = assigns(&again);
    again.sort_unstable();
    assert_eq!(again, vec![(1, 1, 0), (1, 1, 1)]);
    // The old lease of tile 1 is gone: the job ends only when the tiles come back.
    let mut finished = Vec::new();
    for tile in [2, 1, 0] {
        finished.extend(s.handle(
            0,
            Event::TileDone {
                worker: 1,
                job: 1,
                tile,
            },
        ));
    }
    assert!(
        finished.contains(&Action::JobDone { job: 1 }),
        "{finished:?}"
    );
    assert_eq!(s.tiles_in_flight(), 0);
}

#[test]
fn a_new_priority_orders_the_next_tiles() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 10);
    submit(&mut s, 2, 0, SCENE_A, 10);
    s.handle(
        0,
        Event::SetPriority {
            job: 2,
            priority: 3,
        },
    );
    let joined = join(&mut s, 1, 1);
    let out = assigns(&joined);
    assert!(!out.is_empty());
    assert!(out.iter().all(|&(_, job, _)| job == 2), "{out:?}");
}

#[test]
fn cancelling_tells_the_holders_and_forgets_the_scene() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 10);
    join(&mut s, 1, 1);
    let cancelled = s.handle(0, Event::CancelJob { job: 1 });
    assert!(cancelled.contains(&Action::CancelOnWorker { worker: 1, job: 1 }));
    assert!(cancelled.contains(&Action::ForgetScene {
        worker: 1,
        scene: SCENE_A
    }));
    assert!(!s.is_active(1));
    assert_eq!(s.held_by(1), 0);
    // A later job of the same scene sends it again.
    let later = submit(&mut s, 2, 0, SCENE_A, 1);
    assert_eq!(later[0], Action::SendScene { worker: 1, job: 2 });
}

#[test]
fn a_disabled_machine_gets_no_new_tile_until_enabled_even_after_reconnecting() {
    let mut s = without_speculation();
    join_at(&mut s, 0, 1, 1, Some("a"));
    assert!(s.can_hand_out());
    s.handle(
        0,
        Event::DisableMachine {
            machine: "a".into(),
        },
    );
    assert!(!s.can_hand_out());
    assert!(s.is_disabled("a"));
    assert!(assigns(&submit(&mut s, 1, 0, SCENE_A, 3)).is_empty());
    // A reconnect of the machine is still disabled.
    s.handle(0, Event::WorkerLeft { worker: 1 });
    assert!(assigns(&join_at(&mut s, 0, 2, 1, Some("a"))).is_empty());
    assert!(!s.can_hand_out());
    // Another machine is not.
    assert!(!assigns(&join_at(&mut s, 0, 3, 1, Some("b"))).is_empty());
    s.handle(0, Event::WorkerLeft { worker: 3 });
    let enabled = s.handle(
        0,
        Event::EnableMachine {
            machine: "a".into(),
        },
    );
    assert!(s.can_hand_out());
    assert!(assigns(&enabled).iter().all(|&(w, _, _)| w == 2));
    assert!(!assigns(&enabled).is_empty());
}

#[test]
fn a_disabled_workers_tiles_still_count() {
    let mut s = without_speculation();
    join_at(&mut s, 0, 1, 1, Some("a"));
    let out = assigns(&submit(&mut s, 1, 0, SCENE_A, 3));
    assert!(!out.is_empty());
    s.handle(
        0,
        Event::DisableMachine {
            machine: "a".into(),
        },
    );
    let (w, j, t) = out[0];
    let done = s.handle(
        1,
        Event::TileDone {
            worker: w,
            job: j,
            tile: t,
        },
    );
    assert!(done.contains(&Action::AcceptTile { job: j, tile: t }));
    assert!(assigns(&done).is_empty());
}

#[test]
fn a_draining_or_quarantined_farm_cannot_hand_out() {
    let mut s = Scheduler::new();
    assert!(!s.can_hand_out());
    join_at(&mut s, 0, 1, 1, Some("a"));
    join_at(&mut s, 0, 2, 1, Some("b"));
    s.handle(0, Event::WorkerDraining { worker: 1 });
    assert!(s.can_hand_out());
    s.handle(
        0,
        Event::Quarantine {
            machine: "b".into(),
            revoke: Vec::new(),
        },
    );
    assert!(!s.can_hand_out());
    // Enabling a machine that was never disabled changes nothing.
    s.handle(
        0,
        Event::EnableMachine {
            machine: "a".into(),
        },
    );
    assert!(!s.can_hand_out());
}

#[test]
fn a_draining_worker_gets_nothing_more() {
    let mut s = Scheduler::new();
    join(&mut s, 1, 1);
    s.handle(0, Event::WorkerDraining { worker: 1 });
    assert!(assigns(&submit(&mut s, 1, 0, SCENE_A, 3)).is_empty());
    assert_eq!(s.held_by(1), 0);
}

#[test]
fn a_failed_tile_is_retried_elsewhere_then_fails_the_job() {
    let mut s = Scheduler::with_policy(Policy {
        max_attempts: 2,
        speculate: false,
        ..Policy::default()
    });
    submit(&mut s, 1, 0, SCENE_A, 1);
    join(&mut s, 1, 1);
    let failed = fail(&mut s, 0, 1, 1, 0);
    // Not given back to the worker it failed on.
    assert!(assigns(&failed).is_empty());
    let joined = join(&mut s, 2, 1);
    assert_eq!(assigns(&joined), vec![(2, 1, 0)]);
    let failed = fail(&mut s, 0, 2, 1, 0);
    assert_eq!(
        failure(&failed, 1),
        Some("tile 0 failed 2 times; last: boom")
    );
    assert!(!s.is_active(1));
}

#[test]
fn an_expired_lease_requeues_the_tile_and_a_silent_worker_is_dropped() {
    let policy = Policy::default();
    let mut s = without_speculation();
    submit(&mut s, 1, 0, SCENE_A, 1);
    join(&mut s, 1, 1);
    join(&mut s, 2, 1);
    // Both stay alive; worker 1 holds the tile until its lease runs out, and then
    // the tile goes to worker 2.
    let mut expired = Vec::new();
    for now in (1_000..=policy.initial_lease).step_by(1_000) {
        s.handle(now, Event::Heartbeat { worker: 1 });
        s.handle(now, Event::Heartbeat { worker: 2 });
        expired = s.handle(now, Event::Timeout);
        if !expired.is_empty() {
            break;
        }
    }
    assert_eq!(assigns(&expired), vec![(2, 1, 0)]);
    // Heart-beating, but 60 s without a result while holding a tile whose lease ran
    // out: worker 1 is marked unresponsive at the same timeout.
    assert!(
        expired.contains(&Action::WorkerUnresponsive {
            worker: 1,
            silent: policy.initial_lease
        }),
        "{expired:?}"
    );
    let counted = Counters {
        leases_expired: 1,
        tiles_requeued: 1,
        workers_dropped: 0,
        workers_unresponsive: 1,
    };
    assert_eq!(s.counters(), counted);
    // The expired lease is listed (worker 1 may still deliver), the fresh one not.
    let listed = s.expired_leases();
    assert_eq!(listed.len(), 1, "{listed:?}");
    let (job, tile, worker, out_for) = listed[0];
    assert_eq!((job, tile, worker), (1, 0, 1));
    assert!(out_for >= policy.initial_lease, "{out_for}");
    // Worker 1 falls silent and is dropped at the first timeout past the limit;
    // worker 2 keeps the tile.
    let mut now = policy.initial_lease;
    let dropped = loop {
        now += 1_000;
        s.handle(now, Event::Heartbeat { worker: 2 });
        let actions = s.handle(now, Event::Timeout);
        if !actions.is_empty() {
            break actions;
        }
    };
    assert_eq!(dropped, vec![Action::DropWorker { worker: 1 }]);
    assert!(
        s.expired_leases().is_empty(),
        "a dropped worker's lease is gone"
    );
    // Its lease had run out already: dropping it requeues nothing more.
    assert_eq!(
        s.counters(),
        Counters {
            workers_dropped: 1,
            ..counted
        }
    );
    // Its last heartbeat arrived at initial_lease; the first timeout more than the
    // heartbeat timeout later drops it.
    assert_eq!(now, policy.initial_lease + policy.heartbeat_timeout + 1_000);
    let done = s.handle(
        now,
        Event::TileDone {
            worker: 2,
            job: 1,
            tile: 0,
        },
    );
    assert!(done.contains(&Action::JobDone { job: 1 }));
}

#[test]
fn a_straggler_is_duplicated_and_the_first_result_wins() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 1);
    join(&mut s, 1, 1);
    let idle = join(&mut s, 2, 1);
    assert_eq!(assigns(&idle), vec![(2, 1, 0)]);
    let first = s.handle(
        0,
        Event::TileDone {
            worker: 2,
            job: 1,
            tile: 0,
        },
    );
    assert!(first.contains(&Action::AcceptTile { job: 1, tile: 0 }));
    assert!(first.contains(&Action::CancelOnWorker { worker: 1, job: 1 }));
    assert!(first.contains(&Action::JobDone { job: 1 }));
}

fn to_confirm(
    s: &mut Scheduler,
    now: Millis,
    worker: WorkerId,
    tile: u32,
    required: bool,
) -> Vec<Action> {
    s.handle(
        now,
        Event::TileToConfirm {
            worker,
            job: 1,
            tile,
            required,
        },
    )
}

#[test]
fn a_held_result_is_confirmed_only_by_another_machine() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 1);
    assert_eq!(
        assigns(&join_at(&mut s, 0, 1, 1, Some("a"))),
        vec![(1, 1, 0)]
    );
    // Worker 2 of the same machine takes a straggler copy.
    assert_eq!(
        assigns(&join_at(&mut s, 0, 2, 1, Some("a"))),
        vec![(2, 1, 0)]
    );
    let held = to_confirm(&mut s, 10, 1, 0, true);
    assert!(held.contains(&Action::HoldResult {
        worker: 1,
        job: 1,
        tile: 0
    }));
    // Worker 2 is the same machine: it may not confirm. A third machine joins.
    assert!(!assigns(&held).iter().any(|&(w, _, _)| w == 1 || w == 2));
    let copy = s.handle(
        15,
        Event::TileDone {
            worker: 2,
            job: 1,
            tile: 0,
        },
    );
    assert!(!copy.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
    assert!(assigns(&copy).is_empty(), "machine a may not take it again");
    assert_eq!(
        assigns(&join_at(&mut s, 20, 3, 1, Some("b"))),
        vec![(3, 1, 0)]
    );
    let done = s.handle(
        30,
        Event::TileDone {
            worker: 3,
            job: 1,
            tile: 0,
        },
    );
    assert!(done.contains(&Action::AcceptTile { job: 1, tile: 0 }));
    assert!(done.contains(&Action::JobDone { job: 1 }));
}

#[test]
fn an_optional_confirmation_no_machine_may_give_is_given_up_a_required_one_stalls() {
    for required in [false, true] {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 1);
        join_at(&mut s, 0, 1, 1, Some("a"));
        to_confirm(&mut s, 10, 1, 0, required);
        let mut actions = Vec::new();
        for t in (1..=40).map(|k| k * 1_000) {
            s.handle(t, Event::Heartbeat { worker: 1 });
            actions.extend(s.handle(t, Event::Timeout));
        }
        if required {
            let message = failure(&actions, 1).expect("the job stalls and fails");
            assert!(message.contains("tile 0"), "{message}");
        } else {
            assert!(actions.contains(&Action::AcceptHeld { job: 1, tile: 0 }));
            assert!(actions.contains(&Action::JobDone { job: 1 }));
            assert!(failure(&actions, 1).is_none());
        }
    }
}

#[test]
fn a_quarantined_machine_loses_its_tiles_held_results_and_revoked_tiles() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 6);
    assert_eq!(assigns(&join_at(&mut s, 0, 1, 1, Some("liar"))).len(), 2);
    let done = s.handle(
        5,
        Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        },
    );
    assert!(done.contains(&Action::AcceptTile { job: 1, tile: 0 }));
    to_confirm(&mut s, 6, 1, 1, false);
    assert_eq!(s.held_by(1), 2, "tiles 2 and 3");
    let q = s.handle(
        7,
        Event::Quarantine {
            machine: "liar".into(),
            revoke: vec![(1, 0)],
        },
    );
    assert!(assigns(&q).is_empty(), "nobody else is connected");
    assert_eq!(s.held_by(1), 0);
    // An honest machine gets every tile, the revoked and the held one included.
    let honest = assigns(&join_at(&mut s, 8, 2, 3, Some("honest")));
    assert_eq!(honest.len(), 6);
    let mut accepted = Vec::new();
    for &(_, _, tile) in &honest {
        let actions = s.handle(
            9,
            Event::TileDone {
                worker: 2,
                job: 1,
                tile,
            },
        );
        accepted.extend(actions);
    }
    for tile in 0..6 {
        assert!(accepted.contains(&Action::AcceptTile { job: 1, tile }));
    }
    assert!(accepted.contains(&Action::JobDone { job: 1 }));
    // The liar, back under its name, is given nothing.
    assert!(assigns(&join_at(&mut s, 11, 3, 4, Some("liar"))).is_empty());
}

#[test]
fn credit_covers_the_round_trip_within_its_cap() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 1000);
    assert_eq!(assigns(&join_at(&mut s, 0, 1, 2, Some("far"))).len(), 4);
    let more = s.handle(
        1,
        Event::WorkerPace {
            worker: 1,
            rtt: 200,
            tile: 20,
        },
    );
    assert_eq!(
        assigns(&more).len(),
        2 * 15,
        "two threads, fifteen tiles per round trip and a half"
    );
    assert_eq!(s.held_by(1), 34);
    s.handle(
        2,
        Event::WorkerPace {
            worker: 1,
            rtt: 10_000,
            tile: 1,
        },
    );
    // Over two calls: one hands out at most `handout_per_call` tiles.
    assert!(s.has_more());
    s.handle(2, Event::Continue);
    assert!(!s.has_more());
    assert_eq!(s.held_by(1), 2 * 256, "capped per thread");
    s.handle(
        3,
        Event::WorkerPace {
            worker: 1,
            rtt: 0,
            tile: 20,
        },
    );
    assert_eq!(s.held_by(1), 512, "a smaller credit takes nothing back");
}

/// An optional confirmation given up while another machine still holds the tile
/// under a lease that ran out: that holder's copy is still to come, and it is told
/// when the job ends. (The held result was accepted with the lease dropped and the
/// job left ranked by its old count of tiles in flight: the holder kept the tile
/// forever, and the next fill panicked on the job gone from the serving order.)
#[test]
fn a_confirmation_given_up_leaves_the_copies_out_to_come() {
    let mut s = Scheduler::with_policy(Policy {
        initial_lease: 1_000,
        ..Policy::default()
    });
    submit(&mut s, 1, 0, SCENE_A, 1);
    join_at(&mut s, 0, 1, 1, Some("a"));
    to_confirm(&mut s, 10, 1, 0, false);
    assert_eq!(
        assigns(&join_at(&mut s, 20, 2, 1, Some("b"))),
        vec![(2, 1, 0)]
    );
    // b's lease runs out, then b drains: no ready machine may confirm.
    for worker in [1, 2] {
        s.handle(1_100, Event::Heartbeat { worker });
    }
    assert!(s.handle(1_100, Event::Timeout).is_empty());
    s.handle(1_200, Event::WorkerDraining { worker: 2 });
    let given_up = s.handle(1_300, Event::Timeout);
    assert!(given_up.contains(&Action::AcceptHeld { job: 1, tile: 0 }));
    assert!(given_up.contains(&Action::CancelOnWorker { worker: 2, job: 1 }));
    assert_eq!(given_up.last(), Some(&Action::JobDone { job: 1 }));
    assert_eq!(s.held_by(2), 0);
    submit(&mut s, 2, 0, SCENE_B, 3);
    assert_eq!(assigns(&join_at(&mut s, 1_400, 3, 1, Some("c"))).len(), 2);
}

/// A required confirmation that only its own machine could give stalls the job
/// however few attempts a tile has: with `max_attempts` 1, one machine connected;
/// with 2, the tile failed on the other one. (The stall check took `max_attempts`
/// machines open as proof that some may take every tile, forgetting the holder.)
#[test]
fn a_required_confirmation_stalls_with_max_attempts_machines_connected() {
    for max_attempts in [1, 2] {
        let mut s = Scheduler::with_policy(Policy {
            max_attempts,
            speculate: false,
            stall_timeout: 2_000,
            ..Policy::default()
        });
        submit(&mut s, 1, 0, SCENE_A, 1);
        let mut workers = vec![1];
        if max_attempts == 2 {
            join_at(&mut s, 0, 2, 1, Some("b"));
            fail(&mut s, 0, 2, 1, 0);
            workers.push(2);
        }
        assert_eq!(
            assigns(&join_at(&mut s, 0, 1, 1, Some("a"))),
            vec![(1, 1, 0)]
        );
        to_confirm(&mut s, 10, 1, 0, true);
        let mut actions = Vec::new();
        for t in (1..=5).map(|k| k * 1_000) {
            for &worker in &workers {
                s.handle(t, Event::Heartbeat { worker });
            }
            actions.extend(s.handle(t, Event::Timeout));
        }
        let message = failure(&actions, 1).expect("the job stalls and fails");
        let expected = if max_attempts == 1 {
            "no connected worker may render tile 0: its result from a awaits \
             confirmation by another machine, and no other machine is connected"
        } else {
            "no connected worker may render tile 0: its result from a awaits \
             confirmation by another machine, and it failed on the others (b)"
        };
        assert_eq!(message, expected);
    }
}

/// A round trip of any length raises the credit to its cap, never wraps it around.
#[test]
fn a_huge_round_trip_reaches_the_cap() {
    for tile in [0, 1] {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 1000);
        join_at(&mut s, 0, 1, 2, Some("far"));
        let rtt = Millis::MAX;
        s.handle(
            1,
            Event::WorkerPace {
                worker: 1,
                rtt,
                tile,
            },
        );
        while s.has_more() {
            s.handle(1, Event::Continue);
        }
        let cap = Policy::default().max_credit_per_thread as usize;
        assert_eq!(s.held_by(1), 2 * cap);
    }
}

/// A copy from the machine whose result is held puts the tile back: another
/// machine's idle worker gets it at once, not at the next timeout.
#[test]
fn a_tile_put_back_by_its_holding_machine_s_copy_goes_to_an_idle_worker() {
    let mut s = Scheduler::with_policy(Policy {
        speculate: false,
        initial_lease: 1_000,
        ..Policy::default()
    });
    submit(&mut s, 1, 0, SCENE_A, 1);
    join_at(&mut s, 0, 1, 1, Some("a"));
    s.handle(1_000, Event::Heartbeat { worker: 1 });
    s.handle(1_000, Event::Timeout);
    assert_eq!(
        assigns(&join_at(&mut s, 1_000, 2, 1, Some("a"))),
        vec![(2, 1, 0)]
    );
    assert!(assigns(&join_at(&mut s, 1_000, 3, 1, Some("b"))).is_empty());
    assert!(assigns(&to_confirm(&mut s, 1_100, 1, 0, true)).is_empty());
    let copy = s.handle(
        1_200,
        Event::TileDone {
            worker: 2,
            job: 1,
            tile: 0,
        },
    );
    assert_eq!(assigns(&copy), vec![(3, 1, 0)]);
}

/// A revoked tile whose copy is still out on an honest machine: that copy is a
/// result again (accepted, not a duplicate), and its holder is not given the tile a
/// second time. (The copy stayed a duplicate of a tile no longer accepted, and the
/// tile went again to the worker holding it.)
#[test]
fn a_revoked_tile_s_copy_still_out_counts_as_its_result() {
    let mut s = Scheduler::new();
    submit(&mut s, 1, 0, SCENE_A, 2);
    assert_eq!(assigns(&join_at(&mut s, 0, 1, 1, Some("liar"))).len(), 2);
    assert_eq!(
        assigns(&join_at(&mut s, 0, 2, 1, Some("honest"))),
        vec![(2, 1, 0), (2, 1, 1)]
    );
    let done = |s: &mut Scheduler, now, worker, tile| {
        s.handle(
            now,
            Event::TileDone {
                worker,
                job: 1,
                tile,
            },
        )
    };
    assert!(done(&mut s, 5, 1, 0).contains(&Action::AcceptTile { job: 1, tile: 0 }));
    s.handle(
        6,
        Event::Quarantine {
            machine: "liar".into(),
            revoke: vec![(1, 0)],
        },
    );
    let one = done(&mut s, 7, 2, 1);
    assert!(one.contains(&Action::AcceptTile { job: 1, tile: 1 }));
    assert!(assigns(&one).is_empty(), "worker 2 holds tile 0: {one:?}");
    let zero = done(&mut s, 8, 2, 0);
    assert!(zero.contains(&Action::AcceptTile { job: 1, tile: 0 }));
    assert!(zero.contains(&Action::JobDone { job: 1 }));
}

/// A quarantined machine's workers hold nothing afterwards, even tiles of a job
/// that is no longer active: here the job's id was submitted again while they held
/// its tiles, then cancelled. (Those tiles stayed held, as no active job had them.)
#[test]
fn a_quarantined_machine_holds_nothing_even_of_a_replaced_job() {
    let mut s = without_speculation();
    assert!(join_at(&mut s, 0, 1, 1, Some("m0")).is_empty());
    assert!(join_at(&mut s, 0, 2, 1, None).is_empty());
    assert_eq!(
        assigns(&submit(&mut s, 1, 0, SCENE_A, 2)),
        vec![(1, 1, 0), (1, 1, 1)]
    );
    // The same id again (a daemon bug): the new job replaces the old one, whose
    // tiles worker 1 still holds.
    assert_eq!(assigns(&submit(&mut s, 1, 0, SCENE_A, 1)), vec![(2, 1, 0)]);
    s.handle(0, Event::CancelJob { job: 1 });
    assert_eq!(s.held_by(1), 2);
    s.handle(
        0,
        Event::Quarantine {
            machine: "m0".into(),
            revoke: vec![],
        },
    );
    assert_eq!(s.held_by(1), 0);
    assert_eq!(s.tiles_in_flight(), 0);
}

/// A call hands out at most `handout_per_call` tiles and asks to go on; the
/// `Continue`s that follow hand out the rest, in the very order one unbounded call
/// would have.
#[test]
fn a_large_hand_out_is_cut_into_bounded_calls_in_the_same_order() {
    let run = |per_call: usize| {
        let mut s = Scheduler::with_policy(Policy {
            handout_per_call: per_call,
            ..Policy::default()
        });
        for worker in 1..=40 {
            join(&mut s, worker, 4);
        }
        let mut all = assigns(&submit(&mut s, 1, 0, SCENE_A, 1000));
        let mut calls = 1;
        while s.has_more() {
            all.extend(assigns(&s.handle(0, Event::Continue)));
            calls += 1;
        }
        (all, calls)
    };
    let (bounded, calls) = run(64);
    let (whole, one) = run(usize::MAX);
    assert_eq!(one, 1);
    assert_eq!(whole.len(), 40 * 8, "every worker holds its credit");
    assert_eq!(calls, 5, "320 tiles, 64 a call");
    assert_eq!(bounded, whole);
}

/// Leases that run out together are checked a bounded number per call: the timeout
/// that finds them asks to go on, and the `Continue`s that follow run out the rest.
/// The same leases run out and the same tiles go back to the queue as in one call.
#[test]
fn leases_running_out_together_are_checked_over_bounded_calls() {
    let run = |checks_per_call: usize| {
        let mut s = Scheduler::with_policy(Policy {
            checks_per_call,
            heartbeat_timeout: 120_000,
            speculate: false,
            ..Policy::default()
        });
        submit(&mut s, 1, 0, SCENE_A, 40);
        for worker in 1..=10 {
            join(&mut s, worker, 1);
        }
        assert_eq!(s.tiles_in_flight(), 20);
        // Nothing comes back: every lease runs out at the initial lease. (A timeout
        // every second: the clock does not take a longer gap for the farm's time.)
        let at = Policy::default().initial_lease;
        for now in (1_000..at).step_by(1_000) {
            let quiet = s.handle(now, Event::Timeout);
            assert!(quiet.is_empty(), "{now}: {quiet:?}");
        }
        let first = s.handle(at, Event::Timeout);
        let mut calls = vec![s.counters().leases_expired];
        let mut reassigned = assigns(&first).len();
        while s.has_more() {
            reassigned += assigns(&s.handle(at, Event::Continue)).len();
            calls.push(s.counters().leases_expired);
        }
        (calls, s.counters(), reassigned)
    };
    let (bounded, counters, reassigned) = run(6);
    let (whole, whole_counters, whole_reassigned) = run(usize::MAX);
    assert_eq!(whole, vec![20]);
    // Six a call, and then the ten workers holding them late are looked at (four
    // checks were left in the fourth call): every one of them is unresponsive.
    assert_eq!(bounded, vec![6, 12, 18, 20, 20]);
    assert_eq!(counters, whole_counters);
    assert_eq!(counters.workers_unresponsive, 10);
    assert_eq!(counters.tiles_requeued, 20);
    // Each worker still holds its two late tiles: nothing is handed out meanwhile.
    assert_eq!((reassigned, whole_reassigned), (0, 0));
}

/// A scene many workers have is forgotten a bounded number of workers per call, in
/// worker order; a job with that scene submitted before the last of them leaves the
/// scene with those not yet told, and only the others are sent it again.
#[test]
fn a_scene_many_workers_have_is_forgotten_over_bounded_calls() {
    let forgets = |actions: &[Action]| -> Vec<WorkerId> {
        actions
            .iter()
            .filter_map(|a| match *a {
                Action::ForgetScene { worker, scene } if scene == SCENE_A => Some(worker),
                _ => None,
            })
            .collect()
    };
    // Two scenes forgotten per call (each counts for four checks).
    let mut s = Scheduler::with_policy(Policy {
        checks_per_call: 8,
        speculate: false,
        ..Policy::default()
    });
    submit(&mut s, 1, 0, SCENE_A, 10);
    for worker in 1..=5 {
        join(&mut s, worker, 1);
    }
    // Each worker holds two tiles, in order.
    let mut last = Vec::new();
    for tile in 0..10 {
        let worker = WorkerId::from(tile / 2 + 1);
        last = s.handle(
            1,
            Event::TileDone {
                worker,
                job: 1,
                tile,
            },
        );
    }
    assert!(last.contains(&Action::JobDone { job: 1 }));
    assert_eq!(forgets(&last), vec![1, 2]);
    assert!(s.has_more());
    assert_eq!(forgets(&s.handle(2, Event::Continue)), vec![3, 4]);
    assert!(s.has_more());
    // A job of the same scene before worker 5 is told: worker 5 keeps it.
    let sent: Vec<WorkerId> = submit(&mut s, 2, 0, SCENE_A, 10)
        .iter()
        .filter_map(|a| match *a {
            Action::SendScene { worker, .. } => Some(worker),
            _ => None,
        })
        .collect();
    assert_eq!(sent, vec![1, 2, 3, 4]);
    assert!(forgets(&s.handle(3, Event::Continue)).is_empty());
    assert!(!s.has_more());
}
