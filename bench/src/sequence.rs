//! `tessera-bench --suite sequence`: what a sequence job costs on the farm.
//!
//! 1. Throughput: an orbit of the seed scene on a local farm of two one-thread workers
//!    against `tessera render --frames` with two threads, alternated, medians; the
//!    farm's frames must be byte-identical to the local ones.
//! 2. Per-frame overhead: the same comparison on frames so small that rendering them
//!    costs next to nothing, and the difference per frame on the big frames.
//! 3. Memory: the coordinator's and the workers' peak resident memory (and the
//!    coordinator's data directory) for a long sequence of tiny frames against a short
//!    one, so that the growth per frame shows.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use coordinator::client::{Client, LocalFile};
use protocol::{FrameRange, JobId, JobSpec, JobState, JobStatus, Overrides};
use transport::Endpoint;

use super::Options;
use localfarm::{LocalFarm, WorkerSpec};

/// The orbit every part renders, rescaled to other frame counts.
const ORBIT: &str = include_str!("../../scenes/seed-orbit.json");

/// Worker processes of the farm, one rendering thread each; the local render gets as
/// many threads.
pub(crate) const WORKERS: usize = 2;

/// Image size and sampling of one part.
#[derive(Clone, Copy)]
pub(crate) struct Size {
    pub width: u32,
    pub height: u32,
    pub aa: u32,
}

impl Size {
    pub(crate) fn overrides(self) -> Overrides {
        Overrides {
            width: Some(self.width),
            height: Some(self.height),
            aa: Some(self.aa),
            ..Overrides::default()
        }
    }

    pub(crate) fn label(self) -> String {
        format!("{}×{} aa {}", self.width, self.height, self.aa)
    }
}

/// The farm against the local render on one sequence.
struct Comparison {
    size: Size,
    frames: u32,
    runs: u32,
    /// Seconds of each run, in the order they ran.
    farm: Vec<f64>,
    local: Vec<f64>,
    local_command: String,
    /// CPU seconds of the coordinator and of the workers together in each farm run.
    farm_cpu: Vec<(f64, f64)>,
}

impl Comparison {
    fn farm_median(&self) -> f64 {
        median(&self.farm)
    }

    fn local_median(&self) -> f64 {
        median(&self.local)
    }

    /// Farm throughput over local throughput.
    fn ratio(&self) -> f64 {
        self.local_median() / self.farm_median()
    }

    /// Milliseconds per frame the farm takes more than the local render.
    fn overhead_ms(&self) -> f64 {
        1000.0 * (self.farm_median() - self.local_median()) / f64::from(self.frames)
    }
}

/// One long run's memory.
struct Memory {
    frames: u32,
    seconds: f64,
    /// Resident memory just before the job was submitted, coordinator then workers.
    idle_kib: Vec<u64>,
    /// Peak resident memory over the farm's life (VmHWM), same order.
    peak_kib: Vec<u64>,
    /// The largest VmRSS seen while sampling every 20 ms, same order.
    sampled_kib: Vec<u64>,
    /// Bytes in the coordinator's data directory once the job is done.
    data_bytes: u64,
    data_files: u64,
}

/// Runs the suite and writes `sequence.md`.
pub async fn run(opts: &Options, out: &Path) -> Result<()> {
    let load_before = load_average();
    let exe = &opts.tessera;
    let work = tempfile::Builder::new()
        .prefix("tessera-bench-sequence-")
        .tempdir()
        .context("cannot create a temporary directory")?;
    let scene_path = work.path().join("seed-orbit.json");
    std::fs::write(&scene_path, ORBIT)?;

    let (big, tiny, frames, runs, memory_frames) = if opts.quick {
        (
            Size {
                width: 160,
                height: 90,
                aa: 1,
            },
            Size {
                width: 64,
                height: 36,
                aa: 1,
            },
            12,
            1,
            [20, 300],
        )
    } else {
        (
            Size {
                width: 640,
                height: 360,
                aa: 2,
            },
            Size {
                width: 64,
                height: 36,
                aa: 1,
            },
            120,
            3,
            [100, 10_000],
        )
    };

    let throughput = compare(exe, &scene_path, work.path(), big, frames, runs).await?;
    let overhead = compare(exe, &scene_path, work.path(), tiny, frames, runs).await?;

    let memory_size = Size {
        width: 32,
        height: 18,
        aa: 1,
    };
    let mut memory = Vec::new();
    for n in memory_frames {
        memory.push(measure_memory(exe, n, memory_size).await?);
    }

    let load = format!("{load_before} at the start, {} at the end", load_average());
    let md = markdown(opts, &throughput, &overhead, &memory, memory_size, &load);
    std::fs::write(out.join("sequence.md"), &md)?;
    eprintln!("{}", summary(&throughput, &overhead, &memory));
    Ok(())
}

