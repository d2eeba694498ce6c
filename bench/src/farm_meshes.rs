//! `tessera-bench --suite farm-meshes`: scenes with mesh files on a local farm, the
//! files' journey included.
//!
//! 1. Throughput: a 60-frame orbit of the bunny scene, and one 1920 × 1080 aa 4 frame
//!    of a generated mesh of a million triangles, on a fresh farm of two one-thread
//!    workers (what `tessera up` starts on two cores) against `tessera render
//!    --threads 2`, alternating, three runs each. The farm's time runs from the client
//!    reading the scene and hashing its files (what `tessera submit` does first) to the
//!    job's last frame stored, so the upload, the coordinator's check and the workers'
//!    fetches, parses and builds are in it; starting the farm is not. Every frame is
//!    checked byte for byte against the local one.
//! 2. Time to the first tile of a job on a mesh file of about 100 MB on four workers,
//!    against one worker's parse and build of it; then a second job on the same mesh,
//!    which must move no byte.
//! 3. Bytes on the wire per job with 1, 2 and 4 workers and three jobs on one mesh,
//!    from the coordinator's metrics: each file crosses to each worker at most once.
//!
//! The meshes of parts 1 (the million triangles) and 2 are the renderer suite's wavy
//! grids, written when the suite runs: nothing large is kept in the source tree.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};
use coordinator::client::{Client, LocalFile};
use protocol::FrameRange;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use transport::Endpoint;

use super::renderer::mesh::{grid_scene_json, time_tessera, write_grid_file};
use super::scenes::thousands;
use super::sequence::{
    self, check_frames, job_spec, load_average, median, run_local, secs_list, Size, Timeline,
    WORKERS,
};
use super::Options;
use localfarm::WorkerSpec;

/// The coordinator serves its metrics on a free loopback port.
const HTTP: [&str; 2] = ["--http", "127.0.0.1:0"];

/// How the workers of parts 2 and 3 keep the files they fetched.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Keep {
    /// As `tessera up` starts them: a file is kept while a scene naming it is.
    WhileNeeded,
    /// `--cache-dir`, one directory each, as an operator runs them.
    CacheDir,
}

impl Keep {
    fn label(self) -> &'static str {
        match self {
            Keep::WhileNeeded => "no cache directory (as `tessera up` starts them)",
            Keep::CacheDir => "`--cache-dir`, one each",
        }
    }

    /// `workers` one-thread workers kept this way, their caches under `dir`.
    fn specs(self, workers: usize, dir: &Path) -> Vec<WorkerSpec> {
        (0..workers)
            .map(|i| WorkerSpec {
                threads: 1,
                args: match self {
                    Keep::WhileNeeded => Vec::new(),
                    Keep::CacheDir => vec![
                        "--cache-dir".into(),
                        dir.join(format!("cache-{}", i + 1)).display().to_string(),
                    ],
                },
            })
            .collect()
    }
}

const KEEPS: [Keep; 2] = [Keep::WhileNeeded, Keep::CacheDir];

/// What one part measures, and at what size.
struct Plan {
    runs: u32,
    orbit_frames: u32,
    orbit_size: Size,
    /// Triangles of the mesh of the single-frame throughput job, and its frame.
    large_triangles: usize,
    large_size: Size,
    /// Triangles of the mesh of the first-tile part (about 19 bytes of PLY each), its
    /// workers, and its job's frame.
    huge_triangles: usize,
    huge_workers: usize,
    huge_size: Size,
    /// Farms of the bytes part, and the jobs on each.
    wire_workers: &'static [usize],
    wire_jobs: u32,
    wire_size: Size,
}

