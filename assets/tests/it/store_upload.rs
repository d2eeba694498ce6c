//! Uploads into the store: chunk by chunk, across restarts, and what is refused.

use std::fs;

use assets::{AssetError, AssetId, Store, StoreLimits, Upload, CHUNK};

use crate::common::{file, files_under, SmallDisk, ROOMY};

/// Uploads `bytes` as `id` from `from`, chunk by chunk, returning the last answer.
fn upload_from(store: &mut Store, id: &AssetId, bytes: &[u8], from: u64) -> Upload {
    let mut offset = from;
    loop {
        let end = (offset as usize + CHUNK).min(bytes.len());
        let answer = store
            .write_chunk(id, offset, &bytes[offset as usize..end], 1_000)
            .unwrap();
        match answer {
            Upload::Partial { received } => {
                assert_eq!(received, end as u64);
                offset = received;
            }
            Upload::Complete => return answer,
        }
    }
}

#[test]
fn a_chunked_upload_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let (id, bytes) = file(1, CHUNK * 5 / 2);
    assert_eq!(store.missing(&[id]), vec![id]);
    assert_eq!(store.received(&id), 0);

    let first = store.write_chunk(&id, 0, &bytes[..CHUNK], 1_000).unwrap();
    assert_eq!(
        first,
        Upload::Partial {
            received: CHUNK as u64
        }
    );
    assert_eq!(store.received(&id), CHUNK as u64);
    assert!(!store.has(&id), "a partial upload is not a stored file");
    assert_eq!(
        upload_from(&mut store, &id, &bytes, CHUNK as u64),
        Upload::Complete
    );

    assert!(store.has(&id));
    assert_eq!(store.received(&id), id.size);
    assert!(store.missing(&[id]).is_empty());
    assert_eq!(store.read_verified(&id).unwrap(), bytes);
    let mut read = Vec::new();
    while read.len() < bytes.len() {
        let chunk = store.read_chunk(&id, read.len() as u64, CHUNK).unwrap();
        assert!(!chunk.is_empty() && chunk.len() <= CHUNK);
        read.extend(chunk);
    }
    assert_eq!(read, bytes);
    assert!(store.read_chunk(&id, id.size, CHUNK).unwrap().is_empty());
    assert!(matches!(
        store.read_chunk(&id, id.size + 1, 1),
        Err(AssetError::PastEnd { .. })
    ));
    assert!(matches!(
        store.read_chunk(&id, 0, CHUNK + 1),
        Err(AssetError::ChunkTooLarge { .. })
    ));

    // One file under objects/, named by its whole identity; nothing left in partial/.
    let hex = id.hex();
    let stored = dir
        .path()
        .join("objects")
        .join(&hex[..2])
        .join(format!("{hex}-{}", id.size));
    assert_eq!(files_under(dir.path()), vec![(stored, id.size)]);
    let stats = store.stats();
    assert_eq!((stats.files, stats.bytes), (1, id.size));
    assert_eq!((stats.partial_files, stats.partial_bytes), (0, 0));
}

#[test]
fn an_upload_resumes_at_received_after_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let (id, bytes) = file(2, CHUNK * 2 + 17);
    {
        let mut store = Store::open(dir.path(), ROOMY).unwrap();
        store.write_chunk(&id, 0, &bytes[..CHUNK], 1_000).unwrap();
        // The connection drops here, and the coordinator restarts.
    }
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    assert_eq!(store.received(&id), CHUNK as u64);
    assert_eq!(store.stats().partial_files, 1);
    assert_eq!(store.stats().partial_bytes, CHUNK as u64);
    assert!(!store.has(&id));
    let resume = store.received(&id);
    assert_eq!(
        upload_from(&mut store, &id, &bytes, resume),
        Upload::Complete
    );
    assert_eq!(store.read_verified(&id).unwrap(), bytes);
    assert_eq!(store.stats().partial_files, 0);
}