/// A local farm of `workers` one-thread workers, with `tessera up`'s limits and
/// `extra` arguments for the coordinator (`--http 127.0.0.1:0` for its metrics).
pub(crate) async fn start_farm(exe: &Path, workers: usize, extra: &[&str]) -> Result<LocalFarm> {
    start_farm_of(exe, vec![WorkerSpec::default(); workers], extra).await
}

/// [`start_farm`] with workers of these `specs`.
pub(crate) async fn start_farm_of(
    exe: &Path,
    specs: Vec<WorkerSpec>,
    extra: &[&str],
) -> Result<LocalFarm> {
    let workers = specs.len();
    let exe = exe.to_path_buf();
    let extra: Vec<String> = extra.iter().map(|&a| a.to_owned()).collect();
    let farm = tokio::task::spawn_blocking(move || {
        let mut args = localfarm::up_limits();
        args.extend(extra);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        LocalFarm::start_with(&exe, &specs, &args)
    })
    .await
    .context("starting a local farm")??;
    farm.wait_for_workers(workers, Duration::from_secs(20))
        .await?;
    Ok(farm)
}

/// The seed orbit with `frames` frames, its key frames spread over them in proportion.
fn orbit(frames: u32) -> Result<String> {
    let mut scene: serde_json::Value = serde_json::from_str(ORBIT)?;
    let animation = scene
        .get_mut("animation")
        .context("the orbit has no animation")?;
    let old = animation["frames"]
        .as_u64()
        .context("the orbit's frame count")?;
    animation["frames"] = frames.into();
    let tracks = animation["tracks"]
        .as_array_mut()
        .context("the orbit's tracks")?;
    for track in tracks {
        let keys = track["keys"].as_array_mut().context("a track's keys")?;
        for key in keys {
            let k = key["frame"].as_u64().context("a key's frame")?;
            let scaled = 1 + ((k - 1) * (u64::from(frames) - 1) + (old - 1) / 2) / (old - 1);
            key["frame"] = scaled.into();
        }
    }
    Ok(scene.to_string())
}

/// Submits frames 1 to `frames` of `scene` (which names `files`) as one sequence job
/// and waits for it; returns the job, when each step came (see [`Timeline`]) and its
/// final status.
pub(crate) async fn run_sequence(
    client: &mut Client,
    scene: String,
    files: &[LocalFile],
    size: Size,
    frames: u32,
) -> Result<(JobId, Timeline, JobStatus)> {
    let spec = job_spec(
        scene,
        size,
        Some(FrameRange {
            first: 1,
            last: frames,
        }),
    );
    let (job, timeline, status) = follow(client, spec, files, Instant::now()).await?;
    match &status.frames {
        Some(f) if f.done == frames => {}
        other => bail!("benchmark sequence {job} is done but its frames are {other:?}"),
    }
    Ok((job, timeline, status))
}

/// The benchmark's job of `scene` at `size`: one frame, or a sequence of `frames`.
pub(crate) fn job_spec(scene: String, size: Size, frames: Option<FrameRange>) -> JobSpec {
    JobSpec {
        scene,
        overrides: size.overrides(),
        priority: 0,
        verification: protocol::Verification::default(),
        time_limit_ms: None,
        name: "bench".into(),
        submitter: "tessera-bench".into(),
        frame: 1,
        frames,
        assets: Vec::new(),
        after: Vec::new(),
        require: Vec::new(),
    }
}

/// When each step of a job came, in seconds from `started` (given by the caller, so
/// that what the client does before it submits can count too).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Timeline {
    /// The files the coordinator lacked uploaded (at once when it lacked none).
    pub uploaded: f64,
    /// The job accepted: the coordinator has checked the scene, read with its files.
    pub submitted: f64,
    /// The coordinator has the job's first tile.
    pub first_tile: f64,
    /// The job is done: every frame stored.
    pub done: f64,
}

