//! Counting the heap the scheduler holds.
//!
//! Memory is measured, not estimated from `size_of`: a program that wants the figures
//! installs [`CountingAlloc`] as its global allocator, and the simulation reads the
//! current thread's net allocated bytes before and after each `Scheduler::handle` call.
//! The counters are per thread, so tests running in parallel do not disturb each
//! other; the scheduler lives on one thread, so everything it allocates is freed there.
//! The figures are the bytes the program asked for: the allocator's own per-block
//! overhead and fragmentation come on top.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

/// The system allocator, counting each thread's live heap bytes.
///
/// Install it in a binary or an integration test to get memory figures in the
/// simulation's report:
///
/// ```ignore
/// #[global_allocator]
/// static ALLOC: scheduler::sim::CountingAlloc = scheduler::sim::CountingAlloc;
/// ```
pub struct CountingAlloc;

thread_local! {
    static LIVE: Cell<i64> = const { Cell::new(0) };
}

fn add(bytes: i64) {
    // `try_with`: the slot may be gone while the thread is being torn down.
    let _ = LIVE.try_with(|live| live.set(live.get() + bytes));
}

/// Bytes allocated and not yet freed by the current thread, since it started (freeing
/// what another thread allocated makes it go down, even below zero).
pub fn live_bytes() -> i64 {
    LIVE.try_with(Cell::get).unwrap_or(0)
}

/// Whether [`CountingAlloc`] is the global allocator of this program: an allocation
/// must move the counter.
pub fn counting() -> bool {
    let before = live_bytes();
    let probe = std::hint::black_box(Box::new([0u8; 64]));
    let moved = live_bytes() != before;
    drop(probe);
    moved
}

// SAFETY: every method forwards to the system allocator with the same arguments; the
// counting only reads the sizes, and touches a thread-local `Cell` that itself never
// allocates (const-initialised, no destructor).
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded as received.
        let ptr = unsafe { System.alloc(layout) };
        if !ptr.is_null() {
            add(layout.size() as i64);
        }
        ptr
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded as received.
        let ptr = unsafe { System.alloc_zeroed(layout) };
        if !ptr.is_null() {
            add(layout.size() as i64);
        }
        ptr
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded as received.
        unsafe { System.dealloc(ptr, layout) };
        add(-(layout.size() as i64));
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded as received.
        let new = unsafe { System.realloc(ptr, layout, new_size) };
        if !new.is_null() {
            add(new_size as i64 - layout.size() as i64);
        }
        new
    }
}
