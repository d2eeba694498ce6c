//! The worker's cache: eviction order, damage, limits, and disks that refuse writes.

use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::thread::sleep;
use std::time::Duration;

use assets::{AssetError, AssetId, Cache, Lookup};

use crate::common::{file, files_under, permissions_bind, SmallDisk};
use crate::store_upkeep::flip_a_bit;

fn path(dir: &Path, id: &AssetId) -> PathBuf {
    let hex = id.hex();
    dir.join(&hex[..2]).join(format!("{hex}-{}", id.size))
}

fn hit(cache: &mut Cache, id: &AssetId) -> Vec<u8> {
    match cache.get(id) {
        Lookup::Hit(bytes) => bytes,
        other => panic!("expected {id} cached, got {other:?}"),
    }
}

#[test]
fn the_least_recently_used_files_go_first() {
    let dir = tempfile::tempdir().unwrap();
    let mut cache = Cache::open(dir.path(), 3000).unwrap();
    let [a, b, c, d, e] = [1, 2, 3, 4, 5].map(|seed| file(seed, 1000));
    for (id, bytes) in [&a, &b, &c] {
        assert!(cache.put(id, bytes).unwrap());
    }
    assert_eq!(
        hit(&mut cache, &a.0),
        a.1,
        "a is now the most recently used"
    );
    assert!(cache.put(&d.0, &d.1).unwrap());
    assert!(
        !cache.contains(&b.0) && !path(dir.path(), &b.0).exists(),
        "b went first"
    );
    assert!(cache.contains(&a.0) && cache.contains(&c.0));
    assert!(cache.put(&e.0, &e.1).unwrap());
    assert!(!cache.contains(&c.0), "then c");
    assert!(matches!(cache.get(&b.0), Lookup::Absent));
    let stats = cache.stats();
    assert_eq!((stats.files, stats.bytes, stats.max_bytes), (3, 3000, 3000));
    assert_eq!(
        (stats.hits, stats.misses, stats.evicted, stats.damaged),
        (1, 1, 2, 0)
    );
    // Putting a cached file again only marks it used.
    assert!(cache.put(&a.0, &a.1).unwrap());
    assert_eq!(cache.stats().evicted, 2);
}

#[test]
fn the_order_of_use_survives_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let a = file(6, 1000);
    let b = file(7, 1000);
    {
        let mut cache = Cache::open(dir.path(), 2000).unwrap();
        cache.put(&a.0, &a.1).unwrap();
        sleep(Duration::from_millis(20));
        cache.put(&b.0, &b.1).unwrap();
        sleep(Duration::from_millis(20));
        hit(&mut cache, &a.0);
    }
    // Reopened smaller: the file used longest ago goes, though it was written last.
    let mut cache = Cache::open(dir.path(), 1000).unwrap();
    assert!(cache.contains(&a.0) && !cache.contains(&b.0));
    assert_eq!(cache.stats().evicted, 1);
    assert_eq!(hit(&mut cache, &a.0), a.1);
}

#[test]
fn a_damaged_file_is_removed_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    let mut cache = Cache::open(dir.path(), 1 << 20).unwrap();
    let (id, bytes) = file(8, 4000);
    cache.put(&id, &bytes).unwrap();
    flip_a_bit(&path(dir.path(), &id), 3999);
    match cache.get(&id) {
        Lookup::Damaged(AssetError::Corrupt { id: named, .. }) => assert_eq!(named, id),
        other => panic!("expected damage, got {other:?}"),
    }
    assert!(!path(dir.path(), &id).exists());
    assert!(matches!(cache.get(&id), Lookup::Absent));
    let stats = cache.stats();
    assert_eq!(
        (stats.files, stats.bytes, stats.damaged, stats.misses),
        (0, 0, 1, 2)
    );
    // Repaired by fetching it again.
    assert!(cache.put(&id, &bytes).unwrap());
    assert_eq!(hit(&mut cache, &id), bytes);

    // A file cut short while the cache was running is damage too; one removed behind
    // its back is simply absent.
    fs::write(path(dir.path(), &id), &bytes[..10]).unwrap();
    assert!(matches!(
        cache.get(&id),
        Lookup::Damaged(AssetError::Corrupt { .. })
    ));
    cache.put(&id, &bytes).unwrap();
    fs::remove_file(path(dir.path(), &id)).unwrap();
    assert!(matches!(cache.get(&id), Lookup::Absent));
    assert_eq!(cache.stats().files, 0);
}

