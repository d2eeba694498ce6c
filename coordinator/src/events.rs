//! The farm's event stream (`GET /api/v1/events`, docs/events.md): what happened to
//! jobs and workers, each event with an id that increases across the farm's whole
//! life, kept in the database for a stated time and count, and resumable after a
//! reconnect or a coordinator restart.
//!
//! This module holds the decisions, apart from the I/O that carries them out: what an
//! event is and says ([`Announcement`], [`FarmEvent`]), how long events are kept
//! ([`Retention`]), and how one stream hands over from the events replayed from the
//! database to the live ones without a gap or a duplicate ([`Cursor`], [`gap`]).
//!
//! The ids are the database's (`AUTOINCREMENT`, never reused, even after trimming),
//! given by the one thread that writes, and an event is streamed live only once its
//! transaction is committed: an id a client has seen is always in the database, so a
//! resumption after a `kill -9` finds every event it missed, and ids never go back or
//! repeat across a restart.

use std::time::Duration;

use protocol::JobId;
use serde_json::{Map, Value};

/// How long events are kept by default (`--event-retention`).
pub const DEFAULT_RETENTION: Duration = Duration::from_secs(7 * 86_400);

/// How many events are kept by default (`--event-retention-count`).
pub const DEFAULT_RETENTION_COUNT: u64 = 100_000;

/// Events read from the database at a time while a stream replays: a resumption far
/// behind costs the writer short reads between its writes, never one long one.
pub const REPLAY_PAGE: usize = 500;

/// Live events a stream may fall behind by before it is closed (`event: lagged`): the
/// coordinator keeps this many at most for all streams together, whatever their number
/// and speed. A stream closed so resumes from the database with `Last-Event-ID`.
pub const LIVE_BUFFER: usize = 1024;

/// How often an idle stream gets a comment line, so that proxies do not cut it.
pub const HEARTBEAT: Duration = Duration::from_secs(15);

/// The job log's kinds that are announced on the farm's stream, and the stream's own
/// job kinds. Tiles are not: a farm hands out hundreds a second.
pub const JOB_KINDS: &[&str] = &[
    "submitted",
    "started",
    "paused",
    "resumed",
    "priority",
    "cancel",
    "retried",
    "requeued",
    "done",
    "failed",
    "cancelled",
    "deleted",
    "frame_done",
    "frame_failed",
];

/// The kinds of worker events.
pub const WORKER_KINDS: &[&str] = &[
    "joined",
    "left",
    "quarantined",
    "drained",
    "disabled",
    "enabled",
];

/// The kinds the stream itself sends, about the stream: ids skipped because they are
/// no longer kept, and a stream closed because its client fell behind.
pub const STREAM_KINDS: &[&str] = &["gap", "lagged"];

/// Whether `kind` is an event of the farm's stream (a job's or a worker's).
pub fn is_farm_kind(kind: &str) -> bool {
    JOB_KINDS.contains(&kind) || WORKER_KINDS.contains(&kind)
}

/// An event to record: what the coordinator announces, before the writer gives it its
/// id.
#[derive(Clone, Debug, PartialEq)]
pub struct Announcement {
    pub unix_ms: u64,
    pub kind: String,
    /// The job it is about, if any (for `?job=` filters).
    pub job: Option<JobId>,
    /// Its details: `job` and/or `worker` objects.
    pub body: Map<String, Value>,
}

impl Announcement {
    /// An event about a job: `{"job": {"id": JOB, ...details}}`.
    pub fn job(unix_ms: u64, kind: &str, job: JobId, details: Map<String, Value>) -> Self {
        let mut object = Map::new();
        object.insert("id".into(), job.into());
        object.extend(details);
        let mut body = Map::new();
        body.insert("job".into(), Value::Object(object));
        Announcement {
            unix_ms,
            kind: kind.to_owned(),
            job: Some(job),
            body,
        }
    }

    /// An event about a worker (a machine): `{"worker": {...details}}`.
    pub fn worker(unix_ms: u64, kind: &str, details: Map<String, Value>) -> Self {
        let mut body = Map::new();
        body.insert("worker".into(), Value::Object(details));
        Announcement {
            unix_ms,
            kind: kind.to_owned(),
            job: None,
            body,
        }
    }
}

