//! Argument groups that several subcommands share, and the values they parse: the
//! image settings of a render, how a client or a worker reaches its coordinator, what
//! both daemons take, job ids and frame ranges. Each group turns its flags into what
//! the libraries take; the rules that combine them live in the libraries.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Result;
use clap::{Args, ValueEnum};
use protocol::{JobId, Overrides};
use render::limits::{MAX_AA, MAX_DEPTH, MAX_SIDE};
use render::{Sampler, Sampling};
use transport::{ClientTls, Endpoint};

/// Image settings that override the scene's own.
#[derive(Args, Clone, Copy)]
pub struct ImageArgs {
    /// Image width in pixels [default: the scene's, else 600].
    #[arg(long, value_name = "W", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_SIDE)))]
    pub width: Option<u32>,

    /// Image height in pixels [default: the scene's, else 400].
    #[arg(long, value_name = "H", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_SIDE)))]
    pub height: Option<u32>,

    /// Antialiasing: N gives N x N samples per pixel [default: the scene's, else 1].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_AA)))]
    pub aa: Option<u32>,

    /// Maximum reflection depth [default: the scene's, else 10].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(0..=i64::from(MAX_DEPTH)))]
    pub max_depth: Option<u32>,

    /// Where the samples of a pixel go: grid (the regular N x N grid, the reference),
    /// jittered (one random point in each of the N x N cells) or adaptive (4 samples, then
    /// more only where they disagree, up to N x N) [default: grid].
    #[arg(long, value_name = "SAMPLER", value_enum)]
    pub sampler: Option<SamplerArg>,

    /// The error each pixel should reach, in 8-bit levels (for example 1); a pixel
    /// stops taking samples once its estimated error is below it. Implies --sampler
    /// adaptive.
    #[arg(long, value_name = "LEVELS", allow_negative_numbers = true)]
    pub target_error: Option<f64>,
}

/// The samplers as the command line names them.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SamplerArg {
    Grid,
    Jittered,
    Adaptive,
}

impl From<SamplerArg> for Sampler {
    fn from(sampler: SamplerArg) -> Sampler {
        match sampler {
            SamplerArg::Grid => Sampler::Grid,
            SamplerArg::Jittered => Sampler::Jittered,
            SamplerArg::Adaptive => Sampler::Adaptive,
        }
    }
}

impl ImageArgs {
    /// The sampling asked for, with or without a time limit (`None`: the default grid),
    /// checked by [`Sampling::choose`].
    pub fn sampling(self, time_limit: Option<Duration>) -> Result<Option<Sampling>> {
        Ok(Sampling::choose(
            self.sampler.map(Sampler::from),
            self.target_error,
            time_limit.is_some(),
        )?)
    }

    /// The overrides of a farm job cut in tiles of `tile_size`, and its time limit in
    /// milliseconds.
    pub fn farm_job(
        self,
        tile_size: Option<u32>,
        time_limit: Option<Duration>,
    ) -> Result<(Overrides, Option<u64>)> {
        let overrides = Overrides {
            width: self.width,
            height: self.height,
            aa: self.aa,
            max_depth: self.max_depth,
            tile_size,
            sampling: self.sampling(time_limit)?.map(wire_sampling),
        };
        Ok((overrides, time_limit.map(limit_ms)))
    }
}

/// A job's time limit as the protocol carries it: whole milliseconds, at least one.
pub fn limit_ms(time_limit: Duration) -> u64 {
    (time_limit.as_millis() as u64).max(1)
}

/// The renderer's sampling as the protocol carries it.
fn wire_sampling(sampling: Sampling) -> protocol::Sampling {
    match sampling {
        Sampling::Grid => protocol::Sampling::Grid,
        Sampling::Jittered => protocol::Sampling::Jittered,
        Sampling::Adaptive { target_milli } => protocol::Sampling::Adaptive { target_milli },
    }
}

/// Which frames `--frames` asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameRange {
    /// Every frame of the scene (`--frames` alone, or `--frames all`).
    All,
    /// Frames `first` to `last`, both included (`A-B`, or `K` for one).
    Span { first: u64, last: u64 },
}

/// `--frames`, one definition for `render`, `submit` and `up`, so that they read it
/// alike: `--frames` alone is every frame, as `--frames all`.
#[derive(Args, Clone, Copy)]
pub struct FramesArg {
    /// Frames A to B of an animated scene (A-B, K or all; `--frames` alone: all), as a
    /// sequence: one file per frame, frame_0001.png, ..., into the directory -o
    /// [default directory: the scene's file name without .json, here].
    #[arg(long, value_name = "A-B", num_args = 0..=1, default_missing_value = "all",
          value_parser = parse_frame_range)]
    pub frames: Option<FrameRange>,
}

