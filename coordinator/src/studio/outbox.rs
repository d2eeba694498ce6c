//! What waits to be sent to one studio page, as a pure queue with time passed in.
//!
//! A page's link may be far slower than the farm: a 960 × 540 generation is about 3 MB
//! of pixels, rendered in a quarter of a second, and a drag makes ten of them a second.
//! Whatever the page cannot use is therefore dropped here, before it is encoded and
//! sent, rather than queued behind what it can:
//!
//! - a push of a newer generation drops everything still queued of older ones (an
//!   edit or camera move replaced them: the page would discard them on arrival);
//! - a tile of a later pass drops the queued tile of an earlier pass of the same
//!   generation at the same place (the page would paint it over at once);
//! - the finer passes of a generation may be held back until a given time
//!   ([`Meta::not_before`], see [`super::plan::hold_until`]): during a drag, a
//!   generation is replaced before its full-resolution tiles could reach a remote
//!   page, so only its coarse pass is worth sending.
//!
//! The queue stays bounded whatever the page does: a page whose backlog passes
//! [`PAGE_BACKLOG_BYTES`], or that takes nothing for [`PAGE_STALL_MS`] while pushes
//! wait, is dropped ([`Dropped`]); its browser reconnects and sends its scene again.

use std::collections::VecDeque;

use super::views::Millis;

/// Bytes of pixels a page may leave queued before it is dropped: five whole 960 × 540
/// generations, and 16 MiB of memory at most per page.
pub const PAGE_BACKLOG_BYTES: usize = 16 << 20;

/// Held pixels beyond this many bytes are released at once rather than waiting: a view
/// so large that its held passes alone would near [`PAGE_BACKLOG_BYTES`] sends them as
/// they come instead of being dropped for it.
pub const HOLD_BYTES: usize = PAGE_BACKLOG_BYTES / 4;

/// A page that takes nothing for this long while pushes wait has stopped reading (a
/// frozen tab, a dead link that has not closed): it is dropped.
pub const PAGE_STALL_MS: Millis = 10_000;

/// Where a tile goes on the page: a later pass's tile at the same place paints over it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Spot {
    pub scale: u32,
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

/// What the queue needs to know of a push.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Meta {
    pub generation: u64,
    pub pass: u32,
    /// The tile's place, for a tile; `None` for a pass's start or end.
    pub spot: Option<Spot>,
    /// The memory it holds while queued.
    pub bytes: usize,
    /// Not sent before this time (held back while the view may still be moving).
    pub not_before: Millis,
}

/// Why a page was dropped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Dropped {
    #[error("the page left more than {PAGE_BACKLOG_BYTES} bytes of tiles unread")]
    Backlog,
    #[error("the page took nothing for {PAGE_STALL_MS} ms")]
    Stalled,
}

/// What to send next.
#[derive(Debug, PartialEq, Eq)]
pub enum Next<T> {
    Send(T),
    /// Nothing to send before this time (or before a push, if `None`).
    Wait(Option<Millis>),
}

/// One page's queue.
#[derive(Debug)]
pub struct Outbox<T> {
    queue: VecDeque<(Meta, T)>,
    bytes: usize,
    /// The newest generation pushed: older ones are dropped.
    newest: u64,
    /// Since when pushes have waited without the page taking one.
    waiting_since: Option<Millis>,
    /// The newest generation's hold was lifted ([`HOLD_BYTES`]).
    released: bool,
}

impl<T> Default for Outbox<T> {
    fn default() -> Self {
        Outbox {
            queue: VecDeque::new(),
            bytes: 0,
            newest: 0,
            waiting_since: None,
            released: false,
        }
    }
}

impl<T> Outbox<T> {
    pub fn new() -> Outbox<T> {
        Outbox::default()
    }

