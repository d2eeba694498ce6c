//! Webhooks (docs/operations.md, "Webhooks"): each job's end (`done`, `failed`,
//! `cancelled`) posted as JSON to every `--webhook URL`, signed, retried with backoff,
//! delivered at least once across restarts.
//!
//! This module holds the decisions, apart from the I/O that carries them out
//! (`server::webhooks`): one [`Delivery`] per webhook URL, a pure state machine that
//! takes [`Event`]s (an end recorded, an answer, a failure, the time passing; the time
//! is always passed in) and answers [`Action`]s (post this, persist this cursor, drop,
//! give up, wake me then). What a webhook needs to survive a restart is one number,
//! its cursor: every farm event up to it is settled (delivered, given up, dropped, or
//! not a job's end), and a restarted coordinator resumes after it from the farm's
//! event table.
//!
//! The event id a receiver gets is the farm event's id (docs/events.md): it never
//! repeats across restarts, so a receiver deduplicates on it.
//!
//! The rules, stated once:
//!
//! - Events are posted one at a time, in id order (one in flight per webhook).
//! - A post answered 2xx is delivered. Anything else (another status, a redirect, a
//!   refused connection, a timeout, a TLS failure) is a failed attempt, retried after
//!   `backoff × 2^(failures−1)`, capped at [`MAX_BACKOFF`].
//! - An event is given up after `attempts` failed attempts, or after a failed attempt
//!   once it is older than `max_age` (so an event found old after a long outage still
//!   gets one try): one log line with the last status or error, counted.
//! - At most `queue` events wait behind the first (the one being posted, or waiting for
//!   its retry, which only its own attempts settle); when one more comes, the oldest of
//!   them is dropped (a receiver back from an outage gets the newest ends), counted. Events the farm's retention deleted before they were delivered count as
//!   dropped too.

use std::collections::VecDeque;
use std::time::Duration;

/// The job ends a webhook is told of: the farm event kinds it posts.
pub const KINDS: &[&str] = &["done", "failed", "cancelled"];

/// Events waiting per webhook by default (`--webhook-queue`).
pub const DEFAULT_QUEUE: usize = 1000;

/// Failed attempts after which an event is given up by default (`--webhook-attempts`).
pub const DEFAULT_ATTEMPTS: u32 = 10;

/// The first retry's delay by default (`--webhook-backoff`); each next one doubles.
pub const DEFAULT_BACKOFF: Duration = Duration::from_secs(1);

/// The longest delay between two attempts.
pub const MAX_BACKOFF: Duration = Duration::from_secs(300);

/// Age after which an event's next failed attempt is its last.
pub const DEFAULT_MAX_AGE: Duration = Duration::from_secs(3600);

/// How long a post may take, connecting and answering, by default
/// (`--webhook-timeout`).
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(10);

/// How a webhook retries and how much it keeps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Policy {
    /// Events waiting behind the first (the one being posted or retried); at least 1.
    pub queue: usize,
    /// Failed attempts after which an event is given up; at least 1.
    pub attempts: u32,
    /// The first retry's delay.
    pub backoff: Duration,
    /// An event older than this is given up at its next failed attempt.
    pub max_age: Duration,
}

impl Default for Policy {
    fn default() -> Self {
        Policy {
            queue: DEFAULT_QUEUE,
            attempts: DEFAULT_ATTEMPTS,
            backoff: DEFAULT_BACKOFF,
            max_age: DEFAULT_MAX_AGE,
        }
    }
}

impl Policy {
    /// The delay after the `failures`-th failed attempt (from 1): the backoff doubled
    /// each time, never above [`MAX_BACKOFF`] (nor below the backoff when that is
    /// above it).
    pub fn delay_ms(&self, failures: u32) -> u64 {
        let first = self.backoff.as_millis().min(u128::from(u64::MAX)) as u64;
        let cap = (MAX_BACKOFF.as_millis() as u64).max(first);
        let doublings = failures.saturating_sub(1).min(40);
        first.saturating_mul(1u64 << doublings).min(cap)
    }
}