/// An event as recorded, with its id.
#[derive(Clone, Debug, PartialEq)]
pub struct FarmEvent {
    pub id: u64,
    pub unix_ms: u64,
    pub kind: String,
    pub job: Option<JobId>,
    pub body: Map<String, Value>,
}

impl FarmEvent {
    /// Its `data:` line: one line of JSON, `{"id", "unix_ms", "kind", ...body}`.
    pub fn data(&self) -> String {
        let mut object = Map::new();
        object.insert("id".into(), self.id.into());
        object.insert("unix_ms".into(), self.unix_ms.into());
        object.insert("kind".into(), self.kind.clone().into());
        for (key, value) in &self.body {
            object.insert(key.clone(), value.clone());
        }
        // Compact JSON escapes every line break inside strings: one line.
        Value::Object(object).to_string()
    }
}

/// A page of events read back from the database.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FarmPage {
    /// Events after the id asked for, in id order, at most a page of them.
    pub events: Vec<FarmEvent>,
    /// The id of the oldest event kept; with none kept, the id the next event will get.
    pub first_kept: u64,
    /// The id of the latest event recorded (0 before the first): where a stream that
    /// starts from now stands.
    pub last_issued: u64,
}

/// How long and how many events are kept: the older ones are trimmed by the writer as
/// it records new ones.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Retention {
    pub max_age: Duration,
    /// At least 1.
    pub max_count: u64,
}

impl Default for Retention {
    fn default() -> Self {
        Retention {
            max_age: DEFAULT_RETENTION,
            max_count: DEFAULT_RETENTION_COUNT,
        }
    }
}

impl Retention {
    /// Events recorded before this time (ms since the Unix epoch) are trimmed at `now`.
    pub fn cutoff_ms(&self, now_ms: u64) -> u64 {
        now_ms.saturating_sub(self.max_age.as_millis().min(u128::from(u64::MAX)) as u64)
    }
}

/// What a client resuming after `after` is told when events after it are no longer
/// kept: the ids it will not get, before the stream goes on from the oldest kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Gap {
    pub after: u64,
    pub oldest_kept: u64,
}

impl Gap {
    /// Its `data:` line.
    pub fn data(&self) -> String {
        serde_json::json!({
            "after": self.after,
            "oldest_kept": self.oldest_kept,
            "message": format!(
                "events {} to {} are no longer kept: the stream goes on from {}",
                self.after + 1,
                self.oldest_kept - 1,
                self.oldest_kept
            ),
        })
        .to_string()
    }

    /// The id the stream goes on after (the gap event carries it, so that a client
    /// reconnecting right after it is not told of the same gap again).
    pub fn resume_after(&self) -> u64 {
        self.oldest_kept - 1
    }
}

/// The gap between `after` (the last id a client has) and `first_kept`, if events
/// after `after` were trimmed.
pub fn gap(after: u64, first_kept: u64) -> Option<Gap> {
    (after.saturating_add(1) < first_kept).then_some(Gap {
        after,
        oldest_kept: first_kept,
    })
}

/// The last id a stream has passed on: every event goes through [`Cursor::take`], so
/// that the ids a client gets strictly increase. This is the hand-over: a stream
/// subscribes to the live events first, then replays from the database, then takes
/// the live ones, and an event that arrived live while it was replayed has an id the
/// replay already passed, so it is skipped: no duplicate. No gap either: an event
/// committed before the subscription is in the database when the replay reads it, and
/// one committed after is in the subscription.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cursor {
    last: u64,
}

impl Cursor {
    /// A stream resuming after `after` (0 for the first event ever).
    pub fn after(after: u64) -> Cursor {
        Cursor { last: after }
    }

    /// The last id passed on.
    pub fn last(&self) -> u64 {
        self.last
    }

    /// Whether the event `id` is new to this stream (then it is the last one).
    pub fn take(&mut self, id: u64) -> bool {
        if id > self.last {
            self.last = id;
            true
        } else {
            false
        }
    }

    /// Passes over a gap: the stream goes on after it.
    pub fn skip(&mut self, gap: Gap) {
        self.last = self.last.max(gap.resume_after());
    }
}

