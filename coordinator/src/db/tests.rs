//! The job database on real files: a first version's database opened and upgraded,
//! event logs, disabled machines, durability, damaged rows reported one by one, and a
//! file that is not a job database. [`job`] is also what the persistence thread's tests
//! store.

use super::*;
use protocol::Sampling;
use rusqlite::params;

/// The tables as the first version created them, before sampling.
const FIRST_SCHEMA: &str = "
        CREATE TABLE jobs (
            id INTEGER PRIMARY KEY, scene TEXT NOT NULL, hash BLOB NOT NULL,
            width INTEGER NOT NULL, height INTEGER NOT NULL, aa INTEGER NOT NULL,
            max_depth INTEGER NOT NULL, tile_size INTEGER NOT NULL,
            priority INTEGER NOT NULL, state TEXT NOT NULL, error TEXT
        );
        CREATE TABLE tiles (
            job INTEGER NOT NULL, tile INTEGER NOT NULL, rgb BLOB NOT NULL,
            rays INTEGER NOT NULL, worker TEXT NOT NULL, PRIMARY KEY (job, tile)
        );
        INSERT INTO jobs VALUES (3, '{}', zeroblob(32), 34, 17, 2, 10, 16, 0, 'running', NULL);
        INSERT INTO tiles VALUES (3, 0, x'010203', 12, 'w1');";

pub(crate) fn job(id: JobId, sampling: Sampling) -> StoredJob {
    StoredJob {
        after: Vec::new(),
        id,
        scene: "{}".into(),
        hash: [7; 32],
        frame: id as u32,
        last_frame: None,
        sequence: None,
        assets: Vec::new(),
        settings: Settings {
            width: 8,
            height: 8,
            aa: 4,
            max_depth: 10,
            sampling,
        },
        tile_size: 8,
        priority: 0,
        verification: Verification::Full,
        time_limit_ms: Some(1_500),
        stopped_on_time_limit: false,
        paused: false,
        state: JobState::Queued,
        error: None,
        totals: None,
        times: Times {
            submitted: Some(1_000),
            ..Times::default()
        },
        image_sha256: None,
        require: vec!["gpu".into()],
        label: Label {
            name: format!("job {id}"),
            submitter: "ann@host".into(),
            submitted_from: "127.0.0.1".into(),
        },
    }
}

fn jobs(db: &Db) -> Vec<StoredJob> {
    db.load_jobs()
        .unwrap()
        .into_iter()
        .map(|j| j.unwrap())
        .collect()
}

