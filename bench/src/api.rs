//! `tessera-bench --suite api`: the HTTP API (`/api/v1`) against the binary protocol,
//! on one local coordinator, in one run.
//!
//! 1. Latency: a job's status and a submission, each asked over one kept connection,
//!    the HTTP way (`GET /api/v1/jobs/ID`, `POST /api/v1/jobs`) and the binary way
//!    (`Status`, `Submit`), alternating in blocks so both see the same machine. The
//!    farm has no worker, so the submitted jobs only queue and nothing else runs.
//! 2. A hundred clients polling a job's status at once while two one-thread workers
//!    render the hall-of-mirrors scene: the job's time from submission to its end, and
//!    the latency of a
//!    binary status probe every 50 ms (the coordinator's other work), quiet against a
//!    hundred pollers asking every 100 ms and a hundred asking as fast as they are
//!    answered, alternating, three runs each. The pollers run in this process, on the
//!    same two cores: their own cost is in the figures, as it would be on a machine
//!    that runs its pipelines beside the coordinator.

use std::fmt::Write as _;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use coordinator::client::Client;
use protocol::JobState;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use transport::Endpoint;

use super::scenes;
use super::sequence::{job_spec, load_average, median, secs_list, Size};
use super::verification::cpu_seconds;
use super::Options;
use localfarm::{LocalFarm, WorkerSpec};

/// The job of part 1 (it only queues) and of part 2 (two workers render it).
const SMALL: Size = Size {
    width: 64,
    height: 48,
    aa: 1,
};

/// One kept HTTP/1.1 connection to the coordinator's HTTP port: a request, its answer.
struct Http {
    stream: BufReader<TcpStream>,
    host: String,
}

impl Http {
    async fn connect(host: &str) -> Result<Http> {
        let stream = TcpStream::connect(host)
            .await
            .with_context(|| format!("cannot connect to the coordinator's HTTP at {host}"))?;
        stream.set_nodelay(true)?;
        Ok(Http {
            stream: BufReader::new(stream),
            host: host.to_owned(),
        })
    }

    /// `METHOD PATH` with a JSON body (empty for a GET): the status and the body. Every
    /// answer of the API carries its length, which is what keeps the connection.
    async fn request(&mut self, method: &str, path: &str, body: &str) -> Result<(u16, Vec<u8>)> {
        let head = format!(
            "{method} {path} HTTP/1.1\r\nHost: {}\r\nContent-Type: application/json\r\n\
             Content-Length: {}\r\n\r\n",
            self.host,
            body.len()
        );
        let stream = self.stream.get_mut();
        stream.write_all(head.as_bytes()).await?;
        stream.write_all(body.as_bytes()).await?;
        let mut line = String::new();
        self.stream.read_line(&mut line).await?;
        let status: u16 = line
            .split_whitespace()
            .nth(1)
            .and_then(|s| s.parse().ok())
            .with_context(|| format!("{method} {path}: no HTTP status in {line:?}"))?;
        let mut length = None;
        loop {
            line.clear();
            if self.stream.read_line(&mut line).await? == 0 {
                bail!("{method} {path}: the connection closed in the answer's head");
            }
            let header = line.trim_end();
            if header.is_empty() {
                break;
            }
            if let Some((name, value)) = header.split_once(':') {
                if name.eq_ignore_ascii_case("content-length") {
                    length = value.trim().parse::<usize>().ok();
                }
            }
        }
        let length = length.with_context(|| format!("{method} {path}: no Content-Length"))?;
        let mut answer = vec![0; length];
        self.stream.read_exact(&mut answer).await?;
        Ok((status, answer))
    }
}

/// Milliseconds, to two places.
fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// The `q`-quantile (0 to 1) of `xs`, nearest rank.
fn quantile(xs: &[f64], q: f64) -> f64 {
    let mut v = xs.to_vec();
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        return f64::NAN;
    }
    let rank = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len());
    v[rank - 1]
}

