//! The I/O around [`crate::keyring::Keyring`]: reloading the secrets (the binary reads
//! the token files on SIGHUP), closing overlap windows on time, and the hold each
//! authenticated connection keeps on the secret it proved, which ends the connection
//! once that secret is retired.

use std::sync::Arc;
use std::time::Duration;

use protocol::PeerKey;
use tokio::sync::watch;
use tracing::{info, warn};

use super::Shared;
use crate::keyring::{Change, Held, Keyring, ReloadError};

/// Reloads the coordinator's secrets: a cheap handle, for the task that waits for
/// SIGHUP.
#[derive(Clone)]
pub struct TokenReloader {
    shared: Arc<Shared>,
}

impl TokenReloader {
    pub(super) fn new(shared: Arc<Shared>) -> Self {
        TokenReloader { shared }
    }

    /// Makes these the current secrets (as the token files hold them now), keeping the
    /// ones they replace for the overlap window, and logs what changed in one line. On
    /// an error nothing changes (the caller logs it).
    pub fn reload(
        &self,
        worker: Option<Vec<u8>>,
        client: Option<Vec<u8>>,
    ) -> Result<(), ReloadError> {
        let now = self.shared.now();
        let mut outcome = None;
        self.shared.keys.send_if_modified(|ring| {
            let result = ring.reload(worker, client, now);
            let changed = result.as_ref().is_ok_and(|(w, c)| {
                [w, c]
                    .iter()
                    .any(|change| matches!(change, Change::Rotated { .. }))
            });
            outcome = Some(result);
            changed
        });
        let (worker, client) = outcome.expect("the closure ran")?;
        info!(
            worker = %describe(worker, now),
            client = %describe(client, now),
            "reloaded the token files"
        );
        Ok(())
    }
}

impl TokenReloader {
    /// Makes `scrape` the token `/metrics` takes from now on (no overlap: Prometheus
    /// reads its credentials file at every scrape, so both change together).
    pub fn reload_scrape(&self, scrape: Option<Vec<u8>>) {
        let changed = *self
            .shared
            .scrape
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            != scrape;
        if changed {
            info!(
                scrape = if scrape.is_some() {
                    "replaced"
                } else {
                    "removed"
                },
                "reloaded the scrape token"
            );
        }
        *self
            .shared
            .scrape
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = scrape;
    }
}

/// A role's change as the reload's log line says it.
fn describe(change: Change, now: scheduler::Millis) -> String {
    match change {
        Change::None => "no token".into(),
        Change::Unchanged { current } => format!("key {current} (unchanged)"),
        Change::Rotated {
            current,
            previous,
            until,
        } => format!(
            "key {current} (current), key {previous} (previous, accepted for {} s more)",
            until.saturating_sub(now).div_ceil(1000)
        ),
    }
}

/// Retires each previous secret when its overlap window closes, for as long as the
/// coordinator serves.
pub(super) async fn retire(sh: Arc<Shared>) {
    let mut keys = sh.keys.subscribe();
    loop {
        let next = keys.borrow_and_update().next_expiry();
        let window = async {
            match next {
                Some(at) => {
                    let at = sh.clock + Duration::from_millis(at);
                    tokio::time::sleep_until(tokio::time::Instant::from_std(at)).await
                }
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            () = window => {}
            changed = keys.changed() => {
                if changed.is_err() {
                    return;
                }
                continue;
            }
        }
        let now = sh.now();
        let mut retired = Vec::new();
        sh.keys.send_if_modified(|ring| {
            retired = ring.expire(now);
            !retired.is_empty()
        });
        for (role, key) in retired {
            warn!(
                role = role.name(),
                key = %key,
                "the overlap window closed: the previous {role} key is retired, and the \
                 {role}s still using it are disconnected"
            );
        }
    }
}

/// The secret an authenticated connection proved, watched.
#[derive(Clone)]
pub(super) struct KeyHold {
    held: Held,
    keys: watch::Receiver<Keyring>,
}

impl KeyHold {
    pub(super) fn new(sh: &Shared, held: Held) -> Self {
        KeyHold {
            held,
            keys: sh.keys.subscribe(),
        }
    }

    /// The secret as listings and logs show it: its key id and whether it is current.
    /// `None` once retired.
    pub(super) fn peer_key(&self) -> Option<PeerKey> {
        self.keys.borrow().peer_key(self.held)
    }

    /// `3f2a91c0 (current)`, for log lines.
    pub(super) fn describe(&self) -> String {
        self.peer_key()
            .map_or_else(|| format!("{} (retired)", self.held.id), |k| k.to_string())
    }

    /// Completes once the secret is retired: the connection must end.
    pub(super) async fn retired(&mut self) {
        loop {
            if self.keys.borrow_and_update().standing(self.held).is_none() {
                return;
            }
            if self.keys.changed().await.is_err() {
                return std::future::pending().await;
            }
        }
    }
}

/// [`KeyHold::retired`] of a connection that may hold no secret (its role has none):
/// then it never completes.
pub(super) async fn retired(hold: &mut Option<KeyHold>) {
    match hold {
        Some(hold) => hold.retired().await,
        None => std::future::pending().await,
    }
}