/// Uploads what the coordinator lacks of `files`, submits `spec` naming them, and
/// follows the job to its end, which must be `done`.
pub(crate) async fn follow(
    client: &mut Client,
    spec: JobSpec,
    files: &[LocalFile],
    started: Instant,
) -> Result<(JobId, Timeline, JobStatus)> {
    let mut timeline = Timeline::default();
    if !files.is_empty() {
        // The upload apart from the submission, which then finds nothing lacking
        // (`submit_with_files` uploads what it still lacks): the coordinator's check of
        // the scene is timed on its own.
        let keys = files.iter().map(|f| f.asset.key).collect();
        for lacking in client.lacking(keys).await? {
            if let Some(file) = files.iter().find(|f| f.asset.key == lacking.key) {
                client.upload(file, lacking.received).await?;
            }
        }
    }
    timeline.uploaded = started.elapsed().as_secs_f64();
    let job = client.submit_with_files(spec, files).await?;
    timeline.submitted = started.elapsed().as_secs_f64();
    let mut seen = 0;
    let status = loop {
        let status = client.watch(job, seen).await?;
        if seen == 0 && status.tiles_done > 0 {
            timeline.first_tile = started.elapsed().as_secs_f64();
        }
        seen = status.tiles_done;
        if status.state.is_final() {
            break status;
        }
    };
    timeline.done = started.elapsed().as_secs_f64();
    if status.state != JobState::Done {
        bail!(
            "benchmark job {job} ended {:?}: {:?}",
            status.state,
            status.error
        );
    }
    if timeline.first_tile == 0.0 {
        timeline.first_tile = timeline.done;
    }
    Ok((job, timeline, status))
}

/// `tessera render SCENE --frames 1-N --threads 2 -o DIR` with the size (without
/// `frames`, the scene's first frame to the PNG `out`): its wall time, and the command
/// as the report shows it.
pub(crate) async fn run_local(
    exe: &Path,
    scene: &Path,
    size: Size,
    frames: Option<u32>,
    out: &Path,
) -> Result<(f64, String)> {
    if frames.is_some() {
        let _ = std::fs::remove_dir_all(out);
    }
    let mut args: Vec<String> = vec!["render".into(), scene.display().to_string()];
    if let Some(frames) = frames {
        args.extend(["--frames".into(), format!("1-{frames}")]);
    }
    args.extend([
        "--width".into(),
        size.width.to_string(),
        "--height".into(),
        size.height.to_string(),
        "--aa".into(),
        size.aa.to_string(),
        "--threads".into(),
        WORKERS.to_string(),
        "-o".into(),
        out.display().to_string(),
    ]);
    let mut command = tokio::process::Command::new(exe);
    for key in localfarm::tessera_variables() {
        command.env_remove(key);
    }
    command
        .args(&args)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped());
    let started = Instant::now();
    let output = command
        .output()
        .await
        .with_context(|| format!("cannot start {}", exe.display()))?;
    let seconds = started.elapsed().as_secs_f64();
    if !output.status.success() {
        bail!(
            "tessera {} failed ({}): {}",
            args.join(" "),
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        );
    }
    let name = scene.file_name().map_or_else(
        || scene.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    let shown = format!(
        "tessera render {name}{} --width {} --height {} --aa {} --threads {WORKERS} -o {}",
        frames.map_or_else(String::new, |n| format!(" --frames 1-{n}")),
        size.width,
        size.height,
        size.aa,
        if frames.is_some() { "DIR" } else { "OUT.png" }
    );
    Ok((seconds, shown))
}

/// Fetches every frame of a done sequence and checks it byte for byte against the
/// local render's file.
pub(crate) async fn check_frames(
    client: &mut Client,
    job: JobId,
    status: &JobStatus,
    frames: u32,
    local: &Path,
) -> Result<()> {
    let scene_frames = status.frames.as_ref().map_or(frames, |f| f.scene_frames);
    for k in 1..=frames {
        let png = client.fetch_frame(job, k).await?;
        let path = local.join(render::frame_file_name(u64::from(k), scene_frames));
        let expected =
            std::fs::read(&path).with_context(|| format!("cannot read {}", path.display()))?;
        if png != expected {
            bail!(
                "frame {k} of the farm's sequence {job} differs from `tessera render`'s {} \
                 ({} bytes against {}): the benchmark would measure a wrong result",
                path.display(),
                png.len(),
                expected.len()
            );
        }
    }
    Ok(())
}

