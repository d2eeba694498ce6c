//! `tessera-bench --suite liveness`: how long a job waits for a worker whose rendering
//! hangs while its heartbeats go on (a deadlocked render thread, a driver that never
//! returns), with the coordinator's default settings.
//!
//! A local farm of one-thread workers renders the 768-tile job of the report that
//! found the problem (2000 × 1500, aa 4, tiles of 64 pixels); two seconds after the
//! submission, the render threads of one worker are frozen with ptrace
//! ([`localfarm::FrozenThreads`]), the rest of the worker running on, and kept frozen to
//! the job's end. Measured from the freeze: when the worker is listed unresponsive,
//! when the first of its leases ran out, when the last of the tiles it held was done by
//! another machine, and when the job was done. The job must end `done` within 90 s of
//! its submission and its image must be byte for byte `tessera render`'s.
//!
//! Two cases: sampled verification (the default) on two workers, where held audits
//! wait for the one machine that could confirm them, and `--verify full` on three,
//! where every tile needs a second machine.
//!
//! The scene is `scenes/hall-of-mirrors.json`, the heaviest shipped: the seed scene's
//! job of that size is done in under a second on two workers, before any freeze.
//! Freezing threads takes ptrace of another process: root or `CAP_SYS_PTRACE`.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context, Result};
use coordinator::client::Client;
use protocol::{JobEvent, JobId, JobSpec, JobState, Overrides, Verification};
use transport::Endpoint;

use super::Options;
use localfarm::{FrozenThreads, LocalFarm, WorkerSpec};

/// The scene of every job.
const SCENE: &str = include_str!("../../scenes/hall-of-mirrors.json");
/// The longest a job may take from its submission.
const BOUND: Duration = Duration::from_secs(90);
/// How often the farm is looked at while the job runs.
const POLL: Duration = Duration::from_millis(50);
/// The worker whose render threads are frozen (the farm's second).
const VICTIM: usize = 2;

/// One farm and way of checking results.
struct Case {
    name: &'static str,
    workers: usize,
    verification: Verification,
}

const CASES: [Case; 2] = [
    Case {
        name: "sampled verification, two workers",
        workers: 2,
        verification: Verification::Sampled,
    },
    Case {
        name: "--verify full, three workers",
        workers: 3,
        verification: Verification::Full,
    },
];

/// The job and when to freeze.
#[derive(Clone, Copy)]
struct Plan {
    width: u32,
    height: u32,
    aa: u32,
    tile: u32,
    freeze_after: Duration,
    rounds: usize,
}

impl Plan {
    fn new(quick: bool) -> Plan {
        if quick {
            // The same number of tiles, a quarter of the work: a check that the suite
            // works, not a measurement.
            Plan {
                width: 1000,
                height: 750,
                aa: 4,
                tile: 32,
                freeze_after: Duration::from_millis(500),
                rounds: 1,
            }
        } else {
            Plan {
                width: 2000,
                height: 1500,
                aa: 4,
                tile: 64,
                freeze_after: Duration::from_secs(2),
                rounds: 3,
            }
        }
    }

    fn tiles(self) -> u32 {
        self.width.div_ceil(self.tile) * self.height.div_ceil(self.tile)
    }

    fn overrides(self) -> Overrides {
        Overrides {
            width: Some(self.width),
            height: Some(self.height),
            aa: Some(self.aa),
            tile_size: Some(self.tile),
            ..Overrides::default()
        }
    }
}

/// What one run measured; times in seconds from the freeze.
struct Figures {
    /// From submission to the freeze.
    frozen_at: f64,
    /// The frozen worker first listed unresponsive.
    marked: Option<f64>,
    /// The first lease of the frozen worker's ran out.
    first_lease_expired: Option<f64>,
    /// The last of the tiles the frozen worker held was done by another machine.
    taken_over: Option<f64>,
    /// Tiles the frozen worker held and never rendered.
    tiles_held: usize,
    /// The job was done.
    done: f64,
    /// From submission to done.
    job: f64,
    tiles_done_at_freeze: u32,
}