    /// Queues `item` at time `now`, dropping what it makes useless; an error if the page
    /// is to be dropped.
    pub fn push(&mut self, now: Millis, meta: Meta, item: T) -> Result<(), Dropped> {
        if meta.generation < self.newest {
            return Ok(());
        }
        if meta.generation > self.newest {
            self.newest = meta.generation;
            self.released = false;
            self.queue.retain(|(m, _)| m.generation >= meta.generation);
        }
        if let Some(spot) = meta.spot {
            self.queue.retain(|(m, _)| {
                m.generation != meta.generation || m.pass >= meta.pass || m.spot != Some(spot)
            });
        }
        self.queue.push_back((meta, item));
        self.bytes = self.queue.iter().map(|(m, _)| m.bytes).sum();
        let held: usize = self
            .queue
            .iter()
            .filter(|(m, _)| m.not_before > now)
            .map(|(m, _)| m.bytes)
            .sum();
        if held > HOLD_BYTES {
            self.released = true;
        }
        let waiting = *self.waiting_since.get_or_insert(now);
        if self.bytes > PAGE_BACKLOG_BYTES {
            return Err(Dropped::Backlog);
        }
        if now.saturating_sub(waiting) >= PAGE_STALL_MS {
            return Err(Dropped::Stalled);
        }
        Ok(())
    }

    /// What to send at time `now`: pushes go in the order they came, the first held one
    /// holding those behind it (they are of its generation, and a page paints in order).
    pub fn next(&mut self, now: Millis) -> Next<T> {
        let Some((meta, _)) = self.queue.front() else {
            return Next::Wait(None);
        };
        if meta.not_before > now && !self.released {
            return Next::Wait(Some(meta.not_before));
        }
        let (meta, item) = self.queue.pop_front().expect("looked at above");
        self.bytes -= meta.bytes;
        self.waiting_since = (!self.queue.is_empty()).then_some(now);
        Next::Send(item)
    }

    /// Whether the page has taken nothing for [`PAGE_STALL_MS`] while pushes waited.
    pub fn stalled(&self, now: Millis) -> bool {
        self.waiting_since
            .is_some_and(|t| now.saturating_sub(t) >= PAGE_STALL_MS)
    }

    /// Bytes queued.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Pushes queued.
    pub fn len(&self) -> usize {
        self.queue.len()
    }

    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tile(generation: u64, pass: u32, x: u32, bytes: usize, not_before: Millis) -> Meta {
        Meta {
            generation,
            pass,
            spot: Some(Spot {
                // The coarse pass's tiles are the others' grid scaled.
                scale: if pass == 0 { 4 } else { 1 },
                x,
                y: 0,
                width: 64,
                height: 64,
            }),
            bytes,
            not_before,
        }
    }

    fn pass_event(generation: u64, pass: u32) -> Meta {
        Meta {
            generation,
            pass,
            spot: None,
            bytes: 100,
            not_before: 0,
        }
    }

