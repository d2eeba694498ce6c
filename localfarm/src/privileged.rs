//! The rule for tests of what needs privileges (a [`crate::CpuLimit`] needs root): they
//! run where they can; elsewhere they are skipped with a line saying so, except where
//! `TESSERA_REQUIRE_PRIVILEGED=1` (CI) says they must run, and then they fail. So a
//! test that must run never passes without having run.

use std::fmt::Display;
use std::io::Write as _;

/// Whether a missing privilege fails a test instead of skipping it: the environment
/// variable `TESSERA_REQUIRE_PRIVILEGED` set to anything but empty or `0`.
pub fn privileges_required() -> bool {
    std::env::var("TESSERA_REQUIRE_PRIVILEGED").is_ok_and(|v| !v.is_empty() && v != "0")
}

/// For a test whose privileged step failed with `reason`: panics when privileges are
/// required, else writes `skipped: TEST: REASON` on stderr; the test then returns.
pub fn unprivileged(test: &str, reason: &dyn Display) {
    assert!(
        !privileges_required(),
        "{test}: TESSERA_REQUIRE_PRIVILEGED is set, but {reason}"
    );
    // To the process's stderr itself, past the test harness's capture, so that the skip
    // shows in every run.
    let _ = writeln!(
        std::io::stderr(),
        "skipped: {test}: {reason} (with TESSERA_REQUIRE_PRIVILEGED=1 this fails)"
    );
}