/// Runs the suite; writes `liveness.md` and `liveness.csv`.
pub async fn run(opts: &Options, out: &Path) -> Result<()> {
    let plan = Plan::new(opts.quick);
    let work = tempfile::Builder::new()
        .prefix("tessera-bench-liveness-")
        .tempdir()?;
    let reference = render_reference(opts, plan, work.path()).await?;
    let mut csv = String::from(
        "case,round,frozen_at_s,marked_s,first_lease_expired_s,taken_over_s,tiles_held,\
         done_s,job_s\n",
    );
    let mut results: Vec<Vec<Figures>> = CASES.iter().map(|_| Vec::new()).collect();
    for round in 0..plan.rounds {
        for (c, case) in CASES.iter().enumerate() {
            let figures = run_once(opts, plan, case, &reference)
                .await
                .with_context(|| format!("{} (round {})", case.name, round + 1))?;
            eprintln!(
                "liveness: {}: frozen {:.1} s in; marked unresponsive {}, tiles taken over \
                 {}, job done {:.1} s after the freeze ({:.1} s in all)",
                case.name,
                figures.frozen_at,
                seconds(figures.marked),
                seconds(figures.taken_over),
                figures.done,
                figures.job
            );
            writeln!(
                csv,
                "{:?},{},{:.3},{},{},{},{},{:.3},{:.3}",
                case.name,
                round + 1,
                figures.frozen_at,
                csv_seconds(figures.marked),
                csv_seconds(figures.first_lease_expired),
                csv_seconds(figures.taken_over),
                figures.tiles_held,
                figures.done,
                figures.job
            )?;
            results[c].push(figures);
        }
    }
    let md = markdown(plan, &results);
    std::fs::write(out.join("liveness.md"), &md)?;
    std::fs::write(out.join("liveness.csv"), csv)?;
    println!("{md}");
    Ok(())
}

/// `tessera render` of the job, into `dir`: the bytes every run's image must be.
async fn render_reference(opts: &Options, plan: Plan, dir: &Path) -> Result<Vec<u8>> {
    let scene = dir.join("hall-of-mirrors.json");
    std::fs::write(&scene, SCENE)?;
    let png = dir.join("reference.png");
    let mut command = tokio::process::Command::new(&opts.tessera);
    for key in localfarm::tessera_variables() {
        command.env_remove(key);
    }
    let output = command
        .arg("render")
        .arg(&scene)
        .arg("-o")
        .arg(&png)
        .args(["--width", &plan.width.to_string()])
        .args(["--height", &plan.height.to_string()])
        .args(["--aa", &plan.aa.to_string()])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .output()
        .await
        .with_context(|| format!("cannot start {}", opts.tessera.display()))?;
    if !output.status.success() {
        bail!(
            "tessera render failed ({}): {}",
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        );
    }
    Ok(std::fs::read(&png)?)
}

