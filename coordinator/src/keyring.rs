//! The coordinator's secrets over time, as a pure state machine: which secret of a
//! role a peer's handshake proves, what a reload of the token files changes, and when
//! the secret it replaced stops being accepted. Time is passed in (milliseconds on the
//! daemon's monotonic clock); reading files, logging and disconnecting peers happen
//! around it, in the server.
//!
//! A reload that changes a role's secret opens an overlap window: until it closes, the
//! previous secret is accepted beside the new one, so that workers and clients can be
//! given the new token one by one without any of them being refused meanwhile. When it
//! closes, the previous secret is retired: new handshakes with it are refused, and the
//! server ends the connections that proved it, whose peers reconnect with the token
//! their file holds by then.

use protocol::{AuthRole, KeyId, KeyStanding, PeerKey};
use scheduler::Millis;
use thiserror::Error;

/// Retired key ids remembered per role, to tell a peer that its token was rotated out
/// rather than that it is unknown.
const RETIRED_KEPT: usize = 4;

/// One secret and its names.
#[derive(Clone, Debug)]
struct Key {
    secret: Vec<u8>,
    id: KeyId,
    /// Distinct for every secret ever loaded, so that a connection knows whether the
    /// secret it proved is still held even when a later reload brings the same bytes
    /// back.
    generation: u64,
}

/// A role's secrets.
#[derive(Clone, Debug)]
struct RoleKeys {
    current: Key,
    /// The secret the last reload replaced, and when its window closes.
    previous: Option<(Key, Millis)>,
    /// The ids of secrets retired lately, newest last.
    retired: Vec<KeyId>,
}

impl RoleKeys {
    fn retire(&mut self, id: KeyId) {
        self.retired.retain(|&r| r != id);
        self.retired.push(id);
        if self.retired.len() > RETIRED_KEPT {
            self.retired.remove(0);
        }
    }
}

/// The secret a connection proved: enough to tell later whether it is still held.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Held {
    pub role: AuthRole,
    pub id: KeyId,
    generation: u64,
}

/// What the coordinator does with a peer's `Hello`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Choice {
    /// The role has no secret: the peer is accepted without proof.
    Open,
    /// Challenge the peer with this secret; once it proves it, it holds `held`.
    Prove { secret: Vec<u8>, held: Held },
    /// Refuse it at once, saying why.
    Refuse(KeyRefusal),
}

/// Why a peer's key id is refused before any proof: the coordinator holds no secret
/// under it. Each text is one line and names the peer's key id.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum KeyRefusal {
    #[error(
        "authentication failed: this {role} token (key {key}) was retired by a token \
         rotation on the coordinator: give this {role} the farm's new {role} token"
    )]
    Retired { role: AuthRole, key: KeyId },
    #[error(
        "authentication failed: this {role} token (key {key}) is not the coordinator's \
         {role} token (another role's, another farm's, mistyped, or retired long ago)"
    )]
    Unknown { role: AuthRole, key: KeyId },
}

/// Why a reload changed nothing.
#[derive(Clone, Debug, PartialEq, Eq, Error)]
pub enum ReloadError {
    #[error(
        "the new worker token and the new client token are the same secret, so any client \
         could join as a worker: give two different secrets"
    )]
    SameSecret,
    #[error(
        "a reload cannot {} the {role} token (it was {} at start): restart the coordinator \
         to change that",
        if *had { "remove" } else { "add" },
        if *had { "set" } else { "not set" }
    )]
    Presence { role: AuthRole, had: bool },
}

/// What a reload did to one role's secret.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Change {
    /// The role has no secret.
    None,
    /// The file holds the secret already current.
    Unchanged { current: KeyId },
    /// A new secret is current; `previous` is accepted until `until`.
    Rotated {
        current: KeyId,
        previous: KeyId,
        until: Millis,
    },
}

/// The secrets of both roles.
#[derive(Clone, Debug)]
pub struct Keyring {
    worker: Option<RoleKeys>,
    client: Option<RoleKeys>,
    /// How long a replaced secret stays accepted, in milliseconds.
    overlap: Millis,
    /// The last generation given out.
    generations: u64,
}

impl Keyring {
    /// The secrets the coordinator starts with (a role without one admits its peers
    /// without proof), and the overlap window of later reloads.
    pub fn new(worker: Option<Vec<u8>>, client: Option<Vec<u8>>, overlap: Millis) -> Keyring {
        let mut ring = Keyring {
            worker: None,
            client: None,
            overlap,
            generations: 0,
        };
        ring.worker = worker.map(|s| ring.fresh_role(s));
        ring.client = client.map(|s| ring.fresh_role(s));
        ring
    }

