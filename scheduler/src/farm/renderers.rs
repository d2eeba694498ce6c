//! Which machine rendered each accepted tile of the active jobs, so that the core can
//! take back what a machine caught returning wrong pixels rendered
//! ([`Input::Quarantine`](super::Input::Quarantine)). Kept per job as one small
//! number per tile (the machines' names are interned), only while the job is active:
//! a finished job's tiles are too late to take back.

use std::collections::BTreeMap;
use std::sync::Arc;

use protocol::{JobId, WorkerId};

use crate::tiles::ByWorker;

/// No machine known for the tile (not accepted, or rendered by an unnamed worker).
const NONE: u32 = u32::MAX;

#[derive(Default)]
pub(super) struct Renderers {
    /// The machines' names, interned: ordered rather than hashed, so that the table
    /// never grows by hashing every name again at one join.
    names: Vec<Arc<str>>,
    ids: BTreeMap<Arc<str>, u32>,
    /// The machine of each connected worker, looked up on every result.
    by_worker: ByWorker<u32>,
    /// The machine of each result held for confirmation.
    held: BTreeMap<(JobId, u32), u32>,
    /// Per active job, the machine that rendered each accepted tile.
    accepted: BTreeMap<JobId, Vec<u32>>,
}

impl Renderers {
    fn intern(&mut self, name: &str) -> u32 {
        if let Some(&id) = self.ids.get(name) {
            return id;
        }
        let id = self.names.len() as u32;
        let name: Arc<str> = Arc::from(name);
        self.names.push(Arc::clone(&name));
        self.ids.insert(name, id);
        id
    }

    pub(super) fn joined(&mut self, worker: WorkerId, machine: Option<&str>) {
        match machine {
            Some(name) => {
                let id = self.intern(name);
                self.by_worker.insert(worker, id);
            }
            None => {
                self.by_worker.remove(&worker);
            }
        }
    }

    pub(super) fn left(&mut self, worker: WorkerId) {
        self.by_worker.remove(&worker);
    }

    fn set(&mut self, job: JobId, tile: u32, tiles: u32, machine: u32) {
        let by_tile = self
            .accepted
            .entry(job)
            .or_insert_with(|| vec![NONE; tiles as usize]);
        if let Some(slot) = by_tile.get_mut(tile as usize) {
            *slot = machine;
        }
    }

    /// The worker's result for the tile is accepted.
    pub(super) fn accepted(&mut self, job: JobId, tile: u32, tiles: u32, worker: Option<WorkerId>) {
        let machine = worker
            .and_then(|w| self.by_worker.get(&w).copied())
            .unwrap_or(NONE);
        self.set(job, tile, tiles, machine);
    }

    /// The worker's result for the tile is held for confirmation.
    pub(super) fn held(&mut self, job: JobId, tile: u32, worker: WorkerId) {
        if let Some(&machine) = self.by_worker.get(&worker) {
            self.held.insert((job, tile), machine);
        }
    }

    /// The result held for the tile is accepted as it is.
    pub(super) fn accepted_held(&mut self, job: JobId, tile: u32, tiles: u32) {
        let machine = self.held.remove(&(job, tile)).unwrap_or(NONE);
        self.set(job, tile, tiles, machine);
    }

    /// Tiles stored before a restart, with the machine of each.
    pub(super) fn restored(&mut self, job: JobId, tiles: u32, done: &[(u32, &str)]) {
        for &(tile, name) in done {
            let machine = self.intern(name);
            self.set(job, tile, tiles, machine);
        }
    }

    /// An operator put the tiles back in the queue: nobody has rendered them now.
    pub(super) fn requeued(&mut self, job: JobId, tiles: &[u32]) {
        if let Some(by_tile) = self.accepted.get_mut(&job) {
            for &t in tiles {
                if let Some(slot) = by_tile.get_mut(t as usize) {
                    *slot = NONE;
                }
            }
        }
        self.held
            .retain(|&(j, t), _| j != job || !tiles.contains(&t));
    }

    /// The job is no longer active: nothing of it can be taken back.
    pub(super) fn forget_job(&mut self, job: JobId) {
        self.accepted.remove(&job);
        self.held.retain(|(j, _), _| *j != job);
    }

    /// The tiles `machine` rendered in the jobs `active` says are active, in job and
    /// tile order, forgotten here (they will be rendered again).
    pub(super) fn take_back(
        &mut self,
        machine: &str,
        active: impl Fn(JobId) -> bool,
    ) -> Vec<(JobId, Vec<u32>)> {
        let Some(&id) = self.ids.get(machine) else {
            return Vec::new();
        };
        self.held.retain(|_, m| *m != id);
        let mut taken = Vec::new();
        for (&job, by_tile) in &mut self.accepted {
            if !active(job) {
                continue;
            }
            let tiles: Vec<u32> = (0..by_tile.len() as u32)
                .filter(|&t| by_tile[t as usize] == id)
                .collect();
            for &t in &tiles {
                by_tile[t as usize] = NONE;
            }
            if !tiles.is_empty() {
                taken.push((job, tiles));
            }
        }
        taken
    }
}