/// The farm against the local render on frames 1 to `frames` of the orbit at `size`,
/// `runs` times each, alternating (local first, then farm first, ...).
async fn compare(
    exe: &Path,
    scene: &Path,
    work: &Path,
    size: Size,
    frames: u32,
    runs: u32,
) -> Result<Comparison> {
    let local_dir = work.join(format!("local-{}x{}", size.width, size.height));
    let mut result = Comparison {
        size,
        frames,
        runs,
        farm: Vec::new(),
        local: Vec::new(),
        local_command: String::new(),
        farm_cpu: Vec::new(),
    };
    // The first local run gives the reference frames; the farm is checked against them.
    let mut checked_against: Option<PathBuf> = None;
    for run in 0..runs {
        for farm_turn in [run % 2 == 1, run % 2 == 0] {
            if farm_turn {
                // A fresh farm each time: every run starts from the same state (an
                // empty data directory, nothing being deleted behind it).
                let farm = start_farm(exe, WORKERS, &[]).await?;
                let mut client = Client::connect(&Endpoint::plain(farm.address())).await?;
                let pids = farm.pids();
                let cpu = |pids: &[u32]| -> Result<Vec<f64>> {
                    pids.iter()
                        .map(|&p| super::verification::cpu_seconds(p))
                        .collect()
                };
                let before = cpu(&pids)?;
                let (job, timeline, status) =
                    run_sequence(&mut client, ORBIT.to_owned(), &[], size, frames).await?;
                let seconds = timeline.done;
                let used: Vec<f64> = cpu(&pids)?
                    .iter()
                    .zip(&before)
                    .map(|(a, b)| a - b)
                    .collect();
                result
                    .farm_cpu
                    .push((used[0], used.iter().skip(1).sum::<f64>()));
                let reference = checked_against
                    .as_deref()
                    .context("the local frames come first")?;
                check_frames(&mut client, job, &status, frames, reference).await?;
                drop(client);
                drop(farm);
                eprintln!(
                    "sequence {}: farm run {}: {seconds:.3} s",
                    size.label(),
                    run + 1
                );
                result.farm.push(seconds);
            } else {
                let dir = if checked_against.is_none() {
                    local_dir.clone()
                } else {
                    work.join("local-again")
                };
                let (seconds, shown) = run_local(exe, scene, size, Some(frames), &dir).await?;
                if checked_against.is_none() {
                    checked_against = Some(dir);
                }
                eprintln!(
                    "sequence {}: local run {}: {seconds:.3} s",
                    size.label(),
                    run + 1
                );
                result.local.push(seconds);
                result.local_command = shown;
            }
        }
    }
    Ok(result)
}

/// A field of /proc/PID/status in KiB (VmRSS, VmHWM).
fn proc_kib(pid: u32, field: &str) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    text.lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// Bytes and files under `dir`.
fn dir_size(dir: &Path) -> (u64, u64) {
    let mut bytes = 0;
    let mut files = 0;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for entry in entries.flatten() {
            let Ok(meta) = entry.metadata() else {
                continue;
            };
            if meta.is_dir() {
                stack.push(entry.path());
            } else {
                bytes += meta.len();
                files += 1;
            }
        }
    }
    (bytes, files)
}