    fn key(&mut self, secret: Vec<u8>) -> Key {
        self.generations += 1;
        Key {
            id: KeyId::of(&secret),
            secret,
            generation: self.generations,
        }
    }

    fn fresh_role(&mut self, secret: Vec<u8>) -> RoleKeys {
        RoleKeys {
            current: self.key(secret),
            previous: None,
            retired: Vec::new(),
        }
    }

    fn role(&self, role: AuthRole) -> Option<&RoleKeys> {
        match role {
            AuthRole::Worker => self.worker.as_ref(),
            AuthRole::Client => self.client.as_ref(),
        }
    }

    fn role_mut(&mut self, role: AuthRole) -> Option<&mut RoleKeys> {
        match role {
            AuthRole::Worker => self.worker.as_mut(),
            AuthRole::Client => self.client.as_mut(),
        }
    }

    /// The current key id of `role`, if it has a secret.
    pub fn current(&self, role: AuthRole) -> Option<KeyId> {
        self.role(role).map(|keys| keys.current.id)
    }

    /// Which secret a peer of `role` whose hello names `key` must prove at `now`.
    ///
    /// A peer that names no key is challenged with the current secret: it holds none,
    /// and the challenge tells it that one is required.
    pub fn choose(&self, role: AuthRole, key: Option<KeyId>, now: Millis) -> Choice {
        let Some(keys) = self.role(role) else {
            return Choice::Open;
        };
        let prove = |k: &Key| Choice::Prove {
            secret: k.secret.clone(),
            held: Held {
                role,
                id: k.id,
                generation: k.generation,
            },
        };
        let Some(key) = key else {
            return prove(&keys.current);
        };
        if key == keys.current.id {
            return prove(&keys.current);
        }
        match &keys.previous {
            Some((previous, until)) if previous.id == key && now < *until => prove(previous),
            Some((previous, _)) if previous.id == key => {
                Choice::Refuse(KeyRefusal::Retired { role, key })
            }
            _ if keys.retired.contains(&key) => Choice::Refuse(KeyRefusal::Retired { role, key }),
            _ => Choice::Refuse(KeyRefusal::Unknown { role, key }),
        }
    }

    /// Where the secret a connection proved stands now: `None` once it is retired (or
    /// replaced twice), when the connection must end.
    pub fn standing(&self, held: Held) -> Option<KeyStanding> {
        let keys = self.role(held.role)?;
        if keys.current.generation == held.generation {
            return Some(KeyStanding::Current);
        }
        match &keys.previous {
            Some((previous, _)) if previous.generation == held.generation => {
                Some(KeyStanding::Previous)
            }
            _ => None,
        }
    }

    /// The held secret as listings show it, if it is still held.
    pub fn peer_key(&self, held: Held) -> Option<PeerKey> {
        self.standing(held).map(|standing| PeerKey {
            id: held.id,
            standing,
        })
    }

    /// The secrets of `role` accepted at `now` (for the HTTP controls, which compare a
    /// bearer token with them): none if the role has no secret.
    pub fn accepted(&self, role: AuthRole, now: Millis) -> Vec<&[u8]> {
        let Some(keys) = self.role(role) else {
            return Vec::new();
        };
        let mut accepted = vec![keys.current.secret.as_slice()];
        if let Some((previous, until)) = &keys.previous {
            if now < *until {
                accepted.push(previous.secret.as_slice());
            }
        }
        accepted
    }

    /// Takes the secrets the token files hold now, at `now`. A role whose secret
    /// changed keeps its current one as the previous, accepted for the overlap window;
    /// a previous one still in its window is retired at once. On an error nothing
    /// changes.
    pub fn reload(
        &mut self,
        worker: Option<Vec<u8>>,
        client: Option<Vec<u8>>,
        now: Millis,
    ) -> Result<(Change, Change), ReloadError> {
        for (role, new) in [(AuthRole::Worker, &worker), (AuthRole::Client, &client)] {
            let had = self.role(role).is_some();
            if had != new.is_some() {
                return Err(ReloadError::Presence { role, had });
            }
        }
        if worker.is_some() && worker == client {
            return Err(ReloadError::SameSecret);
        }
        let worker = self.replace(AuthRole::Worker, worker, now);
        let client = self.replace(AuthRole::Client, client, now);
        Ok((worker, client))
    }

