//! The scheduler core: which tile goes to which worker, and when a job is finished.
//!
//! A pure state machine. It owns no socket, no clock and no thread: the daemon feeds it
//! [`Event`]s and carries out the [`Action`]s it returns, and tests feed it scripted or
//! random events. Every decision of the farm is made here.
//!
//! Policy:
//! - **Pull with credit.** A worker holds at most its credit of tiles (twice its
//!   threads); it is sent the next one as soon as it returns one, so faster workers
//!   render more tiles.
//! - **Priority, then fair share, then FIFO.** A free slot goes to the highest-priority
//!   job with tiles waiting; among jobs of that priority, to the one with the fewest
//!   tiles in flight; among those, to the oldest. One job alone gets the whole farm;
//!   two jobs of equal priority split it evenly, so a small job behind a huge one
//!   finishes in about twice its solo time instead of waiting for the huge one.
//! - **First result wins.** A result for a tile that is already done, or that is no
//!   longer assigned to the worker that sends it, is dropped.
//! - **Scenes once.** A worker is sent a scene before its first tile of it, and only
//!   then.

use std::collections::{BTreeMap, BTreeSet, HashSet, VecDeque};

use protocol::{JobId, SceneHash, WorkerId};

/// Something that happened, as the daemon saw it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    WorkerJoined {
        worker: WorkerId,
        threads: u32,
    },
    /// The worker's connection is gone; its tiles go back to their queues.
    WorkerLeft {
        worker: WorkerId,
    },
    /// The worker is shutting down: it finishes what it holds and gets nothing more.
    WorkerDraining {
        worker: WorkerId,
    },
    JobSubmitted {
        job: JobId,
        priority: i32,
        scene: SceneHash,
        tiles: u32,
    },
    TileDone {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// The worker could not render the tile: the job fails with `message`.
    TileFailed {
        worker: WorkerId,
        job: JobId,
        tile: u32,
        message: String,
    },
    CancelJob {
        job: JobId,
    },
}

/// What the daemon must do.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Action {
    /// Send the job's scene to the worker (before the `Assign` that follows).
    SendScene {
        worker: WorkerId,
        job: JobId,
    },
    /// Send the tile to the worker.
    Assign {
        worker: WorkerId,
        job: JobId,
        tile: u32,
    },
    /// Keep this result: it is the first for the tile.
    AcceptTile {
        job: JobId,
        tile: u32,
    },
    /// Tell the worker to drop the job's tiles it still holds.
    CancelOnWorker {
        worker: WorkerId,
        job: JobId,
    },
    /// The worker may drop the scene from its cache: no active job uses it.
    ForgetScene {
        worker: WorkerId,
        scene: SceneHash,
    },
    /// Every tile is done: assemble and store the image.
    JobDone {
        job: JobId,
    },
    JobFailed {
        job: JobId,
        message: String,
    },
}

struct Job {
    priority: i32,
    scene: SceneHash,
    waiting: VecDeque<u32>,
    /// Tile → the worker rendering it.
    in_flight: BTreeMap<u32, WorkerId>,
    done: Vec<bool>,
    remaining: u32,
}

struct Worker {
    credit: usize,
    holding: BTreeSet<(JobId, u32)>,
    scenes: HashSet<SceneHash>,
    draining: bool,
}

/// The scheduler's whole state.
#[derive(Default)]
pub struct Scheduler {
    /// Active jobs (queued or running), by id; ids grow with submission order.
    jobs: BTreeMap<JobId, Job>,
    workers: BTreeMap<WorkerId, Worker>,
}

impl Scheduler {
    pub fn new() -> Self {
        Self::default()
    }

    /// Applies one event and returns what to do, in order.
    pub fn handle(&mut self, event: Event) -> Vec<Action> {
        let mut actions = Vec::new();
        match event {
            Event::WorkerJoined { worker, threads } => {
                self.workers.insert(
                    worker,
                    Worker {
                        credit: 2 * threads.max(1) as usize,
                        holding: BTreeSet::new(),
                        scenes: HashSet::new(),
                        draining: false,
                    },
                );
                self.fill(worker, &mut actions);
            }
            Event::WorkerLeft { worker } => {
                if let Some(w) = self.workers.remove(&worker) {
                    for (job, tile) in w.holding {
                        self.requeue(job, tile);
                    }
                    self.fill_all(&mut actions);
                }
            }
            Event::WorkerDraining { worker } => {
                if let Some(w) = self.workers.get_mut(&worker) {
                    w.draining = true;
                }
            }
            Event::JobSubmitted {
                job,
                priority,
                scene,
                tiles,
            } => {
                self.jobs.insert(
                    job,
                    Job {
                        priority,
                        scene,
                        waiting: (0..tiles).collect(),
                        in_flight: BTreeMap::new(),
                        done: vec![false; tiles as usize],
                        remaining: tiles,
                    },
                );
                if tiles == 0 {
                    self.jobs.remove(&job);
                    actions.push(Action::JobDone { job });
                }
                self.fill_all(&mut actions);
            }
            Event::TileDone { worker, job, tile } => {
                self.tile_done(worker, job, tile, &mut actions);
                self.fill(worker, &mut actions);
            }
            Event::TileFailed {
                worker,
                job,
                tile,
                message,
            } => {
                // Like a result, a failure counts only from the worker holding the tile.
                if self.release(worker, job, tile) {
                    self.end_job(job, &mut actions);
                    actions.push(Action::JobFailed { job, message });
                }
                self.fill_all(&mut actions);
            }
            Event::CancelJob { job } => {
                if self.jobs.contains_key(&job) {
                    self.end_job(job, &mut actions);
                }
                self.fill_all(&mut actions);
            }
        }
        actions
    }

