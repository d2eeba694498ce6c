//! `tessera-bench --suite renderer`: the whole `tessera render` process against other
//! programs given by path, side by side in one run, and how the renderer's time scales.
//!
//! - **Anchor** (`--anchor`): an Embree-based tracer of the same model, run on the same
//!   scene files at the same settings; its image must equal Tessera's, pixel for pixel.
//! - **Floor** (`--limit-bench`): SIMD loops of the seed frame's intersection tests and
//!   shading; Tessera's tracing time on the seed frame is reported as a multiple of it.
//! - **Seed structure** (`--seed-cpp`): `render/benches/seed_structured.cpp`, the seed
//!   program's design in C++; Tessera's whole process on the seed frame is reported as
//!   a multiple of its whole process.
//! - **Mesh anchor** (`--anchor-mesh`): the anchor extended to meshes, on the mesh
//!   scenes and on generated meshes of growing size (see [`mesh`]).
//!
//! Every program is timed as a whole process (start to exit, wall clock), each case run
//! `reps` times with the programs alternating, median and minimum reported. A program
//! not given is a column saying so. The scaling half sweeps pixels, objects, lights and
//! mirror depth in process, one thread, and fits the log-log slope of each curve.
//! `--only` runs the sphere half (the cases above and the sweeps) or the mesh half.
//!
//! This module holds what both halves use: the cases and their runs, running and timing
//! a program, and the formatting of times. The sphere half's cases and tables are in
//! [`spheres`], the mesh half in [`mesh`] and the scaling sweeps in [`sweeps`]; [`image`]
//! compares the programs' images, and [`report`] writes the report's head and the CSV
//! of every run.

use std::io::Read as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{bail, Context, Result};

// `mesh` numbers its counts with this, taken from here with the rest it shares.
use super::scenes::thousands;
use super::Options;
use image::{compare, decode, difference, ImageDiff};
use report::{comparison_csv, header_markdown, load_average};
use spheres::{run_limit_bench, spheres_markdown, write_cases};
use sweeps::write_scaling;

mod image;
pub(crate) mod mesh;
mod report;
mod spheres;
mod sweeps;

/// The external programs, each optional.
#[derive(Clone, Debug, Default)]
pub struct External {
    /// The Embree-based tracer: `ANCHOR SCENE -o OUT.png --width W --height H --aa N
    /// --spheres user --threads T`.
    pub anchor: Option<PathBuf>,
    /// The floor program: prints `double AVX2 camera rays`, `double AVX2 camera, skip`
    /// and `double AVX2 shading` lines with their best times.
    pub limit_bench: Option<PathBuf>,
    /// `render/benches/seed_structured.cpp`, built.
    pub seed_cpp: Option<PathBuf>,
    /// The Embree-based tracer of meshes (`embree_whitted_mesh.cpp`): the anchor's
    /// arguments and `--robust`, Embree's watertight mode, the fair match for a
    /// watertight renderer.
    pub anchor_mesh: Option<PathBuf>,
}

/// Which half of the suite to run: both unless one is asked for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Part {
    /// The sphere cases against the anchor, the floor and the seed structure, and the
    /// scaling sweeps.
    Spheres,
    /// The mesh scenes against the mesh anchor, and parse and build time against
    /// triangles.
    Meshes,
}

/// Which anchor a case is run against, and how.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum AnchorKind {
    /// `--anchor`, with `--spheres user`.
    Spheres,
    /// `--anchor-mesh`, with `--spheres user --robust`.
    Meshes,
}

const NOT_GIVEN: &str = "not given";

/// Peak memory is reported only from runs at least this long (seconds): a shorter one
/// may end before its memory is read more than once.
const MIN_RSS_WALL: f64 = 0.05;

/// One frame to render with every program.
struct Case {
    name: String,
    scene: PathBuf,
    width: u32,
    height: u32,
    aa: u32,
    /// The seed frame, where the floor and the seed structure are measured.
    seed_frame: bool,
    anchor: AnchorKind,
}

/// One run of one program.
struct Run {
    /// Start to exit, seconds.
    wall: f64,
    /// The tracing time the program prints, seconds.
    tracing: Option<f64>,
    /// The anchor's scene parsing and BVH building, seconds.
    parse: Option<f64>,
    build: Option<f64>,
    /// Peak resident set, KiB, if it was read while the process ran.
    peak_rss_kib: Option<u64>,
}

/// Every run of one program on one case.
#[derive(Default)]
struct Runs(Vec<Run>);

impl Runs {
    fn median_of(&self, f: impl Fn(&Run) -> Option<f64>) -> Option<f64> {
        median(self.0.iter().filter_map(f).collect())
    }