    fn replace(&mut self, role: AuthRole, secret: Option<Vec<u8>>, now: Millis) -> Change {
        let Some(secret) = secret else {
            return Change::None;
        };
        let until = now.saturating_add(self.overlap);
        let key = self.key(secret);
        let keys = self.role_mut(role).expect("checked by reload");
        if keys.current.secret == key.secret {
            return Change::Unchanged {
                current: keys.current.id,
            };
        }
        let replaced = std::mem::replace(&mut keys.current, key);
        if let Some((displaced, _)) = keys.previous.take() {
            keys.retire(displaced.id);
        }
        keys.retired.retain(|&r| r != keys.current.id);
        let change = Change::Rotated {
            current: keys.current.id,
            previous: replaced.id,
            until,
        };
        keys.previous = Some((replaced, until));
        change
    }

    /// Retires the previous secrets whose window has closed by `now`: their roles and
    /// key ids.
    pub fn expire(&mut self, now: Millis) -> Vec<(AuthRole, KeyId)> {
        let mut retired = Vec::new();
        for role in [AuthRole::Worker, AuthRole::Client] {
            let Some(keys) = self.role_mut(role) else {
                continue;
            };
            if let Some((previous, until)) = &keys.previous {
                if now >= *until {
                    let id = previous.id;
                    keys.previous = None;
                    keys.retire(id);
                    retired.push((role, id));
                }
            }
        }
        retired
    }

