//! The workers as the scheduler knows them: a [`Worker`]'s credit, the tiles it holds
//! and whether it takes tiles, and the [`Machine`] its failures count against. What
//! the scheduler remembers of each connection, apart from the decisions made with it.

use std::collections::BTreeSet;
use std::fmt;

use protocol::{JobId, SceneHash, WorkerId};

use super::Millis;

/// Who failures are counted against: the name a worker gave, or its connection.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(super) enum Machine {
    Named(String),
    Connection(WorkerId),
}

impl fmt::Display for Machine {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Machine::Named(name) => f.write_str(name),
            Machine::Connection(id) => write!(f, "worker {id}"),
        }
    }
}

/// Machines named in a message: the first few, so that a farm of thousands keeps the
/// message on one readable line (and no control character a worker put in its name
/// breaks it).
pub(super) fn name_list(machines: &[&Machine]) -> String {
    const SHOWN: usize = 8;
    let printable = |m: &&Machine| m.to_string().replace(char::is_control, "?");
    let mut list: Vec<String> = machines.iter().take(SHOWN).map(printable).collect();
    if machines.len() > SHOWN {
        list.push(format!("and {} more", machines.len() - SHOWN));
    }
    list.join(", ")
}

pub(super) struct Worker {
    pub(super) machine: Machine,
    pub(super) threads: u32,
    pub(super) credit: usize,
    pub(super) holding: BTreeSet<(JobId, u32)>,
    pub(super) scenes: BTreeSet<SceneHash>,
    pub(super) draining: bool,
    /// Its machine is disabled by an operator: like draining, but undone by an enable.
    pub(super) disabled: bool,
    pub(super) last_seen: Millis,
    /// It holds tiles whose leases ran out and returned nothing for longer than its
    /// progress allowance: its heartbeats prove a connection, not that it renders. It
    /// gets no tile and counts for no one (see the [module doc](super)) until a result
    /// comes.
    pub(super) unresponsive: bool,
    /// Since when a result is due from it: its last result, or when it was last given
    /// a tile while holding none.
    pub(super) progress_since: Millis,
    /// The longest it took to return a result once it was free to work on it (since
    /// the tile's lease began or its previous result, whichever is later): its pace.
    pub(super) slowest_result: Millis,
}

impl Worker {
    /// Whether it may be given new tiles.
    pub(super) fn takes_tiles(&self) -> bool {
        !self.draining && !self.disabled && !self.unresponsive
    }
}