/// A row of a latency table: median, 90th and 99th percentile, in milliseconds.
fn latency_row(what: &str, xs: &[f64]) -> String {
    format!(
        "| {what} | {} | {:.3} | {:.3} | {:.3} |\n",
        xs.len(),
        median(xs),
        quantile(xs, 0.9),
        quantile(xs, 0.99)
    )
}

/// Writes `api.md`.
pub async fn run(opts: &Options, out: &Path) -> Result<()> {
    let mut md = String::from("# The HTTP API against the binary protocol\n\n");
    writeln!(
        md,
        "One local coordinator (`--http`, no client token: loopback may control), \
         `tessera-bench --suite api`. Load average before: {}.\n",
        load_average()
    )?;
    latency(opts, &mut md).await?;
    pollers(opts, &mut md).await?;
    writeln!(md, "Load average after: {}.", load_average())?;
    let path = out.join("api.md");
    std::fs::write(&path, &md).with_context(|| format!("cannot write {}", path.display()))?;
    print!("{md}");
    Ok(())
}

/// Part 1: status and submit, HTTP against binary, on a farm without workers.
async fn latency(opts: &Options, md: &mut String) -> Result<()> {
    let farm = LocalFarm::start_with(&opts.tessera, &[], &["--http", "127.0.0.1:0"])?;
    let http_addr = farm
        .http_address()
        .context("the coordinator serves no HTTP")?
        .to_owned();
    let mut client = Client::connect(&Endpoint::plain(farm.address())).await?;
    let mut http = Http::connect(&http_addr).await?;
    let scene = scenes::seed().json;
    let spec = || job_spec(scene.clone(), SMALL, None);
    let job = client.submit(spec()).await?;
    let body = serde_json::json!({
        "scene": scene,
        "width": SMALL.width,
        "height": SMALL.height,
        "aa": SMALL.aa,
        "name": "bench",
        "submitter": "tessera-bench",
    })
    .to_string();
    let status_path = format!("/api/v1/jobs/{job}");
    let (blocks, per_block, submits) = if opts.quick { (4, 10, 2) } else { (20, 50, 5) };
    let mut binary_status = Vec::new();
    let mut http_status = Vec::new();
    let mut binary_submit = Vec::new();
    let mut http_submit = Vec::new();
    // Warm both connections and the coordinator's caches before timing.
    for _ in 0..20 {
        client.status(job).await?;
        http.request("GET", &status_path, "").await?;
    }
    for _ in 0..blocks {
        for _ in 0..per_block {
            let t = Instant::now();
            client.status(job).await?;
            binary_status.push(ms(t.elapsed()));
        }
        for _ in 0..per_block {
            let t = Instant::now();
            let (code, answer) = http.request("GET", &status_path, "").await?;
            http_status.push(ms(t.elapsed()));
            if code != 200 {
                bail!(
                    "GET {status_path}: {code} {}",
                    String::from_utf8_lossy(&answer)
                );
            }
        }
        for _ in 0..submits {
            let t = Instant::now();
            let id = client.submit(spec()).await?;
            binary_submit.push(ms(t.elapsed()));
            client.cancel(id).await?;
            let t = Instant::now();
            let (code, answer) = http.request("POST", "/api/v1/jobs", &body).await?;
            http_submit.push(ms(t.elapsed()));
            if code != 201 && code != 200 {
                bail!(
                    "POST /api/v1/jobs: {code} {}",
                    String::from_utf8_lossy(&answer)
                );
            }
            let answer: serde_json::Value = serde_json::from_slice(&answer)?;
            let id = answer["id"]
                .as_u64()
                .context("a submission's answer has no id")?;
            client.cancel(id).await?;
        }
    }
    writeln!(
        md,
        "## Latency\n\nEach request over one kept connection, from this process, one at a \
         time; the binary protocol's and the API's alternate in blocks of {per_block} \
         status requests and {submits} submissions (of the seed scene, {}×{} aa {}, \
         cancelled at once: the farm has no worker). Milliseconds from the request's \
         first byte sent to its answer's last byte read.\n",
        SMALL.width, SMALL.height, SMALL.aa
    )?;
    md.push_str("| Request | n | median | p90 | p99 |\n|---|---:|---:|---:|---:|\n");
    md.push_str(&latency_row("status, binary protocol", &binary_status));
    md.push_str(&latency_row("status, `GET /api/v1/jobs/ID`", &http_status));
    md.push_str(&latency_row("submit, binary protocol", &binary_submit));
    md.push_str(&latency_row("submit, `POST /api/v1/jobs`", &http_submit));
    writeln!(
        md,
        "\nMedian ratio HTTP / binary: status {:.2}, submit {:.2}.\n",
        median(&http_status) / median(&binary_status),
        median(&http_submit) / median(&binary_submit)
    )?;
    Ok(())
}

