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

use std::fmt::Write as _;
use std::io::Read as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{anyhow, bail, Context, Result};

use super::scaling::{self, Point};
use super::scenes::{self, thousands};
use super::Options;
use crate::plot::{Panel, Series};

mod mesh;

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

/// Writes the cases' scene files once into `dir`.
fn write_cases(opts: &Options, dir: &Path) -> Result<Vec<Case>> {
    let write = |name: &str, json: &str| -> Result<PathBuf> {
        let path = dir.join(name);
        std::fs::write(&path, json).with_context(|| format!("cannot write {}", path.display()))?;
        Ok(path)
    };
    let seed = write("seed.json", &scenes::seed().json)?;
    let (small, large): ((u32, u32), (u32, u32)) = if opts.quick {
        ((150, 100), (480, 270))
    } else {
        ((600, 400), (1920, 1080))
    };
    let mut cases = vec![
        Case {
            name: format!("seed {}×{} aa 2", small.0, small.1),
            scene: seed.clone(),
            width: small.0,
            height: small.1,
            aa: 2,
            seed_frame: true,
            anchor: AnchorKind::Spheres,
        },
        Case {
            name: format!("seed {}×{} aa 4", large.0, large.1),
            scene: seed,
            width: large.0,
            height: large.1,
            aa: 4,
            seed_frame: false,
            anchor: AnchorKind::Spheres,
        },
    ];
    let counts: &[usize] = if opts.quick {
        &[10, 10_000]
    } else {
        &[10, 10_000, 100_000, 1_000_000]
    };
    for &count in counts {
        let scene = write(
            &format!("spheres-{count}.json"),
            &scenes::spheres(count).json,
        )?;
        let what = if count == 10 {
            "10 spheres + plane".to_owned()
        } else {
            format!("{} small spheres", thousands(count as u64))
        };
        cases.push(Case {
            name: format!("{what} {}×{} aa 1", small.0, small.1),
            scene,
            width: small.0,
            height: small.1,
            aa: 1,
            seed_frame: false,
            anchor: AnchorKind::Spheres,
        });
    }
    Ok(cases)
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

/// The best time in ms of the floor program's line named `name` (`NAME : … best of 11
/// 19.94 ms = …`).
fn limit_bench_ms(output: &str, name: &str) -> Option<f64> {
    output.lines().find_map(|line| {
        let (label, rest) = line.split_once(':')?;
        if label.trim() != name {
            return None;
        }
        let after = &rest[rest.find("best of ")? + "best of ".len()..];
        let mut words = after.split_whitespace();
        words.next()?; // the count of runs
        let ms: f64 = words.next()?.parse().ok()?;
        (words.next()? == "ms").then_some(ms)
    })
}

/// The seed frame's floor from the floor program's output.
fn parse_floor(output: &str) -> Option<Floor> {
    let camera = limit_bench_ms(output, "double AVX2 camera rays");
    let skip = limit_bench_ms(output, "double AVX2 camera, skip");
    let intersection_ms = match (camera, skip) {
        (Some(a), Some(b)) => a.min(b),
        (a, b) => a.or(b)?,
    };
    Some(Floor {
        intersection_ms,
        shading_ms: limit_bench_ms(output, "double AVX2 shading")?,
    })
}

fn run_limit_bench(path: &Path) -> Result<Floor> {
    eprintln!("renderer: running {}", path.display());
    let output = Command::new(path)
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("cannot run {}", path.display()))?;
    let text = String::from_utf8_lossy(&output.stdout);
    if !output.status.success() {
        bail!("{} failed: {}", path.display(), output.status);
    }
    parse_floor(&text).ok_or_else(|| {
        anyhow!(
            "{}: no \"double AVX2 camera rays\" (or \"skip\") and \"double AVX2 shading\" lines in:\n{text}",
            path.display()
        )
    })
}

/// A decoded RGB8 image.
struct Rgb {
    width: u32,
    height: u32,
    bytes: Vec<u8>,
}

/// Reads a PNG, or a binary PPM (P6, maxval 255).
fn decode(path: &Path) -> Result<Rgb> {
    let data = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    if data.starts_with(b"P6") {
        return decode_ppm(&data).with_context(|| format!("{}: not a P6 PPM", path.display()));
    }
    let image = coordinator::decode_png(&data)
        .with_context(|| format!("cannot decode {}", path.display()))?;
    Ok(Rgb {
        width: image.width,
        height: image.height,
        bytes: image.rgb,
    })
}