/// Which events a client asked for (`?job=`, `?kinds=`). The stream's own events
/// (`gap`, `lagged`) always pass.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Filter {
    pub job: Option<JobId>,
    /// Empty: every kind.
    pub kinds: Vec<String>,
}

impl Filter {
    /// The filter of `job` and a comma-separated list of kinds, or one line saying
    /// which kind is unknown.
    pub fn parse(job: Option<JobId>, kinds: Option<&str>) -> Result<Filter, String> {
        let kinds: Vec<String> = kinds
            .unwrap_or("")
            .split(',')
            .map(str::trim)
            .filter(|k| !k.is_empty())
            .map(str::to_owned)
            .collect();
        if let Some(unknown) = kinds.iter().find(|k| !is_farm_kind(k)) {
            return Err(format!(
                "kinds: {unknown:?} is not an event kind: jobs' are {}, workers' {}",
                JOB_KINDS.join(", "),
                WORKER_KINDS.join(", ")
            ));
        }
        Ok(Filter { job, kinds })
    }

    pub fn passes(&self, event: &FarmEvent) -> bool {
        self.job.is_none_or(|job| event.job == Some(job))
            && (self.kinds.is_empty() || self.kinds.contains(&event.kind))
    }
}

/// What a stream sends of a page replayed from the database, in order.
#[derive(Clone, Debug, PartialEq)]
pub enum Item<'a> {
    /// Events after the cursor were trimmed: told before the stream goes on.
    Gap(Gap),
    Event(&'a FarmEvent),
}

/// A page read after `cursor.last()` (at most `limit` events) as the stream sends it:
/// a gap if the events right after the cursor are no longer kept, then the page's
/// events new to the stream that pass `filter`. Returns them, and whether the replay
/// has caught up (a short page: the next events are live ones).
pub fn replay<'a>(
    cursor: &mut Cursor,
    filter: &Filter,
    page: &'a FarmPage,
    limit: usize,
) -> (Vec<Item<'a>>, bool) {
    let mut items = Vec::new();
    if let Some(gap) = gap(cursor.last(), page.first_kept) {
        cursor.skip(gap);
        items.push(Item::Gap(gap));
    }
    for event in &page.events {
        // Taken even when filtered out: the cursor is the stream's place in the ids.
        if cursor.take(event.id) && filter.passes(event) {
            items.push(Item::Event(event));
        }
    }
    (items, page.events.len() < limit)
}