#[test]
fn a_database_of_the_first_version_opens_and_keeps_its_jobs() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tessera.db");
    Connection::open(&path)
        .unwrap()
        .execute_batch(FIRST_SCHEMA)
        .unwrap();

    let mut db = Db::open(&path, false).unwrap();
    let loaded = jobs(&db);
    assert_eq!(loaded.len(), 1);
    assert_eq!(loaded[0].settings.sampling, Sampling::Grid);
    assert_eq!(
        (loaded[0].settings.aa, loaded[0].state),
        (2, JobState::Running)
    );
    assert!(loaded[0].totals.is_none());
    // No name, submitter or address recorded: empty (the daemon shows defaults).
    assert_eq!(loaded[0].label, Label::default());
    // Frames did not exist: it rendered frame 1.
    assert_eq!(loaded[0].frame, 1);
    // An event log of its own, from nothing.
    assert!(db.load_events(3, 0, 10).unwrap().is_empty());
    let tiles = db.load_tiles(3, |_| Some(3)).unwrap();
    let tile = tiles[0].as_ref().ok().unwrap();
    assert_eq!(tile.rgb, [1, 2, 3]);
    assert_eq!((tile.samples, tile.error_sq_sum), (None, None));

    // New jobs and tiles carry the new columns, and survive another opening.
    let adaptive = Sampling::Adaptive { target_milli: 500 };
    db.insert_job(&job(4, adaptive)).unwrap();
    db.insert_job(&job(5, Sampling::Jittered)).unwrap();
    db.save_results(
        &[TileWrite {
            job: 4,
            tile: 0,
            zstd: zstd::bulk::compress(&[7; 192], 1).unwrap(),
            rays: 300,
            worker: "w2".into(),
            samples: 272,
            error_sq_sum: Some(12.5),
            done_ms: 1_234,
        }],
        &[],
    )
    .unwrap();
    let totals = Totals {
        rays: 1000,
        samples: 1024,
        error_sq_sum: 3.25,
        error_pixels: 64,
    };
    let times = Times {
        submitted: Some(1_000),
        started: Some(1_500),
        ended: Some(2_000),
        retried: None,
    };
    db.set_ended(5, JobState::Done, None, totals, times, Some([9; 32]))
        .unwrap();
    drop(db);

    let db = Db::open(&path, false).unwrap();
    let loaded = jobs(&db);
    let sampling: Vec<Sampling> = loaded.iter().map(|j| j.settings.sampling).collect();
    assert_eq!(sampling, [Sampling::Grid, adaptive, Sampling::Jittered]);
    assert_eq!(loaded[2].totals, Some(totals));
    assert_eq!(loaded[2].state, JobState::Done);
    assert_eq!(loaded[2].times, times);
    assert_eq!(loaded[2].image_sha256, Some([9; 32]));
    let tiles = db.load_tiles(4, |_| Some(192)).unwrap();
    let tile = tiles[0].as_ref().ok().unwrap();
    assert_eq!((tile.samples, tile.error_sq_sum), (Some(272), Some(12.5)));
    assert_eq!(tile.rgb, [7; 192]);
    assert_eq!(loaded[1].label, job(4, adaptive).label);
    let frames: Vec<u32> = loaded.iter().map(|j| j.frame).collect();
    assert_eq!(frames, [1, 4, 5]);
}

#[test]
fn event_logs_page_replace_their_marker_and_go_with_their_job() {
    let dir = tempfile::tempdir().unwrap();
    let mut db = Db::open(&dir.path().join("tessera.db"), true).unwrap();
    let entry = |job, seq, detail: &str| EventWrite {
        job,
        event: JobEvent {
            seq,
            unix_ms: 1_000 + seq,
            kind: "k".into(),
            detail: detail.into(),
        },
    };
    let mut batch: Vec<EventWrite> = (1..=5).map(|s| entry(1, s, "a")).collect();
    batch.push(entry(2, 1, "other job"));
    batch.push(entry(1, 4, "replaced"));
    db.save_results(&[], &batch).unwrap();
    let page = db.load_events(1, 2, 2).unwrap();
    let seqs: Vec<u64> = page.iter().map(|e| e.seq).collect();
    assert_eq!(seqs, [3, 4]);
    assert_eq!(page[1].detail, "replaced");
    db.save_results(
        &[],
        &[EventWrite {
            job: 2,
            event: JobEvent {
                seq: 10_001,
                unix_ms: 5,
                kind: "not_kept".into(),
                detail: "1234 further events not kept".into(),
            },
        }],
    )
    .unwrap();
    let positions = db.event_positions().unwrap();
    assert_eq!(positions.get(&1), Some(&(5, 0)));
    assert_eq!(positions.get(&2), Some(&(10_001, 1234)));
    db.delete_job(1).unwrap();
    assert!(db.load_events(1, 0, 100).unwrap().is_empty());
    assert_eq!(db.load_events(2, 0, 100).unwrap().len(), 2);
}

#[test]
fn disabled_machines_are_kept_by_name_until_enabled() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tessera.db");
    let db = Db::open(&path, true).unwrap();
    assert!(db.load_disabled().unwrap().is_empty());
    db.set_disabled("render-07", true).unwrap();
    db.set_disabled("render-07", true).unwrap();
    db.set_disabled("render-01", true).unwrap();
    drop(db);
    let db = Db::open(&path, false).unwrap();
    assert_eq!(db.load_disabled().unwrap(), ["render-01", "render-07"]);
    db.set_disabled("render-07", false).unwrap();
    db.set_disabled("never-disabled", false).unwrap();
    assert_eq!(db.load_disabled().unwrap(), ["render-01"]);
}

