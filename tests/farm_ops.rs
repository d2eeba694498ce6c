//! Operating a farm, against real `tessera` processes on 127.0.0.1: one coordinator per
//! data directory.

mod common;

use common::{client, ok, serial, start_coordinator, try_start_coordinator};

#[test]
fn a_data_directory_in_use_is_refused_with_the_holders_address() {
    let _serial = serial();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (mut first, addr) = start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "first.log");
    let refused = try_start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "second.log")
        .map(|(_, addr)| addr)
        .expect_err("a second coordinator started on the same data directory");
    let log = std::fs::read_to_string(dir.path().join("second.log")).unwrap();
    let errors: Vec<&str> = log.lines().filter(|l| l.starts_with("error: ")).collect();
    assert_eq!(errors.len(), 1, "{refused}");
    assert!(
        errors[0].contains(&format!(
            "the data directory {} is in use by another coordinator (pid {}, listening on \
             {addr})",
            data.display(),
            first.pid()
        )),
        "{}",
        errors[0]
    );
    // The first one goes on serving.
    let listed = ok(client(dir.path(), &addr, &["list"]), "list");
    assert_eq!(listed.stdout.trim(), "no jobs");
    assert!(first.is_running());

    // Killed, it leaves its lock file behind, which does not stop a restart.
    first.kill9();
    assert!(data.join("coordinator.lock").exists());
    let (_again, again) = start_coordinator(dir.path(), &data, "127.0.0.1:0", &[], "third.log");
    ok(
        client(dir.path(), &again, &["list"]),
        "list after a restart",
    );
}