/// Reads `--frames`: `A-B`, `K` or `all`, frame numbers from 1.
pub fn parse_frame_range(text: &str) -> std::result::Result<FrameRange, String> {
    if text == "all" {
        return Ok(FrameRange::All);
    }
    let number = |t: &str| -> std::result::Result<u64, String> {
        if t.is_empty() || !t.bytes().all(|b| b.is_ascii_digit()) {
            return Err(format!(
                "expected A-B, K or all (frame numbers from 1), got {text:?}"
            ));
        }
        let n = t
            .parse::<u64>()
            .map_err(|_| format!("frame {t} is too large"))?;
        if n == 0 {
            return Err("frames are numbered from 1".to_owned());
        }
        Ok(n)
    };
    let (first, last) = match text.split_once('-') {
        Some((a, b)) => (number(a)?, number(b)?),
        None => {
            let k = number(text)?;
            (k, k)
        }
    };
    if last < first {
        return Err(format!(
            "the range ends (frame {last}) before it starts (frame {first})"
        ));
    }
    Ok(FrameRange::Span { first, last })
}

/// A job id as the commands that take one read it.
pub fn parse_job_id(text: &str) -> Result<JobId, String> {
    text.trim().parse().map_err(|_| {
        "a job id is a whole number, as `tessera submit` and `tessera list` print it".to_owned()
    })
}

/// A job's priority as `tessera priority` and `submit --priority` read it.
pub fn parse_priority(text: &str) -> Result<i32, String> {
    text.trim().parse().map_err(|_| {
        "a priority is a whole number, higher runs first (for example 10 or -5)".to_owned()
    })
}

/// A worker tag as `worker --tag` and `submit --require` read it
/// ([`protocol::check_tag`]).
pub fn parse_tag(text: &str) -> Result<String, String> {
    protocol::check_tag(text).map(|()| text.to_owned())
}

/// A tile's number as `tessera requeue` reads it.
pub fn parse_tile_number(text: &str) -> Result<u32, String> {
    text.trim().parse().map_err(|_| {
        "a tile number is a whole number from 0, as `tessera events` names the tiles".to_owned()
    })
}

/// The threads of each worker of a farm on this machine (`up`, `studio`): as asked, or
/// the cores shared among them.
pub fn threads_per_worker(workers: usize, asked: Option<u32>) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    asked.map_or((cores / workers).max(1), |n| n as usize)
}

/// What every client command takes.
#[derive(Args)]
pub struct ClientArgs {
    #[command(flatten)]
    pub peer: PeerArgs,
    /// Machine-readable JSON output.
    #[arg(long)]
    pub json: bool,
}

/// How clients and workers reach a coordinator.
#[derive(Args)]
pub struct PeerArgs {
    /// The coordinator's address, HOST:PORT (the port it listens on for workers and
    /// clients, not its HTTP port).
    #[arg(long, env = "TESSERA_COORDINATOR", value_name = "ADDR", default_value = transport::DEFAULT_ADDRESS,
          value_parser = transport::parse_address)]
    coordinator: String,
    #[command(flatten)]
    secret: SecretArgs,
    /// Speak TLS, trusting the certificates in this PEM file (the coordinator's own
    /// certificate or the CA that signed it).
    #[arg(long, env = "TESSERA_TLS_CA", value_name = "FILE")]
    tls_ca: Option<PathBuf>,
    /// Speak TLS, trusting exactly the coordinator certificate with this SHA-256
    /// fingerprint (64 hex digits, as the coordinator prints at startup; an empty
    /// value counts as none, for container environments).
    #[arg(
        long,
        env = "TESSERA_TLS_FINGERPRINT",
        value_name = "SHA256HEX",
        conflicts_with = "tls_ca",
        value_parser = parse_pin
    )]
    tls_fingerprint: Option<Pin>,
    /// The name the coordinator's certificate must carry [default: the host of
    /// --coordinator].
    #[arg(
        long,
        env = "TESSERA_TLS_SERVER_NAME",
        value_name = "NAME",
        requires = "tls_ca"
    )]
    tls_server_name: Option<String>,
}

impl PeerArgs {
    /// The coordinator's address, the TLS to speak to it and this peer's token.
    pub fn endpoint(&self) -> Result<Endpoint> {
        Ok(Endpoint {
            address: self.coordinator.clone(),
            tls: ClientTls::from_settings(
                self.tls_ca.as_deref(),
                self.tls_server_name.as_deref(),
                self.tls_fingerprint.and_then(|Pin(pin)| pin),
            )?,
            // Checked now, and read again at every connection.
            secret: transport::TokenSource::from_settings(
                self.secret.token_file.as_deref(),
                "TESSERA_TOKEN",
            )?,
        })
    }
}

