//! Virtual time: the messages that cross the simulated network, every event of a run
//! ([`Ev`]), and the agenda that hands them out earliest first, in the order they were
//! scheduled at equal times. The agenda alone decides what happens next, which is
//! what makes a seed name one run exactly.

use std::cmp::Ordering;
use std::collections::BinaryHeap;

use protocol::JobId;

use super::Micros;

/// Worker to coordinator.
#[derive(Clone, Copy, Debug)]
pub(super) enum Up {
    Hello,
    Heartbeat,
    TileDone {
        job: JobId,
        tile: u32,
        /// When the coordinator sent it and when its render began.
        sent: Micros,
        started: Micros,
    },
    /// The connection closed (the process died).
    Closed,
}

/// Coordinator to worker.
#[derive(Clone, Copy, Debug)]
pub(super) enum Down {
    /// The handshake's `Accepted`.
    Welcome,
    Render {
        job: JobId,
        tile: u32,
        sent: Micros,
    },
    Cancel {
        job: JobId,
    },
    /// The coordinator closed the connection.
    Close,
}

#[derive(Clone, Copy, Debug)]
pub(super) enum Ev {
    /// The daemon's timer, armed for the earlier of the two machines' next deadlines.
    Wake,
    /// The core stopped handing out tiles at the bound of one call: it goes on at
    /// once, after what arrived first.
    Continue,
    /// A client's submission of the job (its index in the run) reaches the coordinator.
    Submit {
        job: usize,
    },
    /// The write in progress on the persistence thread ends (it succeeded unless the
    /// disk failed meanwhile).
    WriteDone,
    /// The persistence thread tries a failed write again.
    WriteRetry,
    /// A finished job's image is encoded: it goes to the writer.
    ImageEncoded {
        job: JobId,
    },
    /// A pass of a job in passes is added up (off the lock): its totals reach the
    /// core.
    PassAddedUp {
        job: JobId,
        pass: u32,
        rungs: (u32, u32),
    },
    /// A machine starts (at the beginning or joining later).
    Boot {
        machine: usize,
    },
    Reconnect {
        machine: usize,
    },
    NextJoin,
    /// A message reaches the coordinator.
    Arrival {
        conn: usize,
        msg: Up,
    },
    /// A message reaches a worker.
    Delivery {
        conn: usize,
        msg: Down,
    },
    /// After a `DropWorker`, the connection's task reports `WorkerLeft`.
    ConnectionTaskLeft {
        conn: usize,
    },
    RenderDone {
        machine: usize,
        epoch: u32,
        render: u64,
    },
    HeartbeatTimer {
        machine: usize,
        epoch: u32,
        conn: usize,
    },
    Crash {
        machine: usize,
        epoch: u32,
    },
    Hang {
        machine: usize,
        epoch: u32,
    },
    Thaw {
        machine: usize,
    },
    /// The machine's render threads stop; its runtime goes on.
    RenderHang {
        machine: usize,
        epoch: u32,
    },
    RenderThaw {
        machine: usize,
    },
    /// A crashed machine's supervisor starts its worker again.
    Restart {
        machine: usize,
    },
    /// The network between the machine and the coordinator goes down.
    Cut {
        machine: usize,
    },
    /// The whole coordinator stops, and runs again.
    CoordinatorPause,
    CoordinatorResume,
    /// The disk stops taking writes, and takes them again.
    StorageOutage,
    StorageRecovered,
}

impl Ev {
    /// Whether the coordinator's process handles it (and so, while paused, it waits).
    pub(super) fn at_coordinator(&self) -> bool {
        matches!(
            self,
            Ev::Wake
                | Ev::Continue
                | Ev::Submit { .. }
                | Ev::Arrival { .. }
                | Ev::ConnectionTaskLeft { .. }
                | Ev::WriteDone
                | Ev::WriteRetry
                | Ev::ImageEncoded { .. }
                | Ev::PassAddedUp { .. }
        )
    }
}

pub(super) struct Scheduled {
    pub(super) at: Micros,
    seq: u64,
    pub(super) ev: Ev,
}

impl PartialEq for Scheduled {
    fn eq(&self, other: &Self) -> bool {
        (self.at, self.seq) == (other.at, other.seq)
    }
}
impl Eq for Scheduled {}
impl PartialOrd for Scheduled {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Scheduled {
    /// Earliest first, and in scheduling order at equal times: a min-heap on (at, seq).
    fn cmp(&self, other: &Self) -> Ordering {
        (other.at, other.seq).cmp(&(self.at, self.seq))
    }
}

#[derive(Default)]
pub(super) struct Agenda {
    pub(super) heap: BinaryHeap<Scheduled>,
    seq: u64,
}

impl Agenda {
    pub(super) fn push(&mut self, at: Micros, ev: Ev) {
        self.seq += 1;
        self.heap.push(Scheduled {
            at,
            seq: self.seq,
            ev,
        });
    }
}