/// What happens to a webhook's delivery.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// A job's end was recorded with farm event `id` at `unix_ms`; `body` is what to
    /// post. Ids at or below those already taken are ignored (the hand-over from the
    /// table to the live events sees some twice).
    Ended { id: u64, unix_ms: u64, body: String },
    /// Farm event `id` is not posted (another kind): nothing waits on it.
    Passed { id: u64 },
    /// Events after `after` up to `oldest_kept − 1` were deleted by the farm's event
    /// retention before this webhook read them.
    Gap { after: u64, oldest_kept: u64 },
    /// The post in flight was answered with `status`.
    Answered { status: u16 },
    /// The post in flight failed without an answer (`why`: refused, timed out, TLS).
    Failed { why: String },
    /// The time is now (unix ms): posts that are due go out.
    Tick,
}

/// What the I/O around a [`Delivery`] carries out.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Action {
    /// Post event `id` (its `attempt`-th try, from 1).
    Post { id: u64, attempt: u32, body: String },
    /// Event `id` was delivered.
    Delivered { id: u64, attempts: u32 },
    /// Persist the cursor: every farm event up to it is settled.
    Advance { cursor: u64 },
    /// `count` events were dropped (the ids, for a gap: some may not have been ends).
    Drop { count: u64, why: String },
    /// Event `id` is given up after `attempts` failed attempts; `why` is the last
    /// failure.
    GiveUp { id: u64, attempts: u32, why: String },
    /// Wake the delivery with a [`Event::Tick`] at this time (unix ms).
    WakeAt(u64),
}

/// An end waiting to be delivered.
#[derive(Clone, Debug, PartialEq, Eq)]
struct Pending {
    id: u64,
    unix_ms: u64,
    body: String,
    /// Failed attempts so far.
    failures: u32,
    /// When the next attempt may go (unix ms).
    due: u64,
}

/// One webhook's delivery: the ends waiting, in id order, the first of them possibly
/// in flight.
#[derive(Clone, Debug)]
pub struct Delivery {
    policy: Policy,
    queue: VecDeque<Pending>,
    /// The first of `queue` is being posted.
    in_flight: bool,
    /// The highest farm event id taken (ended, passed or skipped by a gap).
    seen: u64,
    /// The cursor last given out in [`Action::Advance`] (or resumed from).
    cursor: u64,
}

impl Delivery {
    /// A delivery resuming after `cursor` (the last settled farm event id).
    pub fn resume(policy: Policy, cursor: u64) -> Delivery {
        Delivery {
            policy: Policy {
                queue: policy.queue.max(1),
                attempts: policy.attempts.max(1),
                ..policy
            },
            queue: VecDeque::new(),
            in_flight: false,
            seen: cursor,
            cursor,
        }
    }

    /// The highest farm event id taken: a reader of the table goes on after it.
    pub fn seen(&self) -> u64 {
        self.seen
    }

    /// Events waiting, the one in flight included.
    pub fn depth(&self) -> usize {
        self.queue.len()
    }

    /// The cursor last given out.
    pub fn cursor(&self) -> u64 {
        self.cursor
    }

