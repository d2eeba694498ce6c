//! The farm through network latency: a real coordinator and two one-thread workers on
//! this machine, each worker connected through a relay that delays every chunk by half
//! the round-trip time (this kernel has no netem). For each round trip, the same jobs,
//! interleaved: wall time, throughput against direct loopback in the same run, worker
//! utilisation (the render time the tile results report, over wall time × threads), and
//! the bytes on the wire per job in each direction by kind of message. Then the study of
//! compressing tile results ([`compression`](super::compression)).

use std::fmt::Write as _;
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use coordinator::client::Client;
use protocol::{JobSpec, JobState, JobStatus, Overrides};
use transport::Endpoint;

use super::compression;
use super::relay::{self, Direction, Link, Relay, Traffic, DOWN_KINDS, HANDSHAKE, OTHER, UP_KINDS};
use super::scenes;
use super::Options;
use localfarm::LocalFarm;

/// One-thread workers of each farm.
const WORKERS: usize = 2;

/// How the workers reach the coordinator.
#[derive(Clone, Copy, Debug)]
struct Network {
    /// Round-trip time the relay adds; `None` connects the workers directly.
    rtt_ms: Option<u32>,
}

impl Network {
    fn name(self) -> String {
        match self.rtt_ms {
            None => "direct loopback".into(),
            Some(ms) => format!("relay RTT {ms} ms"),
        }
    }

    fn rtt(self) -> Duration {
        Duration::from_millis(u64::from(self.rtt_ms.unwrap_or(0)))
    }
}

/// A job of the suite.
#[derive(Clone, Copy, Debug)]
struct JobSize {
    name: &'static str,
    width: u32,
    height: u32,
    aa: u32,
    repetitions: usize,
}

impl JobSize {
    fn describe(self) -> String {
        format!(
            "{} ({}×{}, aa {}, {} tiles of {})",
            self.name,
            self.width,
            self.height,
            self.aa,
            self.tiles(),
            compression::default_tile_side(self.width, self.height, self.aa)
        )
    }

    fn tiles(self) -> u32 {
        let side = compression::default_tile_side(self.width, self.height, self.aa);
        self.width.div_ceil(side) * self.height.div_ceil(side)
    }
}

struct Plan {
    networks: Vec<Network>,
    jobs: Vec<JobSize>,
    compression_frame: (u32, u32, u32),
    compression_min_time: Duration,
}

fn plan(quick: bool) -> Plan {
    if quick {
        return Plan {
            networks: vec![
                Network { rtt_ms: None },
                Network { rtt_ms: Some(0) },
                Network { rtt_ms: Some(20) },
            ],
            jobs: vec![
                JobSize {
                    name: "seed",
                    width: 320,
                    height: 180,
                    aa: 1,
                    repetitions: 1,
                },
                JobSize {
                    name: "long",
                    width: 480,
                    height: 270,
                    aa: 2,
                    repetitions: 1,
                },
            ],
            compression_frame: (320, 180, 2),
            compression_min_time: Duration::from_millis(2),
        };
    }
    Plan {
        networks: vec![
            Network { rtt_ms: None },
            Network { rtt_ms: Some(0) },
            Network { rtt_ms: Some(20) },
            Network { rtt_ms: Some(100) },
            Network { rtt_ms: Some(200) },
        ],
        jobs: vec![
            JobSize {
                name: "seed",
                width: 1920,
                height: 1080,
                aa: 2,
                repetitions: 3,
            },
            JobSize {
                name: "long",
                width: 2560,
                height: 1440,
                aa: 8,
                repetitions: 2,
            },
        ],
        compression_frame: (1920, 1080, 2),
        compression_min_time: Duration::from_millis(150),
    }
}

/// Worker processes started by this suite (the local farm's coordinator alone is
/// [`LocalFarm`]'s); dropping it stops them.
struct Workers {
    children: Vec<(Child, Option<ChildStdin>)>,
}