fn plan(quick: bool) -> Plan {
    let size = |width, height, aa| Size { width, height, aa };
    if quick {
        Plan {
            runs: 1,
            orbit_frames: 12,
            orbit_size: size(160, 90, 1),
            large_triangles: 100_000,
            large_size: size(320, 180, 1),
            huge_triangles: 300_000,
            huge_workers: 4,
            huge_size: size(320, 180, 1),
            wire_workers: &[1, 2],
            wire_jobs: 3,
            wire_size: size(320, 180, 1),
        }
    } else {
        Plan {
            runs: 3,
            orbit_frames: 60,
            orbit_size: size(640, 360, 2),
            large_triangles: 1_000_000,
            large_size: size(1920, 1080, 4),
            huge_triangles: 5_300_000,
            huge_workers: 4,
            huge_size: size(1280, 720, 1),
            wire_workers: &[1, 2, 4],
            wire_jobs: 3,
            wire_size: size(1280, 720, 1),
        }
    }
}

/// A scene file and what it shows.
struct SceneFile {
    path: PathBuf,
    /// Triangles over every mesh object, instances counted each time.
    triangles: u64,
    /// Bytes of the files it names.
    file_bytes: u64,
}

/// One job on a farm: when each step came, what crossed the network.
#[derive(Clone, Copy, Default)]
struct FarmRun {
    /// Seconds the client took to read the scene with its files and hash them.
    prep: f64,
    timeline: Timeline,
    /// Bytes the coordinator received from the client, and sent to workers, for it.
    received: f64,
    sent: f64,
    /// CPU seconds of the coordinator, and of the workers together, during it.
    cpu: (f64, f64),
    /// CPU seconds of the client (this process: reading and hashing, uploading,
    /// following the job).
    client_cpu: f64,
    /// When the last worker to fetch a file for it had it, from the workers' logs;
    /// `None` when none fetched any.
    fetched: Option<f64>,
}

/// The farm against `tessera render --threads 2` on one job.
struct Throughput {
    what: String,
    scene: SceneFile,
    size: Size,
    /// `None` for a single frame.
    frames: Option<u32>,
    local: Vec<f64>,
    /// CPU seconds of each local run (the `tessera render` process).
    local_cpu: Vec<f64>,
    farm: Vec<FarmRun>,
    local_command: String,
}

impl Throughput {
    fn farm_seconds(&self) -> Vec<f64> {
        self.farm.iter().map(|r| r.timeline.done).collect()
    }

    /// CPU seconds of each farm run: the client, the coordinator and the workers.
    fn farm_cpu(&self) -> Vec<f64> {
        self.farm
            .iter()
            .map(|r| r.client_cpu + r.cpu.0 + r.cpu.1)
            .collect()
    }

    /// Farm throughput over local throughput, of the medians.
    fn ratio(&self) -> f64 {
        median(&self.local) / median(&self.farm_seconds())
    }

    /// The lowest and highest ratio of a farm run to the local run beside it.
    fn ratio_range(&self) -> (f64, f64) {
        let ratios: Vec<f64> = self
            .local
            .iter()
            .zip(&self.farm)
            .map(|(l, f)| l / f.timeline.done)
            .collect();
        let low = ratios.iter().copied().fold(f64::INFINITY, f64::min);
        let high = ratios.iter().copied().fold(0.0, f64::max);
        (low, high)
    }
}

/// Part 2's figures.
struct FirstTile {
    scene: SceneFile,
    workers: usize,
    size: Size,
    /// One thread's parse (the scene and its mesh file) and build, best of two.
    parse: f64,
    build: f64,
    /// The two jobs, for each way of keeping files.
    jobs: Vec<(Keep, [FarmRun; 2])>,
}

/// Part 3's figures: for each farm, its jobs.
struct Wire {
    scene: SceneFile,
    size: Size,
    farms: Vec<(Keep, usize, Vec<FarmRun>)>,
}