#[test]
fn an_upload_whose_last_byte_arrived_before_a_restart_is_finished_at_open() {
    let dir = tempfile::tempdir().unwrap();
    let (id, bytes) = file(3, 100);
    let partial = dir.path().join("partial").join(format!("{}-100", id.hex()));
    fs::create_dir_all(partial.parent().unwrap()).unwrap();
    fs::write(&partial, &bytes).unwrap();
    let (liar, _) = file(4, 100);
    let lying = dir
        .path()
        .join("partial")
        .join(format!("{}-100", liar.hex()));
    fs::write(&lying, &bytes).unwrap();

    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    assert!(store.has(&id));
    assert_eq!(store.read_verified(&id).unwrap(), bytes);
    assert!(!store.has(&liar) && store.received(&liar) == 0);
    assert!(!partial.exists() && !lying.exists());
}

#[test]
fn a_repeated_identical_chunk_is_accepted_and_a_different_one_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let (id, bytes) = file(5, CHUNK * 2 + 10);
    let received = Upload::Partial {
        received: CHUNK as u64,
    };
    assert_eq!(
        store.write_chunk(&id, 0, &bytes[..CHUNK], 1).unwrap(),
        received
    );
    // The reply was lost; the client sends the same chunk again.
    assert_eq!(
        store.write_chunk(&id, 0, &bytes[..CHUNK], 2).unwrap(),
        received
    );
    // A part of it, too.
    assert_eq!(
        store.write_chunk(&id, 10, &bytes[10..20], 3).unwrap(),
        received
    );

    let mut other = bytes[..CHUNK].to_vec();
    other[CHUNK - 1] ^= 1;
    let err = store.write_chunk(&id, 0, &other, 4).unwrap_err();
    assert!(
        matches!(err, AssetError::Overlap { offset: 0, .. }),
        "{err}"
    );
    assert_eq!(
        store.received(&id),
        CHUNK as u64,
        "a refused chunk changes nothing"
    );

    // A chunk that repeats the end of what was received and goes on past it: the
    // repeated part is checked, the rest appended.
    let from = CHUNK - 100;
    let answer = store
        .write_chunk(&id, from as u64, &bytes[from..from + CHUNK], 5)
        .unwrap();
    assert_eq!(
        answer,
        Upload::Partial {
            received: (from + CHUNK) as u64
        }
    );
    assert_eq!(
        upload_from(&mut store, &id, &bytes, (from + CHUNK) as u64),
        Upload::Complete
    );

    // Once complete, a faithful repeat still answers Complete; a different one does not.
    let tail = bytes.len() - 10;
    assert_eq!(
        store
            .write_chunk(&id, tail as u64, &bytes[tail..], 6)
            .unwrap(),
        Upload::Complete
    );
    let err = store
        .write_chunk(&id, tail as u64, &[0; 10], 7)
        .unwrap_err();
    assert!(matches!(err, AssetError::Overlap { .. }), "{err}");
    assert_eq!(store.read_verified(&id).unwrap(), bytes);
}

#[test]
fn a_chunk_out_of_order_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let (id, bytes) = file(6, 3000);
    let err = store
        .write_chunk(&id, 1000, &bytes[1000..2000], 1)
        .unwrap_err();
    assert!(
        matches!(
            err,
            AssetError::OutOfOrder {
                offset: 1000,
                received: 0,
                ..
            }
        ),
        "{err}"
    );
    assert!(files_under(dir.path()).is_empty(), "nothing was written");
    store.write_chunk(&id, 0, &bytes[..1000], 2).unwrap();
    let err = store.write_chunk(&id, 2000, &bytes[2000..], 3).unwrap_err();
    assert!(
        matches!(err, AssetError::OutOfOrder { received: 1000, .. }),
        "{err}"
    );
    assert_eq!(store.received(&id), 1000);
}

