//! What the integration tests share: file contents, and a small file system that fills
//! up, where this machine lets a test mount one.

use std::path::{Path, PathBuf};
use std::process::Command;

use assets::{AssetId, StoreLimits};

/// `len` bytes that differ with `seed`, so that every file has its own hash.
pub fn bytes(seed: u64, len: usize) -> Vec<u8> {
    let mut state = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    (0..len)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state as u8
        })
        .collect()
}

pub fn file(seed: u64, len: usize) -> (AssetId, Vec<u8>) {
    let bytes = bytes(seed, len);
    (AssetId::of(&bytes), bytes)
}

pub const ROOMY: StoreLimits = StoreLimits {
    max_file_bytes: 64 << 20,
    max_total_bytes: 1 << 30,
};

/// The files under `dir`, recursively, with their lengths.
pub fn files_under(dir: &Path) -> Vec<(PathBuf, u64)> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for entry in std::fs::read_dir(&d).unwrap() {
            let entry = entry.unwrap();
            let meta = entry.metadata().unwrap();
            if meta.is_dir() {
                todo.push(entry.path());
            } else {
                out.push((entry.path(), meta.len()));
            }
        }
    }
    out.sort();
    out
}

/// A tmpfs of `bytes` mounted at `dir` for as long as it lives: a disk that really
/// fills up, or is read-only. `None` where mounting is not allowed (not root, or a
/// container without the capability), with the reason printed so the skipped case is
/// visible; a failure instead where `TESSERA_REQUIRE_PRIVILEGED=1` says the case must
/// run (CI runs as root).
pub struct SmallDisk {
    dir: PathBuf,
}

impl SmallDisk {
    pub fn mount(dir: &Path, bytes: u64) -> Option<SmallDisk> {
        std::fs::create_dir_all(dir).unwrap();
        let size = format!("size={bytes}");
        match run("mount", &["-t", "tmpfs", "-o", &size, "tmpfs"], dir) {
            Ok(()) => Some(SmallDisk {
                dir: dir.to_path_buf(),
            }),
            Err(why) => {
                unprivileged(&format!("cannot mount a tmpfs here ({why})"));
                None
            }
        }
    }

    /// Makes the disk read-only, for root too.
    pub fn read_only(&self) {
        run("mount", &["-o", "remount,ro"], &self.dir).expect("remount the tmpfs read-only");
    }
}

fn run(program: &str, args: &[&str], dir: &Path) -> Result<(), String> {
    match Command::new(program).args(args).arg(dir).output() {
        Ok(out) if out.status.success() => Ok(()),
        Ok(out) => Err(String::from_utf8_lossy(&out.stderr).trim().to_string()),
        Err(e) => Err(format!("cannot run {program}: {e}")),
    }
}

/// A case that needs privileges this machine does not give: skipped with a line
/// saying so, or failed where they are required.
fn unprivileged(why: &str) {
    if std::env::var_os("TESSERA_REQUIRE_PRIVILEGED").is_some_and(|v| v == "1") {
        panic!("TESSERA_REQUIRE_PRIVILEGED=1 but {why}");
    }
    eprintln!("SKIPPED a disk case: {why}");
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.dir).status();
    }
}

/// Whether a directory made read-only still takes new files: it does for root, which
/// permissions do not bind.
pub fn permissions_bind(dir: &Path) -> bool {
    let probe = dir.join("probe");
    let writable = std::fs::write(&probe, b"x").is_ok();
    let _ = std::fs::remove_file(&probe);
    !writable
}