/// Runs the suite and writes `farm-meshes.md`.
pub async fn run(opts: &Options, out: &Path) -> Result<()> {
    let load_before = load_average();
    let scenes = opts.mesh_scenes.as_deref().context(
        "the farm-meshes suite renders the bunny of the mesh scenes: give their directory \
         with --mesh-scenes DIR",
    )?;
    let plan = plan(opts.quick);
    let exe = &opts.tessera;
    let work = tempfile::Builder::new()
        .prefix("tessera-bench-farm-meshes-")
        .tempdir()
        .context("cannot create a temporary directory")?;
    let dir = work.path();

    let orbit = bunny_orbit(scenes, dir, plan.orbit_frames)?;
    let mut throughput = vec![
        compare(
            exe,
            &orbit,
            &format!("bunny orbit, {} frames", plan.orbit_frames),
            plan.orbit_size,
            Some(plan.orbit_frames),
            plan.runs,
            dir,
        )
        .await?,
    ];
    let large = grid_scene(dir, "large", plan.large_triangles)?;
    throughput.push(
        compare(
            exe,
            &large,
            "wavy grid, one frame",
            plan.large_size,
            None,
            plan.runs,
            dir,
        )
        .await?,
    );
    let load_mid = load_average();

    let huge = grid_scene(dir, "huge", plan.huge_triangles)?;
    let first_tile = first_tile(exe, huge, plan.huge_workers, plan.huge_size).await?;

    let bunny = bunny_scene(scenes, dir)?;
    let wire = wire(
        exe,
        bunny,
        plan.wire_workers,
        plan.wire_jobs,
        plan.wire_size,
    )
    .await?;

    let load = format!(
        "{load_before} at the start, {load_mid} after the throughput runs, {} at the end",
        load_average()
    );
    let md = markdown(opts, &throughput, &first_tile, &wire, &load);
    std::fs::write(out.join("farm-meshes.md"), &md)
        .with_context(|| format!("cannot write {}", out.join("farm-meshes.md").display()))?;
    eprintln!("{md}");
    Ok(())
}

/// The bunny scene, copied with its mesh into `dir`.
fn bunny_scene(scenes: &Path, dir: &Path) -> Result<SceneFile> {
    let ply = dir.join("bunny.ply");
    if !ply.exists() {
        std::fs::copy(scenes.join("bunny.ply"), &ply)
            .with_context(|| format!("cannot copy {}", scenes.join("bunny.ply").display()))?;
    }
    let path = dir.join("bunny.json");
    std::fs::copy(scenes.join("bunny.json"), &path)
        .with_context(|| format!("cannot copy {}", scenes.join("bunny.json").display()))?;
    scene_file(path)
}

/// The bunny scene with its camera going once round the bunny in `frames` frames (nine
/// keys an eighth of a turn apart, Catmull-Rom), as `bunny-orbit.json` in `dir`.
fn bunny_orbit(scenes: &Path, dir: &Path, frames: u32) -> Result<SceneFile> {
    let bunny = bunny_scene(scenes, dir)?;
    let text = std::fs::read_to_string(&bunny.path)
        .with_context(|| format!("cannot read {}", bunny.path.display()))?;
    let mut scene: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("{}: not JSON", bunny.path.display()))?;
    scene["animation"] = orbit_animation(frames);
    let path = dir.join("bunny-orbit.json");
    std::fs::write(&path, scene.to_string())
        .with_context(|| format!("cannot write {}", path.display()))?;
    scene_file(path)
}

/// The animation of [`bunny_orbit`]: the camera of `bunny.json` (at 1.0 1.2 -4.0,
/// looking at the bunny on the vertical axis) turned round that axis.
fn orbit_animation(frames: u32) -> serde_json::Value {
    let radius = 17f64.sqrt();
    let start = 1f64.atan2(-4.0);
    let keys: Vec<serde_json::Value> = (0..=8u32)
        .map(|k| {
            let angle = start + f64::from(k) * std::f64::consts::FRAC_PI_4;
            let frame = 1 + (k * (frames - 1) + 4) / 8;
            serde_json::json!({
                "frame": frame,
                "value": format!("{:.6} 1.2 {:.6}", radius * angle.sin(), radius * angle.cos()),
            })
        })
        .collect();
    serde_json::json!({
        "frames": frames,
        "fps": 24,
        "tracks": [{ "target": "camera.position", "interpolation": "catmull-rom", "keys": keys }]
    })
}

