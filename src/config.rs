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
//!
//! A few flags are one-off actions rather than settings (`--reset-database`): they
//! have no environment variable and a config file may not give them, so that they
//! never apply to more starts than the one they were typed for.

use std::collections::BTreeSet;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use clap::parser::ValueSource;

/// The subcommands a config file configures.
pub const SECTIONS: [&str; 2] = ["coordinator", "worker"];

/// Settings that are not settings: they say where the settings come from, or print
/// something and exit.
const NOT_SETTINGS: [&str; 3] = ["config", "print-config", "print-fingerprint"];

/// Flags that act on one start only: never read from a config file.
const COMMAND_LINE_ONLY: [&str; 1] = ["reset-database"];

/// The longest duration an option takes: 100 years.
const MAX_DURATION_SECS: u64 = 36_500 * 86_400;

/// A duration option's value: a whole number and a unit, `ms`, `s`, `m`, `h` or `d`
/// (`500ms`, `90s`, `30m`, `12h`, `7d`), more than zero and at most 36500 days. The
/// error says what is wrong with the value (clap adds the option's name).
pub fn parse_duration(text: &str) -> Result<Duration, String> {
    const FORMS: &str = "a whole number and a unit, ms, s, m, h or d (500ms, 90s, 30m, 12h, 7d)";
    let text = text.trim();
    let split = text
        .find(|c: char| !c.is_ascii_digit())
        .unwrap_or(text.len());
    let (number, unit) = text.split_at(split);
    if number.is_empty() {
        return Err(format!("not a duration: give {FORMS}"));
    }
    let millis_per_unit: u64 = match unit {
        "ms" => 1,
        "s" => 1000,
        "m" => 60_000,
        "h" => 3_600_000,
        "d" => 86_400_000,
        "" => return Err(format!("no unit: give {FORMS}")),
        other => return Err(format!("unknown unit `{other}`: give {FORMS}")),
    };
    let millis = number
        .parse::<u64>()
        .ok()
        .and_then(|n| n.checked_mul(millis_per_unit))
        .filter(|&ms| ms <= MAX_DURATION_SECS * 1000)
        .ok_or_else(|| "too long: at most 36500d".to_string())?;
    if millis == 0 {
        return Err("must be longer than zero".into());
    }
    Ok(Duration::from_millis(millis))
}

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
) -> Result<Vec<(String, Vec<OsString>)>> {
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
        if section == "coordinator" && key == "token-file" {
            bail!(
                "{file}: [coordinator] token-file: a coordinator takes two tokens, one for \
                 workers and one for clients: set worker-token-file and client-token-file \
                 (two different secrets) instead"
            );
        }
        let arg = sub
            .get_arguments()
            .find(|a| a.get_long() == Some(key.as_str()) && !a.is_hide_set())
            .filter(|_| !NOT_SETTINGS.contains(&key.as_str()))
            .ok_or_else(|| {
                anyhow!(
                    "{file}: [{section}] {key}: unknown setting (see `tessera {section} --help`)"
                )
            })?;
        if COMMAND_LINE_ONLY.contains(&key.as_str()) {
            bail!(
                "{file}: [{section}] {key}: not a setting: give --{key} on the command line \
                 of the one start that needs it"
            );
        }
        if arg
            .get_env()
            .is_some_and(|var| std::env::var_os(var).is_some())
        {
            continue;
        }
        let takes_value = arg.get_action().takes_values();
        let repeatable = matches!(arg.get_action(), clap::ArgAction::Append);
        let one = |value: &toml::Value| match value {
            toml::Value::String(s) => Some(OsString::from(format!("--{key}={s}"))),
            toml::Value::Integer(n) => Some(format!("--{key}={n}").into()),
            toml::Value::Float(x) => Some(format!("--{key}={x}").into()),
            _ => None,
        };
        let flag: Vec<OsString> = match value {
            toml::Value::Boolean(on) if !takes_value => on
                .then(|| OsString::from(format!("--{key}")))
                .into_iter()
                .collect(),
            // A setting given more than once (`webhook`, `tag`): an array of strings,
            // each a flag.
            toml::Value::Array(items) if repeatable => items
                .iter()
                .map(|item| match item {
                    toml::Value::String(s) => Ok(OsString::from(format!("--{key}={s}"))),
                    _ => Err(anyhow!(
                        "{file}: [{section}] {key}: must be an array of strings"
                    )),
                })
                .collect::<Result<_>>()?,
            _ if takes_value => match one(value) {
                Some(flag) => vec![flag],
                None if repeatable => {
                    bail!("{file}: [{section}] {key}: must be a string or an array of strings")
                }
                None => bail!("{file}: [{section}] {key}: must be a string or a number"),
            },
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
        if COMMAND_LINE_ONLY.contains(&long) {
            if matches.get_flag(id) {
                out.push_str(&format!("# {long}: given, for this start only\n"));
            }
            continue;
        }
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
        if matches!(arg.get_action(), clap::ArgAction::Append) && !raw.is_empty() {
            let shown: Vec<String> = raw
                .iter()
                .map(|v| toml::Value::String(v.clone()).to_string())
                .collect();
            out.push_str(&format!("{long} = [{}]  # {source}\n", shown.join(", ")));
            continue;
        }
        match raw.last() {
            Some(_) if raw.len() > 1 => {
                let list = toml::Value::Array(raw.into_iter().map(toml::Value::String).collect());
                out.push_str(&format!("{long} = {list}  # {source}\n"));
            }
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
    // The secrets themselves are never printed: only where they come from.
    let source = |file_id: &str, variable: &str| match (
        matches.try_get_raw(file_id).ok().flatten().is_some(),
        std::env::var_os(variable),
    ) {
        (true, _) => "a token file".to_string(),
        (false, Some(_)) => format!("{variable} (set)"),
        (false, None) => "none".to_string(),
    };
    if section == "coordinator" {
        out.push_str(&format!(
            "# worker token: {}\n# client token: {}\n",
            source("worker_token_file", "TESSERA_WORKER_TOKEN"),
            source("client_token_file", "TESSERA_CLIENT_TOKEN")
        ));
    } else {
        out.push_str(&format!(
            "# token: {}\n",
            source("token_file", "TESSERA_TOKEN")
        ));
    }
    out
}

/// A share between 0 and 1, as `--audit-share` takes it.
pub fn parse_share(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(share) if (0.0..=1.0).contains(&share) => Ok(share),
        _ => Err(format!("must be a number from 0 to 1, got {text:?}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_take_seconds_minutes_hours_and_days() {
        assert_eq!(parse_duration("90s"), Ok(Duration::from_secs(90)));
        assert_eq!(parse_duration("30m"), Ok(Duration::from_secs(30 * 60)));
        assert_eq!(parse_duration("12h"), Ok(Duration::from_secs(12 * 3600)));
        assert_eq!(parse_duration("7d"), Ok(Duration::from_secs(7 * 86_400)));
        assert_eq!(parse_duration(" 1s "), Ok(Duration::from_secs(1)));
        assert_eq!(
            parse_duration("36500d"),
            Ok(Duration::from_secs(MAX_DURATION_SECS))
        );
    }

    /// A setting given more than once (`--webhook`) is a list in the file, each item a
    /// flag in order; a single value still works, and a list is refused elsewhere.
    #[test]
    fn a_list_in_the_file_gives_a_repeatable_setting_once_per_item() {
        let sub = clap::Command::new("coordinator")
            .arg(
                clap::Arg::new("webhook")
                    .long("webhook")
                    .action(clap::ArgAction::Append),
            )
            .arg(clap::Arg::new("data").long("data"));
        let path = Path::new("c.toml");
        let flags = |text: &str| settings_of(path, text, "coordinator", &sub);
        let listed = flags("[coordinator]\nwebhook = [\"http://a/\", \"http://b/\"]\n").unwrap();
        assert_eq!(
            listed,
            [(
                "webhook".to_string(),
                vec![
                    OsString::from("--webhook=http://a/"),
                    OsString::from("--webhook=http://b/")
                ]
            )]
        );
        let one = flags("[coordinator]\nwebhook = \"http://a/\"\n").unwrap();
        assert_eq!(one[0].1, [OsString::from("--webhook=http://a/")]);
        let error = flags("[coordinator]\ndata = [\"x\"]\n")
            .unwrap_err()
            .to_string();
        assert!(
            error.ends_with("data: must be a string or a number"),
            "{error}"
        );
        let error = flags("[coordinator]\nwebhook = [true]\n")
            .unwrap_err()
            .to_string();
        assert!(error.ends_with("must be an array of strings"), "{error}");
    }

    #[test]
    fn a_bad_duration_says_what_is_wrong() {
        let error = |text: &str| parse_duration(text).unwrap_err();
        assert!(error("90").starts_with("no unit"), "{}", error("90"));
        assert!(
            error("2w").starts_with("unknown unit `w`"),
            "{}",
            error("2w")
        );
        assert!(error("1h30m").starts_with("unknown unit `h30m`"));
        assert!(error("1.5h").starts_with("unknown unit `.5h`"));
        assert!(error("").starts_with("not a duration"));
        assert!(error("d").starts_with("not a duration"));
        assert!(error("-5s").starts_with("not a duration"));
        assert!(error("forever").starts_with("not a duration"));
        assert_eq!(error("0s"), "must be longer than zero");
        assert_eq!(error("36501d"), "too long: at most 36500d");
        assert_eq!(error("99999999999999999999s"), "too long: at most 36500d");
        assert_eq!(error("999999999999999999d"), "too long: at most 36500d");
    }

    #[test]
    fn a_repeatable_setting_takes_an_array_of_strings_from_the_file() {
        use clap::CommandFactory;
        let cli = crate::Cli::command();
        let path = std::env::temp_dir().join(format!("tessera-tags-{}.toml", std::process::id()));
        let expand_with = |text: &str| {
            std::fs::write(&path, text).unwrap();
            let args = ["tessera", "worker", "--config", path.to_str().unwrap()]
                .map(OsString::from)
                .to_vec();
            expand(args, &cli)
        };
        let expanded = expand_with("[worker]\ntag = [\"gpu\", \"ssd\"]\n").unwrap();
        let flags: Vec<&str> = expanded.args.iter().filter_map(|a| a.to_str()).collect();
        assert_eq!(flags[2..4], ["--tag=gpu", "--tag=ssd"], "{flags:?}");
        let matches = cli.clone().try_get_matches_from(&expanded.args).unwrap();
        let (_, worker) = matches.subcommand().unwrap();
        let sub = cli.find_subcommand("worker").unwrap();
        let shown = describe("worker", sub, worker, &expanded.from_file);
        assert!(
            shown.contains("tag = [\"gpu\", \"ssd\"]  # config file\n"),
            "{shown}"
        );
        let error = expand_with("[worker]\ntag = [1]\n")
            .err()
            .unwrap()
            .to_string();
        assert!(
            error.ends_with("[worker] tag: must be an array of strings"),
            "{error}"
        );
        let error = expand_with("[worker]\ntag = true\n")
            .err()
            .unwrap()
            .to_string();
        assert!(
            error.ends_with("[worker] tag: must be a string or an array of strings"),
            "{error}"
        );
        std::fs::remove_file(&path).unwrap();
    }
}