    /// Takes `event` at `now` (unix ms) and says what to do.
    pub fn handle(&mut self, event: Event, now: u64) -> Vec<Action> {
        let mut actions = Vec::new();
        match event {
            Event::Ended { id, unix_ms, body } => {
                if id <= self.seen {
                    return actions;
                }
                self.seen = id;
                // The head (being posted, or waiting for its retry) is settled by its
                // own attempts only: the bound is on the ends behind it.
                let waiting = self.queue.len().saturating_sub(1);
                if waiting >= self.policy.queue {
                    let dropped = self.queue.remove(1).expect("the queue is full");
                    actions.push(Action::Drop {
                        count: 1,
                        why: format!(
                            "the queue is full ({} waiting): event {} dropped for event {id}",
                            self.policy.queue, dropped.id
                        ),
                    });
                }
                self.queue.push_back(Pending {
                    id,
                    unix_ms,
                    body,
                    failures: 0,
                    due: now,
                });
            }
            Event::Passed { id } => {
                self.seen = self.seen.max(id);
            }
            Event::Gap { after, oldest_kept } => {
                let last_missing = oldest_kept.saturating_sub(1);
                let from = after.max(self.seen) + 1;
                if last_missing >= from {
                    actions.push(Action::Drop {
                        count: last_missing - from + 1,
                        why: format!(
                            "events {from} to {last_missing} were deleted by the event \
                             retention before they were delivered"
                        ),
                    });
                    self.seen = last_missing;
                }
            }
            Event::Answered { status } if (200..300).contains(&status) => {
                if let Some(done) = self.take_in_flight() {
                    actions.push(Action::Delivered {
                        id: done.id,
                        attempts: done.failures + 1,
                    });
                }
            }
            Event::Answered { status } => {
                self.failed(format!("answered HTTP {status}"), now, &mut actions);
            }
            Event::Failed { why } => self.failed(why, now, &mut actions),
            Event::Tick => {}
        }
        self.settle(now, &mut actions);
        actions
    }

    /// The post in flight, taken off the queue.
    fn take_in_flight(&mut self) -> Option<Pending> {
        if !self.in_flight {
            return None;
        }
        self.in_flight = false;
        self.queue.pop_front()
    }

    /// The post in flight failed: retried later, or given up.
    fn failed(&mut self, why: String, now: u64, actions: &mut Vec<Action>) {
        if !self.in_flight {
            return;
        }
        self.in_flight = false;
        let policy = self.policy;
        let Some(head) = self.queue.front_mut() else {
            return;
        };
        head.failures += 1;
        let age = now.saturating_sub(head.unix_ms);
        let too_old = u128::from(age) >= policy.max_age.as_millis();
        if head.failures >= policy.attempts || too_old {
            let head = self.queue.pop_front().expect("the head failed");
            let limit = if too_old && head.failures < policy.attempts {
                format!("it is older than {} s", policy.max_age.as_secs())
            } else {
                format!("{} attempts", head.failures)
            };
            actions.push(Action::GiveUp {
                id: head.id,
                attempts: head.failures,
                why: format!("{why} (given up after {limit})"),
            });
        } else {
            head.due = now.saturating_add(policy.delay_ms(head.failures));
        }
    }

    /// Posts the head if it is due (or says when it will be), and gives out the cursor
    /// if it moved.
    fn settle(&mut self, now: u64, actions: &mut Vec<Action>) {
        let cursor = match self.queue.front() {
            Some(head) => head.id - 1,
            None => self.seen,
        };
        // It may only move forward: the head's id is above every id settled.
        if cursor > self.cursor {
            self.cursor = cursor;
            actions.push(Action::Advance { cursor });
        }
        if self.in_flight {
            return;
        }
        if let Some(head) = self.queue.front_mut() {
            if head.due <= now {
                self.in_flight = true;
                actions.push(Action::Post {
                    id: head.id,
                    attempt: head.failures + 1,
                    body: head.body.clone(),
                });
            } else {
                actions.push(Action::WakeAt(head.due));
            }
        }
    }
}

/// A webhook's URL, taken apart.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Url {
    /// `https`: TLS, verified.
    pub tls: bool,
    /// A name or an address (an IPv6 one without its brackets).
    pub host: String,
    pub port: u16,
    /// The path and query, from `/`.
    pub target: String,
    /// `user:password` before the host, sent as HTTP basic authentication.
    pub userinfo: Option<String>,
}

impl Url {
    /// The `Host` header: the port only when it is not the scheme's.
    pub fn host_header(&self) -> String {
        let host = if self.host.contains(':') {
            format!("[{}]", self.host)
        } else {
            self.host.clone()
        };
        let default = if self.tls { 443 } else { 80 };
        if self.port == default {
            host
        } else {
            format!("{host}:{}", self.port)
        }
    }
}