/// A wavy grid of about `triangles` triangles (`NAME.ply`) and its scene (`NAME.json`)
/// in `dir`.
fn grid_scene(dir: &Path, name: &str, triangles: usize) -> Result<SceneFile> {
    let ply = format!("{name}.ply");
    write_grid_file(&dir.join(&ply), triangles)?;
    let path = dir.join(format!("{name}.json"));
    std::fs::write(&path, grid_scene_json(&ply))
        .with_context(|| format!("cannot write {}", path.display()))?;
    scene_file(path)
}

fn scene_file(path: PathBuf) -> Result<SceneFile> {
    let (_, files, triangles) = read_with_files(&path)?;
    let file_bytes = files.iter().map(|f| f.asset.key.size).sum();
    Ok(SceneFile {
        path,
        triangles,
        file_bytes,
    })
}

/// The scene's text, the files it names, hashed, and its triangles: what `tessera
/// submit` reads before it sends anything (it parses the scene with its files beside
/// it, which reads and hashes each file once).
fn read_with_files(path: &Path) -> Result<(String, Vec<LocalFile>, u64)> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let files = render::MeshFiles::beside(dir);
    let scene = render::parse_animated_with(&text, &files)
        .map_err(|e| anyhow!("{}: {e}", path.display()))?;
    let triangles = scene
        .base
        .objects
        .iter()
        .filter_map(|o| match &o.shape {
            render::Shape::Mesh(mesh) => Some(mesh.file.geometry.data.triangles.len() as u64),
            _ => None,
        })
        .sum();
    let files = files
        .files_read()
        .into_iter()
        .map(|f| LocalFile {
            asset: protocol::AssetRef {
                name: f.name,
                key: protocol::AssetKey {
                    sha256: f.sha256,
                    size: f.size,
                },
            },
            path: f.path,
        })
        .collect();
    Ok((text, files, triangles))
}

/// The coordinator's counters of file bytes: received from clients, sent to workers.
#[derive(Clone, Copy)]
struct Traffic {
    received: f64,
    sent: f64,
}

impl Traffic {
    async fn scrape(http: &str) -> Result<Traffic> {
        let text = metrics(http).await?;
        let value = |name: &str| -> Result<f64> {
            text.lines()
                .find_map(|line| line.strip_prefix(name)?.strip_prefix(' '))
                .and_then(|v| v.trim().parse().ok())
                .with_context(|| format!("no {name} in the coordinator's metrics"))
        };
        Ok(Traffic {
            received: value("tessera_asset_received_bytes_total")?,
            sent: value("tessera_asset_sent_bytes_total")?,
        })
    }
}

/// `GET /metrics` from the coordinator's HTTP listener at `http`: the exposition.
async fn metrics(http: &str) -> Result<String> {
    let mut stream = tokio::net::TcpStream::connect(http)
        .await
        .with_context(|| format!("cannot connect to the coordinator's HTTP at {http}"))?;
    stream
        .write_all(format!("GET /metrics HTTP/1.0\r\nHost: {http}\r\n\r\n").as_bytes())
        .await
        .context("cannot ask for the coordinator's metrics")?;
    let mut answer = String::new();
    stream
        .read_to_string(&mut answer)
        .await
        .context("cannot read the coordinator's metrics")?;
    let (head, body) = answer
        .split_once("\r\n\r\n")
        .context("the coordinator's metrics: no HTTP answer")?;
    if !head.starts_with("HTTP/1.1 200") && !head.starts_with("HTTP/1.0 200") {
        bail!(
            "GET /metrics: {}",
            head.lines().next().unwrap_or("no status")
        );
    }
    Ok(body.to_owned())
}

/// CPU seconds so far of each of `pids`.
fn cpu(pids: &[u32]) -> Result<Vec<f64>> {
    pids.iter()
        .map(|&p| super::verification::cpu_seconds(p))
        .collect()
}