/// How the hundred clients of part 2 poll.
#[derive(Clone, Copy, PartialEq)]
enum Polling {
    Quiet,
    Every100Ms,
    FlatOut,
}

impl Polling {
    fn label(self) -> &'static str {
        match self {
            Polling::Quiet => "no poller",
            Polling::Every100Ms => "100 clients, each every 100 ms",
            Polling::FlatOut => "100 clients, each as fast as answered",
        }
    }
}

/// One run of part 2.
struct PollRun {
    polling: Polling,
    job_seconds: f64,
    probes: Vec<f64>,
    polls: u64,
    poll_latencies: Vec<f64>,
    failures: u64,
    /// CPU-seconds the coordinator used during the job.
    coordinator_cpu: f64,
}

/// Part 2: a job rendered with a hundred clients polling its status.
async fn pollers(opts: &Options, md: &mut String) -> Result<()> {
    let one = WorkerSpec {
        threads: 1,
        ..WorkerSpec::default()
    };
    let workers = [one.clone(), one];
    let farm = LocalFarm::start_with(&opts.tessera, &workers, &["--http", "127.0.0.1:0"])?;
    farm.wait_for_workers(2, Duration::from_secs(30)).await?;
    let http_addr = farm
        .http_address()
        .context("the coordinator serves no HTTP")?
        .to_owned();
    let size = if opts.quick {
        Size {
            width: 320,
            height: 180,
            aa: 1,
        }
    } else {
        Size {
            width: 1920,
            height: 1080,
            aa: 4,
        }
    };
    let reps = if opts.quick { 1 } else { 3 };
    let order = [Polling::Quiet, Polling::Every100Ms, Polling::FlatOut];
    let mut runs = Vec::new();
    let mut reference: Option<Vec<u8>> = None;
    for _ in 0..reps {
        for polling in order {
            let (run, png) = poll_run(&farm, &http_addr, size, polling).await?;
            match &reference {
                None => reference = Some(png),
                Some(r) if *r != png => bail!("the job's image differs under {}", polling.label()),
                Some(_) => {}
            }
            eprintln!(
                "api: {}: job {:.2} s, {} polls",
                polling.label(),
                run.job_seconds,
                run.polls
            );
            runs.push(run);
        }
    }
    writeln!(
        md,
        "## A hundred clients polling\n\nThe hall-of-mirrors scene at {}×{} aa {} on two one-thread \
         workers; {reps} runs of each case, alternating. The job's time is from its \
         submission to its end; a binary status probe is sent every 50 ms meanwhile; the \
         coordinator's CPU time is its process's over the job (`/proc`). The pollers \
         run in this process, on the same cores as the farm. Every poll must answer 200 with the job's JSON, and every run's image must be the \
         same bytes.\n",
        size.width, size.height, size.aa
    )?;
    md.push_str(
        "| Case | job s (runs) | median job s | coordinator CPU s | probe median ms | probe p99 ms | polls/s | poll median ms | poll p99 ms | failed polls |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    let quiet_job = median(
        &runs
            .iter()
            .filter(|r| r.polling == Polling::Quiet)
            .map(|r| r.job_seconds)
            .collect::<Vec<_>>(),
    );
    for polling in order {
        let of: Vec<&PollRun> = runs.iter().filter(|r| r.polling == polling).collect();
        let jobs: Vec<f64> = of.iter().map(|r| r.job_seconds).collect();
        let probes: Vec<f64> = of.iter().flat_map(|r| r.probes.clone()).collect();
        let polls: Vec<f64> = of.iter().flat_map(|r| r.poll_latencies.clone()).collect();
        let rate: f64 = of.iter().map(|r| r.polls as f64).sum::<f64>() / jobs.iter().sum::<f64>();
        let failures: u64 = of.iter().map(|r| r.failures).sum();
        let cpu: Vec<f64> = of.iter().map(|r| r.coordinator_cpu).collect();
        writeln!(
            md,
            "| {} | {} | {:.2} ({:.2}×) | {:.2} | {:.2} | {:.2} | {} | {} | {} | {failures} |",
            polling.label(),
            secs_list(&jobs),
            median(&jobs),
            median(&jobs) / quiet_job,
            median(&cpu),
            median(&probes),
            quantile(&probes, 0.99),
            if polls.is_empty() {
                "—".into()
            } else {
                format!("{rate:.0}")
            },
            if polls.is_empty() {
                "—".into()
            } else {
                format!("{:.2}", median(&polls))
            },
            if polls.is_empty() {
                "—".into()
            } else {
                format!("{:.2}", quantile(&polls, 0.99))
            },
        )?;
    }
    md.push('\n');
    if runs.iter().any(|r| r.failures > 0) {
        bail!("polls failed: see the table\n{md}");
    }
    Ok(())
}