#[test]
fn open_drops_leftovers_and_files_of_the_wrong_length() {
    let dir = tempfile::tempdir().unwrap();
    let (good, good_bytes) = file(9, 500);
    let (cut, cut_bytes) = file(10, 500);
    {
        let mut cache = Cache::open(dir.path(), 1 << 20).unwrap();
        cache.put(&good, &good_bytes).unwrap();
        cache.put(&cut, &cut_bytes).unwrap();
    }
    fs::write(path(dir.path(), &cut), &cut_bytes[..499]).unwrap();
    let temp = path(dir.path(), &good).with_file_name(".tmp-crashed");
    fs::write(&temp, b"partial").unwrap();
    let mut cache = Cache::open(dir.path(), 1 << 20).unwrap();
    assert_eq!(cache.stats().files, 1);
    assert_eq!(cache.stats().bytes, 500);
    assert!(!temp.exists() && !path(dir.path(), &cut).exists());
    assert_eq!(hit(&mut cache, &good), good_bytes);
}

#[test]
fn a_file_bigger_than_the_cache_is_not_cached_and_a_lie_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut cache = Cache::open(dir.path(), 1000).unwrap();
    let small = file(11, 600);
    cache.put(&small.0, &small.1).unwrap();
    let (big, big_bytes) = file(12, 1001);
    assert!(!cache.put(&big, &big_bytes).unwrap());
    assert!(
        cache.contains(&small.0),
        "nothing evicted for a file that cannot fit"
    );
    assert_eq!(files_under(dir.path()).len(), 1);

    let err = cache.put(&small.0, &big_bytes).unwrap_err();
    assert!(matches!(err, AssetError::Mismatch { .. }), "{err}");
    let (other, other_bytes) = file(13, 600);
    let err = cache.put(&other, &big_bytes[..600]).unwrap_err();
    assert!(matches!(err, AssetError::Mismatch { .. }), "{err}");
    assert!(!cache.contains(&other));
    assert!(cache.put(&other, &other_bytes).unwrap());
}

#[test]
fn a_directory_that_cannot_be_written_is_an_error_the_caller_can_live_with() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("cache");
    let mut cache = Cache::open(&root, 1 << 20).unwrap();
    let (id, bytes) = file(14, 100);

    // Read-only by its permissions: binds everyone but root.
    fs::set_permissions(&root, fs::Permissions::from_mode(0o555)).unwrap();
    if permissions_bind(&root) {
        let err = cache.put(&id, &bytes).unwrap_err();
        assert!(matches!(err, AssetError::Io { .. }), "{err}");
        assert!(
            err.to_string().contains(&root.display().to_string()),
            "{err}"
        );
        assert!(!cache.contains(&id));
    }
    fs::set_permissions(&root, fs::Permissions::from_mode(0o755)).unwrap();

    // A read-only file system binds root too.
    let disk_dir = dir.path().join("ro");
    if let Some(disk) = SmallDisk::mount(&disk_dir, 1 << 20) {
        let mut on_disk = Cache::open(&disk_dir, 1 << 20).unwrap();
        disk.read_only();
        let err = on_disk.put(&id, &bytes).unwrap_err();
        assert!(matches!(err, AssetError::Io { .. }), "{err}");
        assert!(
            err.to_string().contains(&disk_dir.display().to_string()),
            "{err}"
        );
        assert!(!on_disk.contains(&id));
        assert!(matches!(on_disk.get(&id), Lookup::Absent));
    }

    // Unwritable for anyone: the cache's directory replaced by a regular file.
    fs::remove_dir_all(&root).unwrap();
    fs::write(&root, b"not a directory").unwrap();
    let err = cache.put(&id, &bytes).unwrap_err();
    assert!(matches!(err, AssetError::Io { .. }), "{err}");
    assert!(
        err.to_string().contains(&root.display().to_string()),
        "{err}"
    );
    assert!(!err.to_string().contains('\n'));
    assert!(!cache.contains(&id));
    assert!(matches!(cache.get(&id), Lookup::Absent));
    let err = Cache::open(&root.join("below"), 1000).err().unwrap();
    assert!(matches!(err, AssetError::Io { .. }), "{err}");
}

#[test]
fn a_full_disk_fails_the_put_and_leaves_nothing_behind() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("disk");
    let Some(_disk) = SmallDisk::mount(&root, 128 * 1024) else {
        return;
    };
    let mut cache = Cache::open(&root, 1 << 30).unwrap();
    let (big, big_bytes) = file(15, 512 * 1024);
    let err = cache.put(&big, &big_bytes).unwrap_err();
    let message = err.to_string();
    assert!(matches!(err, AssetError::Io { .. }), "{message}");
    assert!(message.contains(&root.display().to_string()), "{message}");
    assert!(!cache.contains(&big));
    assert!(
        files_under(&root).is_empty(),
        "no temporary file left: {:?}",
        files_under(&root)
    );
    let (small, small_bytes) = file(16, 1000);
    assert!(
        cache.put(&small, &small_bytes).unwrap(),
        "the cache goes on"
    );
    assert_eq!(hit(&mut cache, &small), small_bytes);
}