    fn wall(&self) -> Option<f64> {
        self.median_of(|r| Some(r.wall))
    }

    fn min_wall(&self) -> Option<f64> {
        self.0.iter().map(|r| r.wall).reduce(f64::min)
    }

    fn peak_rss_mib(&self) -> Option<f64> {
        self.0
            .iter()
            .filter(|r| r.wall >= MIN_RSS_WALL)
            .filter_map(|r| Some(r.peak_rss_kib? as f64 / 1024.0))
            .reduce(f64::max)
    }
}

/// The median over runs of `a`'s time divided by `b`'s in the same round: runs made one
/// after the other see about the same load, so on a shared machine this is steadier
/// than the ratio of the two medians.
fn paired_ratio(a: &Runs, b: &Runs) -> Option<f64> {
    paired_ratio_of(a, b, |r| Some(r.wall))
}

/// [`paired_ratio`] of another time of the runs (the tracing time they print), over the
/// rounds where both runs have it.
fn paired_ratio_of(a: &Runs, b: &Runs, f: impl Fn(&Run) -> Option<f64>) -> Option<f64> {
    median(
        a.0.iter()
            .zip(&b.0)
            .filter_map(|(x, y)| Some(f(x)? / f(y)?))
            .collect(),
    )
}

/// The median, `None` for no values.
fn median(mut values: Vec<f64>) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    Some(if n % 2 == 1 {
        values[n / 2]
    } else {
        (values[n / 2 - 1] + values[n / 2]) / 2.0
    })
}

/// What was measured on one case.
struct CaseResult {
    case: Case,
    tessera_1: Runs,
    tessera_2: Runs,
    anchor: Option<Runs>,
    seed_cpp: Option<Runs>,
    /// The anchor's image against Tessera's (1 thread).
    anchor_image: Option<ImageDiff>,
    /// Tessera's 2-thread image against its 1-thread image.
    threads_image: String,
    /// The seed structure's image against Tessera's.
    seed_cpp_image: Option<String>,
}

/// The floor of the seed frame, from the floor program's output.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Floor {
    /// The faster of the `double AVX2 camera rays` and `double AVX2 camera, skip` lines.
    intersection_ms: f64,
    /// The `double AVX2 shading` line.
    shading_ms: f64,
}

impl Floor {
    fn total_ms(&self) -> f64 {
        self.intersection_ms + self.shading_ms
    }
}

/// Runs the suite: `renderer.md`, `renderer.csv`, `renderer-scaling.{md,csv,png}` for
/// the sphere half, `renderer-mesh-build.{md,csv,png}` for the mesh half (whose cases
/// go into `renderer.md` and `renderer.csv` beside the sphere cases).
pub fn run(opts: &Options, out: &Path) -> Result<()> {
    let load = load_average();
    let spheres = opts.renderer_only.is_none_or(|p| p == Part::Spheres);
    let meshes = opts.renderer_only.is_none_or(|p| p == Part::Meshes);
    let dir = tempfile::tempdir().context("cannot make a temporary directory")?;
    let mut md = header_markdown(opts, &load);
    let mut sphere_results = Vec::new();
    if spheres {
        let tessera = &opts.tessera;
        let cases = write_cases(opts, dir.path())?;
        let floor = match &opts.external.limit_bench {
            Some(path) => Some(run_limit_bench(path)?),
            None => None,
        };
        for case in cases {
            sphere_results.push(run_case(opts, tessera, case, dir.path())?);
        }
        md.push_str(&spheres_markdown(&sphere_results, floor));
    }
    let mut mesh_results = Vec::new();
    if meshes {
        mesh_results = mesh::run_cases(opts, dir.path())?;
        md.push_str(&mesh::cases_markdown(opts, &mesh_results));
    }
    std::fs::write(out.join("renderer.md"), md)?;
    let all: Vec<&CaseResult> = sphere_results
        .iter()
        .chain(mesh_results.iter().map(|m| &m.result))
        .collect();
    std::fs::write(out.join("renderer.csv"), comparison_csv(&all))?;
    if spheres {
        eprintln!("renderer: comparison written; now the scaling sweeps");
        write_scaling(opts, out)?;
    }
    if meshes {
        eprintln!("renderer: mesh cases written; now parse and build against triangles");
        mesh::write_build_scaling(opts, out)?;
    }
    Ok(())
}