/// A fresh farm renders a sequence of `frames` tiny frames; its processes' memory.
async fn measure_memory(exe: &Path, frames: u32, size: Size) -> Result<Memory> {
    let farm = start_farm(exe, WORKERS, &[]).await?;
    let pids = farm.pids();
    let idle_kib: Vec<u64> = pids
        .iter()
        .map(|&p| proc_kib(p, "VmRSS").unwrap_or(0))
        .collect();
    let sampled = Arc::new(Mutex::new(idle_kib.clone()));
    let stop = Arc::new(AtomicBool::new(false));
    let sampler = {
        let sampled = Arc::clone(&sampled);
        let stop = Arc::clone(&stop);
        let pids = pids.clone();
        tokio::spawn(async move {
            while !stop.load(Ordering::Relaxed) {
                {
                    let mut max = sampled.lock().expect("sample lock");
                    for (m, &p) in max.iter_mut().zip(&pids) {
                        *m = (*m).max(proc_kib(p, "VmRSS").unwrap_or(0));
                    }
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
    };
    let mut client = Client::connect(&Endpoint::plain(farm.address())).await?;
    let (_, timeline, _) = run_sequence(&mut client, orbit(frames)?, &[], size, frames).await?;
    let seconds = timeline.done;
    stop.store(true, Ordering::Relaxed);
    sampler.await.context("the memory sampler")?;
    let peak_kib = pids
        .iter()
        .map(|&p| proc_kib(p, "VmHWM").unwrap_or(0))
        .collect();
    let sampled_kib = sampled.lock().expect("sample lock").clone();
    let (data_bytes, data_files) = dir_size(&farm.data_dir());
    eprintln!(
        "sequence memory: {frames} frames in {seconds:.1} s; coordinator peak {} KiB",
        proc_kib(pids[0], "VmHWM").unwrap_or(0)
    );
    drop(farm);
    Ok(Memory {
        frames,
        seconds,
        idle_kib,
        peak_kib,
        sampled_kib,
        data_bytes,
        data_files,
    })
}

/// The machine's load averages over 1, 5 and 15 minutes, from /proc/loadavg.
pub(crate) fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|text| {
            text.split_whitespace()
                .take(3)
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_else(|_| "unknown".into())
}

pub(crate) fn median(xs: &[f64]) -> f64 {
    let mut v = xs.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => (v[n / 2 - 1] + v[n / 2]) / 2.0,
    }
}

pub(crate) fn secs_list(xs: &[f64]) -> String {
    xs.iter()
        .map(|s| format!("{s:.2}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn cpu_list(xs: &[(f64, f64)]) -> String {
    xs.iter()
        .map(|(c, w)| format!("{c:.2} + {w:.2}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn mib(kib: u64) -> f64 {
    kib as f64 / 1024.0
}

/// The largest of the workers' figures (index 1 on).
fn worker_max(v: &[u64]) -> u64 {
    v.iter().skip(1).copied().max().unwrap_or(0)
}

fn markdown(
    opts: &Options,
    throughput: &Comparison,
    overhead: &Comparison,
    memory: &[Memory],
    memory_size: Size,
    load: &str,
) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "## Sequence jobs\n");
    if opts.quick {
        let _ = writeln!(
            md,
            "**--quick: a check that the suite works; the figures mean nothing.**\n"
        );
    }
    let _ = writeln!(
        md,
        "Machine: {}. Farm: `tessera coordinator` and {WORKERS} `tessera worker --threads 1` \
         on loopback (a local farm as `tessera up` starts it, a fresh one for each run, \
         started before the timing); time from submission to the sequence job's `done`. Local: the whole \
         `tessera render --frames` process with {WORKERS} threads, writing the PNGs. Runs \
         alternate (local, farm, farm, local, ...); medians. Every farm frame was fetched \
         and checked byte for byte against the local render's file. Load average (1, 5, \
         15 minutes): {load}.\n",
        super::latency::cpu_model()
    );
    let _ = writeln!(
        md,
        "| sequence | frames | runs | farm (s) | local (s) | farm frames/s | local frames/s | \
         farm / local throughput | farm − local per frame (ms) |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for (what, c) in [("orbit", throughput), ("tiny frames", overhead)] {
        let _ = writeln!(
            md,
            "| {what}, {} | {} | {} | {:.3} | {:.3} | {:.2} | {:.2} | {:.3} | {:.2} |",
            c.size.label(),
            c.frames,
            c.runs,
            c.farm_median(),
            c.local_median(),
            f64::from(c.frames) / c.farm_median(),
            f64::from(c.frames) / c.local_median(),
            c.ratio(),
            c.overhead_ms()
        );
    }
    let _ = writeln!(
        md,
        "\nEach run (s): orbit farm {}; local {}. Tiny farm {}; local {}.\n",
        secs_list(&throughput.farm),
        secs_list(&throughput.local),
        secs_list(&overhead.farm),
        secs_list(&overhead.local)
    );
    let _ = writeln!(
        md,
        "CPU of each farm run (s, coordinator + workers, from /proc/PID/stat): orbit {}; \
         tiny {}. The workers could use {WORKERS} × the wall time.\n",
        cpu_list(&throughput.farm_cpu),
        cpu_list(&overhead.farm_cpu)
    );
    let _ = writeln!(
        md,
        "Goal: farm / local throughput ≥ 0.90 on the orbit: **{:.3}** ({}).\n",
        throughput.ratio(),
        if throughput.ratio() >= 0.90 {
            "met"
        } else {
            "not met"
        }
    );
    let _ = writeln!(
        md,
        "Per-frame overhead of the farm: **{:.2} ms** per frame on tiny frames (rendering \
         negligible: the farm's cost per frame, less the local command's), **{:.2} ms** per \
         frame on the orbit's frames.\n",
        overhead.overhead_ms(),
        throughput.overhead_ms()
    );
    let _ = writeln!(md, "Commands:\n");
    let _ = writeln!(
        md,
        "- local: `{}` (and the same at {})",
        throughput.local_command,
        overhead.size.label()
    );
    let _ = writeln!(
        md,
        "- farm: a `JobSpec` with `frames: 1-{}` and the same overrides through \
         `coordinator::client::Client`, as `tessera submit seed-orbit.json --frames 1-{}` \
         sends it\n",
        throughput.frames, throughput.frames
    );

    let _ = writeln!(
        md,
        "### Memory of a long sequence\n\n\
         The orbit stretched to N frames (its key frames spread in proportion), {}, on a \
         fresh farm for each N. Resident memory in MiB: idle = VmRSS before submitting; \
         peak = VmHWM once the job is done (sampled = the largest VmRSS seen every 20 ms); \
         worker = the larger of the two. Data = the coordinator's data directory once the \
         job is done.\n",
        memory_size.label()
    );
    let _ = writeln!(
        md,
        "| frames | time (s) | frames/s | coordinator idle | coordinator peak | coordinator \
         sampled | worker idle | worker peak | worker sampled | data (MiB) | data files |\n\
         |---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for m in memory {
        let _ = writeln!(
            md,
            "| {} | {:.1} | {:.0} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} | {} |",
            m.frames,
            m.seconds,
            f64::from(m.frames) / m.seconds,
            mib(m.idle_kib[0]),
            mib(m.peak_kib[0]),
            mib(m.sampled_kib[0]),
            mib(worker_max(&m.idle_kib)),
            mib(worker_max(&m.peak_kib)),
            mib(worker_max(&m.sampled_kib)),
            m.data_bytes as f64 / (1024.0 * 1024.0),
            m.data_files
        );
    }
    if let [small, large] = memory {
        let _ = writeln!(md, "\n{}", growth(small, large));
    }
    md
}

/// The growth per frame between the short and the long sequence.
fn growth(small: &Memory, large: &Memory) -> String {
    let frames = f64::from(large.frames - small.frames);
    let per = |a: u64, b: u64| (b as f64 - a as f64) * 1024.0 / frames;
    format!(
        "Growth per frame from {} to {} frames: coordinator peak {:.0} bytes, worker peak \
         {:.0} bytes, data directory {:.0} bytes.",
        small.frames,
        large.frames,
        per(small.peak_kib[0], large.peak_kib[0]),
        per(worker_max(&small.peak_kib), worker_max(&large.peak_kib)),
        (large.data_bytes as f64 - small.data_bytes as f64) / frames
    )
}

fn summary(throughput: &Comparison, overhead: &Comparison, memory: &[Memory]) -> String {
    let mut s = format!(
        "sequence: orbit {} × {} frames: farm {:.2} s ({:.1} frames/s), local {:.2} s \
         ({:.1} frames/s), farm/local throughput {:.3}; farm overhead {:.2} ms/frame (tiny \
         frames), {:.2} ms/frame (orbit)",
        throughput.size.label(),
        throughput.frames,
        throughput.farm_median(),
        f64::from(throughput.frames) / throughput.farm_median(),
        throughput.local_median(),
        f64::from(throughput.frames) / throughput.local_median(),
        throughput.ratio(),
        overhead.overhead_ms(),
        throughput.overhead_ms()
    );
    for m in memory {
        let _ = write!(
            s,
            "\nsequence: {} frames: coordinator peak {:.1} MiB, worker peak {:.1} MiB, \
             data {:.2} MiB",
            m.frames,
            mib(m.peak_kib[0]),
            mib(worker_max(&m.peak_kib)),
            m.data_bytes as f64 / (1024.0 * 1024.0)
        );
    }
    if let [small, large] = memory {
        let _ = write!(s, "\nsequence: {}", growth(small, large));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_orbit_stretches_to_any_frame_count() {
        for frames in [20, 100, 121, 300, 10_000] {
            let json = orbit(frames).unwrap();
            let scene = render::parse_animated(&json).unwrap();
            assert_eq!(scene.frame_count(), frames);
        }
        let v: serde_json::Value = serde_json::from_str(&orbit(10_000).unwrap()).unwrap();
        let keys = v["animation"]["tracks"][0]["keys"].as_array().unwrap();
        assert_eq!(keys.first().unwrap()["frame"], 1);
        assert_eq!(keys.last().unwrap()["frame"], 10_000);
    }

    #[test]
    fn medians() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0]), 2.5);
    }
}