    /// Whether the job still has tiles to render.
    pub fn is_active(&self, job: JobId) -> bool {
        self.jobs.contains_key(&job)
    }

    /// Whether any tile of the job has been sent out yet (queued vs running).
    pub fn has_started(&self, job: JobId) -> bool {
        self.jobs
            .get(&job)
            .is_some_and(|j| j.waiting.len() < j.done.len())
    }

    /// Tiles the worker holds.
    pub fn held_by(&self, worker: WorkerId) -> usize {
        self.workers.get(&worker).map_or(0, |w| w.holding.len())
    }

    /// Takes the tile back from the worker if, and only if, the worker holds it for an
    /// active job. Anything else (a stray, late or duplicate message) changes nothing.
    fn release(&mut self, worker: WorkerId, job_id: JobId, tile: u32) -> bool {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return false;
        };
        if job.in_flight.get(&tile) != Some(&worker) {
            return false;
        }
        job.in_flight.remove(&tile);
        if let Some(w) = self.workers.get_mut(&worker) {
            w.holding.remove(&(job_id, tile));
        }
        true
    }

    fn tile_done(&mut self, worker: WorkerId, job_id: JobId, tile: u32, actions: &mut Vec<Action>) {
        if !self.release(worker, job_id, tile) {
            return;
        }
        let job = self.jobs.get_mut(&job_id).expect("release checked the job");
        job.done[tile as usize] = true;
        job.remaining -= 1;
        actions.push(Action::AcceptTile { job: job_id, tile });
        if job.remaining == 0 {
            self.jobs.remove(&job_id);
            actions.push(Action::JobDone { job: job_id });
            self.forget_unused_scene(actions);
        }
    }

    /// After a job ended: workers may drop its scene unless another active job uses it.
    fn forget_unused_scene(&mut self, actions: &mut Vec<Action>) {
        let in_use: HashSet<SceneHash> = self.jobs.values().map(|j| j.scene).collect();
        for (&worker, w) in &mut self.workers {
            let unused: Vec<SceneHash> = w.scenes.difference(&in_use).copied().collect();
            for scene in unused {
                w.scenes.remove(&scene);
                actions.push(Action::ForgetScene { worker, scene });
            }
        }
    }

    /// Removes an active job, telling the workers that hold its tiles to drop them.
    fn end_job(&mut self, job_id: JobId, actions: &mut Vec<Action>) {
        let Some(job) = self.jobs.remove(&job_id) else {
            return;
        };
        let holders: BTreeSet<WorkerId> = job.in_flight.values().copied().collect();
        for worker in holders {
            if let Some(w) = self.workers.get_mut(&worker) {
                w.holding.retain(|(j, _)| *j != job_id);
                actions.push(Action::CancelOnWorker {
                    worker,
                    job: job_id,
                });
            }
        }
        self.forget_unused_scene(actions);
    }

    fn requeue(&mut self, job_id: JobId, tile: u32) {
        if let Some(job) = self.jobs.get_mut(&job_id) {
            if job.in_flight.remove(&tile).is_some() && !job.done[tile as usize] {
                // Back to the front: it was handed out first, so it is the oldest work.
                job.waiting.push_front(tile);
            }
        }
    }

    fn fill_all(&mut self, actions: &mut Vec<Action>) {
        let ids: Vec<WorkerId> = self.workers.keys().copied().collect();
        for worker in ids {
            self.fill(worker, actions);
        }
    }

    /// Gives the worker tiles until its credit is used or nothing is waiting.
    fn fill(&mut self, worker_id: WorkerId, actions: &mut Vec<Action>) {
        loop {
            let Some(worker) = self.workers.get(&worker_id) else {
                return;
            };
            if worker.draining || worker.holding.len() >= worker.credit {
                return;
            }
            let Some(job_id) = self.next_job() else {
                return;
            };
            let job = self
                .jobs
                .get_mut(&job_id)
                .expect("next_job returns an active job");
            let tile = job.waiting.pop_front().expect("next_job has waiting tiles");
            job.in_flight.insert(tile, worker_id);
            let scene = job.scene;
            let worker = self.workers.get_mut(&worker_id).expect("checked above");
            if worker.scenes.insert(scene) {
                actions.push(Action::SendScene {
                    worker: worker_id,
                    job: job_id,
                });
            }
            worker.holding.insert((job_id, tile));
            actions.push(Action::Assign {
                worker: worker_id,
                job: job_id,
                tile,
            });
        }
    }

    /// Highest priority, then fewest tiles in flight, then oldest.
    fn next_job(&self) -> Option<JobId> {
        self.jobs
            .iter()
            .filter(|(_, j)| !j.waiting.is_empty())
            .min_by_key(|(id, j)| (std::cmp::Reverse(j.priority), j.in_flight.len(), **id))
            .map(|(id, _)| *id)
    }
}

