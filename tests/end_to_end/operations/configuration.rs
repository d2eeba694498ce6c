//! Configuring the daemons: settings from a file, the environment and flags, and where
//! each comes from (`--print-config`); a bad config file or retention is one line that
//! says where; `--reset-database` is for one start only; one coordinator per data
//! directory. Real binaries on 127.0.0.1.

use std::time::Duration;

use crate::support::{
    client, ok, path_str, poll, shared, start_coordinator, start_worker_with, tessera, tessera_env,
    try_start_coordinator, write_token_file,
};

/// The value and source `--print-config` shows for `key`, or `None` if not set.
fn setting(printed: &str, key: &str) -> Option<(String, String)> {
    if printed.lines().any(|l| l == format!("# {key}: not set")) {
        return None;
    }
    let line = printed
        .lines()
        .find(|l| l.starts_with(&format!("{key} = ")))
        .unwrap_or_else(|| panic!("no {key} in\n{printed}"));
    let (value, source) = line[key.len() + 3..]
        .split_once("  # ")
        .unwrap_or_else(|| panic!("no source in {line:?}"));
    Some((value.to_owned(), source.to_owned()))
}

#[test]
fn a_flag_beats_the_environment_which_beats_the_config_file() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("tessera.toml"),
        "[coordinator]\nmax-aa = 8\nmax-objects = 10\nmax-pixels = 1000\ninsecure = true\n\
         [worker]\nthreads = 3\nname = \"render-7\"\n",
    )
    .unwrap();
    let out = tessera_env(
        dir.path(),
        &[
            "coordinator",
            "--config",
            "tessera.toml",
            "--max-aa",
            "4",
            "--print-config",
        ],
        &[("TESSERA_MAX_OBJECTS", "20"), ("TESSERA_MAX_PIXELS", "5")],
    );
    assert!(out.status.success(), "{out:?}");
    let printed = String::from_utf8(out.stdout).unwrap();
    assert_eq!(
        setting(&printed, "max-aa"),
        Some(("4".into(), "flag".into()))
    );
    assert_eq!(
        setting(&printed, "max-objects"),
        Some(("20".into(), "environment".into()))
    );
    assert_eq!(
        setting(&printed, "max-pixels"),
        Some(("5".into(), "environment".into()))
    );
    assert_eq!(
        setting(&printed, "insecure"),
        Some(("true".into(), "config file".into()))
    );
    assert_eq!(
        setting(&printed, "listen"),
        Some(("\"127.0.0.1:7878\"".into(), "default".into()))
    );
    // The file is found through the environment too, and each daemon reads its table.
    let out = tessera_env(
        dir.path(),
        &["worker", "--print-config"],
        &[("TESSERA_CONFIG", "tessera.toml")],
    );
    let printed = String::from_utf8(out.stdout).unwrap();
    assert_eq!(
        setting(&printed, "threads"),
        Some(("3".into(), "config file".into()))
    );
    assert_eq!(
        setting(&printed, "name"),
        Some(("\"render-7\"".into(), "config file".into()))
    );
    // The printed settings are themselves a valid config file.
    let section = printed.split_once("[worker]\n").unwrap().1;
    std::fs::write(
        dir.path().join("again.toml"),
        format!("[worker]\n{section}"),
    )
    .unwrap();
    let again = tessera_env(
        dir.path(),
        &["worker", "--config", "again.toml", "--print-config"],
        &[],
    );
    assert!(again.status.success(), "{again:?}");
    assert_eq!(
        setting(&String::from_utf8(again.stdout).unwrap(), "threads").map(|(value, _)| value),
        Some("3".into())
    );
}