/// The programs of one case, one after the other, `reps` times.
fn run_case(opts: &Options, tessera: &Path, case: Case, dir: &Path) -> Result<CaseResult> {
    let size = |cmd: &mut Command| {
        cmd.arg("--width")
            .arg(case.width.to_string())
            .arg("--height")
            .arg(case.height.to_string())
            .arg("--aa")
            .arg(case.aa.to_string());
    };
    let tessera_png = |threads: u32| dir.join(format!("tessera-{threads}.png"));
    let tessera_cmd = |threads: u32| {
        let mut cmd = Command::new(tessera);
        cmd.arg("render")
            .arg(&case.scene)
            .arg("-o")
            .arg(tessera_png(threads));
        size(&mut cmd);
        cmd.arg("--threads").arg(threads.to_string());
        cmd
    };
    let anchor_png = dir.join("anchor.png");
    let anchor_path = match case.anchor {
        AnchorKind::Spheres => &opts.external.anchor,
        AnchorKind::Meshes => &opts.external.anchor_mesh,
    };
    let anchor_cmd = anchor_path.as_ref().map(|path| {
        let mut cmd = Command::new(path);
        cmd.arg(&case.scene).arg("-o").arg(&anchor_png);
        size(&mut cmd);
        cmd.args(["--spheres", "user", "--threads", "1"]);
        if case.anchor == AnchorKind::Meshes {
            cmd.arg("--robust");
        }
        cmd
    });
    let seed_ppm = dir.join("seed-structured.ppm");
    let seed_cmd = opts
        .external
        .seed_cpp
        .as_ref()
        .filter(|_| case.seed_frame)
        .map(|path| {
            let mut cmd = Command::new(path);
            cmd.arg(&case.scene).arg("-o").arg(&seed_ppm);
            size(&mut cmd);
            cmd
        });

    let (mut tessera_1, mut tessera_2) = (Runs::default(), Runs::default());
    let mut anchor = anchor_cmd.as_ref().map(|_| Runs::default());
    let mut seed_cpp = seed_cmd.as_ref().map(|_| Runs::default());
    for rep in 0..opts.reps {
        tessera_1
            .0
            .push(time_process(&mut tessera_cmd(1), Program::Tessera)?);
        if let (Some(cmd), Some(runs)) = (&anchor_cmd, &mut anchor) {
            runs.0
                .push(time_process(&mut clone_command(cmd), Program::Anchor)?);
        }
        tessera_2
            .0
            .push(time_process(&mut tessera_cmd(2), Program::Tessera)?);
        if let (Some(cmd), Some(runs)) = (&seed_cmd, &mut seed_cpp) {
            runs.0
                .push(time_process(&mut clone_command(cmd), Program::SeedCpp)?);
        }
        eprintln!(
            "renderer: {} run {}/{}: tessera {:.3} s / {:.3} s (1 / 2 threads){}",
            case.name,
            rep + 1,
            opts.reps,
            tessera_1.0.last().map_or(0.0, |r| r.wall),
            tessera_2.0.last().map_or(0.0, |r| r.wall),
            anchor
                .as_ref()
                .and_then(|r| r.0.last())
                .map_or(String::new(), |r| format!(", anchor {:.3} s", r.wall)),
        );
    }
    let ours = decode(&tessera_png(1))?;
    let threads_image = compare(&ours, &decode(&tessera_png(2))?);
    let anchor_image = match anchor {
        Some(_) => Some(difference(&ours, &decode(&anchor_png)?)),
        None => None,
    };
    let seed_cpp_image = match seed_cpp {
        Some(_) => Some(compare(&ours, &decode(&seed_ppm)?)),
        None => None,
    };
    Ok(CaseResult {
        case,
        tessera_1,
        tessera_2,
        anchor,
        seed_cpp,
        anchor_image,
        threads_image,
        seed_cpp_image,
    })
}

/// A copy of `cmd`'s program and arguments (`Command` is not `Clone`).
fn clone_command(cmd: &Command) -> Command {
    let mut copy = Command::new(cmd.get_program());
    copy.args(cmd.get_args());
    copy
}

#[derive(Clone, Copy)]
enum Program {
    Tessera,
    Anchor,
    SeedCpp,
}