/// One job of `scene` on `farm` through `client`: timed from the client reading the
/// scene and its files; what crossed the network and the CPU it took.
async fn farm_job(
    farm: &localfarm::LocalFarm,
    client: &mut Client,
    scene: &Path,
    size: Size,
    frames: Option<u32>,
) -> Result<(protocol::JobId, FarmRun, protocol::JobStatus)> {
    let http = farm
        .http_address()
        .context("the local coordinator serves no HTTP")?;
    let pids = farm.pids();
    let traffic = Traffic::scrape(http).await?;
    let cpu_before = cpu(&pids)?;
    let client_before = super::verification::own_cpu_seconds()?;
    let since = time_of_day();
    let started = Instant::now();
    let (text, files, _) = read_with_files(scene)?;
    let prep = started.elapsed().as_secs_f64();
    let range = frames.map(|last| FrameRange { first: 1, last });
    let spec = job_spec(text, size, range);
    let (job, timeline, status) = sequence::follow(client, spec, &files, started).await?;
    let used: Vec<f64> = cpu(&pids)?
        .iter()
        .zip(&cpu_before)
        .map(|(a, b)| a - b)
        .collect();
    let client_cpu = super::verification::own_cpu_seconds()? - client_before;
    let after = Traffic::scrape(http).await?;
    let run = FarmRun {
        prep,
        timeline,
        received: after.received - traffic.received,
        sent: after.sent - traffic.sent,
        cpu: (used[0], used.iter().skip(1).sum()),
        client_cpu,
        fetched: last_fetch(farm, pids.len() - 1, since),
    };
    Ok((job, run, status))
}

/// Now, in seconds of the UTC day, as the daemons' log lines write it.
fn time_of_day() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
        % 86_400.0
}

/// The time of day (seconds, UTC) of a daemon's log line (`2026-11-28T11:06:52.335436Z
/// INFO ...`).
fn log_time_of_day(line: &str) -> Option<f64> {
    let stamp = line.split_whitespace().next()?;
    let (_, time) = stamp.split_once('T')?;
    let mut parts = time.strip_suffix('Z')?.split(':');
    let mut seconds = 0.0;
    for unit in [3600.0, 60.0, 1.0] {
        seconds += unit * parts.next()?.parse::<f64>().ok()?;
    }
    Some(seconds)
}

/// Seconds after `since` (a time of day) of the last `file fetched` in the logs of the
/// farm's `workers`: when the last of them had its files. Lines from before `since` (an
/// earlier job's) are not counted; a day's end between the two is.
fn last_fetch(farm: &localfarm::LocalFarm, workers: usize, since: f64) -> Option<f64> {
    let dir = farm.data_dir().parent()?.to_path_buf();
    (1..=workers)
        .filter_map(|i| std::fs::read_to_string(dir.join(format!("local-{i}.log"))).ok())
        .flat_map(|log| {
            log.lines()
                .filter(|l| l.contains("file fetched"))
                .filter_map(log_time_of_day)
                .collect::<Vec<_>>()
        })
        .map(|t| (t - since).rem_euclid(86_400.0))
        .filter(|&after| after < 43_200.0)
        .reduce(f64::max)
}