#[test]
fn a_bad_config_file_is_one_line_that_says_where() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    for (text, expected) in [
        (
            "[coordinator]\nlisten = \"127.0.0.1:1\"\nmax-aaa = 3\n",
            "bad.toml: [coordinator] max-aaa: unknown setting",
        ),
        ("[coordinator\n", "bad.toml:1:13:"),
        ("[coordinatr]\n", "bad.toml: unknown section `coordinatr`"),
        (
            "[coordinator]\ninsecure = \"yes\"\n",
            "bad.toml: [coordinator] insecure: must be true or false",
        ),
        (
            "[coordinator]\nmax-aa = [1]\n",
            "bad.toml: [coordinator] max-aa: must be a string or a number",
        ),
    ] {
        std::fs::write(dir.path().join("bad.toml"), text).unwrap();
        let run = tessera(
            dir.path(),
            &["coordinator", "--config", "bad.toml"],
            Duration::from_secs(20),
        );
        assert!(!run.status.success(), "{text:?} was accepted");
        let stderr = run.stderr.trim();
        assert_eq!(stderr.lines().count(), 1, "{text:?}: {stderr}");
        assert!(
            stderr.starts_with(&format!("error: {expected}")),
            "{text:?}: {stderr}"
        );
    }
    let run = tessera(
        dir.path(),
        &["coordinator", "--config", "missing.toml"],
        Duration::from_secs(20),
    );
    assert!(
        run.stderr
            .starts_with("error: cannot read the config file missing.toml"),
        "{}",
        run.stderr
    );
}

#[test]
fn a_bad_retention_is_one_line_that_names_the_option() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("bad.toml"),
        "[coordinator]\nretention = \"1h30m\"\n",
    )
    .unwrap();
    for (args, env, value) in [
        (vec!["--retention", "2w"], vec![], "2w"),
        (vec!["--retention=90"], vec![], "90"),
        (vec!["--retention", "0s"], vec![], "0s"),
        (vec![], vec![("TESSERA_RETENTION", "soon")], "soon"),
        (vec!["--config", "bad.toml"], vec![], "1h30m"),
    ] {
        let mut all = vec!["coordinator", "--listen", "127.0.0.1:0"];
        all.extend(&args);
        all.push("--print-config");
        let out = tessera_env(dir.path(), &all, &env);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} {env:?} accepted");
        assert_eq!(
            stderr.trim().lines().count(),
            1,
            "{args:?} {env:?}: {stderr}"
        );
        assert!(
            stderr.starts_with(&format!(
                "error: invalid value '{value}' for '--retention <DURATION>': "
            )),
            "{args:?} {env:?}: {stderr}"
        );
    }
}

#[test]
fn print_config_shows_the_retention_and_where_it_comes_from() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("tessera.toml"),
        "[coordinator]\nretention = \"12h\"\n",
    )
    .unwrap();
    let printed = |args: &[&str], env: &[(&str, &str)]| {
        let mut all = vec!["coordinator"];
        all.extend(args);
        all.push("--print-config");
        let out = tessera_env(dir.path(), &all, env);
        assert!(out.status.success(), "{args:?}: {out:?}");
        String::from_utf8(out.stdout).unwrap()
    };
    assert_eq!(setting(&printed(&[], &[]), "retention"), None);
    let pair = |v: &str, s: &str| Some((v.to_owned(), s.to_owned()));
    assert_eq!(
        setting(&printed(&["--config", "tessera.toml"], &[]), "retention"),
        pair("\"12h\"", "config file")
    );
    assert_eq!(
        setting(
            &printed(
                &["--config", "tessera.toml"],
                &[("TESSERA_RETENTION", "30m")]
            ),
            "retention"
        ),
        pair("\"30m\"", "environment")
    );
    assert_eq!(
        setting(
            &printed(
                &["--config", "tessera.toml", "--retention", "7d"],
                &[("TESSERA_RETENTION", "30m")]
            ),
            "retention"
        ),
        pair("\"7d\"", "flag")
    );
    // --reset-database acts on one start: shown when given, never read from a file.
    assert!(!printed(&[], &[]).contains("reset-database"));
    assert!(printed(&["--reset-database"], &[])
        .lines()
        .any(|l| l == "# reset-database: given, for this start only"));
    std::fs::write(
        dir.path().join("reset.toml"),
        "[coordinator]\nreset-database = true\n",
    )
    .unwrap();
    let run = tessera(
        dir.path(),
        &["coordinator", "--config", "reset.toml"],
        Duration::from_secs(20),
    );
    assert!(!run.status.success(), "reset-database taken from a file");
    assert_eq!(
        run.stderr.trim(),
        "error: reset.toml: [coordinator] reset-database: not a setting: give \
         --reset-database on the command line of the one start that needs it"
    );
}

