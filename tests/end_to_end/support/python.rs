//! The Python tools the API's tests run: `openapi-spec-validator` and `schemathesis`,
//! in a virtual environment's interpreter (`TESSERA_PYTHON`, or
//! `/opt/tessera-venv/bin/python` as CI makes it). Without them a test says so and
//! passes, unless `TESSERA_REQUIRE_PYTHON=1` (as in CI), where missing tools fail it.

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
    let python = python();
    let found = Command::new(&python)
        .args(["-c", "import openapi_spec_validator, schemathesis"])
        .output()
        .is_ok_and(|out| out.status.success());
    if found {
        return Some(python);
    }
    assert!(
        std::env::var("TESSERA_REQUIRE_PYTHON").as_deref() != Ok("1"),
        "TESSERA_REQUIRE_PYTHON=1 but {} lacks openapi-spec-validator or schemathesis \
         (set TESSERA_PYTHON to a virtual environment's python that has them)",
        python.display()
    );
    eprintln!(
        "skipped: no openapi-spec-validator and schemathesis in {} (set TESSERA_PYTHON)",
        python.display()
    );
    None
}