    fn drain(outbox: &mut Outbox<&'static str>, now: Millis) -> Vec<&'static str> {
        let mut sent = Vec::new();
        while let Next::Send(item) = outbox.next(now) {
            sent.push(item);
        }
        sent
    }

    #[test]
    fn a_newer_generation_drops_what_is_queued_of_older_ones() {
        let mut outbox = Outbox::new();
        outbox.push(0, tile(1, 0, 0, 10, 0), "1a").unwrap();
        outbox.push(0, tile(1, 0, 64, 10, 0), "1b").unwrap();
        outbox.push(0, pass_event(1, 0), "1 done").unwrap();
        assert_eq!(outbox.next(0), Next::Send("1a"));
        outbox.push(1, tile(2, 0, 0, 10, 0), "2a").unwrap();
        // A late push of the older generation (its job was cancelled meanwhile).
        outbox.push(1, tile(1, 1, 0, 10, 0), "1 late").unwrap();
        assert_eq!(outbox.bytes(), 10);
        assert_eq!(drain(&mut outbox, 1), ["2a"]);
        assert_eq!(outbox.next(1), Next::Wait(None));
    }

    #[test]
    fn a_later_pass_replaces_the_queued_tile_at_its_place() {
        let mut outbox = Outbox::new();
        outbox.push(0, tile(1, 0, 0, 10, 0), "coarse").unwrap();
        outbox.push(0, tile(1, 1, 0, 10, 0), "one sample").unwrap();
        outbox
            .push(0, tile(1, 1, 64, 10, 0), "one sample, next")
            .unwrap();
        outbox.push(0, pass_event(1, 1), "pass 1 done").unwrap();
        outbox.push(0, tile(1, 2, 0, 10, 0), "final").unwrap();
        // An earlier pass's tile after a later one's is kept: the page paints in order.
        outbox
            .push(0, tile(1, 1, 0, 10, 0), "one sample, late")
            .unwrap();
        assert_eq!(
            drain(&mut outbox, 0),
            [
                "coarse",
                "one sample, next",
                "pass 1 done",
                "final",
                "one sample, late"
            ]
        );
    }

    #[test]
    fn held_pushes_wait_and_hold_those_behind_them() {
        let mut outbox = Outbox::new();
        outbox.push(0, tile(1, 0, 0, 10, 0), "coarse").unwrap();
        outbox.push(0, tile(1, 1, 0, 10, 200), "fine").unwrap();
        outbox
            .push(0, tile(1, 0, 64, 10, 0), "coarse, late")
            .unwrap();
        assert_eq!(drain(&mut outbox, 10), ["coarse"]);
        assert_eq!(outbox.next(10), Next::Wait(Some(200)));
        // Superseded while held: never sent.
        outbox.push(150, tile(2, 0, 0, 10, 0), "next").unwrap();
        assert_eq!(drain(&mut outbox, 150), ["next"]);
        outbox
            .push(150, tile(2, 1, 0, 10, 350), "next, fine")
            .unwrap();
        assert_eq!(outbox.next(349), Next::Wait(Some(350)));
        assert_eq!(drain(&mut outbox, 350), ["next, fine"]);
    }

    #[test]
    fn a_hold_too_large_is_released() {
        let mut outbox = Outbox::new();
        let big = HOLD_BYTES / 2;
        outbox.push(0, tile(1, 1, 0, big, 200), "a").unwrap();
        outbox.push(0, tile(1, 1, 64, big, 200), "b").unwrap();
        assert_eq!(outbox.next(0), Next::Wait(Some(200)));
        outbox.push(0, tile(1, 1, 128, big, 200), "c").unwrap();
        assert_eq!(drain(&mut outbox, 0), ["a", "b", "c"]);
        // The next generation is held again.
        outbox.push(1, tile(2, 1, 0, 10, 200), "d").unwrap();
        assert_eq!(outbox.next(1), Next::Wait(Some(200)));
    }

    #[test]
    fn a_page_that_leaves_too_much_unread_is_dropped() {
        let mut outbox = Outbox::new();
        let tile_bytes = 64 * 64 * 3;
        let mut pushed = 0;
        let dropped = loop {
            let x = pushed as u32 * 64;
            match outbox.push(0, tile(1, 2, x, tile_bytes, 0), "tile") {
                Ok(()) => pushed += 1,
                Err(why) => break why,
            }
        };
        assert_eq!(dropped, Dropped::Backlog);
        assert_eq!(pushed, PAGE_BACKLOG_BYTES / tile_bytes);
    }

    #[test]
    fn a_page_that_takes_nothing_is_dropped_even_if_its_backlog_stays_small() {
        let mut outbox = Outbox::new();
        // Edits keep coming: each drops the last, so the backlog never grows.
        let mut now = 0;
        let dropped = loop {
            let generation = now / 100 + 1;
            if let Err(why) = outbox.push(now, tile(generation, 0, 0, 10, 0), "tile") {
                break why;
            }
            assert!(outbox.bytes() <= 10);
            now += 100;
        };
        assert_eq!(dropped, Dropped::Stalled);
        assert_eq!(now, PAGE_STALL_MS);
        // A page that reads, however slowly, is not.
        let mut outbox = Outbox::new();
        for now in (0..3 * PAGE_STALL_MS).step_by(100) {
            outbox.push(now, tile(1, 2, 0, 10, 0), "a").unwrap();
            outbox.push(now, tile(1, 2, 64, 10, 0), "b").unwrap();
            assert!(matches!(outbox.next(now + 99), Next::Send(_)));
            assert!(!outbox.stalled(now + 99));
        }
        assert!(!outbox.is_empty());
        assert!(outbox.stalled(3 * PAGE_STALL_MS + PAGE_STALL_MS));
    }
}