#[test]
fn a_data_directory_in_use_is_refused_with_the_holders_address() {
    let _turn = shared();
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

#[test]
fn print_config_gives_the_verdict_the_start_would() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let token = dir.path().join("client.token");
    write_token_file(&token, "client-secret\n");
    let env = [("TESSERA_TOKEN_FILE", path_str(&token))];
    let start = tessera_env(
        dir.path(),
        &["coordinator", "--listen", "127.0.0.1:0", "--data", "data"],
        &env,
    );
    let printed = tessera_env(
        dir.path(),
        &[
            "coordinator",
            "--listen",
            "127.0.0.1:0",
            "--data",
            "data",
            "--print-config",
        ],
        &env,
    );
    for (out, what) in [(&start, "the start"), (&printed, "--print-config")] {
        assert_eq!(out.status.code(), Some(1), "{what}: {out:?}");
        assert_eq!(out.stdout, b"", "{what}: nothing on stdout");
    }
    let line = String::from_utf8(printed.stderr).unwrap();
    assert!(
        line.starts_with("error: TESSERA_TOKEN_FILE is set (unset it for the coordinator)")
            && line.lines().count() == 1,
        "{line}"
    );
    assert_eq!(line, String::from_utf8(start.stderr).unwrap());
    // Nothing was created by the check.
    assert!(!dir.path().join("data").exists());
}

#[test]
fn a_token_file_open_to_other_users_is_warned_about_by_every_reader() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let open = |name: &str, token: &str| {
        let path = d.join(name);
        std::fs::write(&path, token).unwrap();
        std::fs::set_permissions(&path, std::os::unix::fs::PermissionsExt::from_mode(0o644))
            .unwrap();
        path
    };
    let worker_token = open("worker.token", "worker-secret\n");
    let client_token = open("client.token", "client-secret\n");
    let warning = |path: &std::path::Path| {
        format!(
            "the token file {p} is open to other users (mode 0644): `chmod 600 {p}` keeps it \
             to its owner",
            p = path.display()
        )
    };
    let (coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &[
            "--worker-token-file",
            path_str(&worker_token),
            "--client-token-file",
            path_str(&client_token),
        ],
        "coordinator.log",
    );
    let log = coordinator.log_text();
    for path in [&worker_token, &client_token] {
        assert_eq!(
            log.lines().filter(|l| l.contains(&warning(path))).count(),
            1,
            "{log}"
        );
    }

    // A client: one line on stderr, then its answer.
    let run = ok(
        tessera(
            d,
            &[
                "list",
                "--coordinator",
                &addr,
                "--token-file",
                path_str(&client_token),
            ],
            Duration::from_secs(20),
        ),
        "list",
    );
    assert_eq!(run.stderr, format!("warning: {}\n", warning(&client_token)));
    assert_eq!(run.stdout, "no jobs\n");

    // A worker: in its log, once.
    let worker = start_worker_with(d, &addr, "w1", &["--token-file", path_str(&worker_token)]);
    // Its first line, before it connects.
    let log = poll("the worker's first line", Duration::from_secs(20), || {
        let log = worker.log_text();
        log.contains('\n').then_some(log)
    });
    assert_eq!(
        log.lines()
            .filter(|l| l.contains(&warning(&worker_token)))
            .count(),
        1,
        "{log}"
    );

    // A private file: no warning.
    std::fs::set_permissions(
        &client_token,
        std::os::unix::fs::PermissionsExt::from_mode(0o600),
    )
    .unwrap();
    let run = ok(
        tessera(
            d,
            &[
                "list",
                "--coordinator",
                &addr,
                "--token-file",
                path_str(&client_token),
            ],
            Duration::from_secs(20),
        ),
        "list",
    );
    assert_eq!(run.stderr, "");
}
