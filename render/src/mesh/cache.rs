//! Geometry kept across scenes: a worker renders job after job on the same meshes, and
//! each would otherwise read every file again and build its hierarchy again. Geometry
//! is found by the SHA-256 of what it was read from ([`super::MeshFile::sha256`]), which
//! is known before the file is read as a mesh, and the least recently used is dropped
//! beyond a number of triangles, which is what reading and building cost and what the
//! geometry and its hierarchy hold in memory.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use super::{lock, MeshGeometry};

/// Built geometry shared by every scene given the same cache, by the SHA-256 of its
/// file (and a glTF's buffers). A handle: clones share one cache, across threads.
#[derive(Clone)]
pub struct GeometryCache {
    inner: Arc<Mutex<Lru>>,
}

/// What a cache holds, and how often it was asked for what it held.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    pub entries: usize,
    /// The triangles of the geometry held, at most the cache's `max_triangles`.
    pub triangles: u64,
    /// Files whose geometry was found.
    pub hits: u64,
    /// Files that had to be read.
    pub misses: u64,
}

struct Lru {
    max_triangles: u64,
    /// Each geometry and when it was last used.
    entries: HashMap<[u8; 32], (Arc<MeshGeometry>, u64)>,
    /// The same, by when they were last used: the first is dropped first.
    by_use: BTreeMap<u64, [u8; 32]>,
    clock: u64,
    stats: CacheStats,
}

impl Lru {
    fn touch(&mut self, sha256: &[u8; 32]) -> Option<Arc<MeshGeometry>> {
        self.clock += 1;
        let (geometry, used) = self.entries.get_mut(sha256)?;
        self.by_use.remove(used);
        *used = self.clock;
        self.by_use.insert(self.clock, *sha256);
        Some(geometry.clone())
    }
}

fn triangles(geometry: &MeshGeometry) -> u64 {
    geometry.data.triangles.len() as u64
}

impl GeometryCache {
    /// A cache that keeps at most `max_triangles` triangles of geometry (0 keeps none).
    pub fn new(max_triangles: u64) -> Self {
        GeometryCache {
            inner: Arc::new(Mutex::new(Lru {
                max_triangles,
                entries: HashMap::new(),
                by_use: BTreeMap::new(),
                clock: 0,
                stats: CacheStats::default(),
            })),
        }
    }

    pub fn stats(&self) -> CacheStats {
        lock(&self.inner).stats
    }

    /// The geometry read from bytes of SHA-256 `sha256`, if it is held: now the most
    /// recently used.
    pub(crate) fn get(&self, sha256: &[u8; 32]) -> Option<Arc<MeshGeometry>> {
        let mut lru = lock(&self.inner);
        let found = lru.touch(sha256);
        match found {
            Some(_) => lru.stats.hits += 1,
            None => lru.stats.misses += 1,
        }
        found
    }

    /// Keeps `geometry`, just read from bytes of SHA-256 `sha256`, dropping the least
    /// recently used beyond the limit; the geometry to use. If another scene kept the
    /// same bytes' geometry meanwhile, that one: its hierarchy is built once for both.
    /// A geometry larger than the whole cache is used but not kept, and drops nothing.
    pub(crate) fn keep(&self, sha256: [u8; 32], geometry: Arc<MeshGeometry>) -> Arc<MeshGeometry> {
        let mut lru = lock(&self.inner);
        if let Some(held) = lru.touch(&sha256) {
            return held;
        }
        let size = triangles(&geometry);
        if size > lru.max_triangles {
            return geometry;
        }
        while lru.stats.triangles + size > lru.max_triangles {
            let Some((_, oldest)) = lru.by_use.pop_first() else {
                break;
            };
            if let Some((dropped, _)) = lru.entries.remove(&oldest) {
                lru.stats.triangles -= triangles(&dropped);
            }
        }
        let clock = lru.clock;
        lru.entries.insert(sha256, (geometry.clone(), clock));
        lru.by_use.insert(clock, sha256);
        lru.stats.triangles += size;
        lru.stats.entries = lru.entries.len();
        geometry
    }
}

impl std::fmt::Debug for GeometryCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let lru = lock(&self.inner);
        f.debug_struct("GeometryCache")
            .field("max_triangles", &lru.max_triangles)
            .field("stats", &lru.stats)
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::MeshData;

    /// Geometry of `n` triangles.
    fn geometry(n: usize) -> Arc<MeshGeometry> {
        Arc::new(MeshGeometry::new(MeshData {
            positions: vec![[0.0; 3]; 3],
            triangles: vec![[0, 1, 2]; n],
            corner_normals: vec![[super::super::NO_NORMAL; 3]; n],
            ..MeshData::default()
        }))
    }

    #[test]
    fn the_least_recently_used_is_dropped_beyond_the_limit() {
        let cache = GeometryCache::new(10);
        let (a, b, c) = ([1; 32], [2; 32], [3; 32]);
        let kept_a = cache.keep(a, geometry(4));
        cache.keep(b, geometry(4));
        // `a` used since `b` was kept: `b` is the one dropped for `c`.
        assert!(Arc::ptr_eq(&cache.get(&a).unwrap(), &kept_a));
        cache.keep(c, geometry(4));
        assert!(cache.get(&b).is_none());
        assert!(cache.get(&a).is_some() && cache.get(&c).is_some());
        assert_eq!(
            cache.stats(),
            CacheStats {
                entries: 2,
                triangles: 8,
                hits: 3,
                misses: 1
            }
        );
    }

    #[test]
    fn geometry_larger_than_the_cache_is_used_but_not_kept() {
        let cache = GeometryCache::new(10);
        cache.keep([1; 32], geometry(6));
        let big = geometry(11);
        assert!(Arc::ptr_eq(&cache.keep([2; 32], big.clone()), &big));
        assert!(cache.get(&[2; 32]).is_none());
        assert!(cache.get(&[1; 32]).is_some());
        assert_eq!(cache.stats().triangles, 6);
    }

    #[test]
    fn the_geometry_kept_first_is_the_one_everyone_uses() {
        let cache = GeometryCache::new(10);
        let first = cache.keep([1; 32], geometry(2));
        let second = cache.keep([1; 32], geometry(2));
        assert!(Arc::ptr_eq(&first, &second));
        let shared = cache.clone();
        let third = std::thread::spawn(move || shared.get(&[1; 32]).unwrap())
            .join()
            .unwrap();
        assert!(Arc::ptr_eq(&first, &third));
        assert_eq!(cache.stats().entries, 1);
    }
}