/// What the stream says when it closes a client that fell behind: the id to resume
/// after.
pub fn lagged_data(last: u64) -> String {
    serde_json::json!({
        "last_id": last,
        "message": format!(
            "this client fell more than {LIVE_BUFFER} events behind the farm: reconnect \
             with Last-Event-ID: {last} to resume from the database"
        ),
    })
    .to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event(id: u64) -> FarmEvent {
        FarmEvent {
            id,
            unix_ms: 1000 + id,
            kind: "done".into(),
            job: Some(id),
            body: Map::new(),
        }
    }

    /// The hand-over as a stream lives it: live events arrive while the replay runs
    /// (some of them also in the replay), then more after it.
    #[test]
    fn a_stream_hands_over_from_replay_to_live_without_gap_or_duplicate() {
        let mut cursor = Cursor::after(3);
        // Committed before the subscription: only in the database.
        let replayed = [4, 5, 6, 7];
        // Committed after the subscription: 6 and 7 were also read by the replay.
        let live = [6, 7, 8, 9];
        let mut sent = Vec::new();
        for id in replayed.into_iter().chain(live) {
            if cursor.take(id) {
                sent.push(id);
            }
        }
        assert_eq!(sent, [4, 5, 6, 7, 8, 9]);
        assert_eq!(cursor.last(), 9);
        // What the client already has is never sent again.
        assert!(!cursor.take(9));
        assert!(!cursor.take(2));
    }

    /// Pages replayed one after the other while the writer trims: the second page
    /// finds events after the cursor gone and tells of the gap; filtered events move
    /// the cursor too.
    #[test]
    fn a_replay_tells_of_gaps_page_by_page_and_knows_when_it_caught_up() {
        let page = |first_kept, ids: &[u64]| FarmPage {
            events: ids.iter().map(|&id| event(id)).collect(),
            first_kept,
            last_issued: 0,
        };
        let all = Filter::default();
        let mut cursor = Cursor::after(2);
        let first = page(3, &[3, 4]);
        let (items, done) = replay(&mut cursor, &all, &first, 2);
        assert_eq!(
            items,
            [Item::Event(&first.events[0]), Item::Event(&first.events[1])]
        );
        assert!(!done, "a full page: more may follow");
        // Meanwhile 5 to 9 were trimmed.
        let second = page(10, &[10]);
        let (items, done) = replay(&mut cursor, &all, &second, 2);
        let gap = Gap {
            after: 4,
            oldest_kept: 10,
        };
        assert_eq!(items, [Item::Gap(gap), Item::Event(&second.events[0])]);
        assert!(done);
        assert_eq!(cursor.last(), 10);
        // Filtered out, yet passed: the live part skips it too.
        let job_1 = Filter::parse(Some(1), None).unwrap();
        let third = page(10, &[11]);
        let (items, _) = replay(&mut cursor, &job_1, &third, 2);
        assert!(items.is_empty());
        assert!(!cursor.take(11));
    }

    #[test]
    fn a_gap_is_told_only_when_events_after_the_id_were_trimmed() {
        // Oldest kept is right after the client's last: nothing missed.
        assert_eq!(gap(41, 42), None);
        // The client is ahead of the oldest kept: nothing missed.
        assert_eq!(gap(50, 42), None);
        // Nothing kept yet, next id 1: a new client misses nothing.
        assert_eq!(gap(0, 1), None);
        // One event trimmed is a gap.
        assert_eq!(
            gap(40, 42),
            Some(Gap {
                after: 40,
                oldest_kept: 42
            })
        );
        let g = gap(10, 42).expect("events 11 to 41 were trimmed");
        assert_eq!(
            g,
            Gap {
                after: 10,
                oldest_kept: 42
            }
        );
        let mut cursor = Cursor::after(10);
        cursor.skip(g);
        assert_eq!(cursor.last(), 41);
        assert!(cursor.take(42));
        let data: Value = serde_json::from_str(&g.data()).unwrap();
        assert_eq!(data["after"], 10);
        assert_eq!(data["oldest_kept"], 42);
    }

    #[test]
    fn retention_cuts_at_its_age() {
        let r = Retention {
            max_age: Duration::from_secs(60),
            max_count: 10,
        };
        assert_eq!(r.cutoff_ms(100_000), 40_000);
        assert_eq!(r.cutoff_ms(1_000), 0);
        let forever = Retention {
            max_age: Duration::MAX,
            max_count: 1,
        };
        assert_eq!(forever.cutoff_ms(u64::MAX), 0);
    }

    #[test]
    fn an_event_is_one_line_of_json_with_its_id_time_and_kind() {
        let mut details = Map::new();
        details.insert("name".into(), "two\nlines".into());
        let a = Announcement::job(5, "submitted", 7, details);
        let e = FarmEvent {
            id: 12,
            unix_ms: a.unix_ms,
            kind: a.kind,
            job: a.job,
            body: a.body,
        };
        let line = e.data();
        assert!(!line.contains('\n'), "{line}");
        let v: Value = serde_json::from_str(&line).unwrap();
        assert_eq!(v["id"], 12);
        assert_eq!(v["unix_ms"], 5);
        assert_eq!(v["kind"], "submitted");
        assert_eq!(v["job"]["id"], 7);
        assert_eq!(v["job"]["name"], "two\nlines");
    }

    #[test]
    fn filters_pass_the_job_and_kinds_asked_for() {
        let all = Filter::parse(None, None).unwrap();
        assert!(all.passes(&event(1)));
        let job = Filter::parse(Some(2), Some("")).unwrap();
        assert!(job.passes(&event(2)) && !job.passes(&event(3)));
        let kinds = Filter::parse(None, Some("submitted, done")).unwrap();
        assert!(kinds.passes(&event(1)));
        let other = Filter::parse(None, Some("joined")).unwrap();
        assert!(!other.passes(&event(1)));
        let wrong = Filter::parse(None, Some("tile_done")).unwrap_err();
        assert!(
            wrong.contains("\"tile_done\" is not an event kind"),
            "{wrong}"
        );
    }
}