/// The farm against `tessera render --threads 2` on `scene` (a sequence of `frames`,
/// or its first frame), `runs` times each, alternating (local first, then farm first,
/// ...), a fresh farm for each run; the farm's frames checked against the first local
/// run's.
async fn compare(
    exe: &Path,
    scene: &SceneFile,
    what: &str,
    size: Size,
    frames: Option<u32>,
    runs: u32,
    work: &Path,
) -> Result<Throughput> {
    let reference = work.join(format!("reference-{}", size.width));
    let again = work.join(format!("again-{}", size.width));
    let out = |first: bool| match (first, frames) {
        (true, Some(_)) => reference.clone(),
        (true, None) => reference.with_extension("png"),
        (false, Some(_)) => again.clone(),
        (false, None) => again.with_extension("png"),
    };
    let mut result = Throughput {
        what: what.to_owned(),
        scene: scene_file(scene.path.clone())?,
        size,
        frames,
        local: Vec::new(),
        local_cpu: Vec::new(),
        farm: Vec::new(),
        local_command: String::new(),
    };
    for run in 0..runs {
        for farm_turn in [run % 2 == 1, run % 2 == 0] {
            if farm_turn {
                let farm = sequence::start_farm(exe, WORKERS, &HTTP).await?;
                let mut client = Client::connect(&Endpoint::plain(farm.address())).await?;
                let (job, timing, status) =
                    farm_job(&farm, &mut client, &scene.path, size, frames).await?;
                match frames {
                    Some(n) => check_frames(&mut client, job, &status, n, &out(true)).await?,
                    None => {
                        let png = client.fetch(job).await?;
                        let local = std::fs::read(out(true))
                            .with_context(|| format!("cannot read {}", out(true).display()))?;
                        if png != local {
                            bail!(
                                "the farm's image of {} differs from `tessera render`'s: the \
                                 benchmark would measure a wrong result",
                                scene.path.display()
                            );
                        }
                    }
                }
                drop(client);
                drop(farm);
                eprintln!(
                    "farm-meshes: {what}: farm run {}: {:.3} s (first tile {:.3} s)",
                    run + 1,
                    timing.timeline.done,
                    timing.timeline.first_tile
                );
                result.farm.push(timing);
            } else {
                let first = result.local.is_empty();
                let cpu_before = super::verification::children_cpu_seconds()?;
                let (seconds, shown) = run_local(exe, &scene.path, size, frames, &out(first))
                    .await
                    .with_context(|| format!("{what}: the local render"))?;
                result
                    .local_cpu
                    .push(super::verification::children_cpu_seconds()? - cpu_before);
                eprintln!("farm-meshes: {what}: local run {}: {seconds:.3} s", run + 1);
                result.local.push(seconds);
                result.local_command = shown;
            }
        }
    }
    Ok(result)
}

/// Part 2: one thread's parse and build of `scene`, then two jobs of it on a fresh
/// farm of `workers` one-thread workers.
async fn first_tile(exe: &Path, scene: SceneFile, workers: usize, size: Size) -> Result<FirstTile> {
    let dir = scene.path.parent().unwrap_or(Path::new("."));
    let (parse, build) = time_tessera(&scene.path, dir, 1, 2)?;
    eprintln!(
        "farm-meshes: {} triangles, {} bytes: parse {parse:.3} s, build {build:.3} s (1 thread)",
        thousands(scene.triangles),
        thousands(scene.file_bytes)
    );
    let mut jobs = Vec::new();
    for keep in KEEPS {
        let caches = tempfile::tempdir().context("cannot create a temporary directory")?;
        let farm = sequence::start_farm_of(exe, keep.specs(workers, caches.path()), &HTTP).await?;
        let mut client = Client::connect(&Endpoint::plain(farm.address())).await?;
        let (_, first, _) = farm_job(&farm, &mut client, &scene.path, size, None).await?;
        let (_, second, _) = farm_job(&farm, &mut client, &scene.path, size, None).await?;
        for (i, r) in [first, second].iter().enumerate() {
            eprintln!(
                "farm-meshes: first tile, {}, job {}: {:.3} s ({} bytes received, {} sent)",
                keep.label(),
                i + 1,
                r.timeline.first_tile,
                r.received,
                r.sent
            );
        }
        jobs.push((keep, [first, second]));
    }
    Ok(FirstTile {
        scene,
        workers,
        size,
        parse,
        build,
        jobs,
    })
}

/// Part 3: `jobs` jobs of `scene` one after another on fresh farms of each size.
async fn wire(
    exe: &Path,
    scene: SceneFile,
    farms: &[usize],
    jobs: u32,
    size: Size,
) -> Result<Wire> {
    let mut out = Vec::new();
    for keep in KEEPS {
        for &workers in farms {
            let caches = tempfile::tempdir().context("cannot create a temporary directory")?;
            let farm =
                sequence::start_farm_of(exe, keep.specs(workers, caches.path()), &HTTP).await?;
            let mut client = Client::connect(&Endpoint::plain(farm.address())).await?;
            let mut runs = Vec::new();
            for _ in 0..jobs {
                let (_, run, _) = farm_job(&farm, &mut client, &scene.path, size, None).await?;
                runs.push(run);
            }
            eprintln!(
                "farm-meshes: {}, {workers} worker(s): bytes sent per job {:?}",
                keep.label(),
                runs.iter().map(|r| r.sent).collect::<Vec<_>>()
            );
            out.push((keep, workers, runs));
        }
    }
    Ok(Wire {
        scene,
        size,
        farms: out,
    })
}