/// Runs `cmd` to its end: wall time, peak memory and the times it prints.
fn time_process(cmd: &mut Command, program: Program) -> Result<Run> {
    cmd.stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    let shown = format!("{cmd:?}");
    let started = Instant::now();
    let mut child = cmd
        .spawn()
        .with_context(|| format!("cannot start {shown}"))?;
    // `spawn` returns once the program is executing, so from here on the process's
    // memory is the program's own.
    let watcher = PeakWatcher::start(child.id());
    let mut stderr = String::new();
    if let Some(mut pipe) = child.stderr.take() {
        pipe.read_to_string(&mut stderr)
            .with_context(|| format!("reading the output of {shown}"))?;
    }
    let status = child
        .wait()
        .with_context(|| format!("waiting for {shown}"))?;
    let wall = started.elapsed().as_secs_f64();
    let peak_rss_kib = watcher.stop();
    if !status.success() {
        bail!("{shown} failed ({status}):\n{stderr}");
    }
    let run = match program {
        Program::Tessera => Run {
            wall,
            tracing: tessera_seconds(&stderr),
            parse: None,
            build: None,
            peak_rss_kib,
        },
        Program::Anchor => Run {
            wall,
            tracing: labelled_seconds(&stderr, "tracing"),
            parse: labelled_seconds(&stderr, "parse"),
            build: labelled_seconds(&stderr, "build"),
            peak_rss_kib,
        },
        Program::SeedCpp => Run {
            wall,
            tracing: labelled_seconds(&stderr, "render"),
            parse: labelled_seconds(&stderr, "parse"),
            build: None,
            peak_rss_kib,
        },
    };
    if run.tracing.is_none() {
        bail!("{shown}: no tracing time in its output:\n{stderr}");
    }
    Ok(run)
}

/// Reads a running process's peak resident set (`VmHWM` of `/proc/PID/status`) every
/// few milliseconds on a thread of its own. The high-water mark only grows, so the last
/// reading is the peak unless the process grew in its last few milliseconds: exact for
/// the large cases, whose peak is reached while loading the scene. (`ru_maxrss` of
/// `wait4` would not do: Linux carries the spawning process's own peak over `exec`.)
struct PeakWatcher {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: std::thread::JoinHandle<Option<u64>>,
}

impl PeakWatcher {
    fn start(pid: u32) -> Self {
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::spawn(move || {
            let path = format!("/proc/{pid}/status");
            let mut peak = None;
            while !flag.load(std::sync::atomic::Ordering::Relaxed) {
                if let Some(kib) = std::fs::read_to_string(&path)
                    .ok()
                    .and_then(|s| vm_hwm_kib(&s))
                {
                    peak = Some(peak.map_or(kib, |p: u64| p.max(kib)));
                }
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
            peak
        });
        PeakWatcher { stop, thread }
    }

    /// The largest reading, `None` if the process ended before the first.
    fn stop(self) -> Option<u64> {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        self.thread.join().unwrap_or(None)
    }
}

/// `VmHWM:   123456 kB` of a `/proc/PID/status` text, in KiB.
fn vm_hwm_kib(status: &str) -> Option<u64> {
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line["VmHWM:".len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()
}

/// The render time of `tessera render`'s summary line (`out.png: 600x400, …, 0.086 s,
/// 31.7 M rays/s (1 threads)`), in seconds.
fn tessera_seconds(stderr: &str) -> Option<f64> {
    let line = stderr.lines().rev().find(|l| l.contains("rays/s"))?;
    line.split(", ")
        .filter_map(|part| part.strip_suffix(" s"))
        .find_map(|number| number.trim().parse().ok())
}

/// The seconds after `label` in output such as `parse 0.004 s, build 0.002 s, tracing
/// 0.129 s (cpu 0.066 s)`: the first place where `label` is followed by a number and `s`.
fn labelled_seconds(text: &str, label: &str) -> Option<f64> {
    text.match_indices(label).find_map(|(at, _)| {
        let before = text[..at].chars().next_back();
        if before.is_some_and(|c| c.is_alphanumeric()) {
            return None;
        }
        let mut words = text[at + label.len()..].split_whitespace();
        let value: f64 = words.next()?.parse().ok()?;
        let unit = words.next()?;
        (unit == "s" || unit.starts_with("s,") || unit.starts_with("s)")).then_some(value)
    })
}

fn ms(seconds: f64) -> String {
    let ms = seconds * 1e3;
    if ms < 100.0 {
        format!("{ms:.1} ms")
    } else {
        format!("{ms:.0} ms")
    }
}

fn median_min(runs: &Runs) -> String {
    match (runs.wall(), runs.min_wall()) {
        (Some(median), Some(min)) => format!("{} ({})", ms(median), ms(min)),
        _ => "–".into(),
    }
}

/// The CPU's model name from /proc/cpuinfo.
fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_owned())
        })
        .unwrap_or_else(|| "unknown".into())
}

fn slope_text(slope: Option<f64>) -> String {
    slope.map_or("–".into(), |s| format!("{s:.2}"))
}

#[cfg(test)]
mod tests;
