//! `GET /api/v1/events`: the farm's events as server-sent events (docs/events.md).
//!
//! A stream subscribes to the live events first, then replays from the database what
//! the client missed (`Last-Event-ID`, or `?after=N`), a page at a time, then passes on
//! the live events it has not replayed: the decisions are [`events::replay`] and
//! [`events::Cursor`], this module only carries them out.
//!
//! Memory stays bounded whatever the clients do: the live events wait in one buffer of
//! [`events::LIVE_BUFFER`] for all streams, and the body is made only as fast as the
//! client reads it. A stream that falls behind that buffer while it replays simply
//! reads on from the database; one that falls behind while live is closed with a last
//! event, `lagged`, naming the id to resume after.

use std::collections::VecDeque;
use std::convert::Infallible;
use std::sync::Arc;

use axum::extract::{Query, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use protocol::JobId;
use tokio::sync::broadcast::{self, error::RecvError};

use super::refusal;
use crate::events::{self, Cursor, FarmEvent, Filter, Item, REPLAY_PAGE};
use crate::server::Observer;

/// The query of [`farm_events`]: `?after=N` (for clients that cannot set
/// `Last-Event-ID`), `?job=N`, `?kinds=a,b`, `?follow=false` (end once caught up).
#[derive(serde::Deserialize)]
pub(super) struct EventsQuery {
    after: Option<u64>,
    job: Option<JobId>,
    kinds: Option<String>,
    follow: Option<bool>,
}

/// `GET /api/v1/events`: the farm's job and worker events, each with its id, kind and
/// one line of JSON, after the client's last (`Last-Event-ID`, which wins over
/// `?after`, since a browser reconnecting sends it with the URL it first used), then
/// live. Without either, live events only.
pub(super) async fn farm_events(
    State(observer): State<Observer>,
    headers: HeaderMap,
    Query(query): Query<EventsQuery>,
) -> Response {
    let header = headers
        .get("last-event-id")
        .map(|v| v.to_str().unwrap_or("\u{fffd}"));
    let after = match resume_point(header, query.after) {
        Ok(after) => after,
        Err(message) => return refusal(StatusCode::BAD_REQUEST, message),
    };
    let filter = match Filter::parse(query.job, query.kinds.as_deref()) {
        Ok(filter) => filter,
        Err(message) => return refusal(StatusCode::BAD_REQUEST, message),
    };
    // Subscribed before the first read: see `events::Cursor`.
    let live = observer.subscribe_events();
    let phase = match after {
        // The first page now, so that a database that cannot be read is an error
        // status rather than a stream that ends at once.
        Some(after) => match observer.farm_events_after(after, REPLAY_PAGE).await {
            Ok(page) => Phase::Replay(Some(page)),
            Err(why) => {
                return refusal(
                    StatusCode::SERVICE_UNAVAILABLE,
                    format!("cannot read the farm's events: {why}"),
                )
            }
        },
        None => Phase::Live,
    };
    // A stream from now starts with an `id:` and no data: the latest event's id, which
    // a client then resumes after should it be cut before the first event comes (an
    // event without data is not dispatched, but sets the id to resume from).
    let mut pending = VecDeque::new();
    let start = match after {
        Some(after) => after,
        None => match observer.farm_events_after(u64::MAX, 0).await {
            Ok(page) => {
                pending.push_back(Event::default().id(page.last_issued.to_string()));
                page.last_issued
            }
            Err(why) => {
                return refusal(
                    StatusCode::SERVICE_UNAVAILABLE,
                    format!("cannot read the farm's events: {why}"),
                )
            }
        },
    };
    let stream = EventStream {
        observer,
        live,
        cursor: Cursor::after(start),
        filter,
        follow: query.follow.unwrap_or(true),
        phase,
        fresh: false,
        pending,
    };
    let body = futures_util::stream::unfold(stream, |mut stream| async move {
        let event = stream.next().await?;
        Some((Ok::<_, Infallible>(event), stream))
    });
    Sse::new(body)
        .keep_alive(
            KeepAlive::new()
                .interval(events::HEARTBEAT)
                .text("heartbeat"),
        )
        .into_response()
}

/// Where a stream resumes: after `Last-Event-ID` if sent (and not empty), else after
/// `?after`, else nowhere (live only); or one line saying the header is not an id.
fn resume_point(header: Option<&str>, after: Option<u64>) -> Result<Option<u64>, String> {
    match header.map(str::trim).filter(|v| !v.is_empty()) {
        Some(value) => value
            .parse::<u64>()
            .map(Some)
            .map_err(|_| format!("Last-Event-ID: {value:?} is not an event id (a whole number)")),
        None => Ok(after),
    }
}

/// Where a stream is.
enum Phase {
    /// Reading what the client missed from the database; a page already read, if any.
    Replay(Option<events::FarmPage>),
    /// Passing on the events recorded from now on.
    Live,
    /// Ended: nothing more once what is pending is sent.
    Done,
}

/// One client's stream.
struct EventStream {
    observer: Observer,
    live: broadcast::Receiver<Arc<FarmEvent>>,
    cursor: Cursor,
    filter: Filter,
    /// Go on with the live events once caught up (`?follow=false`: end there).
    follow: bool,
    phase: Phase,
    /// No live event taken since the last replay: falling behind now is the replay's
    /// length, not the client's pace, and is made up from the database.
    fresh: bool,
    pending: VecDeque<Event>,
}

impl EventStream {
    /// The next event to send; `None` once the stream ends.
    async fn next(&mut self) -> Option<Event> {
        loop {
            if let Some(event) = self.pending.pop_front() {
                return Some(event);
            }
            match &mut self.phase {
                Phase::Done => return None,
                Phase::Replay(page) => {
                    let page = match page.take() {
                        Some(page) => page,
                        None => match self
                            .observer
                            .farm_events_after(self.cursor.last(), REPLAY_PAGE)
                            .await
                        {
                            Ok(page) => page,
                            // The client resumes with the last id it got.
                            Err(_) => return None,
                        },
                    };
                    let (items, caught_up) =
                        events::replay(&mut self.cursor, &self.filter, &page, REPLAY_PAGE);
                    self.pending.extend(items.into_iter().map(|item| {
                        match item {
                            Item::Gap(gap) => Event::default()
                                .id(gap.resume_after().to_string())
                                .event("gap")
                                .data(gap.data()),
                            Item::Event(event) => sse(event),
                        }
                    }));
                    if caught_up {
                        self.fresh = true;
                        self.phase = if self.follow {
                            Phase::Live
                        } else {
                            Phase::Done
                        };
                    }
                }
                Phase::Live => match self.live.recv().await {
                    Ok(event) => {
                        self.fresh = false;
                        if self.cursor.take(event.id) && self.filter.passes(&event) {
                            return Some(sse(&event));
                        }
                    }
                    // Every event it missed is in the database.
                    Err(RecvError::Lagged(_)) if self.fresh => self.phase = Phase::Replay(None),
                    Err(RecvError::Lagged(_)) => {
                        let last = self.cursor.last();
                        self.phase = Phase::Done;
                        return Some(
                            Event::default()
                                .id(last.to_string())
                                .event("lagged")
                                .data(events::lagged_data(last)),
                        );
                    }
                    Err(RecvError::Closed) => return None,
                },
            }
        }
    }
}

/// A recorded event as a server-sent event: its id, its kind and its JSON.
fn sse(event: &FarmEvent) -> Event {
    Event::default()
        .id(event.id.to_string())
        .event(&event.kind)
        .data(event.data())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_header_wins_over_the_query_and_must_be_an_id() {
        assert_eq!(resume_point(Some("41"), Some(3)), Ok(Some(41)));
        assert_eq!(resume_point(Some(" "), Some(3)), Ok(Some(3)));
        assert_eq!(resume_point(None, None), Ok(None));
        let wrong = resume_point(Some("abc"), None).unwrap_err();
        assert!(wrong.contains("\"abc\" is not an event id"), "{wrong}");
    }
}
