//! The store's upkeep: damage on disk, what a restart finds, collection, and many files.

use std::fs::{self, OpenOptions};
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use assets::{AssetError, AssetId, Store, StoreLimits, Upload};

use crate::common::{file, files_under, ROOMY};

fn object(dir: &Path, id: &AssetId) -> PathBuf {
    let hex = id.hex();
    dir.join("objects")
        .join(&hex[..2])
        .join(format!("{hex}-{}", id.size))
}

/// Flips one bit of the file at `path`, as a failing disk would.
pub fn flip_a_bit(path: &Path, at: u64) {
    let mut byte = [0u8];
    let bytes = fs::read(path).unwrap();
    byte[0] = bytes[at as usize] ^ 0x10;
    let mut f = OpenOptions::new().write(true).open(path).unwrap();
    f.seek(SeekFrom::Start(at)).unwrap();
    f.write_all(&byte).unwrap();
}

#[test]
fn a_corrupted_object_is_detected_on_read_and_removed() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let (id, bytes) = file(20, 5000);
    let (other, other_bytes) = file(21, 5000);
    store.put(&id, &bytes, 1).unwrap();
    store.put(&other, &other_bytes, 1).unwrap();
    store.pin(7, &[id]);
    flip_a_bit(&object(dir.path(), &id), 1234);
    flip_a_bit(&object(dir.path(), &other), 0);

    // Chunks are served as they are on disk (a worker hashes what it fetched); the
    // whole-file read checks.
    assert_eq!(store.read_chunk(&id, 0, 10).unwrap(), bytes[..10]);
    let err = store.read_verified(&id).unwrap_err();
    match &err {
        AssetError::Corrupt {
            id: named,
            actual,
            path,
        } => {
            assert_eq!(*named, id);
            assert_ne!(actual.sha256, id.sha256);
            assert_eq!(actual.size, id.size);
            assert_eq!(*path, object(dir.path(), &id));
        }
        other => panic!("expected corruption, got {other}"),
    }
    assert!(err.to_string().contains(&id.hex()));
    assert!(!object(dir.path(), &id).exists(), "removed");
    assert!(!store.has(&id));
    assert_eq!(store.missing(&[id, other]), vec![id]);
    assert!(
        store.pinned(&id),
        "pins outlive the file: the job still needs it"
    );

    let err = store.verify(&other).unwrap_err();
    assert!(matches!(err, AssetError::Corrupt { .. }), "{err}");
    assert!(!store.has(&other));
    assert_eq!(store.stats().files, 0);
    assert_eq!(store.stats().bytes, 0);

    // The client uploads it again.
    assert_eq!(
        store.write_chunk(&id, 0, &bytes, 2).unwrap(),
        Upload::Complete
    );
    assert_eq!(store.read_verified(&id).unwrap(), bytes);
    store.verify(&id).unwrap();
    let err = store.read_verified(&other).unwrap_err();
    assert!(matches!(err, AssetError::NotFound { .. }), "{err}");
}

#[test]
fn open_indexes_without_hashing_and_drops_what_a_crash_left() {
    let dir = tempfile::tempdir().unwrap();
    let (good, good_bytes) = file(22, 3000);
    let (cut, cut_bytes) = file(23, 3000);
    {
        let mut store = Store::open(dir.path(), ROOMY).unwrap();
        store.put(&good, &good_bytes, 1).unwrap();
        store.put(&cut, &cut_bytes, 1).unwrap();
    }
    // A truncated object, a write that never finished, and a stranger.
    fs::write(object(dir.path(), &cut), &cut_bytes[..100]).unwrap();
    let temp = object(dir.path(), &good).with_file_name(".tmp-leftover");
    fs::write(&temp, b"half a file").unwrap();
    let stranger = dir.path().join("objects").join("README");
    fs::write(&stranger, b"kept").unwrap();
    // A damaged file of the right length is only found when read: open does not hash.
    flip_a_bit(&object(dir.path(), &good), 0);

    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    assert!(store.has(&good));
    assert!(!store.has(&cut) && !object(dir.path(), &cut).exists());
    assert!(!temp.exists());
    assert!(
        stranger.exists(),
        "files that are not the store's are left alone"
    );
    assert_eq!(store.stats().files, 1);
    assert_eq!(store.stats().bytes, 3000);
    assert!(matches!(
        store.verify(&good),
        Err(AssetError::Corrupt { .. })
    ));
}

#[test]
fn missing_keeps_the_order_given_without_repeats() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let files: Vec<_> = (30..35).map(|seed| file(seed, 100)).collect();
    store.put(&files[1].0, &files[1].1, 1).unwrap();
    let ids: Vec<AssetId> = [4, 1, 0, 4, 2, 0].iter().map(|&i| files[i].0).collect();
    assert_eq!(
        store.missing(&ids),
        vec![files[4].0, files[0].0, files[2].0]
    );
    // Same hash, other size: a different file.
    let wrong_size = AssetId {
        size: 99,
        ..files[1].0
    };
    assert_eq!(store.missing(&[wrong_size]), vec![wrong_size]);
}