    /// When the next overlap window closes, if one is open.
    pub fn next_expiry(&self) -> Option<Millis> {
        [&self.worker, &self.client]
            .into_iter()
            .flatten()
            .filter_map(|keys| keys.previous.as_ref().map(|&(_, until)| until))
            .min()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const WINDOW: Millis = 2_000;

    fn ring() -> Keyring {
        Keyring::new(Some(b"w1".to_vec()), Some(b"c1".to_vec()), WINDOW)
    }

    fn id(secret: &[u8]) -> KeyId {
        KeyId::of(secret)
    }

    /// The secret a peer naming `key` must prove, or why it is refused.
    fn proves(ring: &Keyring, role: AuthRole, key: &[u8], now: Millis) -> Result<Vec<u8>, String> {
        match ring.choose(role, Some(id(key)), now) {
            Choice::Prove { secret, held } => {
                assert_eq!(held.id, id(&secret));
                Ok(secret)
            }
            Choice::Refuse(why) => Err(why.to_string()),
            Choice::Open => panic!("open"),
        }
    }

    fn held(ring: &Keyring, role: AuthRole, key: &[u8], now: Millis) -> Held {
        match ring.choose(role, Some(id(key)), now) {
            Choice::Prove { held, .. } => held,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_peer_proves_the_secret_its_key_id_names() {
        let ring = ring();
        assert_eq!(
            proves(&ring, AuthRole::Worker, b"w1", 0),
            Ok(b"w1".to_vec())
        );
        assert_eq!(
            proves(&ring, AuthRole::Client, b"c1", 0),
            Ok(b"c1".to_vec())
        );
        // Another role's token is unknown to this role.
        assert_eq!(
            proves(&ring, AuthRole::Worker, b"c1", 0).unwrap_err(),
            format!(
                "authentication failed: this worker token (key {}) is not the coordinator's \
                 worker token (another role's, another farm's, mistyped, or retired long ago)",
                id(b"c1")
            )
        );
        // No key id: challenged with the current secret (and told it needs one).
        assert!(matches!(
            ring.choose(AuthRole::Client, None, 0),
            Choice::Prove { secret, .. } if secret == b"c1"
        ));
        // A role without a secret is open.
        let open = Keyring::new(Some(b"w".to_vec()), None, WINDOW);
        assert_eq!(
            open.choose(AuthRole::Client, Some(id(b"x")), 0),
            Choice::Open
        );
        assert_eq!(open.current(AuthRole::Client), None);
    }

    #[test]
    fn after_a_rotation_both_secrets_pass_until_the_window_closes() {
        let mut ring = ring();
        let old_worker = held(&ring, AuthRole::Worker, b"w1", 0);
        let changes = ring
            .reload(Some(b"w2".to_vec()), Some(b"c2".to_vec()), 1_000)
            .unwrap();
        assert_eq!(
            changes.0,
            Change::Rotated {
                current: id(b"w2"),
                previous: id(b"w1"),
                until: 3_000
            }
        );
        assert_eq!(ring.next_expiry(), Some(3_000));
        // Within the window: both, and a connection on the old one is "previous".
        for now in [1_000, 2_999] {
            assert_eq!(
                proves(&ring, AuthRole::Worker, b"w1", now),
                Ok(b"w1".to_vec())
            );
            assert_eq!(
                proves(&ring, AuthRole::Worker, b"w2", now),
                Ok(b"w2".to_vec())
            );
            assert_eq!(
                proves(&ring, AuthRole::Client, b"c1", now),
                Ok(b"c1".to_vec())
            );
            assert_eq!(ring.accepted(AuthRole::Client, now).len(), 2);
        }
        assert_eq!(ring.standing(old_worker), Some(KeyStanding::Previous));
        let new_worker = held(&ring, AuthRole::Worker, b"w2", 1_500);
        assert_eq!(
            ring.peer_key(new_worker),
            Some(PeerKey {
                id: id(b"w2"),
                standing: KeyStanding::Current
            })
        );
        // The window closes at 3000 even before `expire` runs...
        let retired = format!(
            "authentication failed: this worker token (key {}) was retired by a token \
             rotation on the coordinator: give this worker the farm's new worker token",
            id(b"w1")
        );
        assert_eq!(
            proves(&ring, AuthRole::Worker, b"w1", 3_000),
            Err(retired.clone())
        );
        assert_eq!(ring.accepted(AuthRole::Client, 3_000), [b"c2".as_slice()]);
        // ...and `expire` retires it: its connections are no longer held.
        assert_eq!(ring.expire(2_999), []);
        assert_eq!(
            ring.expire(3_000),
            [(AuthRole::Worker, id(b"w1")), (AuthRole::Client, id(b"c1"))]
        );
        assert_eq!(ring.next_expiry(), None);
        assert_eq!(ring.standing(old_worker), None);
        assert_eq!(ring.standing(new_worker), Some(KeyStanding::Current));
        assert_eq!(proves(&ring, AuthRole::Worker, b"w1", 3_000), Err(retired));
        assert_eq!(
            proves(&ring, AuthRole::Worker, b"w2", 99_000),
            Ok(b"w2".to_vec())
        );
    }

    #[test]
    fn an_unchanged_file_keeps_the_window_and_a_second_rotation_retires_the_first() {
        let mut ring = ring();
        let first = held(&ring, AuthRole::Worker, b"w1", 0);
        ring.reload(Some(b"w2".to_vec()), Some(b"c1".to_vec()), 0)
            .unwrap();
        // The same files again: nothing moves, the window is not reopened.
        let again = ring
            .reload(Some(b"w2".to_vec()), Some(b"c1".to_vec()), 500)
            .unwrap();
        assert_eq!(
            again,
            (
                Change::Unchanged { current: id(b"w2") },
                Change::Unchanged { current: id(b"c1") }
            )
        );
        assert_eq!(ring.next_expiry(), Some(WINDOW));
        let second = held(&ring, AuthRole::Worker, b"w2", 600);
        // A third secret within the window: w1 is retired at once, w2 is previous.
        ring.reload(Some(b"w3".to_vec()), Some(b"c1".to_vec()), 1_000)
            .unwrap();
        assert_eq!(ring.standing(first), None);
        assert_eq!(ring.standing(second), Some(KeyStanding::Previous));
        assert!(proves(&ring, AuthRole::Worker, b"w1", 1_000)
            .unwrap_err()
            .contains("was retired"));
        assert_eq!(ring.next_expiry(), Some(1_000 + WINDOW));
        // Back to w1: a new generation, so the connections of the old w1 stay ended.
        ring.reload(Some(b"w1".to_vec()), Some(b"c1".to_vec()), 1_500)
            .unwrap();
        assert_eq!(ring.standing(first), None);
        assert_eq!(
            proves(&ring, AuthRole::Worker, b"w1", 1_500),
            Ok(b"w1".to_vec())
        );
    }

    #[test]
    fn a_bad_reload_changes_nothing() {
        let mut ring = ring();
        assert_eq!(
            ring.reload(Some(b"same".to_vec()), Some(b"same".to_vec()), 0),
            Err(ReloadError::SameSecret)
        );
        assert_eq!(
            ring.reload(Some(b"w2".to_vec()), None, 0)
                .unwrap_err()
                .to_string(),
            "a reload cannot remove the client token (it was set at start): restart the \
             coordinator to change that"
        );
        let mut open = Keyring::new(None, None, WINDOW);
        assert_eq!(
            open.reload(Some(b"w".to_vec()), None, 0),
            Err(ReloadError::Presence {
                role: AuthRole::Worker,
                had: false
            })
        );
        assert_eq!(open.reload(None, None, 0), Ok((Change::None, Change::None)));
        assert_eq!(
            proves(&ring, AuthRole::Worker, b"w1", 0),
            Ok(b"w1".to_vec())
        );
        assert_eq!(ring.next_expiry(), None);
    }
}