fn mib(bytes: f64) -> f64 {
    bytes / (1024.0 * 1024.0)
}

fn markdown(
    opts: &Options,
    throughput: &[Throughput],
    first: &FirstTile,
    wire: &Wire,
    load: &str,
) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "## Meshes on the farm\n");
    if opts.quick {
        let _ = writeln!(
            md,
            "**--quick: a check that the suite works; the figures mean nothing.**\n"
        );
    }
    let _ = writeln!(
        md,
        "Machine: {}. Load average (1, 5, 15 minutes): {load}.\n",
        super::latency::cpu_model()
    );
    let _ = writeln!(
        md,
        "### Throughput, files included\n\n\
         Farm: a fresh `tessera coordinator` (with `tessera up`'s limits) and {WORKERS} \
         `tessera worker --threads 1` on loopback for each run, started before the \
         timing. Its time runs from the client reading the scene and hashing its files to \
         the job's last frame stored: upload, the coordinator's check, the workers' \
         fetches, parses and builds included. Local: the whole `tessera render` process \
         with {WORKERS} threads, writing the PNGs. Runs alternate (local, farm, farm, \
         local, ...); every farm frame was fetched and checked byte for byte against the \
         local one.\n"
    );
    let _ = writeln!(
        md,
        "| job | triangles | file | frames | runs | farm (s) | local (s) | farm / local \
         throughput (medians) | range over paired runs |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for t in throughput {
        let (low, high) = t.ratio_range();
        let _ = writeln!(
            md,
            "| {}, {} | {} | {:.1} MiB | {} | {} | {:.3} | {:.3} | **{:.3}** | {:.3}–{:.3} |",
            t.what,
            t.size.label(),
            thousands(t.scene.triangles),
            mib(t.scene.file_bytes as f64),
            t.frames.unwrap_or(1),
            t.local.len(),
            median(&t.farm_seconds()),
            median(&t.local),
            t.ratio(),
            low,
            high
        );
    }
    let _ = writeln!(md);
    for t in throughput {
        let _ = writeln!(
            md,
            "- {}: each run (s): farm {}; local {}. Local command: `{}`.",
            t.what,
            secs_list(&t.farm_seconds()),
            secs_list(&t.local),
            t.local_command
        );
    }
    let _ = writeln!(
        md,
        "\nCPU seconds (user + system) of each run: the farm's client, coordinator and \
         workers together; the local process. On a machine shared with other work the \
         wall times measure the share of the cores each side got as much as its own \
         cost; the CPU times do not.\n"
    );
    let _ = writeln!(
        md,
        "| job | farm CPU (s) | local CPU (s) | local / farm CPU (medians) |\n\
         |---|---|---|---:|"
    );
    for t in throughput {
        let _ = writeln!(
            md,
            "| {} | {} | {} | **{:.3}** |",
            t.what,
            secs_list(&t.farm_cpu()),
            secs_list(&t.local_cpu),
            median(&t.local_cpu) / median(&t.farm_cpu())
        );
    }
    let _ = writeln!(
        md,
        "\nWhere the farm's time goes (medians over the runs, seconds from the client \
         starting; CPU seconds of the coordinator + the workers):\n"
    );
    let _ = writeln!(
        md,
        "| job | client reads and hashes | uploaded | submitted (checked) | last worker has \
         the file | first tile | done | CPU |\n|---|---:|---:|---:|---:|---:|---:|---:|"
    );
    for t in throughput {
        let m = |f: fn(&FarmRun) -> f64| median(&t.farm.iter().map(f).collect::<Vec<_>>());
        let _ = writeln!(
            md,
            "| {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.2} + {:.2} |",
            t.what,
            m(|r| r.prep),
            m(|r| r.timeline.uploaded),
            m(|r| r.timeline.submitted),
            m(|r| r.fetched.unwrap_or(f64::NAN)),
            m(|r| r.timeline.first_tile),
            m(|r| r.timeline.done),
            m(|r| r.cpu.0),
            m(|r| r.cpu.1)
        );
    }

    let f = first;
    let _ = writeln!(
        md,
        "\n### Time to the first tile of a large mesh\n\n\
         A wavy grid of {} triangles, {:.1} MiB of binary PLY, written when the suite \
         runs; a job of it at {} on a fresh farm of {} one-thread workers, then a second \
         job of the same scene, with workers of each kind. One worker's parse (the scene and its file, hashed) and \
         build, in one process on one thread, best of two: {:.3} s + {:.3} s = **{:.3} s**.\n",
        thousands(f.scene.triangles),
        mib(f.scene.file_bytes as f64),
        f.size.label(),
        f.workers,
        f.parse,
        f.build,
        f.parse + f.build
    );
    let _ = writeln!(
        md,
        "| workers keep files with | job | client reads and hashes (s) | uploaded (s) | \
         submitted (s) | last worker has the file (s) | first tile (s) | first tile / one worker's parse + build | done \
         (s) | CPU (s) | bytes received | bytes sent to workers |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for (keep, runs) in &f.jobs {
        for (i, r) in runs.iter().enumerate() {
            let _ = writeln!(
                md,
                "| {} | {} | {:.3} | {:.3} | {:.3} | {} | {:.3} | {:.2} | {:.3} | {:.2} + \
                 {:.2} | {} | {} |",
                keep.label(),
                i + 1,
                r.prep,
                r.timeline.uploaded,
                r.timeline.submitted,
                r.fetched
                    .map_or("none fetched".to_owned(), |t| format!("{t:.3}")),
                r.timeline.first_tile,
                r.timeline.first_tile / (f.parse + f.build),
                r.timeline.done,
                r.cpu.0,
                r.cpu.1,
                thousands(r.received as u64),
                thousands(r.sent as u64)
            );
        }
    }

    let w = wire;
    let size = w.scene.file_bytes as f64;
    let _ = writeln!(
        md,
        "\n### Bytes on the wire per job\n\n\
         The bunny scene ({} bytes of PLY) at {}, jobs one after another on a fresh farm \
         for each number of workers; the coordinator's `tessera_asset_received_bytes_total` \
         and `tessera_asset_sent_bytes_total` before and after each job. Sent / file = \
         how many workers fetched the file for that job.\n",
        thousands(w.scene.file_bytes),
        w.size.label()
    );
    let _ = writeln!(
        md,
        "| workers keep files with | workers | job | received from the client | sent to \
         workers | sent / file | total sent so far / file |\n|---|---:|---:|---:|---:|---:|---:|"
    );
    for (keep, workers, runs) in &w.farms {
        let mut total = 0.0;
        for (i, r) in runs.iter().enumerate() {
            total += r.sent;
            let _ = writeln!(
                md,
                "| {} | {workers} | {} | {} | {} | {:.2} | {:.2} |",
                keep.label(),
                i + 1,
                thousands(r.received as u64),
                thousands(r.sent as u64),
                r.sent / size,
                total / size
            );
        }
    }
    let _ = writeln!(md, "\nCommand: `tessera-bench --suite farm-meshes`.");
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_orbit_goes_round_once_from_the_scenes_camera() {
        let a = orbit_animation(60);
        let keys = a["tracks"][0]["keys"].as_array().unwrap();
        assert_eq!(keys.len(), 9);
        assert_eq!(keys[0]["frame"], 1);
        assert_eq!(keys[8]["frame"], 60);
        assert_eq!(keys[0]["value"], "1.000000 1.2 -4.000000");
        assert_eq!(keys[8]["value"], keys[0]["value"]);
    }

    #[test]
    fn a_log_lines_time_is_read_to_the_microsecond() {
        let line = "2026-11-28T11:06:52.335436Z  INFO worker::files: file fetched file=x";
        let t = log_time_of_day(line).unwrap();
        assert!((t - (11.0 * 3600.0 + 6.0 * 60.0 + 52.335436)).abs() < 1e-6);
        assert_eq!(log_time_of_day("not a log line"), None);
    }
}