impl Workers {
    fn start(exe: &Path, addresses: &[String], log_dir: &Path) -> Result<Workers> {
        let mut children = Vec::new();
        for (i, address) in addresses.iter().enumerate() {
            let name = format!("latency-{}", i + 1);
            let log = std::fs::File::create(log_dir.join(format!("{name}.log")))?;
            let mut command = Command::new(exe);
            for key in localfarm::tessera_variables() {
                command.env_remove(key);
            }
            let mut child = command
                .args(["worker", "--coordinator", address, "--threads", "1"])
                .args(["--name", &name, "--exit-on-stdin-eof"])
                .stdin(Stdio::piped())
                .stdout(Stdio::null())
                .stderr(log)
                .spawn()
                .with_context(|| format!("cannot start {}", exe.display()))?;
            let stdin = child.stdin.take();
            children.push((child, stdin));
        }
        Ok(Workers { children })
    }
}

impl Drop for Workers {
    fn drop(&mut self) {
        for (child, stdin) in &mut self.children {
            drop(stdin.take());
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// A coordinator, its workers and their relays. Fields drop in order: workers first.
struct Farm {
    _workers: Workers,
    relays: Vec<Relay>,
    coordinator: LocalFarm,
    _logs: tempfile::TempDir,
}

impl Farm {
    async fn start(exe: &Path, network: Network) -> Result<Farm> {
        let tessera = exe.to_path_buf();
        let coordinator = tokio::task::spawn_blocking(move || LocalFarm::start(&tessera, &[]))
            .await
            .context("starting a coordinator")??;
        let target: SocketAddr = coordinator
            .address()
            .parse()
            .context("the coordinator's address")?;
        let mut relays = Vec::new();
        let mut addresses = Vec::new();
        for _ in 0..WORKERS {
            match network.rtt_ms {
                None => addresses.push(coordinator.address().to_string()),
                Some(_) => {
                    let relay = Relay::start(
                        target,
                        Link {
                            one_way: network.rtt() / 2,
                            bandwidth: None,
                        },
                    )?;
                    addresses.push(relay.address().to_string());
                    relays.push(relay);
                }
            }
        }
        let logs = tempfile::Builder::new()
            .prefix("tessera-latency-")
            .tempdir()?;
        let workers = Workers::start(exe, &addresses, logs.path())?;
        coordinator
            .wait_for_workers(WORKERS, Duration::from_secs(20))
            .await?;
        Ok(Farm {
            _workers: workers,
            relays,
            coordinator,
            _logs: logs,
        })
    }

    /// The relays' counts so far; `None` without relays.
    fn traffic(&self) -> Option<Traffic> {
        if self.relays.is_empty() {
            return None;
        }
        let mut sum = Traffic::default();
        for r in &self.relays {
            sum.add(&r.traffic());
        }
        Some(sum)
    }
}

/// The job as submitted: the seed scene with its size overridden. Built through serde
/// so that the spec carries the protocol's default for anything this suite does not
/// choose (the verification level, where the protocol has one).
fn job_spec(job: JobSize) -> Result<JobSpec> {
    let overrides = Overrides {
        width: Some(job.width),
        height: Some(job.height),
        aa: Some(job.aa),
        ..Overrides::default()
    };
    let spec = serde_json::json!({
        "scene": scenes::seed().json,
        "overrides": overrides,
        "priority": 0,
        "verification": "Sampled",
        "name": "bench",
        "submitter": "tessera-bench",
        "frame": 1,
    });
    serde_json::from_value(spec).context("building the job's spec")
}

/// Submits the job and follows it to its end: wall time seen by the client, and the
/// final status.
pub(super) async fn run_job(address: &str, spec: JobSpec) -> Result<(f64, JobStatus)> {
    let mut client = Client::connect(&Endpoint::plain(address.to_string())).await?;
    let started = Instant::now();
    let job = client.submit(spec).await?;
    let mut seen = 0;
    loop {
        let status = client.watch(job, seen).await?;
        seen = status.tiles_done;
        match status.state {
            JobState::Done => return Ok((started.elapsed().as_secs_f64(), status)),
            JobState::Failed | JobState::Cancelled => {
                bail!("job {job} ended {:?}: {:?}", status.state, status.error)
            }
            _ => {}
        }
    }
}

/// One measured job.
struct Run {
    repetition: usize,
    network: usize,
    job: usize,
    wall: f64,
    /// Submission to completion as the coordinator measured it.
    job_seconds: f64,
    tiles: u32,
    /// Through the relays, from submission until the job's last messages had arrived.
    traffic: Option<Traffic>,
}

impl Run {
    fn utilisation(&self) -> Option<f64> {
        self.traffic
            .as_ref()
            .map(|t| t.render_us as f64 / 1e6 / (self.wall * WORKERS as f64))
    }
}

/// Runs the suite; writes `latency.md`, `latency.csv` and `compression.csv`.
pub async fn run(opts: &Options, out: &Path) -> Result<()> {
    let plan = plan(opts.quick);
    let trips = if opts.quick { 50 } else { 200 };
    let self_test =
        tokio::task::spawn_blocking(move || relay::self_test(trips, Duration::from_millis(20)))
            .await
            .context("relay self-test")??;
    eprintln!(
        "relay: round trip {:.0} µs direct, {:.0} µs relayed, {:.2} ms set to 20 ms",
        self_test.direct_us,
        self_test.relayed_us,
        self_test.delayed_us / 1e3
    );
    let mut runs = Vec::new();
    let most = plan.jobs.iter().map(|j| j.repetitions).max().unwrap_or(0);
    for repetition in 0..most {
        for (n, network) in plan.networks.iter().enumerate() {
            let farm = Farm::start(&opts.tessera, *network).await?;
            for (j, job) in plan.jobs.iter().enumerate() {
                if repetition >= job.repetitions {
                    continue;
                }
                let before = farm.traffic();
                let (wall, status) = run_job(farm.coordinator.address(), job_spec(*job)?).await?;
                // Let the job's last messages (scene releases, late copies) arrive.
                tokio::time::sleep(network.rtt() + Duration::from_millis(100)).await;
                let traffic = match (farm.traffic(), before) {
                    (Some(after), Some(before)) => Some(after.since(&before)),
                    _ => None,
                };
                let run = Run {
                    repetition,
                    network: n,
                    job: j,
                    wall,
                    job_seconds: status.elapsed_ms as f64 / 1e3,
                    tiles: status.tiles_total,
                    traffic,
                };
                eprintln!(
                    "latency: {} {}: {:.3} s{}",
                    network.name(),
                    job.name,
                    wall,
                    run.utilisation().map_or(String::new(), |u| format!(
                        ", utilisation {:.0}%",
                        100.0 * u
                    ))
                );
                runs.push(run);
            }
            drop(farm);
        }
    }
    let (w, h, aa) = plan.compression_frame;
    let frames =
        tokio::task::spawn_blocking(move || compression::render_tiles(w, h, aa, &[64, 32]))
            .await
            .context("rendering the tiles to compress")??;
    let min_time = plan.compression_min_time;
    let (frames, measured) = tokio::task::spawn_blocking(move || {
        let m = compression::measure(&frames, min_time);
        (frames, m)
    })
    .await
    .context("measuring the codecs")?;
    let measured = measured?;
    let mut md = latency_markdown(&plan, &runs, &self_test);
    md.push('\n');
    md.push_str(&compression::markdown(&frames, &measured));
    std::fs::write(out.join("latency.md"), &md)?;
    std::fs::write(out.join("latency.csv"), latency_csv(&plan, &runs))?;
    std::fs::write(
        out.join("compression.csv"),
        compression::csv(&frames, &measured),
    )?;
    println!("{md}");
    Ok(())
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => (v[n / 2 - 1] + v[n / 2]) / 2.0,
    }
}

fn range(v: &[f64]) -> (f64, f64) {
    v.iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &x| {
            (lo.min(x), hi.max(x))
        })
}

/// Every kind of message in a fixed order, direction first.
fn all_kinds() -> Vec<(Direction, &'static str)> {
    let mut kinds = vec![(Direction::Up, HANDSHAKE)];
    kinds.extend(UP_KINDS.iter().map(|k| (Direction::Up, *k)));
    kinds.push((Direction::Up, OTHER));
    kinds.push((Direction::Down, HANDSHAKE));
    kinds.extend(DOWN_KINDS.iter().map(|k| (Direction::Down, *k)));
    kinds.push((Direction::Down, OTHER));
    kinds
}

fn latency_markdown(plan: &Plan, runs: &[Run], st: &relay::SelfTest) -> String {
    let mut md = String::new();
    let cpu = cpu_model();
    let _ = writeln!(
        md,
        "## Through network latency\n\n\
         A coordinator and {WORKERS} one-thread workers on 127.0.0.1; each worker reaches \
         the coordinator directly or through a relay that delays every chunk by half the \
         round-trip time each way, without limiting bandwidth. Jobs: the seed scene, \
         {}. Runs interleaved (every network in turn, then again), each on a fresh farm. \
         Wall time from submission to the client seeing `done`; throughput against direct \
         loopback as the ratio of medians in this run (and the range of the ratios run by \
         run); utilisation = the render time the tile results report, over wall time × \
         {WORKERS} threads (measured by the relays, so not for the direct runs). CPU: {cpu}.\n\n\
         The relay itself: round trip of a 64-byte message {:.0} µs direct, {:.0} µs \
         through an undelayed relay (it adds {:.0} µs), {:.2} ms through one set to \
         {} ms.\n",
        plan.jobs
            .iter()
            .map(|j| j.describe())
            .collect::<Vec<_>>()
            .join(" and "),
        st.direct_us,
        st.relayed_us,
        st.relayed_us - st.direct_us,
        st.delayed_us / 1e3,
        st.rtt.as_millis(),
    );
    let _ = writeln!(
        md,
        "| job | network | runs | wall (s), median | range | throughput vs direct | per-run ratios | utilisation | up bytes/job | down bytes/job |\n\
         |---|---|---:|---:|---|---:|---|---:|---:|---:|"
    );
    for (j, job) in plan.jobs.iter().enumerate() {
        let direct: Vec<&Run> = runs
            .iter()
            .filter(|r| r.job == j && r.network == 0)
            .collect();
        let direct_median = median(direct.iter().map(|r| r.wall).collect());
        for (n, network) in plan.networks.iter().enumerate() {
            let these: Vec<&Run> = runs
                .iter()
                .filter(|r| r.job == j && r.network == n)
                .collect();
            let walls: Vec<f64> = these.iter().map(|r| r.wall).collect();
            let m = median(walls.clone());
            let (lo, hi) = range(&walls);
            let ratios: Vec<String> = these
                .iter()
                .filter_map(|r| {
                    direct
                        .iter()
                        .find(|d| d.repetition == r.repetition)
                        .map(|d| format!("{:.2}", d.wall / r.wall))
                })
                .collect();
            let utils: Vec<f64> = these.iter().filter_map(|r| r.utilisation()).collect();
            let ups: Vec<f64> = these
                .iter()
                .filter_map(|r| r.traffic.as_ref().map(|t| t.up_bytes as f64))
                .collect();
            let downs: Vec<f64> = these
                .iter()
                .filter_map(|r| r.traffic.as_ref().map(|t| t.down_bytes as f64))
                .collect();
            let or_dash = |v: &[f64], f: &dyn Fn(f64) -> String| {
                if v.is_empty() {
                    "—".to_string()
                } else {
                    f(median(v.to_vec()))
                }
            };
            let _ = writeln!(
                md,
                "| {} | {} | {} | {:.3} | {:.3}–{:.3} | {:.2} | {} | {} | {} | {} |",
                job.name,
                network.name(),
                these.len(),
                m,
                lo,
                hi,
                direct_median / m,
                ratios.join(", "),
                or_dash(&utils, &|u| format!("{:.0}%", 100.0 * u)),
                or_dash(&ups, &|b| format!("{b:.0}")),
                or_dash(&downs, &|b| format!("{b:.0}")),
            );
        }
    }
    // Bytes by kind: the first relayed run of each job at the smallest round trip.
    let _ = writeln!(
        md,
        "\n### Bytes on the wire per job, by kind of message\n\n\
         Counted by the relays on the first run of each job through the undelayed relay, \
         from submission until the job's last messages arrived; frames include their \
         4-byte length prefix. Heartbeats depend on the job's duration (one a second each \
         way per worker). TCP/IP headers come on top (about 52 bytes per segment of up to \
         1448 bytes on Ethernet: under 4 %).\n"
    );
    let _ = writeln!(
        md,
        "| job | direction | kind | frames | bytes | share of direction | bytes per tile |\n|---|---|---|---:|---:|---:|---:|"
    );
    for (j, job) in plan.jobs.iter().enumerate() {
        let Some(run) = runs
            .iter()
            .filter(|r| r.job == j && r.traffic.is_some())
            .min_by_key(|r| (plan.networks[r.network].rtt_ms, r.repetition))
        else {
            continue;
        };
        let t = run.traffic.as_ref().expect("filtered");
        for (direction, kind) in all_kinds() {
            let c = t.kind(direction, kind);
            if c.frames == 0 {
                continue;
            }
            let total = match direction {
                Direction::Up => t.up_bytes,
                Direction::Down => t.down_bytes,
            };
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {} | {:.2}% | {:.1} |",
                job.name,
                match direction {
                    Direction::Up => "worker → coordinator",
                    Direction::Down => "coordinator → worker",
                },
                kind,
                c.frames,
                c.bytes,
                100.0 * c.bytes as f64 / total.max(1) as f64,
                c.bytes as f64 / f64::from(run.tiles.max(1))
            );
        }
        let _ = writeln!(
            md,
            "| {} | both | all ({:.1} s) | | {} up, {} down | | {:.0} up, {:.1} down |",
            job.name,
            run.wall,
            t.up_bytes,
            t.down_bytes,
            t.up_bytes as f64 / f64::from(run.tiles.max(1)),
            t.down_bytes as f64 / f64::from(run.tiles.max(1))
        );
    }
    md
}