#[test]
fn bytes_that_do_not_match_their_claimed_id_are_refused_and_not_kept() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let (claimed, _) = file(7, CHUNK + 500);
    let (actual, bytes) = file(8, CHUNK + 500);
    store.write_chunk(&claimed, 0, &bytes[..CHUNK], 1).unwrap();
    let err = store
        .write_chunk(&claimed, CHUNK as u64, &bytes[CHUNK..], 2)
        .unwrap_err();
    match &err {
        AssetError::Mismatch {
            claimed: c,
            actual: a,
        } => assert_eq!((*c, *a), (claimed, actual)),
        other => panic!("expected a mismatch, got {other}"),
    }
    let message = err.to_string();
    assert!(
        message.contains(&claimed.hex()) && message.contains(&actual.hex()),
        "{message}"
    );
    assert!(!message.contains('\n'));
    assert!(!store.has(&claimed) && !store.has(&actual));
    assert_eq!(store.received(&claimed), 0, "the upload starts over");
    assert!(files_under(dir.path()).is_empty(), "nothing stored");
    assert_eq!(store.stats(), Default::default());

    // A whole file put with the wrong identity is refused the same way.
    let err = store.put(&claimed, &bytes, 3).unwrap_err();
    assert!(matches!(err, AssetError::Mismatch { .. }), "{err}");
    assert!(files_under(dir.path()).is_empty());
}

#[test]
fn limits_are_checked_before_anything_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let limits = StoreLimits {
        max_file_bytes: 1000,
        max_total_bytes: 1 << 20,
    };
    let mut store = Store::open(dir.path(), limits).unwrap();
    let (big, bytes) = file(9, 1001);
    let err = store.write_chunk(&big, 0, &bytes[..10], 1).unwrap_err();
    assert!(
        matches!(err, AssetError::FileTooLarge { limit: 1000, .. }),
        "{err}"
    );
    assert!(err.to_string().contains(&big.hex()));
    let err = store.put(&big, &bytes, 1).unwrap_err();
    assert!(matches!(err, AssetError::FileTooLarge { .. }), "{err}");

    let (id, bytes) = file(10, 1000);
    let err = store.write_chunk(&id, 990, &bytes[..20], 1).unwrap_err();
    assert!(
        matches!(
            err,
            AssetError::PastEnd {
                offset: 990,
                len: 20,
                ..
            }
        ),
        "{err}"
    );
    let err = store
        .write_chunk(&id, u64::MAX, &bytes[..20], 1)
        .unwrap_err();
    assert!(matches!(err, AssetError::PastEnd { .. }), "{err}");

    let mut roomy = Store::open(dir.path(), ROOMY).unwrap();
    let (huge, _) = file(11, 10);
    let huge = AssetId {
        size: CHUNK as u64 * 2,
        ..huge
    };
    let err = roomy
        .write_chunk(&huge, 0, &vec![0; CHUNK + 1], 1)
        .unwrap_err();
    assert!(
        matches!(err, AssetError::ChunkTooLarge { len, .. } if len == CHUNK + 1),
        "{err}"
    );
    assert!(files_under(dir.path()).is_empty(), "nothing was written");
}

#[test]
fn the_store_refuses_to_grow_past_its_total_counting_uploads_in_progress() {
    let dir = tempfile::tempdir().unwrap();
    let limits = StoreLimits {
        max_file_bytes: 10_000,
        max_total_bytes: 10_000,
    };
    let mut store = Store::open(dir.path(), limits).unwrap();
    let (a, a_bytes) = file(12, 6000);
    assert!(store.put(&a, &a_bytes, 1).unwrap());
    let (b, b_bytes) = file(13, 3000);
    store.write_chunk(&b, 0, &b_bytes[..1000], 1).unwrap();

    // 6000 stored + 1000 received + 3500 would be over 10,000; without the upload in
    // progress it would fit.
    let (c, c_bytes) = file(14, 3500);
    let err = store.write_chunk(&c, 0, &c_bytes[..100], 1).unwrap_err();
    match &err {
        AssetError::StoreFull {
            used,
            needed,
            limit,
            ..
        } => {
            assert_eq!((*used, *needed, *limit), (7000, 3500, 10_000));
        }
        other => panic!("expected a full store, got {other}"),
    }
    assert!(err.to_string().contains(&dir.path().display().to_string()));
    assert_eq!(store.received(&c), 0);
    let err = store.put(&c, &c_bytes, 1).unwrap_err();
    assert!(matches!(err, AssetError::StoreFull { .. }), "{err}");

    // The upload in progress finishes (6000 + 3000 fit), and once collection frees
    // room the refused file fits.
    assert_eq!(
        upload_from(&mut store, &b, &b_bytes, 1000),
        Upload::Complete
    );
    let collected = store.collect(1_000_000, 10);
    assert_eq!(collected.ids.len(), 2);
    assert!(store.put(&c, &c_bytes, 1).unwrap());
}