/// One job on a fresh farm, a worker frozen [`Plan::freeze_after`] into it.
async fn run_once(opts: &Options, plan: Plan, case: &Case, reference: &[u8]) -> Result<Figures> {
    let exe = opts.tessera.clone();
    let specs = vec![WorkerSpec::default(); case.workers];
    let farm = tokio::task::spawn_blocking(move || LocalFarm::start(&exe, &specs))
        .await
        .context("starting a farm")??;
    farm.wait_for_workers(case.workers, Duration::from_secs(20))
        .await?;
    let victim_pid = farm.pids()[VICTIM];
    let victim = format!("local-{VICTIM}");
    let mut client = Client::connect(&Endpoint::plain(farm.address().to_string())).await?;
    let submitted = Instant::now();
    let job = client
        .submit(JobSpec {
            scene: SCENE.to_owned(),
            overrides: plan.overrides(),
            priority: 0,
            verification: case.verification,
            time_limit_ms: None,
            name: "liveness".into(),
            submitter: "tessera-bench".into(),
            frame: 1,
            frames: None,
            assets: Vec::new(),
            after: Vec::new(),
            require: Vec::new(),
        })
        .await?;

    tokio::time::sleep_until((submitted + plan.freeze_after).into()).await;
    let status = client.status(job).await?;
    if status.state != JobState::Running {
        bail!(
            "job {job} is {:?} at the freeze, {} s in: it must still be running",
            status.state,
            plan.freeze_after.as_secs_f64()
        );
    }
    let frozen = tokio::task::spawn_blocking(move || FrozenThreads::freeze(victim_pid, "render-"))
        .await?
        .context("the liveness suite freezes a worker's render threads with ptrace")?;
    let froze = Instant::now();
    let froze_unix_ms = unix_ms();
    let frozen_at = (froze - submitted).as_secs_f64();
    // What it holds now: its render threads stopped, it returns nothing more.
    let in_flight = client
        .workers()
        .await?
        .iter()
        .find(|w| w.name == victim)
        .map_or(0, |w| w.tiles_in_flight as usize);
    let listed_unix_ms = unix_ms();

    let mut marked = None;
    let done = loop {
        // The listing first: the mark and the job's end can come at the same timeout.
        if marked.is_none() {
            let workers = client.workers().await?;
            if workers.iter().any(|w| w.name == victim && w.unresponsive) {
                marked = Some(froze.elapsed().as_secs_f64());
            }
        }
        let status = client.status(job).await?;
        match status.state {
            JobState::Done => break froze.elapsed().as_secs_f64(),
            JobState::Failed | JobState::Cancelled => bail!(
                "job {job} ended {:?} with a worker frozen: {:?}",
                status.state,
                status.error
            ),
            _ => {}
        }
        if submitted.elapsed() > BOUND {
            bail!(
                "job {job} not done {} s after its submission ({}/{} tiles, a worker frozen \
                 {frozen_at:.1} s in; marked unresponsive: {})",
                BOUND.as_secs(),
                status.tiles_done,
                status.tiles_total,
                seconds(marked)
            );
        }
        tokio::time::sleep(POLL).await;
    };
    let job_seconds = submitted.elapsed().as_secs_f64();
    frozen.thaw()?;

    let png = client.fetch(job).await?;
    if png != reference {
        bail!(
            "job {job}'s image differs from `tessera render`'s ({} bytes against {})",
            png.len(),
            reference.len()
        );
    }
    let events = all_events(&mut client, job).await?;
    let timeline = Timeline::of(&events, &victim, in_flight, listed_unix_ms, froze_unix_ms);
    Ok(Figures {
        frozen_at,
        marked,
        first_lease_expired: timeline.first_lease_expired,
        taken_over: timeline.taken_over,
        tiles_held: timeline.tiles_held,
        done,
        job: job_seconds,
        tiles_done_at_freeze: status.tiles_done,
    })
}

/// Every event of the job, in order.
async fn all_events(client: &mut Client, job: JobId) -> Result<Vec<JobEvent>> {
    let mut events: Vec<JobEvent> = Vec::new();
    loop {
        let after = events.last().map_or(0, |e| e.seq);
        let page = client.events(job, after).await?;
        if page.is_empty() {
            return Ok(events);
        }
        events.extend(page);
    }
}

/// What the job's event log says of the frozen worker's tiles.
struct Timeline {
    first_lease_expired: Option<f64>,
    taken_over: Option<f64>,
    tiles_held: usize,
}