fn decode_ppm(data: &[u8]) -> Result<Rgb> {
    // Four white-space separated fields (P6, width, height, maxval), then one white
    // space byte, then the pixels.
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while data.get(at).is_some_and(u8::is_ascii_whitespace) {
            at += 1;
        }
        let start = at;
        while data.get(at).is_some_and(|b| !b.is_ascii_whitespace()) {
            at += 1;
        }
        if start == at {
            bail!("truncated header");
        }
        fields.push(std::str::from_utf8(&data[start..at])?.to_owned());
    }
    let (width, height): (u32, u32) = (fields[1].parse()?, fields[2].parse()?);
    if fields[3] != "255" {
        bail!("maxval {} (expected 255)", fields[3]);
    }
    let bytes = data
        .get(at + 1..at + 1 + width as usize * height as usize * 3)
        .ok_or_else(|| anyhow!("truncated pixels"))?
        .to_vec();
    Ok(Rgb {
        width,
        height,
        bytes,
    })
}

/// How two images differ: kept as numbers, for the CSV, and said in words by
/// `Display` for the tables.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ImageDiff {
    Sizes {
        a: (u32, u32),
        b: (u32, u32),
    },
    /// Pixels with any channel different, and the largest difference of a channel
    /// (levels of 255).
    Pixels {
        differing: u64,
        max_level: u8,
    },
}

impl ImageDiff {
    /// The differing pixels and the largest channel difference, `None` for images of
    /// different sizes.
    fn counts(self) -> Option<(u64, u8)> {
        match self {
            ImageDiff::Sizes { .. } => None,
            ImageDiff::Pixels {
                differing,
                max_level,
            } => Some((differing, max_level)),
        }
    }
}

impl std::fmt::Display for ImageDiff {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            ImageDiff::Sizes { a, b } => {
                write!(f, "sizes differ ({}×{} and {}×{})", a.0, a.1, b.0, b.1)
            }
            ImageDiff::Pixels { differing: 0, .. } => f.write_str("identical"),
            ImageDiff::Pixels {
                differing,
                max_level,
            } => write!(
                f,
                "{} {} (up to {max_level} levels)",
                thousands(differing),
                if differing == 1 {
                    "pixel differs"
                } else {
                    "pixels differ"
                }
            ),
        }
    }
}

/// How many pixels differ and by how much.
fn difference(a: &Rgb, b: &Rgb) -> ImageDiff {
    if (a.width, a.height) != (b.width, b.height) {
        return ImageDiff::Sizes {
            a: (a.width, a.height),
            b: (b.width, b.height),
        };
    }
    let mut differing = 0u64;
    let mut max_level = 0u8;
    for (p, q) in a.bytes.chunks_exact(3).zip(b.bytes.chunks_exact(3)) {
        if p != q {
            differing += 1;
            for (x, y) in p.iter().zip(q) {
                max_level = max_level.max(x.abs_diff(*y));
            }
        }
    }
    ImageDiff::Pixels {
        differing,
        max_level,
    }
}

/// `identical`, or how many pixels differ and by how much.
fn compare(a: &Rgb, b: &Rgb) -> String {
    difference(a, b).to_string()
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

/// Today's date (UTC) as YYYY-MM-DD.
fn utc_date() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    civil_date(secs / 86_400)
}

/// The proleptic Gregorian date `days` days after 1970-01-01.
fn civil_date(days: u64) -> String {
    // Days since 0000-03-01, in 400-year eras of 146,097 days.
    let z = days + 719_468;
    let era = z / 146_097;
    let doe = z % 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + u64::from(month <= 2);
    format!("{year:04}-{month:02}-{day:02}")
}

/// The 1-minute load average, from /proc/loadavg.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_owned))
        .unwrap_or_else(|| "unknown".into())
}

