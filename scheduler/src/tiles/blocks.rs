//! A queue kept in small blocks of the same size, reused: appending never moves what
//! is queued, and taking from the front frees nothing.
//!
//! A queue in one buffer (or in buffers that double) grows by copying everything it
//! holds and frees the old buffer: a large request or a large free can make the C
//! library's allocator first merge and sort every small block freed since it last did,
//! a pause of a millisecond or two on the heap of a farm of thousands. Here each block
//! is under a kilobyte, and a block emptied at the front moves to the back for reuse:
//! once the queue has been at its longest, it allocates nothing (any allocation may
//! still be the one that pays for that tidying, so the fewer the better).

use std::collections::VecDeque;

/// Bytes per block: under the kilobyte from which the allocator treats a request as
/// large.
const BLOCK_BYTES: usize = 960;

pub(super) struct Blocks<T> {
    /// The blocks in use, front first, then the emptied ones kept for reuse: an
    /// emptied block moves from the front to the back, so that keeping it needs no
    /// list that grows.
    blocks: VecDeque<Vec<T>>,
    /// Blocks in use (the first of `blocks`).
    used: usize,
    /// Entries of the first block already taken.
    head: usize,
    len: usize,
}

impl<T> Default for Blocks<T> {
    fn default() -> Self {
        Blocks {
            blocks: VecDeque::new(),
            used: 0,
            head: 0,
            len: 0,
        }
    }
}

impl<T: Copy> Blocks<T> {
    const PER_BLOCK: usize = if std::mem::size_of::<T>() == 0 {
        1
    } else {
        let n = BLOCK_BYTES / std::mem::size_of::<T>();
        if n == 0 {
            1
        } else {
            n
        }
    };

    pub(super) fn len(&self) -> usize {
        self.len
    }

    pub(super) fn push_back(&mut self, value: T) {
        let last = self
            .used
            .checked_sub(1)
            .and_then(|i| self.blocks.get_mut(i));
        match last {
            Some(block) if block.len() < Self::PER_BLOCK => block.push(value),
            _ => {
                if self.used == self.blocks.len() {
                    self.blocks.push_back(Vec::with_capacity(Self::PER_BLOCK));
                }
                self.blocks[self.used].push(value);
                self.used += 1;
            }
        }
        self.len += 1;
    }

    /// Where the entry `index` places from the front is.
    fn place(&self, index: usize) -> (usize, usize) {
        let at = self.head + index;
        (at / Self::PER_BLOCK, at % Self::PER_BLOCK)
    }

    pub(super) fn get(&self, index: usize) -> Option<&T> {
        if index >= self.len {
            return None;
        }
        let (block, at) = self.place(index);
        self.blocks.get(block)?.get(at)
    }

    pub(super) fn get_mut(&mut self, index: usize) -> Option<&mut T> {
        if index >= self.len {
            return None;
        }
        let (block, at) = self.place(index);
        self.blocks.get_mut(block)?.get_mut(at)
    }

    pub(super) fn front(&self) -> Option<&T> {
        self.get(0)
    }

    pub(super) fn front_mut(&mut self) -> Option<&mut T> {
        self.get_mut(0)
    }

    pub(super) fn back_mut(&mut self) -> Option<&mut T> {
        let last = self.len.checked_sub(1)?;
        self.get_mut(last)
    }

    /// Drops the `n` entries at the front (all of them, if there are fewer), keeping
    /// the blocks they emptied.
    pub(super) fn advance(&mut self, n: usize) {
        let n = n.min(self.len);
        self.len -= n;
        self.head += n;
        while self.used > 0 && (self.head >= Self::PER_BLOCK || self.len == 0) {
            if let Some(mut block) = self.blocks.pop_front() {
                block.clear();
                self.blocks.push_back(block);
            }
            self.used -= 1;
            self.head = self.head.saturating_sub(Self::PER_BLOCK);
        }
        if self.used == 0 {
            self.head = 0;
        }
    }

    pub(super) fn pop_front(&mut self) {
        self.advance(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_queue_across_many_blocks_keeps_its_order_and_reuses_its_blocks() {
        let mut q: Blocks<u64> = Blocks::default();
        let mut model = VecDeque::new();
        let mut next = 0u64;
        for round in 0..50 {
            for _ in 0..(round * 37) % 400 {
                q.push_back(next);
                model.push_back(next);
                next += 1;
            }
            let take = (round * 53) % 300;
            q.advance(take);
            for _ in 0..take.min(model.len()) {
                model.pop_front();
            }
            assert_eq!(q.len(), model.len());
            for (i, v) in model.iter().enumerate() {
                assert_eq!(q.get(i), Some(v));
            }
            assert_eq!(q.front(), model.front());
            assert_eq!(q.get(model.len()), None);
        }
        let held = q.blocks.len();
        q.advance(usize::MAX);
        assert_eq!((q.len(), q.used), (0, 0));
        assert_eq!(q.front(), None);
        assert_eq!(q.blocks.len(), held);
        for v in 0..1_000 {
            q.push_back(v);
        }
        assert_eq!(q.blocks.len(), held.max(1_000_usize.div_ceil(120)));
        *q.back_mut().unwrap() = 7;
        *q.front_mut().unwrap() = 8;
        assert_eq!((q.front(), q.get(999)), (Some(&8), Some(&7)));
    }
}