fn latency_csv(plan: &Plan, runs: &[Run]) -> String {
    let kinds = all_kinds();
    let mut csv = String::from(
        "repetition,network,rtt_ms,relayed,job,width,height,aa,tiles,wall_s,job_s,render_s,utilisation,up_bytes,down_bytes",
    );
    for (direction, kind) in &kinds {
        let d = match direction {
            Direction::Up => "up",
            Direction::Down => "down",
        };
        let k = kind.replace(' ', "_");
        let _ = write!(csv, ",{d}_{k}_frames,{d}_{k}_bytes");
    }
    csv.push('\n');
    for r in runs {
        let network = plan.networks[r.network];
        let job = plan.jobs[r.job];
        let _ = write!(
            csv,
            "{},{},{},{},{},{},{},{},{},{:.4},{:.3},",
            r.repetition,
            network.name(),
            network.rtt_ms.unwrap_or(0),
            network.rtt_ms.is_some(),
            job.name,
            job.width,
            job.height,
            job.aa,
            r.tiles,
            r.wall,
            r.job_seconds
        );
        match &r.traffic {
            Some(t) => {
                let _ = write!(
                    csv,
                    "{:.4},{:.4},{},{}",
                    t.render_us as f64 / 1e6,
                    r.utilisation().unwrap_or(f64::NAN),
                    t.up_bytes,
                    t.down_bytes
                );
                for (direction, kind) in &kinds {
                    let c = t.kind(*direction, kind);
                    let _ = write!(csv, ",{},{}", c.frames, c.bytes);
                }
            }
            None => {
                csv.push_str(",,,");
                for _ in &kinds {
                    csv.push_str(",,");
                }
            }
        }
        csv.push('\n');
    }
    csv
}

/// The processor's name and core count, from /proc/cpuinfo.
pub(super) fn cpu_model() -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let name = info
        .lines()
        .find_map(|l| l.strip_prefix("model name"))
        .and_then(|l| l.split_once(':'))
        .map_or("unknown", |(_, v)| v.trim())
        .to_string();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    format!("{cores} × {name}")
}
