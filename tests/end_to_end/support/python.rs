//! The Python tools the API's tests run: `openapi-spec-validator` and `schemathesis`,
//! and `pytest` for the Python client's own suite, in a virtual environment's
//! interpreter (`TESSERA_PYTHON`, or `/opt/tessera-venv/bin/python` as CI makes it).
//! Without them a test says so and passes, unless `TESSERA_REQUIRE_PYTHON=1` (as in
//! CI), where missing tools fail it.

use std::path::PathBuf;
use std::process::Command;

/// The interpreter: `TESSERA_PYTHON`, or CI's virtual environment's.
pub fn python() -> PathBuf {
    std::env::var_os("TESSERA_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/opt/tessera-venv/bin/python"))
}

/// The interpreter, if it has both tools; `None` (the test then passes, saying it
/// skipped) when it has not and `TESSERA_REQUIRE_PYTHON` is not 1; with it set (CI),
/// missing tools fail.
pub fn python_tools_or_skip() -> Option<PathBuf> {
    python_with_or_skip(&["openapi_spec_validator", "schemathesis"])
}

/// The interpreter, if it can import every one of `modules`; `None` (the test then
/// passes, saying it skipped) when it cannot and `TESSERA_REQUIRE_PYTHON` is not 1;
/// with it set (CI), a missing module fails.
pub fn python_with_or_skip(modules: &[&str]) -> Option<PathBuf> {
    let python = python();
    let found = Command::new(&python)
        .args(["-c", &format!("import {}", modules.join(", "))])
        .output()
        .is_ok_and(|out| out.status.success());
    if found {
        return Some(python);
    }
    let names = modules.join(", ");
    assert!(
        std::env::var("TESSERA_REQUIRE_PYTHON").as_deref() != Ok("1"),
        "TESSERA_REQUIRE_PYTHON=1 but {} cannot import {names} (set TESSERA_PYTHON to a \
         virtual environment's python that has them)",
        python.display()
    );
    eprintln!(
        "skipped: {} cannot import {names} (set TESSERA_PYTHON)",
        python.display()
    );
    None
}
