//! The farm's part of the scaling report: speed-up with 1 to N local workers, and the
//! pull scheduler against a static equal split when one worker is slow.

use std::fmt::Write as _;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use coordinator::client::Client;
use protocol::{JobSpec, JobState, Overrides};
use render::{render_tile, Rect, RenderSettings, Tracer};
use transport::Endpoint;

use super::measure;
use super::scenes::{self, BenchScene};
use super::Options;
use crate::plot::{Panel, Series};
use localfarm::{CpuLimit, LocalFarm, WorkerSpec};

/// The seed report's table 1: MPI processes, seconds, speed-up (600 × 400, aa 2, on a
/// 6-core, 12-thread machine, static split of the pixels).
pub const SEED_TABLE_1: [(u32, f64, f64); 5] = [
    (1, 4.24122, 1.0),
    (2, 2.52337, 1.681),
    (4, 1.35328, 3.135),
    (8, 1.29287, 3.514),
    (12, 0.943565, 4.420),
];

/// One farm size.
pub struct FarmPoint {
    pub workers: usize,
    pub seconds: f64,
}

/// Submits `bench` to the farm, waits for it, fetches it; returns the wall time from
/// submission to `done` and the PNG.
async fn run_job(
    farm: &LocalFarm,
    bench: &BenchScene,
    overrides: Overrides,
) -> Result<(f64, Vec<u8>)> {
    let mut client = Client::connect(&Endpoint::plain(farm.address())).await?;
    let started = Instant::now();
    let job = client
        .submit(JobSpec {
            scene: bench.json.clone(),
            overrides,
            priority: 0,
            verification: protocol::Verification::default(),
            time_limit_ms: None,
            name: "bench".into(),
            submitter: "tessera-bench".into(),
            frame: 1,
            frames: None,
            assets: Vec::new(),
            after: Vec::new(),
            require: Vec::new(),
        })
        .await?;
    let mut seen = 0;
    let status = loop {
        let status = client.watch(job, seen).await?;
        seen = status.tiles_done;
        match status.state {
            JobState::Done => break status,
            JobState::Failed | JobState::Cancelled => {
                bail!(
                    "benchmark job {job} ended {:?}: {:?}",
                    status.state,
                    status.error
                )
            }
            _ => {}
        }
    };
    let seconds = started.elapsed().as_secs_f64();
    let png = client.fetch(job).await?;
    let _ = status;
    Ok((seconds, png))
}

/// The job of the speed-up table: the seed scene, big enough to keep every worker busy.
fn speedup_job(opts: &Options) -> Overrides {
    let (width, height, aa) = if opts.quick {
        (300, 200, 1)
    } else {
        (1920, 1080, 3)
    };
    Overrides {
        width: Some(width),
        height: Some(height),
        aa: Some(aa),
        ..Overrides::default()
    }
}

/// Wall time of one job on farms of 1 to `max_workers` one-thread workers.
pub async fn speedup(opts: &Options, max_workers: usize) -> Result<Vec<FarmPoint>> {
    let bench = scenes::seed();
    let overrides = speedup_job(opts);
    let mut out = Vec::new();
    let mut first_png: Option<Vec<u8>> = None;
    for workers in 1..=max_workers {
        let specs = vec![WorkerSpec::default(); workers];
        let exe = opts.tessera.clone();
        let farm = tokio::task::spawn_blocking(move || LocalFarm::start(&exe, &specs))
            .await
            .context("starting a local farm")??;
        farm.wait_for_workers(workers, Duration::from_secs(20))
            .await?;
        // Best of two, like the local timings' best-of.
        let mut best = f64::INFINITY;
        for _ in 0..2 {
            let (seconds, png) = run_job(&farm, &bench, overrides).await?;
            best = best.min(seconds);
            match &first_png {
                None => first_png = Some(png),
                Some(first) if *first != png => {
                    bail!("the farm with {workers} workers gave a different image")
                }
                Some(_) => {}
            }
        }
        eprintln!("farm: {workers} worker(s): {:.3} s", best);
        out.push(FarmPoint {
            workers,
            seconds: best,
        });
    }
    Ok(out)
}