/// Takes a webhook's URL apart: `http://` or `https://`, a host, an optional port, a
/// path and query; a fragment is left out. The error says what is wrong with it.
/// Taken apart here rather than with the `url` crate, which nothing else in the build
/// uses and which would bring its IDNA tables for this one flag.
pub fn parse_url(url: &str) -> Result<Url, String> {
    let (scheme, rest) = url
        .split_once("://")
        .ok_or("not a URL: give http://HOST[:PORT]/PATH or https://...")?;
    let tls = match scheme.to_ascii_lowercase().as_str() {
        "https" => true,
        "http" => false,
        other => return Err(format!("the scheme must be http or https, not {other:?}")),
    };
    let rest = rest.split('#').next().unwrap_or("");
    let split = rest.find(['/', '?']).unwrap_or(rest.len());
    let (authority, target) = rest.split_at(split);
    let target = match target {
        "" => "/".to_owned(),
        t if t.starts_with('?') => format!("/{t}"),
        t => t.to_owned(),
    };
    if target
        .chars()
        .any(|c| c.is_ascii_whitespace() || c.is_ascii_control())
    {
        return Err("the path has spaces or control characters: percent-encode them".into());
    }
    let (userinfo, hostport) = match authority.rsplit_once('@') {
        Some((user, host)) => (Some(user.to_owned()), host),
        None => (None, authority),
    };
    let (host, port) = if let Some(inner) = hostport.strip_prefix('[') {
        let (host, after) = inner
            .split_once(']')
            .ok_or("an IPv6 address lacks its closing bracket")?;
        (host, after.strip_prefix(':'))
    } else {
        match hostport.rsplit_once(':') {
            Some((host, port)) => (host, Some(port)),
            None => (hostport, None),
        }
    };
    if host.is_empty() {
        return Err("no host".into());
    }
    if !host
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || "-._:".contains(c))
    {
        return Err(format!("{host:?} is not a host name or address"));
    }
    let port = match port {
        Some(p) => p
            .parse::<u16>()
            .ok()
            .filter(|&p| p > 0)
            .ok_or_else(|| format!("{p:?} is not a port"))?,
        None if tls => 443,
        None => 80,
    };
    Ok(Url {
        tls,
        host: host.to_owned(),
        port,
        target,
        userinfo,
    })
}

