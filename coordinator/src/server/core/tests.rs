//! The core's small parts: the refusal an ended job gets, a worker's pixels as
//! stored, the event log's cap, and a worker's rate.

use std::sync::Arc;
use std::time::Duration;

use protocol::JobState;
use tokio::sync::mpsc;

use super::controls::ended_refusal;
use super::records::{decompress, EventLog, TilePixels, WorkerRecord, EVENT_LOG_CAP};

#[test]
fn an_ended_job_refused_says_what_is_accepted_and_how_to_retry_it() {
    assert_eq!(
        ended_refusal(5, "resumed", JobState::Cancelled).message,
        "job 5 cannot be resumed: it is cancelled, only a paused job can be \
         (`tessera retry 5` puts it back in the queue)"
    );
    assert_eq!(
        ended_refusal(5, "paused", JobState::Failed).message,
        "job 5 cannot be paused: it is failed, only a queued or running job can be \
         (`tessera retry 5` puts it back in the queue)"
    );
    assert_eq!(
        ended_refusal(5, "given a new priority", JobState::Done).message,
        "job 5 cannot be given a new priority: it is done, only a queued or running \
         job can be"
    );
    assert_eq!(
        ended_refusal(5, "resumed", JobState::Done).message,
        "job 5 cannot be resumed: it is done, only a paused job can be"
    );
}

#[test]
fn a_workers_compressed_pixels_are_stored_as_sent_unless_padded() {
    let rgb: Vec<u8> = (0..3 * 32 * 32).map(|i| (i % 7) as u8).collect();
    let sent = zstd::bulk::compress(&rgb, 1).unwrap();
    let kept = TilePixels::received(rgb.clone(), sent.clone());
    assert_eq!(
        (kept.rgb.as_slice(), kept.zstd.as_slice()),
        (&rgb[..], &sent[..])
    );

    // The same frame followed by a skippable frame of padding decompresses to the
    // same pixels, and would cost the database far more than the tile: it is
    // compressed again.
    let mut padded = sent.clone();
    padded.extend_from_slice(&[0x50, 0x2a, 0x4d, 0x18]);
    padded.extend_from_slice(&(1u32 << 20).to_le_bytes());
    padded.resize(padded.len() + (1 << 20), 0);
    assert_eq!(decompress(&padded, rgb.len()).unwrap(), rgb);
    let stored = TilePixels::received(rgb.clone(), padded);
    assert!(stored.zstd.len() <= zstd::zstd_safe::compress_bound(rgb.len()));
    assert_eq!(
        zstd::bulk::decompress(&stored.zstd, rgb.len()).unwrap(),
        rgb
    );

    // Raw pixels are compressed for the database.
    let raw = TilePixels::raw(rgb.clone());
    assert_eq!(zstd::bulk::decompress(&raw.zstd, rgb.len()).unwrap(), rgb);
}

#[test]
fn an_event_log_keeps_its_cap_then_counts_what_it_drops_and_keeps_the_end() {
    let mut log = EventLog::new();
    for seq in 1..=EVENT_LOG_CAP {
        assert_eq!(log.number(false), Some(seq));
    }
    for _ in 0..1500 {
        assert_eq!(log.number(false), None);
    }
    assert_eq!(log.dropped, 1500);
    // The end is kept, numbered after those not kept.
    let end = EVENT_LOG_CAP + 1501;
    assert_eq!(log.number(true), Some(end));
    // After a restart the numbering and the count go on from what is stored: the
    // highest number, and the marker's count.
    let restored = EventLog::restored(end, 1500);
    assert_eq!((restored.next_seq, restored.dropped), (end + 1, 1500));
    // Past the cap without an end, the highest number stored is the marker's.
    let restored = EventLog::restored(EVENT_LOG_CAP + 1, 1500);
    assert_eq!(restored.next_seq, EVENT_LOG_CAP + 1501);
    assert_eq!(EventLog::restored(0, 0), EventLog::new());
}

#[test]
fn a_workers_rate_is_while_it_rendered_in_the_last_minute() {
    let mut w = WorkerRecord::new(
        std::time::Instant::now(),
        "w".into(),
        std::net::Ipv4Addr::LOCALHOST.into(),
        "build".into(),
        1,
        mpsc::unbounded_channel().0,
        Arc::default(),
    );
    let start = w.connected;
    let at = |s: u64| start + Duration::from_secs(s);
    // 10 s of work at a million rays a second, then idle.
    for s in 1..=10 {
        w.count_result(at(s), 1_000_000, 1_000_000);
    }
    let busy = w.current_rate(at(10));
    assert!((busy - 1e6).abs() < 1.0, "{busy}");
    // Within the minute, idle time does not dilute it (the minute's average would
    // say 10e6 / 60)...
    let later = w.current_rate(at(60));
    assert!((later - 1e6).abs() < 1.0, "{later}");
    // ...and a worker idle for longer than that renders nothing now, whatever it did
    // before (the lifetime average would still say 10e6 / 300).
    assert_eq!(w.current_rate(at(300)), 0.0);
    // A result of 6 M rays rendered in 2 s: 3 M rays a second.
    w.count_result(at(301), 2_000_000, 6_000_000);
    assert!((w.current_rate(at(301)) - 3e6).abs() < 1.0);
    assert_eq!(w.recent.len(), 1, "older results are forgotten");
}