impl Timeline {
    /// From the events `tile_assigned` (`tile N to NAME`), `tile_done` (`tile N by NAME
    /// in ...`) and `tile_lease_expired` (`tile N on NAME for ...`), in seconds from
    /// `froze_unix_ms`. The tiles the frozen worker held are the last `in_flight`
    /// assigned to it before `listed_unix_ms`, when it was listed with that many: a
    /// worker renders its tiles in the order it gets them, so those it holds are the
    /// latest. (Its tiles without a `tile_done` of its own would not do: under full
    /// verification the log names the machine that confirmed a result, not the one
    /// that rendered it first.)
    fn of(
        events: &[JobEvent],
        victim: &str,
        in_flight: usize,
        listed_unix_ms: u64,
        froze_unix_ms: u64,
    ) -> Timeline {
        let since = |ms: u64| (ms as f64 - froze_unix_ms as f64) / 1000.0;
        let parse = |detail: &str, word: &str| -> Option<(u32, String)> {
            let rest = detail.strip_prefix("tile ")?;
            let (tile, rest) = rest.split_once(' ')?;
            let name = rest.strip_prefix(word)?.strip_prefix(' ')?;
            let name = name.split(' ').next()?;
            Some((tile.parse().ok()?, name.to_owned()))
        };
        let mut assigned: Vec<u32> = Vec::new();
        let mut done_at: BTreeMap<u32, u64> = BTreeMap::new();
        let mut first_lease_expired = None;
        for event in events {
            match event.kind.as_str() {
                "tile_assigned" if event.unix_ms <= listed_unix_ms => {
                    if let Some((tile, name)) = parse(&event.detail, "to") {
                        if name == victim {
                            assigned.retain(|&t| t != tile);
                            assigned.push(tile);
                        }
                    }
                }
                "tile_done" => {
                    if let Some((tile, _)) = parse(&event.detail, "by") {
                        let at = done_at.entry(tile).or_default();
                        *at = (*at).max(event.unix_ms);
                    }
                }
                "tile_lease_expired"
                    if first_lease_expired.is_none()
                        && parse(&event.detail, "on").is_some_and(|(_, name)| name == victim) =>
                {
                    first_lease_expired = Some(since(event.unix_ms));
                }
                _ => {}
            }
        }
        let held = &assigned[assigned.len().saturating_sub(in_flight)..];
        let taken_over = held
            .iter()
            .map(|t| done_at.get(t).copied())
            .collect::<Option<Vec<u64>>>()
            .and_then(|at| at.into_iter().max())
            .map(since);
        Timeline {
            first_lease_expired,
            taken_over,
            tiles_held: held.len(),
        }
    }
}

fn markdown(plan: Plan, results: &[Vec<Figures>]) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "## A worker whose render threads hang\n");
    let _ = writeln!(
        md,
        "`scenes/hall-of-mirrors.json` at {} × {}, aa {}, tiles of {} ({} tiles), on a \
         local farm of one-thread workers with the coordinator's default settings \
         (`--progress-timeout-ms` 20000); {:.0} s after the submission the render threads \
         of one worker are frozen (ptrace), its heartbeats going on, and stay frozen to \
         the job's end. Times in seconds from the freeze: the worker listed unresponsive \
         (polled every {} ms), the first of its leases run out and the last tile it held \
         done by another machine (the job's event log), the job `done`. Every image was \
         byte for byte `tessera render`'s. CPU: {}.\n",
        plan.width,
        plan.height,
        plan.aa,
        plan.tile,
        plan.tiles(),
        plan.freeze_after.as_secs_f64(),
        POLL.as_millis(),
        super::latency::cpu_model()
    );
    let _ = writeln!(
        md,
        "| case | run | tiles done at the freeze | tiles it held | first lease out | its \
         tiles done elsewhere | marked unresponsive | job done | submission to done |"
    );
    let _ = writeln!(md, "|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for (case, runs) in CASES.iter().zip(results) {
        for (i, f) in runs.iter().enumerate() {
            let _ = writeln!(
                md,
                "| {} | {} | {} | {} | {} | {} | {} | {:.1} | {:.1} |",
                case.name,
                i + 1,
                f.tiles_done_at_freeze,
                f.tiles_held,
                seconds(f.first_lease_expired),
                seconds(f.taken_over),
                seconds(f.marked),
                f.done,
                f.job
            );
        }
    }
    md
}

fn seconds(s: Option<f64>) -> String {
    s.map_or("—".to_owned(), |s| format!("{s:.1}"))
}

fn csv_seconds(s: Option<f64>) -> String {
    s.map_or(String::new(), |s| format!("{s:.3}"))
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}
