//! Settings of the daemons from a TOML file, the environment and the command line.
//!
//! Every setting of `tessera coordinator` and `tessera worker` is a flag, an
//! environment variable (`TESSERA_` and the flag's name in capitals, `-` as `_`) and a
//! key of the config file's `[coordinator]` or `[worker]` table (the flag's name).
//! Precedence: flag, then environment, then file, then the built-in default.
//!
//! The file is applied by turning its keys into flags placed before the user's own, so
//! that clap checks their values exactly as it checks typed ones, and a flag given
//! later on the command line overrides them; keys whose environment variable is set
//! are left out, so the environment wins over the file.

use std::collections::BTreeSet;
use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use clap::parser::ValueSource;

/// The subcommands a config file configures.
pub const SECTIONS: [&str; 2] = ["coordinator", "worker"];

/// Settings that are not settings: they say where the settings come from.
const NOT_SETTINGS: [&str; 2] = ["config", "print-config"];

/// The command line with the config file's settings put in, and the names of the
/// settings that came from the file (and were not typed again on the command line).
pub struct Expanded {
    pub args: Vec<OsString>,
    pub from_file: BTreeSet<String>,
}

/// Puts the settings of the config file (`--config FILE` or `TESSERA_CONFIG`) of
/// `args`' subcommand into `args`, right after the subcommand's name.
pub fn expand(args: Vec<OsString>, cli: &clap::Command) -> Result<Expanded> {
    let unchanged = |args| {
        Ok(Expanded {
            args,
            from_file: BTreeSet::new(),
        })
    };
    let Some(section) = args.get(1).and_then(|a| a.to_str()) else {
        return unchanged(args);
    };
    if !SECTIONS.contains(&section) {
        return unchanged(args);
    }
    let Some(path) = config_path(&args[2..]) else {
        return unchanged(args);
    };
    let sub = cli
        .find_subcommand(section)
        .expect("every section is a subcommand");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("cannot read the config file {}", path.display()))?;
    let settings = settings_of(&path, &text, section, sub)?;
    let mut from_file = BTreeSet::new();
    let mut flags = Vec::new();
    for (key, flag) in settings {
        let typed = args[2..].iter().any(|a| {
            let a = a.to_string_lossy();
            a == format!("--{key}") || a.starts_with(&format!("--{key}="))
        });
        if !typed {
            from_file.insert(key);
        }
        flags.extend(flag);
    }
    let mut expanded = args[..2].to_vec();
    expanded.extend(flags);
    expanded.extend(args[2..].iter().cloned());
    Ok(Expanded {
        args: expanded,
        from_file,
    })
}

/// `--config FILE` or `--config=FILE` among the subcommand's arguments, else
/// `TESSERA_CONFIG`.
fn config_path(args: &[OsString]) -> Option<PathBuf> {
    let mut iter = args.iter();
    while let Some(arg) = iter.next() {
        let arg = arg.to_string_lossy();
        if arg == "--" {
            break;
        }
        if arg == "--config" {
            return iter.next().map(PathBuf::from);
        }
        if let Some(path) = arg.strip_prefix("--config=") {
            return Some(PathBuf::from(path));
        }
    }
    std::env::var_os("TESSERA_CONFIG")
        .filter(|p| !p.is_empty())
        .map(PathBuf::from)
}

/// The section's settings as flags, each with its key, in file order; settings whose
/// environment variable is set are left out.
fn settings_of(
    path: &Path,
    text: &str,
    section: &str,
    sub: &clap::Command,
) -> Result<Vec<(String, Option<OsString>)>> {
    let file = path.display();
    let table: toml::Table = text.parse().map_err(|e: toml::de::Error| {
        let at = e
            .span()
            .map(|span| {
                let before = &text[..span.start.min(text.len())];
                let line = before.matches('\n').count() + 1;
                let column = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
                format!(":{line}:{column}")
            })
            .unwrap_or_default();
        anyhow!("{file}{at}: {}", e.message().trim())
    })?;
    for (key, value) in &table {
        if !SECTIONS.contains(&key.as_str()) {
            bail!("{file}: unknown section `{key}` (the sections are [coordinator] and [worker])");
        }
        if !value.is_table() {
            bail!("{file}: `{key}` must be a table ([{key}])");
        }
    }
    let Some(settings) = table.get(section).and_then(toml::Value::as_table) else {
        return Ok(Vec::new());
    };
    let mut flags = Vec::new();
    for (key, value) in settings {
        let arg = sub
            .get_arguments()
            .find(|a| a.get_long() == Some(key.as_str()) && !a.is_hide_set())
            .filter(|_| !NOT_SETTINGS.contains(&key.as_str()))
            .ok_or_else(|| {
                anyhow!(
                    "{file}: [{section}] {key}: unknown setting (see `tessera {section} --help`)"
                )
            })?;
        if arg
            .get_env()
            .is_some_and(|var| std::env::var_os(var).is_some())
        {
            continue;
        }
        let takes_value = arg.get_action().takes_values();
        let flag = match value {
            toml::Value::Boolean(on) if !takes_value => {
                on.then(|| OsString::from(format!("--{key}")))
            }
            toml::Value::String(s) if takes_value => Some(format!("--{key}={s}").into()),
            toml::Value::Integer(n) if takes_value => Some(format!("--{key}={n}").into()),
            toml::Value::Float(x) if takes_value => Some(format!("--{key}={x}").into()),
            _ if takes_value => {
                bail!("{file}: [{section}] {key}: must be a string or a number")
            }
            _ => bail!("{file}: [{section}] {key}: must be true or false"),
        };
        flags.push((key.clone(), flag));
    }
    Ok(flags)
}

/// The effective settings of a daemon as a config file, each with where it came from.
pub fn describe(
    section: &str,
    sub: &clap::Command,
    matches: &clap::ArgMatches,
    from_file: &BTreeSet<String>,
) -> String {
    let mut out = format!(
        "# The effective settings of `tessera {section}`: flag, then environment, then config \
         file, then default.\n[{section}]\n"
    );
    for arg in sub.get_arguments() {
        let Some(long) = arg.get_long() else {
            continue;
        };
        if arg.is_hide_set() || NOT_SETTINGS.contains(&long) || long == "help" {
            continue;
        }
        let id = arg.get_id().as_str();
        let source = match matches.value_source(id) {
            Some(ValueSource::CommandLine) if from_file.contains(long) => "config file",
            Some(ValueSource::CommandLine) => "flag",
            Some(ValueSource::EnvVariable) => "environment",
            Some(ValueSource::DefaultValue) => "default",
            _ => "",
        };
        let raw: Vec<String> = matches
            .get_raw(id)
            .map(|values| values.map(|v| v.to_string_lossy().into_owned()).collect())
            .unwrap_or_default();
        match raw.last() {
            Some(value) => {
                let shown = if value.parse::<f64>().is_ok() || value == "true" || value == "false" {
                    value.clone()
                } else {
                    toml::Value::String(value.clone()).to_string()
                };
                out.push_str(&format!("{long} = {shown}  # {source}\n"));
            }
            None => out.push_str(&format!("# {long}: not set\n")),
        }
    }
    let secret = match (
        matches.get_raw("token_file").is_some(),
        std::env::var_os("TESSERA_TOKEN"),
    ) {
        (true, _) => "the token file",
        (false, Some(_)) => "TESSERA_TOKEN (set)",
        (false, None) => "none",
    };
    out.push_str(&format!("# shared secret: {secret}\n"));
    out
}
