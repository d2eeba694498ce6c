//! The Python client (`clients/python`, docs/api.md "From Python"): installed with pip
//! from the source tree, offline, into a directory of its own, then its pytest suite
//! run against real coordinators and workers of the binary under test.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use tempfile::TempDir;

use crate::support::{path_str, python_with_or_skip, repo, shared, BIN};

/// The longest the suite may take (it takes seconds; CI's machine may be loaded).
const SUITE_TIMEOUT: Duration = Duration::from_secs(300);

/// The files of the client's source tree that pip builds it from (its tests stay in
/// the checkout, where pytest runs them against the installed copy).
const PACKAGE: &[&str] = &["pyproject.toml", "README.md", "src"];

fn copy_tree(from: &Path, to: &Path) {
    if from.is_dir() {
        std::fs::create_dir_all(to).unwrap();
        for entry in std::fs::read_dir(from).unwrap() {
            let entry = entry.unwrap();
            let name = entry.file_name();
            // What an earlier build or run left in a working copy is not the source.
            let name_str = name.to_string_lossy();
            if name_str == "__pycache__" || name_str.ends_with(".egg-info") {
                continue;
            }
            copy_tree(&entry.path(), &to.join(&name));
        }
    } else {
        std::fs::create_dir_all(to.parent().expect("a file's directory")).unwrap();
        std::fs::copy(from, to).unwrap_or_else(|e| panic!("cannot copy {}: {e}", from.display()));
    }
}

/// The last `lines` lines of a file, for a failure's message.
fn tail(path: &Path, lines: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let all: Vec<&str> = text.lines().collect();
    all[all.len().saturating_sub(lines)..].join("\n")
}

#[test]
fn the_python_client_installs_with_pip_and_passes_its_suite_against_a_real_farm() {
    let Some(python) = python_with_or_skip(&["pytest", "setuptools", "wheel"]) else {
        return;
    };
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let source = repo().join("clients/python");
    let tree = d.join("source");
    for name in PACKAGE {
        copy_tree(&source.join(name), &tree.join(name));
    }

    // `pip install ./clients/python`, offline, with the environment's setuptools.
    let site = d.join("site");
    let installed = Command::new(&python)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "--no-index",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            path_str(&site),
            path_str(&tree),
        ])
        .output()
        .expect("cannot run pip");
    assert!(
        installed.status.success(),
        "pip install clients/python failed:\n{}{}",
        String::from_utf8_lossy(&installed.stdout),
        String::from_utf8_lossy(&installed.stderr)
    );
    assert!(
        site.join("tessera_client/py.typed").is_file(),
        "py.typed is installed"
    );

    let output = d.join("pytest.out");
    let mut suite = Command::new(&python)
        .args([
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "clients/python",
        ])
        .current_dir(repo())
        .env("PYTHONPATH", &site)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .env("TESSERA_BIN", BIN)
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(&output).unwrap())
        .stderr(std::fs::File::create(d.join("pytest.err")).unwrap())
        .spawn()
        .expect("cannot run pytest");
    let started = Instant::now();
    let status = loop {
        if let Some(status) = suite.try_wait().unwrap() {
            break Some(status);
        }
        if started.elapsed() > SUITE_TIMEOUT {
            let _ = suite.kill();
            let _ = suite.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let said = format!(
        "{}\n{}",
        tail(&output, 120),
        tail(&d.join("pytest.err"), 40)
    );
    let status = status.unwrap_or_else(|| {
        panic!("the Python client's suite did not end within {SUITE_TIMEOUT:?}:\n{said}")
    });
    assert!(
        status.success(),
        "the Python client's suite failed ({status}):\n{said}"
    );
    // It ran tests, and every one passed: none skipped, none left out.
    let last = said
        .lines()
        .rev()
        .find(|l| l.contains(" passed"))
        .unwrap_or_default()
        .to_owned();
    assert!(
        !last.is_empty() && !last.contains("skipped") && !last.contains("deselected"),
        "{said}"
    );
    eprintln!(
        "python client: {} in {:.1} s",
        last.trim(),
        started.elapsed().as_secs_f64()
    );
}