#[test]
fn ordered_commits_skip_the_sync_and_synced_ones_make_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut db = Db::open(&dir.path().join("tessera.db"), true).unwrap();
    let level = |db: &Db| -> i64 {
        db.conn
            .query_row("PRAGMA synchronous", [], |r| r.get(0))
            .unwrap()
    };
    // FULL is 2, NORMAL 1.
    assert_eq!(level(&db), 2);
    db.set_durability(Durability::Ordered).unwrap();
    assert_eq!(level(&db), 1);
    db.set_durability(Durability::Ordered).unwrap();
    assert_eq!(level(&db), 1);
    db.set_durability(Durability::Synced).unwrap();
    assert_eq!(level(&db), 2);
}

#[test]
fn damaged_rows_are_reported_one_by_one_not_fatal() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tessera.db");
    let mut db = Db::open(&path, true).unwrap();
    db.insert_job(&job(1, Sampling::Grid)).unwrap();
    db.insert_job(&job(2, Sampling::Grid)).unwrap();
    let tile = |tile| TileWrite {
        job: 1,
        tile,
        zstd: zstd::bulk::compress(&[tile as u8; 192], 1).unwrap(),
        rays: 1,
        worker: "w".into(),
        samples: 64,
        error_sq_sum: None,
        done_ms: 1_234,
    };
    db.save_results(&[tile(0), tile(1), tile(2), tile(3), tile(4), tile(5)], &[])
        .unwrap();
    // A frame that expands beyond its tile, whose checksum is right: refused
    // without being expanded.
    let big = zstd::bulk::compress(&[5; 4096], 1).unwrap();
    db.conn
        .execute(
            "UPDATE tiles SET rgb = ?1, sha256 = ?2 WHERE tile = 5",
            params![big, &tile_checksum(&big)[..]],
        )
        .unwrap();
    db.conn
        .execute_batch(
            "UPDATE tiles SET rgb = x'00' WHERE tile = 1;
                 UPDATE tiles SET rays = 'many' WHERE tile = 2;
                 UPDATE tiles SET encoding = 'lz4' WHERE tile = 3;
                 UPDATE tiles SET rgb = x'0102', sha256 = NULL WHERE tile = 4;
                 UPDATE jobs SET state = 'sideways' WHERE id = 2;",
        )
        .unwrap();
    let loaded = db.load_jobs().unwrap();
    assert!(loaded[0].is_ok());
    assert!(loaded[1].as_ref().unwrap_err().what.contains("sideways"));
    let tiles = db.load_tiles(1, |_| Some(192)).unwrap();
    assert_eq!(tiles[0].as_ref().ok().map(|t| t.tile), Some(0));
    assert_eq!(
        tiles[0].as_ref().ok().map(|t| &t.rgb[..]),
        Some(&[0; 192][..])
    );
    let why = |i: usize| tiles[i].as_ref().err().map(|b| (b.tile, b.what.clone()));
    assert_eq!(why(1).unwrap().0, Some(1));
    assert_eq!(why(2).unwrap().0, Some(2));
    assert!(why(3).unwrap().1.contains("unknown pixel encoding \"lz4\""));
    assert!(why(4).unwrap().1.contains("do not decompress"));
    assert!(why(5).unwrap().1.contains("do not decompress"));
    // A tile the job does not have.
    let tiles = db.load_tiles(1, |t| (t == 0).then_some(192)).unwrap();
    assert!(tiles[5].as_ref().unwrap_err().what.contains("no such tile"));
}

#[test]
fn a_file_that_is_not_a_job_database_is_refused_unless_new() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tessera.db");
    std::fs::write(
        &path,
        b"garbage that is not SQLite at all, not even close....",
    )
    .unwrap();
    assert!(Db::open(&path, false).is_err());
    let empty = dir.path().join("empty.db");
    std::fs::write(&empty, b"").unwrap();
    assert!(Db::open(&empty, false).is_err());
    assert!(Db::open(&empty, true).is_ok());
}