/// The command line this run was started with, as one line for a shell.
fn invocation() -> String {
    std::env::args()
        .map(|a| {
            if !a.is_empty()
                && a.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_./=:,+".contains(c))
            {
                a
            } else {
                format!("'{}'", a.replace('\'', r"'\''"))
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// The report's head: how to regenerate it, the machine, the programs.
fn header_markdown(opts: &Options, load: &str) -> String {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let ext = &opts.external;
    let given = |p: &Option<PathBuf>| {
        p.as_ref()
            .map_or(NOT_GIVEN.to_owned(), |p| format!("`{}`", p.display()))
    };
    let mut md = String::new();
    let _ = writeln!(
        md,
        "# The renderer against other programs\n\n\
         Regenerate (from the repository root, after `cargo build --release --workspace`, \
         which builds tessera-bench and the tessera it runs):\n\n\
         ```\n{}\n```\n\n\
         The external programs are built with\n\n\
         ```\n\
         g++ -std=c++17 -O3 -march=x86-64-v2 -fno-math-errno embree_whitted.cpp -lembree3 -lz -lpthread -o ew\n\
         g++ -std=c++17 -O3 -march=x86-64-v2 -fno-math-errno embree_whitted_mesh.cpp -lembree3 -lz -lpthread -o ewm\n\
         g++ -std=c++17 -O3 -mavx2 limit_bench.cpp -o limit_bench\n\
         g++ -O3 -march=x86-64-v2 render/benches/seed_structured.cpp -o seed_structured\n\
         ```\n\n\
         - CPU: {} ({cores} logical CPUs); load average {} when the run started \
         (the machine may be shared: medians and alternation are there for that)\n\
         - {}, {}\n\
         - anchor: {}; mesh anchor: {}; floor: {}; seed structure in C++: {}\n\
         - every time is a whole process, start to exit (parse, build, render, PNG \
         written), wall clock, median of {} runs (minimum in brackets); the programs \
         run in turn, case by case (Tessera 1 thread, anchor, Tessera 2 threads, seed \
         structure), so a disturbance hits them alike\n",
        invocation(),
        cpu_model(),
        load,
        render::build_identity(),
        utc_date(),
        given(&ext.anchor),
        given(&ext.anchor_mesh),
        given(&ext.limit_bench),
        given(&ext.seed_cpp),
        opts.reps,
    );
    md
}

/// The sphere cases: whole process, where the time goes, the floor, the seed structure.
fn spheres_markdown(results: &[CaseResult], floor: Option<Floor>) -> String {
    let mut md = String::new();
    let _ = writeln!(
        md,
        "## Whole process\n\n\
         | case | Tessera, 1 thread | anchor, 1 thread | Tessera / anchor | Tessera, 2 threads | speed-up 2 / 1 | images identical? |\n\
         |---|---:|---:|---:|---:|---:|---|"
    );
    for r in results {
        let ratio = r.anchor.as_ref().map_or(NOT_GIVEN.to_owned(), |a| {
            paired_ratio(&r.tessera_1, a).map_or("–".into(), |x| format!("{x:.2}"))
        });
        let speedup =
            paired_ratio(&r.tessera_1, &r.tessera_2).map_or("–".into(), |x| format!("{x:.2}"));
        let mut images = r
            .anchor_image
            .map_or_else(|| format!("{NOT_GIVEN} (anchor)"), |d| d.to_string());
        if r.threads_image != "identical" {
            let _ = write!(images, "; Tessera 2 threads against 1: {}", r.threads_image);
        }
        let _ = writeln!(
            md,
            "| {} | {} | {} | {ratio} | {} | {speedup} | {images} |",
            r.case.name,
            median_min(&r.tessera_1),
            r.anchor.as_ref().map_or(NOT_GIVEN.to_owned(), median_min),
            median_min(&r.tessera_2),
        );
    }
    let _ = writeln!(
        md,
        "\nTessera / anchor (below 1: Tessera is faster) and the speed-up are medians of \
         the ratios of runs made one after the other (Tessera 1 thread to the anchor's \
         next run, to Tessera's 2-thread run), steadier than ratios of medians when the \
         machine is shared. The images are compared pixel for \
         pixel after decoding both PNGs (Tessera's 1-thread image against the anchor's; \
         Tessera's 2-thread image is also checked against its 1-thread one and only \
         mentioned if it differs).\n\n\
         ### Where the time goes (medians)\n\n\
         | case | Tessera tracing, 1 thread | Tessera tracing, 2 threads | anchor parse | anchor build | anchor tracing | Tessera peak RSS | anchor peak RSS |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|"
    );
    let opt_ms = |v: Option<f64>| v.map_or(NOT_GIVEN.to_owned(), ms);
    let mib = |v: Option<f64>| v.map_or("–".to_owned(), |m| format!("{m:.0} MiB"));
    for r in results {
        let a = r.anchor.as_ref();
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            r.case.name,
            opt_ms(r.tessera_1.median_of(|x| x.tracing)),
            opt_ms(r.tessera_2.median_of(|x| x.tracing)),
            opt_ms(a.and_then(|a| a.median_of(|x| x.parse))),
            opt_ms(a.and_then(|a| a.median_of(|x| x.build))),
            opt_ms(a.and_then(|a| a.median_of(|x| x.tracing))),
            mib(r.tessera_1.peak_rss_mib()),
            a.map_or(NOT_GIVEN.to_owned(), |a| mib(a.peak_rss_mib())),
        );
    }
    let _ = writeln!(
        md,
        "\nTracing is what each program prints: for Tessera the render line of `tessera \
         render` (after loading the scene and building the tracer, before writing the \
         PNG), for the anchor the time after the BVH build. Peak RSS is the largest \
         `VmHWM` read from `/proc/PID/status` every 5 ms during the case's runs (– when \
         no run lasted 50 ms).\n"
    );

    let seed = results.iter().find(|r| r.case.seed_frame);
    let seed_name = seed.map_or("the seed frame".to_owned(), |r| r.case.name.clone());
    let _ = writeln!(md, "## Against the floor ({seed_name})\n");
    let best_tracing = seed.and_then(|r| {
        r.tessera_1
            .0
            .iter()
            .filter_map(|x| x.tracing)
            .reduce(f64::min)
    });
    match (
        floor,
        seed.and_then(|r| r.tessera_1.median_of(|x| x.tracing)),
        best_tracing,
    ) {
        (Some(f), Some(tracing), Some(best)) => {
            let _ = writeln!(
                md,
                "| intersection floor | shading floor | floor | Tessera tracing, 1 thread: median (best) | × the floor: median (best) |\n\
                 |---:|---:|---:|---:|---:|\n\
                 | {:.2} ms | {:.2} ms | {:.2} ms | {} ({}) | {:.2} ({:.2}) |\n\n\
                 The floor program's best times: intersection is the faster of its \
                 \"double AVX2 camera rays\" and \"double AVX2 camera, skip\" lines (the \
                 seed frame's camera rays against its three objects in AVX2 doubles, rays \
                 held in L1), shading its \"double AVX2 shading\" line (the two-light \
                 shading kernel on the frame's hits). Tessera's figures are the median \
                 and the best tracing time of the seed frame's 1-thread runs above (the \
                 best compares like with like: the floor is a best of 11).\n",
                f.intersection_ms,
                f.shading_ms,
                f.total_ms(),
                ms(tracing),
                ms(best),
                tracing * 1e3 / f.total_ms(),
                best * 1e3 / f.total_ms()
            );
        }
        _ => {
            let _ = writeln!(md, "Floor program {NOT_GIVEN}.\n");
        }
    }

    let _ = writeln!(md, "## Against the seed's structure in C++ ({seed_name})\n");
    match seed.and_then(|r| Some((r, r.seed_cpp.as_ref()?))) {
        Some((r, runs)) => {
            let multiple = match paired_ratio(&r.tessera_1, runs) {
                Some(x) => format!("{x:.3} (Tessera {:.1}× faster)", 1.0 / x),
                None => "–".into(),
            };
            let _ = writeln!(
                md,
                "| seed structure, whole process | its rendering | Tessera, 1 thread, whole process | Tessera ÷ seed structure | images |\n\
                 |---:|---:|---:|---:|---|\n\
                 | {} | {} | {} | {multiple} | {} |\n\n\
                 `render/benches/seed_structured.cpp` keeps the seed program's design \
                 (objects behind virtual calls, a new vector of intersections for every \
                 ray, the textbook quadratic, a fixed epsilon, double, one thread) with the \
                 shading of docs/scene-format.md. The ratio is the median of the ratios of \
                 runs in the same round, as above. Where its pixels differ from Tessera's, \
                 it is at silhouettes and shadow edges, where its fixed epsilon and \
                 quadratic round differently from Tessera's exact methods.\n",
                median_min(runs),
                opt_ms(runs.median_of(|x| x.tracing)),
                median_min(&r.tessera_1),
                r.seed_cpp_image.as_deref().unwrap_or("–"),
            );
        }
        None => {
            let _ = writeln!(md, "Seed structure in C++ {NOT_GIVEN}.\n");
        }
    }
    md
}

/// Every program's runs on every case, sphere and mesh cases alike; the anchor's rows
/// also give its image's difference from Tessera's as numbers.
fn comparison_csv(results: &[&CaseResult]) -> String {
    let mut csv = String::from(
        "case,width,height,aa,program,threads,runs,median_s,min_s,tracing_median_s,parse_median_s,build_median_s,peak_rss_mib,image_against_tessera_1_thread,differing_pixels,max_channel_difference\n",
    );
    let opt = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.6}"));
    for r in results {
        let anchor = match r.case.anchor {
            AnchorKind::Spheres => "anchor",
            AnchorKind::Meshes => "anchor-mesh",
        };
        let mut rows: Vec<(&str, u32, &Runs, String, Option<ImageDiff>)> = vec![
            ("tessera", 1, &r.tessera_1, String::new(), None),
            ("tessera", 2, &r.tessera_2, r.threads_image.clone(), None),
        ];
        if let Some(runs) = &r.anchor {
            rows.push((
                anchor,
                1,
                runs,
                r.anchor_image.map(|d| d.to_string()).unwrap_or_default(),
                r.anchor_image,
            ));
        }
        if let Some(runs) = &r.seed_cpp {
            rows.push((
                "seed-structured-cpp",
                1,
                runs,
                r.seed_cpp_image.clone().unwrap_or_default(),
                None,
            ));
        }
        for (program, threads, runs, image, diff) in rows {
            let (differing, max_level) = diff
                .and_then(ImageDiff::counts)
                .map_or((String::new(), String::new()), |(n, l)| {
                    (n.to_string(), l.to_string())
                });
            let _ = writeln!(
                csv,
                "\"{}\",{},{},{},{program},{threads},{},{},{},{},{},{},{},\"{image}\",{differing},{max_level}",
                r.case.name,
                r.case.width,
                r.case.height,
                r.case.aa,
                runs.0.len(),
                opt(runs.wall()),
                opt(runs.min_wall()),
                opt(runs.median_of(|x| x.tracing)),
                opt(runs.median_of(|x| x.parse)),
                opt(runs.median_of(|x| x.build)),
                runs.peak_rss_mib()
                    .map_or(String::new(), |m| format!("{m:.1}")),
            );
        }
    }
    csv
}

/// One sweep of the scaling half.
struct Sweep {
    name: &'static str,
    title: &'static str,
    x_label: &'static str,
    points: Vec<Point>,
}

impl Sweep {
    fn render_points(&self) -> Vec<(f64, f64)> {
        self.points.iter().map(|p| (p.x, p.seconds * 1e3)).collect()
    }

    fn setup_points(&self) -> Vec<(f64, f64)> {
        self.points
            .iter()
            .filter_map(|p| Some((p.x, p.setup_seconds? * 1e3)))
            .collect()
    }
}

fn slope_text(slope: Option<f64>) -> String {
    slope.map_or("–".into(), |s| format!("{s:.2}"))
}

/// Time against pixels, objects, lights and mirror depth: renderer-scaling.{md,csv,png}.
fn write_scaling(opts: &Options, out: &Path) -> Result<()> {
    let objects: &[usize] = if opts.quick {
        &[10, 100, 1000, 10_000]
    } else {
        &[10, 100, 1000, 10_000, 100_000, 1_000_000]
    };
    let sweeps = [
        Sweep {
            name: "pixels",
            title: "Time against pixels (seed, aa 1)",
            x_label: "pixels (log)",
            points: scaling::time_against_pixels(opts)?,
        },
        Sweep {
            name: "objects",
            title: "Time against objects (spheres, aa 1)",
            x_label: "spheres (log)",
            points: scaling::time_against_objects(opts, objects)?,
        },
        Sweep {
            name: "lights",
            title: "Time against lights (seed objects, aa 1)",
            x_label: "lights (log)",
            points: scaling::time_against_lights(opts)?,
        },
        Sweep {
            name: "depth",
            title: "Time against mirror depth (hall of mirrors)",
            x_label: "max depth (log; 0 in the table only)",
            points: scaling::time_against_depth(opts)?,
        },
    ];
    let (w, h) = if opts.quick { (150, 100) } else { (600, 400) };
    let hall = if opts.quick { 120 } else { 480 };
    let mut md = format!(
        "# How the renderer's time scales\n\n\
         Regenerated with the renderer comparison (`renderer.md`, same command). In \
         process through the `render` crate, 1 thread, each point the fastest of up to \
         {} renders within {} ms; the slope is the least-squares fit of log time against \
         log x (1: linear, 0: flat).\n\n\
         - CPU: {}\n\
         - pixels: the seed scene at aa 1 from 150 × 100 up (the seed report's figure 3)\n\
         - objects: `spheres(count)`, small spheres over a plane, at {w} × {h}, aa 1; \
         loading (JSON parsing and checking) and building the tracer timed apart from \
         rendering (the seed report's figure 2)\n\
         - lights: the seed scene's three objects under 1 to 64 equal lights on a circle \
         above, {w} × {h}, aa 1\n\
         - depth: `scenes/hall-of-mirrors.json` (facing mirrors of reflectance 0.9) at \
         {hall} × {hall}, aa 1, with its depth limit from 0 up; the fit leaves out depth 0\n\n\
         | sweep | from | to | slope (render) | slope (load + build) |\n\
         |---|---:|---:|---:|---:|\n",
        opts.max_runs,
        opts.min_time.as_millis(),
        cpu_model(),
    );
    for sweep in &sweeps {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} |",
            sweep.name,
            thousands(sweep.points.first().map_or(0.0, |p| p.x) as u64),
            thousands(sweep.points.last().map_or(0.0, |p| p.x) as u64),
            slope_text(scaling::loglog_slope(&sweep.render_points())),
            if sweep.name == "objects" {
                slope_text(scaling::loglog_slope(&sweep.setup_points()))
            } else {
                "–".into()
            },
        );
    }
    let mut csv = String::from("sweep,x,render_s,load_build_s,rays\n");
    for sweep in &sweeps {
        let with_setup = sweep.name == "objects";
        let _ = writeln!(
            md,
            "\n### {}\n\n| {} | render | rays | ns per ray |{}\n|---:|---:|---:|---:|{}",
            sweep.title,
            sweep.name,
            if with_setup { " load + build |" } else { "" },
            if with_setup { "---:|" } else { "" },
        );
        for p in &sweep.points {
            let _ = writeln!(
                md,
                "| {} | {} | {} | {:.1} |{}",
                thousands(p.x as u64),
                ms(p.seconds),
                thousands(p.rays),
                p.seconds * 1e9 / p.rays.max(1) as f64,
                p.setup_seconds
                    .map_or(String::new(), |s| format!(" {} |", ms(s))),
            );
            let _ = writeln!(
                csv,
                "{},{},{:.6},{},{}",
                sweep.name,
                p.x,
                p.seconds,
                p.setup_seconds.map_or(String::new(), |s| format!("{s:.6}")),
                p.rays
            );
        }
    }
    std::fs::write(out.join("renderer-scaling.md"), md)?;
    std::fs::write(out.join("renderer-scaling.csv"), csv)?;
    let panels: Vec<Panel> = sweeps.iter().map(scaling_panel).collect();
    crate::plot::write_png(&out.join("renderer-scaling.png"), &panels, 2, (600, 440))
}

