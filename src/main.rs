//! `tessera`: the command line. This file parses the arguments (with the daemons'
//! config file), hands each subcommand to its module under [`commands`], and reports
//! what went wrong: one line on stderr, or with `--json` an object on stdout.

mod args;
mod commands;
mod config;
mod local_render;
mod output;
mod render_state;
mod report;
mod scene_file;
mod sequences;
mod session;
mod signals;
mod submission;
#[cfg(test)]
mod workspace_layout;

use std::ffi::OsString;
use std::process::ExitCode;

use anyhow::Result;
use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

/// Tessera renders ray-traced images of JSON scenes (spheres, planes, triangles, boxes,
/// meshes from OBJ, PLY, STL and glTF files, point lights, mirrors and checkerboards), on
/// this machine or on a farm of workers.
#[derive(Parser)]
#[command(
    name = "tessera",
    version,
    propagate_version = true,
    args_override_self = true
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// The subcommands, in the order `tessera --help` lists them; each module's `Args`
/// holds the subcommand's description and flags.
#[derive(Subcommand)]
enum Command {
    Render(commands::render::Args),
    Refine(commands::refine::Args),
    Up(commands::up::Args),
    Studio(commands::studio::Args),
    Coordinator(commands::coordinator::Args),
    Worker(commands::worker::Args),
    Submit(commands::submit::Args),
    #[command(flatten)]
    Job(commands::jobs::Command),
    Workers(commands::workers::Args),
    Simulate(commands::simulate::Args),
}

/// Runs the subcommand; `print_config` (the daemons' effective settings) makes a
/// daemon check its settings as its start would, and print them instead of starting.
fn run(command: Command, print_config: Option<String>) -> Result<()> {
    match command {
        Command::Render(args) => commands::render::run(args),
        Command::Refine(args) => commands::refine::run(args),
        Command::Up(args) => commands::up::run(args),
        Command::Studio(args) => commands::studio::run(args),
        Command::Coordinator(args) => commands::coordinator::run(args, print_config),
        Command::Worker(args) => commands::worker::run(args, print_config),
        Command::Submit(args) => commands::submit::run(args),
        Command::Job(command) => command.run(),
        Command::Workers(args) => commands::workers::run(args),
        Command::Simulate(args) => commands::simulate::run(args),
    }
}

fn main() -> ExitCode {
    let cli = Cli::command();
    let args: Vec<OsString> = std::env::args_os().collect();
    let json = wants_json(&args);
    let expanded = match config::expand(args, &cli) {
        Ok(expanded) => expanded,
        Err(e) => {
            report_error(json, &format!("{e:#}"), None);
            return ExitCode::FAILURE;
        }
    };
    let matches = match cli.clone().try_get_matches_from(expanded.args) {
        Ok(matches) => matches,
        // A bad value is one line that names the option and says what is wrong.
        Err(e)
            if e.kind() == clap::error::ErrorKind::ValueValidation || (json && e.use_stderr()) =>
        {
            let text = e.render().to_string();
            let line = text.lines().next().unwrap_or_default();
            report_error(json, line.strip_prefix("error: ").unwrap_or(line), None);
            return ExitCode::from(2);
        }
        Err(e) => e.exit(),
    };
    let parsed = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    let mut settings = None;
    if let Some((name, sub)) = matches.subcommand() {
        let print_config = config::SECTIONS.contains(&name) && sub.get_flag("print_config");
        if !signals::keeps_running(name, print_config) {
            signals::end_quietly_on_a_closed_pipe();
        }
        if print_config {
            let command = cli.find_subcommand(name).expect("parsed subcommands exist");
            settings = Some(config::describe(name, command, sub, &expanded.from_file));
        }
    }
    let daemon = matches
        .subcommand()
        .is_some_and(|(name, _)| signals::keeps_running(name, false));
    match run(parsed.command, settings) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            let unreachable = e.chain().any(|c| c.is::<transport::CannotReach>());
            let hint = if unreachable && !daemon {
                "; --coordinator ADDR or TESSERA_COORDINATOR chooses the coordinator"
            } else {
                ""
            };
            // A coordinator's refusal keeps its kind in JSON, for scripts to act on.
            let kind = e
                .downcast_ref::<protocol::Refusal>()
                .map(|r| r.kind.as_str());
            report_error(json, &format!("{e:#}{hint}"), kind);
            match e.downcast_ref::<signals::Interrupted>() {
                Some(signal) => ExitCode::from(signal.exit_code),
                None => ExitCode::FAILURE,
            }
        }
    }
}

/// Whether the command line asks for JSON (`--json`, before any `--`).
fn wants_json(args: &[OsString]) -> bool {
    args.iter()
        .skip(1)
        .take_while(|a| *a != "--")
        .any(|a| a == "--json")
}

/// A command's error: one line `error: MESSAGE` on stderr, or with `--json`, the object
/// `{"error": "MESSAGE"}` on stdout, where the command's result would have been, with
/// `"kind"` when the coordinator refused the request (docs/protocol.md, `RefusalKind`).
fn report_error(json: bool, message: &str, kind: Option<&str>) {
    if json {
        let value = match kind {
            Some(kind) => serde_json::json!({ "error": message, "kind": kind }),
            None => serde_json::json!({ "error": message }),
        };
        println!("{value}");
    } else {
        eprintln!("error: {message}");
    }
}