#[cfg(test)]
mod tests {
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

    fn submit(
        s: &mut Scheduler,
        job: JobId,
        priority: i32,
        scene: SceneHash,
        tiles: u32,
    ) -> Vec<Action> {
        s.handle(Event::JobSubmitted {
            job,
            priority,
            scene,
            tiles,
        })
    }

    #[test]
    fn a_worker_holds_its_credit_and_gets_the_next_tile_when_it_returns_one() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 10);
        let joined = s.handle(Event::WorkerJoined {
            worker: 7,
            threads: 1,
        });
        assert_eq!(joined[0], Action::SendScene { worker: 7, job: 1 });
        assert_eq!(assigns(&joined), vec![(7, 1, 0), (7, 1, 1)]);
        let done = s.handle(Event::TileDone {
            worker: 7,
            job: 1,
            tile: 0,
        });
        assert_eq!(done[0], Action::AcceptTile { job: 1, tile: 0 });
        assert_eq!(assigns(&done), vec![(7, 1, 2)]);
        assert_eq!(s.held_by(7), 2);
    }

    #[test]
    fn results_are_accepted_once_and_only_from_the_holder() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 3);
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
        });
        s.handle(Event::WorkerJoined {
            worker: 2,
            threads: 1,
        });
        // Tile 0 is worker 1's: worker 2's result for it is dropped.
        let stray = s.handle(Event::TileDone {
            worker: 2,
            job: 1,
            tile: 0,
        });
        assert!(!stray.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
        let first = s.handle(Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        });
        assert!(first.contains(&Action::AcceptTile { job: 1, tile: 0 }));
        let again = s.handle(Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        });
        assert!(!again.iter().any(|a| matches!(a, Action::AcceptTile { .. })));
    }

    #[test]
    fn a_leaving_worker_s_tiles_go_to_another_and_the_job_finishes() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 4);
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
        });
        let joined = s.handle(Event::WorkerJoined {
            worker: 2,
            threads: 1,
        });
        assert_eq!(assigns(&joined), vec![(2, 1, 2), (2, 1, 3)]);
        let left = s.handle(Event::WorkerLeft { worker: 1 });
        assert!(assigns(&left).is_empty(), "worker 2 is at its credit");
        let mut actions = Vec::new();
        for tile in [2, 3, 0, 1] {
            actions.extend(s.handle(Event::TileDone {
                worker: 2,
                job: 1,
                tile,
            }));
        }
        assert!(actions.contains(&Action::JobDone { job: 1 }));
        assert!(!s.is_active(1));
    }

    #[test]
    fn equal_priorities_share_the_farm_and_higher_priority_goes_first() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 100);
        submit(&mut s, 2, 0, SCENE_A, 4);
        let joined = s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 2,
        });
        // Fewest tiles in flight first: the two jobs alternate.
        assert_eq!(
            assigns(&joined),
            vec![(1, 1, 0), (1, 2, 0), (1, 1, 1), (1, 2, 1)]
        );
        let urgent = submit(&mut s, 3, 5, SCENE_B, 2);
        assert!(assigns(&urgent).is_empty(), "the worker is at its credit");
        let next = s.handle(Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        });
        assert_eq!(assigns(&next), vec![(1, 3, 0)]);
        assert!(next.contains(&Action::SendScene { worker: 1, job: 3 }));
    }

    #[test]
    fn cancelling_tells_the_holders_and_forgets_the_scene() {
        let mut s = Scheduler::new();
        submit(&mut s, 1, 0, SCENE_A, 10);
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
        });
        let cancelled = s.handle(Event::CancelJob { job: 1 });
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
    fn a_draining_worker_gets_nothing_more_and_a_failure_fails_the_job() {
        let mut s = Scheduler::new();
        s.handle(Event::WorkerJoined {
            worker: 1,
            threads: 1,
        });
        s.handle(Event::WorkerDraining { worker: 1 });
        assert!(assigns(&submit(&mut s, 1, 0, SCENE_A, 3)).is_empty());
        s.handle(Event::WorkerJoined {
            worker: 2,
            threads: 1,
        });
        let failed = s.handle(Event::TileFailed {
            worker: 2,
            job: 1,
            tile: 0,
            message: "boom".into(),
        });
        assert!(failed.contains(&Action::JobFailed {
            job: 1,
            message: "boom".into()
        }));
        assert!(!s.is_active(1));
    }
}