/// One job under `polling`: its figures and its image.
async fn poll_run(
    farm: &LocalFarm,
    http_addr: &str,
    size: Size,
    polling: Polling,
) -> Result<(PollRun, Vec<u8>)> {
    let endpoint = Endpoint::plain(farm.address());
    let mut client = Client::connect(&endpoint).await?;
    let coordinator = farm.pids()[0];
    let cpu_before = cpu_seconds(coordinator)?;
    let started = Instant::now();
    let job = client
        .submit(job_spec(scenes::hall_of_mirrors().json, size, None))
        .await?;
    let stop = Arc::new(AtomicBool::new(false));
    let polls = Arc::new(AtomicU64::new(0));
    let failures = Arc::new(AtomicU64::new(0));
    let mut tasks = Vec::new();
    if polling != Polling::Quiet {
        for _ in 0..100 {
            let (stop, polls, failures) = (stop.clone(), polls.clone(), failures.clone());
            let addr = http_addr.to_owned();
            let path = format!("/api/v1/jobs/{job}");
            tasks.push(tokio::spawn(async move {
                let mut latencies = Vec::new();
                let Ok(mut http) = Http::connect(&addr).await else {
                    failures.fetch_add(1, Ordering::Relaxed);
                    return latencies;
                };
                while !stop.load(Ordering::Relaxed) {
                    let t = Instant::now();
                    match http.request("GET", &path, "").await {
                        Ok((200, body)) if body.starts_with(b"{") => {
                            latencies.push(ms(t.elapsed()));
                            polls.fetch_add(1, Ordering::Relaxed);
                        }
                        _ => {
                            failures.fetch_add(1, Ordering::Relaxed);
                            return latencies;
                        }
                    }
                    if polling == Polling::Every100Ms {
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                }
                latencies
            }));
        }
    }
    let mut probe = Client::connect(&endpoint).await?;
    let mut probes = Vec::new();
    let job_seconds = loop {
        let t = Instant::now();
        let status = probe.status(job).await?;
        probes.push(ms(t.elapsed()));
        match status.state {
            JobState::Done => break started.elapsed().as_secs_f64(),
            JobState::Failed | JobState::Cancelled => {
                bail!("job {job} ended {:?}: {:?}", status.state, status.error)
            }
            _ => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    };
    let coordinator_cpu = cpu_seconds(coordinator)? - cpu_before;
    stop.store(true, Ordering::Relaxed);
    let mut poll_latencies = Vec::new();
    for task in tasks {
        poll_latencies.extend(task.await?);
    }
    let png = client.fetch(job).await?;
    client.delete(job).await?;
    Ok((
        PollRun {
            polling,
            job_seconds,
            probes,
            polls: polls.load(Ordering::Relaxed),
            poll_latencies,
            failures: failures.load(Ordering::Relaxed),
            coordinator_cpu,
        },
        png,
    ))
}
