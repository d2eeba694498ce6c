//! Which tests may run at the same time.
//!
//! The harness runs the tests of this binary in parallel, as many at once as it has
//! threads (`--test-threads`, by default the number of cores). Every test takes its
//! turn first thing and holds it to its end:
//!
//! - [`exclusive`]: no other test runs meanwhile. For the tests whose outcome depends
//!   on timing (heartbeat, lease and handshake deadlines, processes frozen, killed or
//!   cut off for seconds, jobs that must still be running when something happens to
//!   them), that measure time, memory or CPU, or that keep the machine busy for long
//!   enough to upset such tests.
//! - [`shared`]: beside any other shared test. For the tests that hold whatever the
//!   machine's load: commands refused at once, and farms whose only checks are the
//!   bytes they give and the states they end in.
//!
//! A shared turn waits for an exclusive one to end, and an exclusive turn waits for
//! every running test to end (and makes later shared turns wait for it).

use std::sync::{RwLock, RwLockReadGuard, RwLockWriteGuard};
use std::thread;
use std::time::Instant;

static MACHINE: RwLock<()> = RwLock::new(());

/// A test's turn on the machine; when dropped, prints how long the test took.
pub struct Turn {
    _shared: Option<RwLockReadGuard<'static, ()>>,
    _exclusive: Option<RwLockWriteGuard<'static, ()>>,
    started: Instant,
}

/// Waits until no other test runs, and keeps every other test waiting until dropped.
pub fn exclusive() -> Turn {
    let guard = MACHINE.write().unwrap_or_else(|e| e.into_inner());
    Turn {
        _shared: None,
        _exclusive: Some(guard),
        started: Instant::now(),
    }
}

/// Waits until no exclusive test runs, and keeps exclusive tests waiting until dropped.
pub fn shared() -> Turn {
    let guard = MACHINE.read().unwrap_or_else(|e| e.into_inner());
    Turn {
        _shared: Some(guard),
        _exclusive: None,
        started: Instant::now(),
    }
}

impl Drop for Turn {
    fn drop(&mut self) {
        eprintln!(
            "[{}: {:.1} s]",
            thread::current().name().unwrap_or("test"),
            self.started.elapsed().as_secs_f64()
        );
    }
}