impl PeerArgs {
    /// The warning a token file open to other users deserves, if it is one.
    pub fn token_file_warning(&self) -> Option<String> {
        self.secret
            .token_file
            .as_deref()
            .and_then(transport::exposed_token_file)
    }
}

impl ClientArgs {
    /// The coordinator the command talks to; a token file open to other users is
    /// warned about on stderr.
    pub fn target(&self) -> Result<Endpoint> {
        let endpoint = self.peer.endpoint()?;
        if let Some(warning) = self.peer.token_file_warning() {
            eprintln!("warning: {warning}");
        }
        Ok(endpoint)
    }
}

/// A `--tls-fingerprint`: none when given empty. (An `Option` of an `Option` would be
/// a flag whose value may be left out, to clap.)
#[derive(Clone, Copy)]
struct Pin(Option<[u8; 32]>);

fn parse_pin(text: &str) -> Result<Pin, String> {
    transport::parse_pin(text).map(Pin)
}

/// The secret of a worker or a client: the worker token or the client token of its
/// farm, whichever its role needs.
#[derive(Args)]
struct SecretArgs {
    /// File holding this peer's token: the farm's worker token for a worker, its client
    /// token for a client [or set TESSERA_TOKEN to the token itself].
    #[arg(long, env = "TESSERA_TOKEN_FILE", value_name = "FILE")]
    token_file: Option<PathBuf>,
}

/// What both daemons take: where their settings come from, HTTP and logs.
#[derive(Args)]
pub struct DaemonArgs {
    /// A TOML file of settings: a [coordinator] and a [worker] table whose keys are the
    /// flags' names. Flags beat environment variables, which beat the file.
    #[arg(long, value_name = "FILE", env = "TESSERA_CONFIG")]
    config: Option<PathBuf>,
    /// Print the effective settings, and where each comes from, then exit.
    #[arg(long)]
    print_config: bool,
    /// Serve HTTP on this address: /healthz and /readyz, and on a coordinator also
    /// /metrics (Prometheus), the status page at / and the studio. A coordinator with
    /// TLS serves HTTPS there with the same certificate.
    #[arg(long, value_name = "ADDR", env = "TESSERA_HTTP")]
    pub http: Option<SocketAddr>,
    /// How logs on stderr look: text (coloured on a terminal) or json (one object a line).
    #[arg(
        long,
        value_name = "FORMAT",
        value_enum,
        default_value = "text",
        env = "TESSERA_LOG_FORMAT"
    )]
    log_format: LogFormat,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

impl DaemonArgs {
    /// Logs of the daemons go to stderr, filtered by `RUST_LOG` (default `info`):
    /// readable text, or one JSON object a line whose fields (`job`, `tile`, `worker`,
    /// ...) are top-level keys, for log collectors.
    ///
    /// `RUST_LOG` takes a default level and levels by target (`debug`,
    /// `coordinator=debug,info`), read by `Targets`, which needs no regular
    /// expressions; an empty or unreadable value means `info`.
    pub fn init_logging(&self) {
        use tracing_subscriber::filter::{LevelFilter, Targets};
        use tracing_subscriber::layer::SubscriberExt;
        use tracing_subscriber::util::SubscriberInitExt;
        let filter = std::env::var("RUST_LOG")
            .ok()
            .filter(|text| !text.trim().is_empty())
            .and_then(|text| text.parse::<Targets>().ok())
            .unwrap_or_else(|| Targets::new().with_default(LevelFilter::INFO));
        let logs = tracing_subscriber::fmt().with_writer(std::io::stderr);
        match self.log_format {
            LogFormat::Text => logs
                .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
                .finish()
                .with(filter)
                .init(),
            LogFormat::Json => logs.json().flatten_event(true).finish().with(filter).init(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_ranges_are_a_dash_b_k_or_all() {
        assert_eq!(parse_frame_range("all"), Ok(FrameRange::All));
        assert_eq!(
            parse_frame_range("3-5"),
            Ok(FrameRange::Span { first: 3, last: 5 })
        );
        assert_eq!(
            parse_frame_range("7"),
            Ok(FrameRange::Span { first: 7, last: 7 })
        );
        assert_eq!(
            parse_frame_range("5-3").unwrap_err(),
            "the range ends (frame 3) before it starts (frame 5)"
        );
        assert_eq!(
            parse_frame_range("0").unwrap_err(),
            "frames are numbered from 1"
        );
        for bad in ["", "-", "1-", "-3", "+1", "1-2-3", " 1", "1.5", "a-b"] {
            assert_eq!(
                parse_frame_range(bad).unwrap_err(),
                format!("expected A-B, K or all (frame numbers from 1), got {bad:?}"),
                "{bad:?}"
            );
        }
        assert_eq!(
            parse_frame_range("99999999999999999999").unwrap_err(),
            "frame 99999999999999999999 is too large"
        );
    }
}