#[test]
fn collect_removes_unpinned_old_files_and_stale_uploads_only() {
    let dir = tempfile::tempdir().unwrap();
    let limits = StoreLimits {
        max_file_bytes: 1 << 20,
        max_total_bytes: 1 << 30,
    };
    let mut store = Store::open(dir.path(), limits).unwrap();
    let hour = 3_600_000;
    let t0 = 1_700_000_000_000u64;
    let (pinned_old, a) = file(40, 1000);
    let (unpinned_old, b) = file(41, 2000);
    let (unpinned_recent, c) = file(42, 3000);
    let (stale, d) = file(43, 4000);
    let (fresh, e) = file(44, 5000);
    store.put(&pinned_old, &a, t0).unwrap();
    store.put(&unpinned_old, &b, t0).unwrap();
    store.put(&unpinned_recent, &c, t0 + 2 * hour).unwrap();
    store.write_chunk(&stale, 0, &d[..100], t0).unwrap();
    store.write_chunk(&fresh, 0, &e[..200], t0).unwrap();
    store
        .write_chunk(&fresh, 200, &e[200..300], t0 + 2 * hour)
        .unwrap();
    store.pin(1, &[pinned_old]);
    store.pin(2, &[pinned_old, unpinned_recent]);
    store.unpin(2, t0 + hour / 2);
    assert!(store.pinned(&pinned_old) && !store.pinned(&unpinned_recent));
    assert_eq!(store.stats().pinned_files, 1);

    let collected = store.collect(t0 + 2 * hour + 1, hour);
    assert_eq!(collected.ids, vec![unpinned_old]);
    assert_eq!(collected.bytes, 2000);
    assert_eq!(collected.partials, vec![stale]);
    assert_eq!(collected.partial_bytes, 100);
    assert!(collected.errors.is_empty());
    assert!(store.has(&pinned_old) && store.has(&unpinned_recent));
    assert!(!store.has(&unpinned_old) && !object(dir.path(), &unpinned_old).exists());
    assert_eq!(store.received(&stale), 0);
    assert_eq!(store.received(&fresh), 300);

    // Released, a file gets the whole grace period from its release.
    store.unpin(1, t0 + 10 * hour);
    let collected = store.collect(t0 + 11 * hour, hour);
    assert_eq!(
        collected.ids,
        vec![unpinned_recent],
        "released an hour ago exactly"
    );
    assert_eq!(collected.partials, vec![fresh]);
    let collected = store.collect(t0 + 11 * hour + 1, hour);
    assert_eq!(collected.ids, vec![pinned_old]);
    assert_eq!(store.stats(), Default::default());
    assert!(files_under(&dir.path().join("objects")).is_empty());
    assert!(files_under(&dir.path().join("partial")).is_empty());
}

#[test]
fn after_a_restart_a_files_time_is_its_modification_time() {
    let dir = tempfile::tempdir().unwrap();
    let (id, bytes) = file(45, 100);
    let (partial, partial_bytes) = file(46, 100);
    {
        let mut store = Store::open(dir.path(), ROOMY).unwrap();
        store.put(&id, &bytes, 0).unwrap();
        store
            .write_chunk(&partial, 0, &partial_bytes[..10], 0)
            .unwrap();
    }
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64;
    let hour = 3_600_000;
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let kept = store.collect(now, hour);
    assert!(
        kept.ids.is_empty() && kept.partials.is_empty(),
        "written moments ago"
    );
    let gone = store.collect(now + 2 * hour, hour);
    assert_eq!((gone.ids, gone.partials), (vec![id], vec![partial]));
}

#[test]
fn ten_thousand_small_files() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let started = Instant::now();
    let files: Vec<_> = (0..10_000u64)
        .map(|seed| file(seed, 64 + (seed % 64) as usize))
        .collect();
    for (id, bytes) in &files {
        assert!(store.put(id, bytes, 1).unwrap());
    }
    let put = started.elapsed();
    let mut ids: Vec<AssetId> = files.iter().map(|(id, _)| *id).collect();
    let absent: Vec<AssetId> = (10_000..10_100u64).map(|seed| file(seed, 10).0).collect();
    ids.extend(&absent);
    ids.extend(&absent);
    assert_eq!(store.missing(&ids), absent);
    let total: u64 = files.iter().map(|(id, _)| id.size).sum();
    let stats = store.stats();
    assert_eq!((stats.files, stats.bytes), (10_000, total));

    let reopened = Instant::now();
    let store = Store::open(dir.path(), ROOMY).unwrap();
    assert_eq!(store.stats(), stats);
    assert_eq!(store.missing(&ids), absent);
    let reopen = reopened.elapsed();
    eprintln!("10,000 files: stored in {put:?}, reopened and checked in {reopen:?}");
    assert!(
        put.as_secs() < 120 && reopen.as_secs() < 20,
        "{put:?}, {reopen:?}"
    );
}