/// Markdown for the speed-up table, beside the seed's table 1.
pub fn speedup_markdown(points: &[FarmPoint], cores: usize, opts: &Options) -> String {
    let job = speedup_job(opts);
    let mut md = String::new();
    let _ = writeln!(
        md,
        "### Farm speed-up ({} one-thread workers on this {cores}-core machine; seed scene \
         {}×{}, aa {})\n",
        points.len(),
        job.width.unwrap_or(0),
        job.height.unwrap_or(0),
        job.aa.unwrap_or(0)
    );
    let _ = writeln!(
        md,
        "| workers | time (s) | speed-up | efficiency per worker | efficiency per core used | seed (MPI processes) | seed time (s) | seed speed-up | seed efficiency |\n|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    let base = points.first().map_or(1.0, |p| p.seconds);
    let rows = points.len().max(SEED_TABLE_1.len());
    for i in 0..rows {
        let ours = points.get(i).map_or_else(
            || "| | | | | |".to_owned(),
            |p| {
                let s = base / p.seconds;
                format!(
                    "| {} | {:.3} | {:.2} | {:.0}% | {:.0}% |",
                    p.workers,
                    p.seconds,
                    s,
                    100.0 * s / p.workers as f64,
                    100.0 * s / p.workers.min(cores) as f64
                )
            },
        );
        let seed = SEED_TABLE_1.get(i).map_or_else(
            || " | | | |".to_owned(),
            |&(n, t, s)| {
                format!(
                    " {n} | {t:.3} | {s:.2} | {:.0}% |",
                    100.0 * s / f64::from(n)
                )
            },
        );
        let _ = writeln!(md, "{ours}{seed}");
    }
    md
}

/// A scene whose cost sits in one region: a cluster of mirror spheres in the top half of
/// the frame, a plain floor below.
pub fn concentrated() -> BenchScene {
    let mut objects = vec![serde_json::json!({
        "type": "plane", "normal": [0, 1, 0], "distance": -2.0, "color": [0.5, 0.5, 0.5, 0]
    })];
    for i in 0..5 {
        for j in 0..4 {
            objects.push(serde_json::json!({
                "type": "sphere",
                "center": [-2.0 + f64::from(i), 1.2 + 0.8 * f64::from(j), 3.0 + 0.3 * f64::from(i + j)],
                "radius": 0.45,
                "color": [0.8, 0.8, 0.9, 0.9]
            }));
        }
    }
    let scene = serde_json::json!({
        "camera": { "position": [0, 0.5, -6], "look_at": [0, 0.5, 0] },
        "image": { "width": 600, "height": 400, "aa": 1, "max_depth": 20 },
        "lights": [
            { "position": [-5, 9, -6], "color": [1, 1, 1] },
            { "position": [6, 4, -3], "color": [0.5, 0.5, 0.5] }
        ],
        "objects": objects
    });
    BenchScene {
        name: "concentrated",
        what: "20 mirror spheres in the top half, a plain floor below".into(),
        json: scene.to_string(),
    }
}

/// The pull scheduler against a static split.
pub struct SplitResult {
    /// How many times slower the slow worker is: its process has 1/`slowdown` of a core.
    pub slowdown: f64,
    pub pull_seconds: f64,
    /// Seconds each half of the frame takes on one thread at full speed (top, bottom).
    pub band_seconds: [f64; 2],
}

impl SplitResult {
    /// The static split's makespan when the slow worker gets the `slow_band`.
    pub fn static_seconds(&self, slow_band: usize) -> f64 {
        let [top, bottom] = self.band_seconds;
        let (slow, fast) = if slow_band == 0 {
            (top, bottom)
        } else {
            (bottom, top)
        };
        (slow * self.slowdown).max(fast)
    }
}

/// Two one-thread workers, one slowed `slowdown` times (its process limited to
/// 1/`slowdown` of a core by a cgroup, so this needs root): the real farm's makespan,
/// and that of the seed's static split (the frame cut into two equal bands of rows, one
/// per process), computed from each band's measured time.
pub async fn split(opts: &Options, slowdown: f64) -> Result<SplitResult> {
    let bench = concentrated();
    let scene = render::parse_scene(&bench.json).context("the concentrated scene")?;
    let (width, height, aa) = if opts.quick {
        (200, 150, 1)
    } else {
        (1200, 800, 2)
    };
    let settings = RenderSettings {
        width,
        height,
        aa,
        ..scene.settings
    };
    let pool = measure::pool(1)?;
    let tracer = Tracer::new(&scene, settings);
    let half = height / 2;
    let bands = [
        Rect {
            x: 0,
            y: 0,
            width,
            height: half,
        },
        Rect {
            x: 0,
            y: half,
            width,
            height: height - half,
        },
    ];
    let mut band_seconds = [0.0; 2];
    for (band, rect) in bands.iter().enumerate() {
        let started = Instant::now();
        pool.install(|| render_tile(&tracer, *rect))
            .context("a band of the frame")?;
        band_seconds[band] = started.elapsed().as_secs_f64();
    }
    let specs = vec![WorkerSpec::default(); 2];
    let exe = opts.tessera.clone();
    let farm = tokio::task::spawn_blocking(move || LocalFarm::start(&exe, &specs))
        .await
        .context("starting a local farm")??;
    // The second worker stands for a slower machine: the kernel gives its process a
    // share of one core, as an operator would limit it (this takes root). Declared
    // after the farm, so the limit goes first.
    let slow_pid = farm.pids()[2];
    let _slow = CpuLimit::apply(slow_pid, 1.0 / slowdown)
        .context("slowing a worker for the static split")?;
    farm.wait_for_workers(2, Duration::from_secs(20)).await?;
    let overrides = Overrides {
        width: Some(width),
        height: Some(height),
        aa: Some(aa),
        ..Overrides::default()
    };
    let (pull_seconds, _) = run_job(&farm, &bench, overrides).await?;
    eprintln!(
        "split: pull {:.3} s; bands {:.3} s and {:.3} s",
        pull_seconds, band_seconds[0], band_seconds[1]
    );
    Ok(SplitResult {
        slowdown,
        pull_seconds,
        band_seconds,
    })
}

/// Markdown for the split comparison.
pub fn split_markdown(r: &SplitResult) -> String {
    let fast = r.static_seconds(1);
    let slow = r.static_seconds(0);
    format!(
        "### Pull scheduler against a static split\n\n\
         Scene `concentrated` (20 mirror spheres in the top half, a floor below); two \
         one-thread workers, one slowed {:.0}× (a cgroup gives its process 1/{:.0} of a \
         core). \
         One thread renders the top half in {:.3} s and the bottom half in {:.3} s.\n\n\
         | split | makespan (s) | vs pull |\n|---|---:|---:|\n\
         | pull (Tessera's scheduler, measured on the farm) | {:.3} | 1.00 |\n\
         | static, equal bands, slow worker on the cheap half | {:.3} | {:.2} |\n\
         | static, equal bands, slow worker on the costly half | {:.3} | {:.2} |\n",
        r.slowdown,
        r.slowdown,
        r.band_seconds[0],
        r.band_seconds[1],
        r.pull_seconds,
        fast,
        fast / r.pull_seconds,
        slow,
        slow / r.pull_seconds
    )
}

/// Speed-up against workers, ours and the seed's, with the ideal line.
pub fn speedup_panel(points: &[FarmPoint]) -> Panel {
    let base = points.first().map_or(1.0, |p| p.seconds);
    let most = points.len().max(12) as f64;
    Panel {
        title: "Speed-up against workers / processes".into(),
        x_label: "workers (Tessera) or MPI processes (seed)".into(),
        y_label: "speed-up".into(),
        log_x: false,
        log_y: false,
        series: vec![
            Series {
                label: "Tessera, this machine".into(),
                points: points
                    .iter()
                    .map(|p| (p.workers as f64, base / p.seconds))
                    .collect(),
                joined: true,
                markers: true,
            },
            Series {
                label: "seed, table 1 (12 threads)".into(),
                points: SEED_TABLE_1
                    .iter()
                    .map(|&(n, _, s)| (f64::from(n), s))
                    .collect(),
                joined: true,
                markers: true,
            },
            Series {
                label: "ideal".into(),
                points: vec![(1.0, 1.0), (most, most)],
                joined: true,
                markers: false,
            },
        ],
    }
}