#[test]
fn an_empty_file_is_stored_by_one_empty_chunk() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    let id = AssetId::of(b"");
    assert_eq!(store.write_chunk(&id, 0, b"", 1).unwrap(), Upload::Complete);
    assert!(store.has(&id));
    assert_eq!(store.read_verified(&id).unwrap(), b"");
}

#[test]
fn a_directory_that_cannot_be_written_is_an_error_naming_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path(), ROOMY).unwrap();
    // partial/ replaced by a regular file: no upload can be created (root included).
    let partial = dir.path().join("partial");
    fs::remove_dir(&partial).unwrap();
    fs::write(&partial, b"not a directory").unwrap();
    let (id, bytes) = file(15, 100);
    let err = store.write_chunk(&id, 0, &bytes, 1).unwrap_err();
    assert!(matches!(err, AssetError::Io { .. }), "{err}");
    assert!(
        err.to_string().contains(&partial.display().to_string()),
        "{err}"
    );
    assert_eq!(store.received(&id), 0);
    assert!(!store.has(&id));

    // The same with objects/ for a whole file.
    let objects = dir.path().join("objects");
    fs::remove_dir(&objects).unwrap();
    fs::write(&objects, b"not a directory").unwrap();
    let err = store.put(&id, &bytes, 1).unwrap_err();
    assert!(
        err.to_string().contains(&objects.display().to_string()),
        "{err}"
    );
    assert!(!store.has(&id));

    // And a store whose directory cannot be created does not open.
    let err = Store::open(&partial.join("store"), ROOMY).err().unwrap();
    assert!(matches!(err, AssetError::Io { .. }), "{err}");
}

/// A chunk that finds the disk full is cut back, so the upload stays as reported and
/// resumes after a restart; the error says the disk is full, and a caller that will not
/// resume ([`Store::abandon`]) gets the bytes back.
#[test]
fn a_full_disk_fails_the_chunk_and_leaves_the_upload_as_reported() {
    let dir = tempfile::tempdir().unwrap();
    let Some(_disk) = SmallDisk::mount(&dir.path().join("disk"), 256 * 1024) else {
        return;
    };
    let root = dir.path().join("disk");
    let mut store = Store::open(&root, ROOMY).unwrap();
    let (id, bytes) = file(16, 600 * 1024);
    let mut offset = 0;
    let err = loop {
        let end = (offset + 200 * 1024).min(bytes.len());
        match store.write_chunk(&id, offset as u64, &bytes[offset..end], 1) {
            Ok(Upload::Partial { received }) => offset = received as usize,
            Ok(Upload::Complete) => panic!("600 KiB fit on a 256 KiB disk"),
            Err(e) => break e,
        }
    };
    let message = err.to_string();
    assert!(matches!(err, AssetError::Io { .. }), "{message}");
    assert!(
        message.contains("partial"),
        "names the upload's path: {message}"
    );
    assert!(!store.has(&id));
    // The partial file holds exactly the bytes reported received.
    let received = store.received(&id);
    assert_eq!(received, offset as u64);
    let partial = root
        .join("partial")
        .join(format!("{}-{}", id.hex(), id.size));
    if received > 0 {
        assert_eq!(fs::read(&partial).unwrap(), bytes[..offset]);
    }
    assert!(err.is_disk_full(), "{message}");
    drop(store);
    let mut reopened = Store::open(&root, ROOMY).unwrap();
    assert_eq!(reopened.received(&id), received);
    // A caller that will not resume gives the bytes back: the disk has room again.
    assert_eq!(reopened.abandon(&id).unwrap(), received);
    assert_eq!(reopened.received(&id), 0);
    assert_eq!(reopened.stats().partial_bytes, 0);
    assert!(!partial.exists());
    assert_eq!(
        reopened.abandon(&id).unwrap(),
        0,
        "nothing left to give back"
    );
}
