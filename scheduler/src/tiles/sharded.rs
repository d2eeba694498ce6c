//! Hash tables that never grow all at once: a [`Sharded`] map is a fixed number of
//! small tables, each key in the one its hash picks. A table that outgrows its room
//! moves every entry to a new one in a single call: the table of a whole farm's
//! workers moving at one join took milliseconds (and freed a large block, which can
//! make the allocator tidy its free lists first). Here a growth moves one shard, a
//! sixty-fourth of the entries.

use std::collections::hash_map::{Entry, HashMap};
use std::hash::{BuildHasher, BuildHasherDefault, Hash, Hasher};
use std::ops::Index;

/// Hashes a worker id or a tile number (counters) by one multiplication: the maps keyed
/// by them are looked up on every message of every worker, and a general-purpose hash of eight
/// bytes costs more than the lookup itself. Nothing walks them in an order that
/// decides anything (what does sorts first).
#[derive(Default)]
pub(crate) struct IdHasher(u64);

impl Hasher for IdHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ u64::from(b)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        }
    }

    fn write_u64(&mut self, id: u64) {
        self.0 = id.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }

    fn write_u32(&mut self, id: u32) {
        self.write_u64(u64::from(id));
    }
}

/// Shards per map: enough that a farm of tens of thousands of workers keeps each one
/// to a few hundred entries, few enough that finding the shard costs little.
const SHARDS: usize = 64;

type Shard<K, V> = HashMap<K, V, BuildHasherDefault<IdHasher>>;

/// A map keyed by ids, hashed with [`IdHasher`], in [`SHARDS`] tables.
///
/// Its order of iteration, like a single table's, is arbitrary but the same from run
/// to run for the same calls (the hash has no random seed): shard by shard, each in
/// its table's order. What walks it in an order that decides or shows anything sorts
/// first.
pub(crate) struct Sharded<K, V> {
    shards: Box<[Shard<K, V>; SHARDS]>,
    /// Entries in all the shards, kept rather than summed over them at every join.
    len: usize,
}

impl<K, V> Default for Sharded<K, V> {
    fn default() -> Self {
        Sharded {
            shards: Box::new(std::array::from_fn(|_| Shard::default())),
            len: 0,
        }
    }
}

impl<K: Hash + Eq, V> Sharded<K, V> {
    /// The shard of a key: bits of its hash that the table within does not use, so
    /// that neither the slot it takes there (the low bits) nor the tag that tells
    /// keys apart in a probe (the top seven) is the same for all of a shard's keys.
    fn shard(&self, key: &K) -> usize {
        let hash = BuildHasherDefault::<IdHasher>::default().hash_one(key);
        (hash >> 32) as usize % SHARDS
    }

    pub(crate) fn get(&self, key: &K) -> Option<&V> {
        self.shards[self.shard(key)].get(key)
    }

    pub(crate) fn get_mut(&mut self, key: &K) -> Option<&mut V> {
        let shard = self.shard(key);
        self.shards[shard].get_mut(key)
    }

    pub(crate) fn insert(&mut self, key: K, value: V) -> Option<V> {
        let shard = self.shard(&key);
        let old = self.shards[shard].insert(key, value);
        if old.is_none() {
            self.len += 1;
        }
        old
    }

    /// Inserts the entry unless the key has one already; whether it did.
    pub(crate) fn insert_new(&mut self, key: K, value: V) -> bool {
        let shard = self.shard(&key);
        match self.shards[shard].entry(key) {
            Entry::Occupied(_) => false,
            Entry::Vacant(e) => {
                e.insert(value);
                self.len += 1;
                true
            }
        }
    }

    pub(crate) fn remove(&mut self, key: &K) -> Option<V> {
        let shard = self.shard(key);
        let old = self.shards[shard].remove(key);
        if old.is_some() {
            self.len -= 1;
        }
        old
    }

    pub(crate) fn len(&self) -> usize {
        self.len
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Makes room for `additional` more entries spread evenly over the shards.
    pub(crate) fn reserve(&mut self, additional: usize) {
        let each = additional.div_ceil(SHARDS);
        for shard in self.shards.iter_mut() {
            shard.reserve(each);
        }
    }

    pub(crate) fn iter(&self) -> impl Iterator<Item = (&K, &V)> {
        self.shards.iter().flat_map(HashMap::iter)
    }

    pub(crate) fn values(&self) -> impl Iterator<Item = &V> {
        self.shards.iter().flat_map(HashMap::values)
    }
}

impl<K: Hash + Eq, V> Index<&K> for Sharded<K, V> {
    type Output = V;

    fn index(&self, key: &K) -> &V {
        self.get(key).expect("no entry for the key")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_spread_over_the_shards_and_are_found_again() {
        let mut map: Sharded<u64, u64> = Sharded::default();
        for id in 1..=20_000u64 {
            assert_eq!(map.insert(id, id * 2), None);
        }
        assert_eq!(map.len(), 20_000);
        let most = map.shards.iter().map(HashMap::len).max().unwrap();
        let least = map.shards.iter().map(HashMap::len).min().unwrap();
        assert!(least > 250 && most < 380, "{least}..{most}");
        for id in 1..=20_000u64 {
            assert_eq!(map.get(&id), Some(&(id * 2)));
        }
        assert_eq!(map.remove(&7), Some(14));
        assert_eq!(map.get(&7), None);
        assert!(map.insert_new(7, 1));
        assert!(!map.insert_new(7, 2));
        *map.get_mut(&7).unwrap() += 1;
        assert_eq!(map.get(&7), Some(&2));
        assert_eq!(map.remove(&7), Some(2));
        assert_eq!(map.remove(&7), None);
        assert_eq!(map.len(), 19_999);
        assert_eq!(map.iter().count(), 19_999);
        assert_eq!(map.values().count(), 19_999);
        assert!(!map.is_empty());
    }

    #[test]
    fn the_order_of_iteration_is_the_same_for_the_same_calls() {
        let build = || {
            let mut map: Sharded<u32, u32> = Sharded::default();
            for tile in (0..5_000u32).rev() {
                map.insert(tile, tile);
            }
            map.iter().map(|(&k, _)| k).collect::<Vec<u32>>()
        };
        assert_eq!(build(), build());
    }
}