/// The label of a webhook in metrics and logs: its URL without the user information
/// and the query (which may carry credentials).
pub fn label(url: &str) -> String {
    let (scheme, rest) = url.split_once("://").unwrap_or(("", url));
    let rest = rest.split(['?', '#']).next().unwrap_or("");
    let (authority, path) = match rest.find('/') {
        Some(i) => rest.split_at(i),
        None => (rest, ""),
    };
    let host = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    format!("{scheme}://{host}{path}")
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn ended(id: u64, unix_ms: u64) -> Event {
        Event::Ended {
            id,
            unix_ms,
            body: format!("body {id}"),
        }
    }

    fn small() -> Policy {
        Policy {
            queue: 3,
            attempts: 3,
            backoff: Duration::from_millis(100),
            max_age: Duration::from_secs(60),
        }
    }

    fn posted(actions: &[Action]) -> Vec<u64> {
        actions
            .iter()
            .filter_map(|a| match a {
                Action::Post { id, .. } => Some(*id),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn an_end_is_posted_at_once_and_the_cursor_moves_once_delivered() {
        let mut d = Delivery::resume(small(), 4);
        let a = d.handle(ended(7, 1_000), 1_000);
        assert_eq!(
            a,
            [
                Action::Advance { cursor: 6 },
                Action::Post {
                    id: 7,
                    attempt: 1,
                    body: "body 7".into()
                }
            ]
        );
        // Another end while 7 is in flight waits.
        assert_eq!(d.handle(ended(9, 1_001), 1_001), []);
        let a = d.handle(Event::Answered { status: 204 }, 1_002);
        assert_eq!(
            a,
            [
                Action::Delivered { id: 7, attempts: 1 },
                Action::Advance { cursor: 8 },
                Action::Post {
                    id: 9,
                    attempt: 1,
                    body: "body 9".into()
                }
            ]
        );
        // The same id again (read from the table and live) is ignored.
        assert_eq!(d.handle(ended(9, 1_001), 1_003), []);
        d.handle(Event::Answered { status: 200 }, 1_004);
        assert_eq!(d.cursor(), 9);
        // Other kinds move the cursor only with the next settlement.
        d.handle(Event::Passed { id: 12 }, 1_005);
        assert_eq!(d.seen(), 12);
        assert_eq!(d.depth(), 0);
    }

    #[test]
    fn a_failure_is_retried_with_doubling_delays_then_given_up_with_its_reason() {
        let mut d = Delivery::resume(small(), 0);
        d.handle(ended(1, 0), 0);
        let a = d.handle(Event::Answered { status: 500 }, 10);
        assert_eq!(a, [Action::WakeAt(110)]);
        // Too early: nothing.
        assert_eq!(d.handle(Event::Tick, 50), [Action::WakeAt(110)]);
        assert_eq!(posted(&d.handle(Event::Tick, 110)), [1]);
        let a = d.handle(
            Event::Failed {
                why: "connection refused".into(),
            },
            120,
        );
        assert_eq!(a, [Action::WakeAt(320)]);
        assert_eq!(posted(&d.handle(Event::Tick, 320)), [1]);
        let a = d.handle(Event::Answered { status: 503 }, 330);
        assert_eq!(
            a,
            [
                Action::GiveUp {
                    id: 1,
                    attempts: 3,
                    why: "answered HTTP 503 (given up after 3 attempts)".into()
                },
                Action::Advance { cursor: 1 }
            ]
        );
    }

    #[test]
    fn an_old_event_gets_one_attempt() {
        let mut d = Delivery::resume(small(), 0);
        d.handle(ended(1, 0), 61_000);
        let a = d.handle(Event::Answered { status: 404 }, 61_001);
        assert!(
            matches!(&a[0], Action::GiveUp { id: 1, attempts: 1, why } if why.contains("older than 60 s")),
            "{a:?}"
        );
    }

    #[test]
    fn a_full_queue_drops_its_oldest_waiting_not_the_first() {
        let mut d = Delivery::resume(small(), 0);
        for id in 1..=4 {
            d.handle(ended(id, 0), 0);
        }
        // 1 in flight, 2 3 4 waiting: 5 drops 2.
        let a = d.handle(ended(5, 0), 0);
        assert!(
            matches!(&a[0], Action::Drop { count: 1, why } if why.contains("event 2 dropped")),
            "{a:?}"
        );
        assert_eq!(d.depth(), 4);
        d.handle(Event::Answered { status: 200 }, 1);
        let mut delivered = vec![1];
        while d.depth() > 0 {
            let a = d.handle(Event::Answered { status: 200 }, 2);
            delivered.extend(a.iter().filter_map(|a| match a {
                Action::Delivered { id, .. } => Some(*id),
                _ => None,
            }));
        }
        assert_eq!(delivered, [1, 3, 4, 5]);
        assert_eq!(d.cursor(), 5);
        // The first waiting for its retry is not dropped either.
        let mut d = Delivery::resume(small(), 0);
        d.handle(ended(1, 0), 0);
        d.handle(Event::Answered { status: 500 }, 1);
        for id in 2..=5 {
            d.handle(ended(id, 2), 2);
        }
        assert_eq!(d.depth(), 4);
        assert_eq!(posted(&d.handle(Event::Tick, 101)), [1]);
    }

    #[test]
    fn a_gap_counts_the_ids_deleted_before_delivery() {
        let mut d = Delivery::resume(small(), 10);
        let a = d.handle(
            Event::Gap {
                after: 10,
                oldest_kept: 15,
            },
            0,
        );
        assert_eq!(
            a,
            [
                Action::Drop {
                    count: 4,
                    why: "events 11 to 14 were deleted by the event retention before they \
                          were delivered"
                        .into()
                },
                Action::Advance { cursor: 14 }
            ]
        );
        // No gap: nothing.
        assert_eq!(
            d.handle(
                Event::Gap {
                    after: 14,
                    oldest_kept: 15
                },
                0
            ),
            []
        );
    }

    #[test]
    fn delays_double_up_to_the_cap() {
        let p = Policy::default();
        let delays: Vec<u64> = (1..=11).map(|f| p.delay_ms(f)).collect();
        assert_eq!(
            delays,
            [
                1_000, 2_000, 4_000, 8_000, 16_000, 32_000, 64_000, 128_000, 256_000, 300_000,
                300_000
            ]
        );
        assert_eq!(p.delay_ms(u32::MAX), 300_000);
    }

    #[test]
    fn urls_are_taken_apart_or_refused_with_the_reason() {
        let u = parse_url("https://u:p@hooks.example.com/in?x=1#f").unwrap();
        assert_eq!(
            u,
            Url {
                tls: true,
                host: "hooks.example.com".into(),
                port: 443,
                target: "/in?x=1".into(),
                userinfo: Some("u:p".into()),
            }
        );
        assert_eq!(u.host_header(), "hooks.example.com");
        let u = parse_url("http://[::1]:8080").unwrap();
        assert_eq!(
            (u.host.as_str(), u.port, u.target.as_str()),
            ("::1", 8080, "/")
        );
        assert_eq!(u.host_header(), "[::1]:8080");
        assert_eq!(parse_url("http://h?q").unwrap().target, "/?q");
        for (bad, why) in [
            ("hooks.example.com/in", "not a URL"),
            ("ftp://h/", "scheme must be http or https"),
            ("http:///x", "no host"),
            ("http://h:99999/", "not a port"),
            ("http://h:0/", "not a port"),
            ("http://h/a b", "spaces"),
            ("http://[::1/", "closing bracket"),
            ("http://h%20/", "not a host"),
        ] {
            let e = parse_url(bad).unwrap_err();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }

    #[test]
    fn labels_leave_out_credentials() {
        assert_eq!(
            label("https://user:pw@hooks.example.com:8443/a/b?token=x#f"),
            "https://hooks.example.com:8443/a/b"
        );
        assert_eq!(label("http://127.0.0.1:9/"), "http://127.0.0.1:9/");
        assert_eq!(label("http://h?x"), "http://h");
    }

    /// What the I/O feeds a delivery, chosen at random.
    #[derive(Clone, Debug)]
    enum Step {
        /// An end (or another kind) with the next id, `skip` ids after the last.
        Next {
            skip: u64,
            end: bool,
        },
        Answer(u16),
        Fail,
        /// Time passes, in ms.
        Wait(u64),
        /// Retention deleted events ahead of the reader.
        Gap(u64),
    }

    fn step() -> impl Strategy<Value = Step> {
        prop_oneof![
            4 => (0u64..3, any::<bool>()).prop_map(|(skip, end)| Step::Next { skip, end }),
            2 => prop_oneof![Just(200u16), Just(204), Just(500), Just(404), Just(302)]
                .prop_map(Step::Answer),
            1 => Just(Step::Fail),
            2 => (0u64..5_000).prop_map(Step::Wait),
            1 => (1u64..4).prop_map(Step::Gap),
        ]
    }

    proptest! {
        /// Whatever happens: posts go in id order and never repeat a settled event,
        /// every end is delivered, given up, dropped or still waiting (none skipped
        /// silently), the queue stays bounded, retries wait within the backoff's
        /// bounds, and the cursor never goes back nor passes an event still waiting.
        #[test]
        fn no_end_is_lost_or_reordered(steps in proptest::collection::vec(step(), 1..200)) {
            let policy = small();
            let mut d = Delivery::resume(policy, 0);
            let mut now = 0u64;
            let mut next_id = 0u64;
            let mut ends = Vec::new();
            let mut settled = std::collections::BTreeSet::new();
            let mut dropped = std::collections::BTreeSet::new();
            let mut in_flight: Option<u64> = None;
            let mut last_posted = 0u64;
            let mut last_cursor = 0u64;
            let mut failed_at: Option<u64> = None;
            for s in steps {
                let event = match s {
                    Step::Next { skip, end } => {
                        next_id += skip + 1;
                        if end {
                            ends.push(next_id);
                            ended(next_id, now)
                        } else {
                            Event::Passed { id: next_id }
                        }
                    }
                    Step::Answer(status) => Event::Answered { status },
                    Step::Fail => Event::Failed { why: "refused".into() },
                    Step::Wait(ms) => {
                        now += ms;
                        Event::Tick
                    }
                    Step::Gap(n) => {
                        // Only ahead of what was read: nothing read is deleted.
                        let after = next_id;
                        next_id += n + 1;
                        Event::Gap { after, oldest_kept: next_id }
                    }
                };
                let answered = matches!(event, Event::Answered { .. } | Event::Failed { .. });
                let had = in_flight;
                let mut resolved = false;
                // The first end not settled nor dropped: being posted or retried.
                let head = ends
                    .iter()
                    .copied()
                    .find(|id| !settled.contains(id) && !dropped.contains(id));
                for action in d.handle(event, now) {
                    match action {
                        Action::Post { id, attempt, .. } => {
                            prop_assert!(in_flight.is_none(), "one post at a time");
                            prop_assert!(id >= last_posted, "in id order");
                            prop_assert!(!settled.contains(&id) && !dropped.contains(&id));
                            prop_assert!(attempt <= policy.attempts);
                            if attempt > 1 {
                                prop_assert_eq!(id, last_posted, "a retry is of the same event");
                                let since = now - failed_at.expect("a retry follows a failure");
                                prop_assert!(since >= policy.delay_ms(attempt - 1));
                                prop_assert!(since <= MAX_BACKOFF.as_millis() as u64 + 5_000);
                            }
                            in_flight = Some(id);
                            last_posted = id;
                        }
                        Action::Delivered { id, .. } | Action::GiveUp { id, .. } => {
                            prop_assert_eq!(in_flight.take(), Some(id));
                            prop_assert!(settled.insert(id));
                            resolved = true;
                        }
                        Action::Drop { count, why } => {
                            if let Some(rest) = why.split("event ").nth(1) {
                                if why.contains("queue is full") {
                                    prop_assert_eq!(count, 1);
                                    let id: u64 = rest.split(' ').next().unwrap().parse().unwrap();
                                    prop_assert!(ends.contains(&id));
                                    prop_assert!(Some(id) != in_flight, "never the one in flight");
                                    prop_assert!(Some(id) != head, "never the first");
                                    prop_assert!(dropped.insert(id));
                                }
                            }
                        }
                        Action::Advance { cursor } => {
                            prop_assert!(cursor > last_cursor);
                            last_cursor = cursor;
                        }
                        Action::WakeAt(at) => prop_assert!(at > now),
                    }
                }
                if answered && had.is_some() && !resolved {
                    // Failed, kept for a retry.
                    prop_assert_eq!(in_flight, had);
                    failed_at = Some(now);
                    in_flight = None;
                }
                prop_assert!(d.depth() <= policy.queue + 1, "bounded");
                let queued: Vec<u64> = ends
                    .iter()
                    .copied()
                    .filter(|id| !settled.contains(id) && !dropped.contains(id))
                    .collect();
                prop_assert_eq!(queued.len(), d.depth());
                if let Some(&first) = queued.first() {
                    prop_assert!(d.cursor() < first, "the cursor never passes a waiting end");
                }
            }
            // Every end is accounted for.
            prop_assert_eq!(settled.len() + dropped.len() + d.depth(), ends.len());
        }
    }
}