fn scaling_panel(sweep: &Sweep) -> Panel {
    // A log axis has no 0: the depth sweep's first point stays in the table.
    let positive = |points: Vec<(f64, f64)>| -> Vec<(f64, f64)> {
        points.into_iter().filter(|p| p.0 > 0.0).collect()
    };
    let render = positive(sweep.render_points());
    let mut series = vec![Series {
        label: format!(
            "render (slope {})",
            slope_text(scaling::loglog_slope(&render))
        ),
        points: render,
        joined: true,
        markers: true,
    }];
    let setup = positive(sweep.setup_points());
    if !setup.is_empty() {
        series.push(Series {
            label: format!(
                "load + build (slope {})",
                slope_text(scaling::loglog_slope(&setup))
            ),
            points: setup,
            joined: true,
            markers: true,
        });
    }
    Panel {
        title: sweep.title.into(),
        x_label: sweep.x_label.into(),
        y_label: "time (ms, log)".into(),
        log_x: true,
        log_y: true,
        series,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_render_time_of_tessera_render() {
        let line = "t.png: 600x400, 4 samples/pixel (grid 2x2, 960000 in all), estimated \
                    error 17.547 levels, 0.086 s, 31.7 M rays/s (1 threads)\n";
        assert_eq!(tessera_seconds(line), Some(0.086));
        assert_eq!(tessera_seconds("nothing here"), None);
    }

    #[test]
    fn reads_the_anchors_phases() {
        let line = "/tmp/a.png: 600x400, aa 2, mode packet8, spheres user(double), 1 threads: \
                    parse 0.004 s, build 0.002 s, tracing 0.129 s (cpu 0.066 s), write 0.013 s, \
                    2716246 rays, 21.0 M rays/s (camera 960000, reflection 196993, shadow 1559253)";
        assert_eq!(labelled_seconds(line, "parse"), Some(0.004));
        assert_eq!(labelled_seconds(line, "build"), Some(0.002));
        assert_eq!(labelled_seconds(line, "tracing"), Some(0.129));
        assert_eq!(labelled_seconds(line, "render"), None);
        let seed = "s.ppm: 600x400, aa 2, 1 thread: parse 0.000 s, render 0.517 s";
        assert_eq!(labelled_seconds(seed, "render"), Some(0.517));
    }

    #[test]
    fn reads_the_floor() {
        let out = "\
double AVX2 camera rays     : 2716160 rays x 3 objects: best of 11 19.94 ms = 7.34 ns/ray = 2.45 ns per ray-object test, 136 M rays/s (rays hitting: 79%)
double AVX2 random rays     : 2716160 rays x 3 objects: best of 11 28.67 ms = 10.55 ns/ray
float  AVX2 camera rays     : 2716160 rays x 3 objects: best of 11 10.73 ms = 3.95 ns/ray
double AVX2 camera, skip    : 2716160 rays x 3 objects: best of 11 19.01 ms = 7.00 ns/ray
double AVX2 shading         : 1156608 hits, 2 lights: best of 11 13.63 ms = 11.78 ns/hit
";
        let floor = parse_floor(out).expect("both lines");
        assert_eq!(floor.intersection_ms, 19.01);
        assert_eq!(floor.shading_ms, 13.63);
        let without_skip: String = out
            .lines()
            .filter(|l| !l.contains("skip"))
            .collect::<Vec<_>>()
            .join("\n");
        assert_eq!(
            parse_floor(&without_skip).map(|f| f.intersection_ms),
            Some(19.94)
        );
        assert_eq!(
            parse_floor("double AVX2 camera rays : best of 3 1.0 ms"),
            None
        );
    }

    #[test]
    fn compares_images_pixel_by_pixel() {
        let a = Rgb {
            width: 2,
            height: 1,
            bytes: vec![0, 0, 0, 10, 20, 30],
        };
        let same = Rgb {
            bytes: a.bytes.clone(),
            ..a
        };
        assert_eq!(compare(&a, &same), "identical");
        let other = Rgb {
            bytes: vec![0, 0, 0, 10, 23, 30],
            ..a
        };
        assert_eq!(compare(&a, &other), "1 pixel differs (up to 3 levels)");
        let ppm = decode_ppm(b"P6\n2 1\n255\n\x00\x00\x00\x0a\x14\x1e").expect("valid");
        assert_eq!(compare(&a, &ppm), "identical");
    }

    #[test]
    fn reads_the_peak_resident_set() {
        let status = "Name:\ttessera\nVmPeak:\t  123 kB\nVmHWM:\t   45678 kB\nVmRSS:\t 100 kB\n";
        assert_eq!(vm_hwm_kib(status), Some(45678));
        assert_eq!(vm_hwm_kib("Name:\tzombie\n"), None);
    }

    #[test]
    fn dates_from_days_since_1970() {
        assert_eq!(civil_date(0), "1970-01-01");
        assert_eq!(civil_date(11_016), "2000-02-29");
        assert_eq!(civil_date(19_723), "2024-01-01");
    }

    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median(Vec::new()), None);
    }
}
