//! The mesh half of `tessera-bench --suite renderer`.
//!
//! - **Mesh scenes** (`--mesh-scenes`, `--anchor-mesh`): the scenes the renderer's mesh
//!   code is measured on, each run as a whole `tessera render` process at 1 and 2
//!   threads and as the Embree mesh anchor's at 1 thread, alternating, with the same
//!   machinery as the sphere cases. The anchor's world vertices are single precision,
//!   so its image may differ from Tessera's in a few pixels by a level: the table gives
//!   how many and by how much, not only whether they are identical.
//! - **Parse and build against triangles**: wavy grids of 1,000 to 10 million
//!   triangles written by the bench as binary PLY, Tessera's parse (the scene and its
//!   mesh file) and build (`Tracer::new`, which builds the mesh's hierarchy) timed in
//!   process, and the anchor's as it prints them; log-log slopes show whether either
//!   grows faster than linearly.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result};
use render::{MeshFiles, Scene, Shape, Tracer};

use super::{
    cpu_model, ms, paired_ratio, paired_ratio_of, run_case, slope_text, thousands, time_process,
    AnchorKind, Case, CaseResult, Options, Program, Runs, NOT_GIVEN,
};
use crate::measure;
use crate::plot::{Panel, Series};
use crate::scaling;

/// The mesh scenes, in the order of the report: four single meshes from 20,000 to
/// 89,000 triangles, then 64 instances of one.
const SCENES: [&str; 5] = ["bunny", "armadillo", "elephant", "dragon", "bunny64"];

/// One mesh scene's runs, with the triangles it shows.
pub(super) struct MeshResult {
    pub result: CaseResult,
    /// Over every mesh object, instances counted each time.
    triangles: u64,
}

/// Runs every mesh scene: Tessera at 1 and 2 threads and the mesh anchor at 1,
/// alternating, `reps` times. Nothing when the scenes are not given.
pub(super) fn run_cases(opts: &Options, dir: &Path) -> Result<Vec<MeshResult>> {
    let Some(scenes) = &opts.mesh_scenes else {
        eprintln!("renderer: mesh scenes not given (--mesh-scenes DIR); skipping them");
        return Ok(Vec::new());
    };
    let mut out = Vec::new();
    for name in SCENES {
        let path = scenes.join(format!("{name}.json"));
        let scene = load(&path, scenes)?;
        let case = Case {
            name: name.to_owned(),
            scene: path,
            width: scene.settings.width,
            height: scene.settings.height,
            aa: scene.settings.aa,
            seed_frame: false,
            anchor: AnchorKind::Meshes,
        };
        let triangles = referenced_triangles(&scene);
        drop(scene);
        out.push(MeshResult {
            result: run_case(opts, &opts.tessera, case, dir)?,
            triangles,
        });
    }
    Ok(out)
}

/// Reads and parses the scene at `path`, its mesh files beside it in `dir`.
fn load(path: &Path, dir: &Path) -> Result<Scene> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    render::parse_scene_with(&text, &MeshFiles::beside(dir))
        .with_context(|| format!("{}", path.display()))
}

/// The triangles of every mesh object of `scene`, a file shown by several objects
/// counted once per object: what the renderer traces, not what it holds.
fn referenced_triangles(scene: &Scene) -> u64 {
    scene
        .objects
        .iter()
        .filter_map(|o| match &o.shape {
            Shape::Mesh(mesh) => Some(mesh.file.geometry.data.triangles.len() as u64),
            _ => None,
        })
        .sum()
}

/// The mesh scenes' tables for `renderer.md`.
pub(super) fn cases_markdown(opts: &Options, results: &[MeshResult]) -> String {
    let mut md = String::from("## Mesh scenes\n\n");
    let Some(scenes) = &opts.mesh_scenes else {
        let _ = writeln!(
            md,
            "Mesh scenes {NOT_GIVEN} (`--mesh-scenes DIR`, the directory of bunny.json \
             and the others).\n"
        );
        return md;
    };
    let anchor_given = opts.external.anchor_mesh.is_some();
    let _ = writeln!(
        md,
        "The scenes of `{}` as they are (each names its image size and aa), Tessera \
         against the Embree mesh anchor run with `--spheres user --robust --threads 1` \
         (Embree's watertight mode, the fair match for a watertight renderer). Whole \
         process as above, median of {} runs (minimum in brackets), the programs in turn \
         (Tessera 1 thread, anchor, Tessera 2 threads). Triangles count every instance.\n\n\
         | scene | triangles | Tessera, 1 thread | anchor, 1 thread | Tessera / anchor | Tessera, 2 threads | speed-up 2 / 1, whole | speed-up 2 / 1, tracing | pixels differing | largest difference |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        scenes.display(),
        opts.reps,
    );
    let ratio = |x: Option<f64>| x.map_or("–".into(), |x| format!("{x:.2}"));
    for m in results {
        let r = &m.result;
        let against = r.anchor.as_ref().map_or(NOT_GIVEN.to_owned(), |a| {
            ratio(paired_ratio(&r.tessera_1, a))
        });
        let (differing, largest) = match r.anchor_image {
            None => (NOT_GIVEN.to_owned(), NOT_GIVEN.to_owned()),
            Some(diff) => match diff.counts() {
                Some((n, level)) => (
                    thousands(n),
                    format!("{level} level{}", if level == 1 { "" } else { "s" }),
                ),
                None => (diff.to_string(), "–".into()),
            },
        };
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {against} | {} | {} | {} | {differing} | {largest} |",
            r.case.name,
            thousands(m.triangles),
            super::median_min(&r.tessera_1),
            r.anchor
                .as_ref()
                .map_or(NOT_GIVEN.to_owned(), super::median_min),
            super::median_min(&r.tessera_2),
            ratio(paired_ratio(&r.tessera_1, &r.tessera_2)),
            ratio(paired_ratio_of(&r.tessera_1, &r.tessera_2, |x| x.tracing)),
        );
    }
    let threads_differ: Vec<String> = results
        .iter()
        .filter(|m| m.result.threads_image != "identical")
        .map(|m| format!("{}: {}", m.result.case.name, m.result.threads_image))
        .collect();
    let _ = writeln!(
        md,
        "\nThe ratios are medians of the ratios of runs in the same round, as above; the \
         tracing speed-up is that of the render time `tessera render` prints (after \
         loading the scene and building the hierarchies). Pixels differing and the \
         largest difference of a channel (in levels of 255) compare Tessera's 1-thread \
         PNG with the anchor's: a few pixels by a level are expected, the anchor's \
         vertices being single precision. Tessera's 2-thread images are {}.\n\n\
         ### Where the time goes (medians)\n\n\
         | scene | Tessera tracing, 1 thread | Tessera tracing, 2 threads | anchor parse | anchor build | anchor tracing | Tessera peak RSS | anchor peak RSS |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|",
        if threads_differ.is_empty() {
            "identical to the 1-thread ones".to_owned()
        } else {
            format!("not all identical to the 1-thread ones ({})", threads_differ.join("; "))
        },
    );
    let opt_ms = |v: Option<f64>| v.map_or("–".to_owned(), ms);
    let mib = |v: Option<f64>| v.map_or("–".to_owned(), |m| format!("{m:.0} MiB"));
    for m in results {
        let r = &m.result;
        let a = r.anchor.as_ref();
        let anchor_ms = |f: fn(&super::Run) -> Option<f64>| {
            a.map_or(NOT_GIVEN.to_owned(), |a| opt_ms(a.median_of(f)))
        };
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            r.case.name,
            opt_ms(r.tessera_1.median_of(|x| x.tracing)),
            opt_ms(r.tessera_2.median_of(|x| x.tracing)),
            anchor_ms(|x| x.parse),
            anchor_ms(|x| x.build),
            anchor_ms(|x| x.tracing),
            mib(r.tessera_1.peak_rss_mib()),
            a.map_or(NOT_GIVEN.to_owned(), |a| mib(a.peak_rss_mib())),
        );
    }
    let _ = writeln!(
        md,
        "\nParse and build against mesh size, from 1,000 triangles up, are in \
         `renderer-mesh-build.md`{}.\n",
        if anchor_given {
            ""
        } else {
            " (Tessera alone: the mesh anchor was not given)"
        }
    );
    md
}

/// The sizes of the parse and build sweep: powers of ten from 1,000 up to `max`, and
/// `max` itself if it is none.
fn sweep_sizes(max: usize) -> Vec<usize> {
    let mut sizes: Vec<usize> = std::iter::successors(Some(1_000usize), |n| n.checked_mul(10))
        .take_while(|&n| n <= max)
        .collect();
    if sizes.last() != Some(&max) && max >= 1_000 {
        sizes.push(max);
    }
    sizes
}

/// The columns and rows of cells of a grid of `triangles` triangles (two per cell,
/// rounded down to an even count): the most nearly square factorisation, so that the
/// grid is a surface, not a strip, for every power of ten.
fn grid_cells(triangles: usize) -> (usize, usize) {
    let cells = (triangles / 2).max(1);
    let mut rows = (cells as f64).sqrt() as usize;
    while rows > 1 && !cells.is_multiple_of(rows) {
        rows -= 1;
    }
    (cells / rows.max(1), rows.max(1))
}

/// What [`write_grid_ply`] wrote.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct GridCounts {
    pub vertices: usize,
    pub triangles: usize,
}

/// [`write_grid_ply`] to the file `path`: the same bytes for the same `triangles`, so
/// that a benchmark can make a mesh of any size when it runs instead of keeping one.
pub(crate) fn write_grid_file(path: &Path, triangles: usize) -> Result<GridCounts> {
    let file =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut w = std::io::BufWriter::new(file);
    write_grid_ply(&mut w, triangles)
        .and_then(|c| w.flush().map(|()| c))
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Writes a wavy grid of about `triangles` triangles (see [`grid_cells`]) as binary
/// little-endian PLY: float vertices shared between cells, faces of three `int`
/// indices, as scanned meshes are stored. The waves give the hierarchy boxes of every
/// shape, not a plane's; the heights stay well apart from the cell size, so no
/// triangle is degenerate.
fn write_grid_ply(out: &mut impl std::io::Write, triangles: usize) -> std::io::Result<GridCounts> {
    let (columns, rows) = grid_cells(triangles);
    let vertices = (columns + 1) * (rows + 1);
    let counts = GridCounts {
        vertices,
        triangles: 2 * columns * rows,
    };
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment tessera-bench wavy grid, \
         {columns} x {rows} cells\nelement vertex {vertices}\nproperty float x\n\
         property float y\nproperty float z\nelement face {}\n\
         property list uchar int vertex_indices\nend_header\n",
        counts.triangles
    )?;
    // Square cells over [-1, 1] on the longer side.
    let cell = 2.0 / columns.max(rows) as f64;
    for j in 0..=rows {
        for i in 0..=columns {
            let x = -1.0 + i as f64 * cell;
            let z = -1.0 + j as f64 * cell;
            let y = 0.1 * (6.0 * x).sin() * (5.0 * z).cos();
            for v in [x, y, z] {
                out.write_all(&(v as f32).to_le_bytes())?;
            }
        }
    }
    let index = |i: usize, j: usize| (j * (columns + 1) + i) as i32;
    let mut face = [0u8; 13];
    face[0] = 3;
    for j in 0..rows {
        for i in 0..columns {
            let (a, b, c, d) = (
                index(i, j),
                index(i + 1, j),
                index(i + 1, j + 1),
                index(i, j + 1),
            );
            for tri in [[a, b, c], [a, c, d]] {
                for (k, v) in tri.iter().enumerate() {
                    face[1 + 4 * k..5 + 4 * k].copy_from_slice(&v.to_le_bytes());
                }
                out.write_all(&face)?;
            }
        }
    }
    Ok(counts)
}

/// A scene of the grid alone at 8 × 8, aa 1: its tracing is negligible, so the
/// anchor's whole run is about parsing and building.
pub(crate) fn grid_scene_json(file: &str) -> String {
    format!(
        r#"{{
 "camera": {{ "position": "0 2.5 -2.5", "look_at": "0 0 0" }},
 "image": {{ "width": 8, "height": 8, "aa": 1 }},
 "lights": [ {{ "position": "-5 10 -5", "color": "1 1 1 0" }} ],
 "objects": [ {{ "type": "mesh", "file": "{file}", "color": "0.8 0.7 0.6 0" }} ]
}}
"#
    )
}

/// One size of the parse and build sweep: the best of its runs, seconds.
struct BuildPoint {
    triangles: usize,
    file_bytes: u64,
    tessera_parse: [f64; 2],
    /// At 1 and 2 threads.
    tessera_build: [f64; 2],
    anchor_parse: Option<f64>,
    anchor_build: Option<f64>,
    anchor_peak_mib: Option<f64>,
}

/// The best parse and build of `runs` Tessera runs on `threads` threads: the scene
/// read and parsed (its mesh file read, hashed and parsed) afresh each time, since a
/// mesh's hierarchy is kept with its geometry once built.
pub(crate) fn time_tessera(
    scene: &Path,
    dir: &Path,
    threads: usize,
    runs: u32,
) -> Result<(f64, f64)> {
    let pool = measure::pool(threads)?;
    let (mut parse, mut build) = (f64::INFINITY, f64::INFINITY);
    for _ in 0..runs {
        let (p, b) = pool.install(|| -> Result<(f64, f64)> {
            let started = Instant::now();
            let parsed = load(scene, dir)?;
            let parsed_at = started.elapsed().as_secs_f64();
            let built = Instant::now();
            let tracer = Tracer::new(&parsed, parsed.settings);
            let b = built.elapsed().as_secs_f64();
            // Freed outside the timings.
            drop((tracer, parsed));
            Ok((parsed_at, b))
        })?;
        parse = parse.min(p);
        build = build.min(b);
    }
    Ok((parse, build))
}

/// Parse and build against triangles: `renderer-mesh-build.{md,csv,png}`.
pub(super) fn write_build_scaling(opts: &Options, out: &Path) -> Result<()> {
    let dir = tempfile::tempdir().context("cannot make a temporary directory")?;
    let runs = opts.reps.min(3);
    let mut points = Vec::new();
    for triangles in sweep_sizes(opts.mesh_max_triangles) {
        let ply = dir.path().join("grid.ply");
        let scene = dir.path().join("grid.json");
        let counts = write_grid_file(&ply, triangles)?;
        std::fs::write(&scene, grid_scene_json("grid.ply"))
            .with_context(|| format!("cannot write {}", scene.display()))?;
        let file_bytes = std::fs::metadata(&ply).map_or(0, |m| m.len());
        let one = time_tessera(&scene, dir.path(), 1, runs)?;
        let two = time_tessera(&scene, dir.path(), 2, runs)?;
        let mut anchor = Runs::default();
        if let Some(path) = &opts.external.anchor_mesh {
            for _ in 0..runs {
                let mut cmd = Command::new(path);
                cmd.arg(&scene)
                    .arg("-o")
                    .arg(dir.path().join("anchor.png"))
                    .args(["--spheres", "user", "--robust", "--threads", "1"]);
                anchor.0.push(time_process(&mut cmd, Program::Anchor)?);
            }
        }
        let best =
            |f: fn(&super::Run) -> Option<f64>| anchor.0.iter().filter_map(f).reduce(f64::min);
        let point = BuildPoint {
            triangles: counts.triangles,
            file_bytes,
            tessera_parse: [one.0, two.0],
            tessera_build: [one.1, two.1],
            anchor_parse: best(|r| r.parse),
            anchor_build: best(|r| r.build),
            anchor_peak_mib: anchor.peak_rss_mib(),
        };
        eprintln!(
            "meshes: {} triangles: Tessera parse {}, build {} / {} (1 / 2 threads); anchor parse {}, build {}",
            thousands(point.triangles as u64),
            ms(point.tessera_parse[0]),
            ms(point.tessera_build[0]),
            ms(point.tessera_build[1]),
            point.anchor_parse.map_or(NOT_GIVEN.to_owned(), ms),
            point.anchor_build.map_or(NOT_GIVEN.to_owned(), ms),
        );
        points.push(point);
        std::fs::remove_file(&ply).with_context(|| format!("cannot remove {}", ply.display()))?;
    }
    std::fs::write(
        out.join("renderer-mesh-build.md"),
        build_markdown(opts, runs, &points),
    )?;
    std::fs::write(out.join("renderer-mesh-build.csv"), build_csv(&points))?;
    crate::plot::write_png(
        &out.join("renderer-mesh-build.png"),
        &build_panels(&points),
        2,
        (600, 440),
    )
}

/// The curves of the sweep: name, points (triangles, seconds). A time below the
/// anchor's resolution (0 ms printed) is left out: it has no place on a log scale.
fn curves(points: &[BuildPoint]) -> Vec<(&'static str, Vec<(f64, f64)>)> {
    let of = |f: &dyn Fn(&BuildPoint) -> Option<f64>| -> Vec<(f64, f64)> {
        points
            .iter()
            .filter_map(|p| Some((p.triangles as f64, f(p)?)))
            .filter(|&(_, s)| s > 0.0)
            .collect()
    };
    vec![
        ("Tessera parse, 1 thread", of(&|p| Some(p.tessera_parse[0]))),
        (
            "Tessera parse, 2 threads",
            of(&|p| Some(p.tessera_parse[1])),
        ),
        ("anchor parse", of(&|p| p.anchor_parse)),
        ("Tessera build, 1 thread", of(&|p| Some(p.tessera_build[0]))),
        (
            "Tessera build, 2 threads",
            of(&|p| Some(p.tessera_build[1])),
        ),
        ("anchor build", of(&|p| p.anchor_build)),
    ]
}

/// Triangles per second, in millions; "–" for a time below the anchor's resolution
/// (it prints milliseconds, so a small mesh's parse may read 0).
fn per_second(triangles: usize, seconds: Option<f64>) -> String {
    match seconds {
        None => NOT_GIVEN.to_owned(),
        Some(s) if s <= 0.0 => "–".to_owned(),
        Some(s) => format!("{:.2} M/s", triangles as f64 / s / 1e6),
    }
}

fn build_markdown(opts: &Options, runs: u32, points: &[BuildPoint]) -> String {
    let mut md = format!(
        "# Parse and build against triangles\n\n\
         Regenerated with the renderer comparison (`renderer.md`, same command). Wavy \
         grids written by the bench as binary little-endian PLY (float vertices shared \
         between cells, `int` indices), one mesh in a scene of its own at 8 × 8, aa 1. \
         Each figure is the best of {runs} runs.\n\n\
         - CPU: {}\n\
         - Tessera, in process: *parse* is reading the scene and `parse_scene_with` \
         (reading, hashing and parsing the mesh file), *build* is `Tracer::new` (the \
         mesh's hierarchy), both in a rayon pool of 1 and of 2 threads\n\
         - anchor ({}): the parse and build times it prints, 1 thread, `--spheres user \
         --robust`\n\n\
         Slopes are least-squares fits of log time against log triangles (1: linear).\n\n\
         | curve | slope |\n|---|---:|\n",
        cpu_model(),
        opts.external
            .anchor_mesh
            .as_ref()
            .map_or(NOT_GIVEN.to_owned(), |p| format!("`{}`", p.display())),
    );
    for (name, curve) in curves(points) {
        let _ = writeln!(
            md,
            "| {name} | {} |",
            slope_text(scaling::loglog_slope(&curve))
        );
    }
    let _ = writeln!(
        md,
        "\n## Times\n\n\
         | triangles | file | Tessera parse | Tessera build, 1 thread | Tessera build, 2 threads | build speed-up 2 / 1 | anchor parse | anchor build | anchor peak RSS |\n\
         |---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    let opt_ms = |v: Option<f64>| v.map_or(NOT_GIVEN.to_owned(), ms);
    for p in points {
        let _ = writeln!(
            md,
            "| {} | {:.1} MiB | {} | {} | {} | {:.2} | {} | {} | {} |",
            thousands(p.triangles as u64),
            p.file_bytes as f64 / (1024.0 * 1024.0),
            ms(p.tessera_parse[0]),
            ms(p.tessera_build[0]),
            ms(p.tessera_build[1]),
            p.tessera_build[0] / p.tessera_build[1],
            opt_ms(p.anchor_parse),
            opt_ms(p.anchor_build),
            p.anchor_peak_mib
                .map_or("–".to_owned(), |m| format!("{m:.0} MiB")),
        );
    }
    let _ = writeln!(
        md,
        "\nTessera's parse is at 1 thread (at 2 threads it is in the CSV); the anchor's \
         peak RSS is its whole process's.\n\n\
         ## Triangles per second\n\n\
         | triangles | Tessera parse | Tessera build, 1 thread | Tessera build, 2 threads | anchor parse | anchor build |\n\
         |---:|---:|---:|---:|---:|---:|"
    );
    for p in points {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} |",
            thousands(p.triangles as u64),
            per_second(p.triangles, Some(p.tessera_parse[0])),
            per_second(p.triangles, Some(p.tessera_build[0])),
            per_second(p.triangles, Some(p.tessera_build[1])),
            per_second(p.triangles, p.anchor_parse),
            per_second(p.triangles, p.anchor_build),
        );
    }
    md
}

fn build_csv(points: &[BuildPoint]) -> String {
    let mut csv = String::from(
        "triangles,file_bytes,tessera_parse_1_thread_s,tessera_parse_2_threads_s,tessera_build_1_thread_s,tessera_build_2_threads_s,anchor_parse_s,anchor_build_s,anchor_peak_rss_mib\n",
    );
    let opt = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.6}"));
    for p in points {
        let _ = writeln!(
            csv,
            "{},{},{:.6},{:.6},{:.6},{:.6},{},{},{}",
            p.triangles,
            p.file_bytes,
            p.tessera_parse[0],
            p.tessera_parse[1],
            p.tessera_build[0],
            p.tessera_build[1],
            opt(p.anchor_parse),
            opt(p.anchor_build),
            p.anchor_peak_mib
                .map_or(String::new(), |m| format!("{m:.1}")),
        );
    }
    csv
}

/// Two log-log panels, parse and build, each curve labelled with its slope.
fn build_panels(points: &[BuildPoint]) -> Vec<Panel> {
    let mut curves = curves(points).into_iter();
    let mut panel = |title: &str| Panel {
        title: title.into(),
        x_label: "triangles (log)".into(),
        y_label: "time (ms, log)".into(),
        log_x: true,
        log_y: true,
        series: curves
            .by_ref()
            .take(3)
            .filter(|(_, c)| !c.is_empty())
            .map(|(name, c)| Series {
                label: format!("{name} (slope {})", slope_text(scaling::loglog_slope(&c))),
                points: c.iter().map(|&(x, s)| (x, s * 1e3)).collect(),
                joined: true,
                markers: true,
            })
            .collect(),
    };
    vec![
        panel("Parse against triangles (wavy grid PLY)"),
        panel("Build against triangles (wavy grid PLY)"),
    ]
}

#[cfg(test)]
mod tests {
    use super::super::ImageDiff;
    use super::*;

    #[test]
    fn the_sweep_goes_by_powers_of_ten_to_its_cap() {
        assert_eq!(
            sweep_sizes(10_000_000),
            [1_000, 10_000, 100_000, 1_000_000, 10_000_000]
        );
        assert_eq!(sweep_sizes(250_000), [1_000, 10_000, 100_000, 250_000]);
        assert_eq!(sweep_sizes(1_000), [1_000]);
    }

    #[test]
    fn grids_have_the_triangles_asked_for_and_are_not_strips() {
        for n in [1_000, 10_000, 100_000, 1_000_000, 10_000_000, 20_000_000] {
            let (columns, rows) = grid_cells(n);
            assert_eq!(2 * columns * rows, n, "{n}");
            assert!(columns <= 2 * rows, "{n}: {columns} x {rows}");
        }
        // An odd count is rounded down; a prime number of cells makes a strip.
        assert_eq!(grid_cells(1_001), (25, 20));
        assert_eq!(grid_cells(2 * 7_919), (7_919, 1));
    }

    #[test]
    fn the_grid_ply_reads_back_with_no_degenerate_triangle() {
        for n in [1_000, 10_000] {
            let mut bytes = Vec::new();
            let counts = write_grid_ply(&mut bytes, n).expect("written to memory");
            assert_eq!(counts.triangles, n);
            let mesh = render::mesh::ply::read(&bytes).expect("a valid PLY");
            assert_eq!(mesh.positions.len(), counts.vertices);
            assert_eq!(mesh.triangles.len(), n);
            assert!(mesh
                .triangles
                .iter()
                .all(|t| t.iter().all(|&i| (i as usize) < counts.vertices)));
            assert!(!mesh
                .triangles
                .iter()
                .any(|&t| render::mesh::load::degenerate(&mesh, t)));
            // Vertices are shared: a grid has about half as many as triangles.
            assert!(counts.vertices < n * 2 / 3, "{}", counts.vertices);
        }
    }

    #[test]
    fn the_grid_scene_parses_with_its_mesh_file() {
        let dir = tempfile::tempdir().expect("a temporary directory");
        let mut bytes = Vec::new();
        write_grid_ply(&mut bytes, 1_000).expect("written to memory");
        std::fs::write(dir.path().join("g.ply"), bytes).expect("written");
        let scene =
            render::parse_scene_with(&grid_scene_json("g.ply"), &MeshFiles::beside(dir.path()))
                .expect("a valid scene");
        assert_eq!((scene.settings.width, scene.settings.height), (8, 8));
        assert_eq!(referenced_triangles(&scene), 1_000);
    }

    #[test]
    fn the_tracing_speed_up_pairs_runs_of_one_round() {
        let run = |wall: f64, tracing: Option<f64>| super::super::Run {
            wall,
            tracing,
            parse: None,
            build: None,
            peak_rss_kib: None,
        };
        let one = Runs(vec![
            run(1.0, Some(0.8)),
            run(1.2, Some(0.9)),
            run(2.0, None),
        ]);
        let two = Runs(vec![
            run(0.6, Some(0.4)),
            run(0.7, Some(0.5)),
            run(1.0, Some(0.5)),
        ]);
        // Rounds 1 and 2 only: 2.0 and 1.8.
        let speedup = paired_ratio_of(&one, &two, |r| r.tracing).expect("two rounds");
        assert!((speedup - 1.9).abs() < 1e-12, "{speedup}");
    }

    #[test]
    fn throughput_is_in_millions_and_none_below_the_resolution() {
        assert_eq!(per_second(2_000_000, Some(0.5)), "4.00 M/s");
        assert_eq!(per_second(1_000, Some(0.0)), "–");
        assert_eq!(per_second(1_000, None), NOT_GIVEN);
    }

    #[test]
    fn image_differences_are_counted_and_said() {
        let diff = ImageDiff::Pixels {
            differing: 3,
            max_level: 1,
        };
        assert_eq!(diff.counts(), Some((3, 1)));
        assert_eq!(diff.to_string(), "3 pixels differ (up to 1 levels)");
        let sizes = ImageDiff::Sizes {
            a: (8, 8),
            b: (4, 4),
        };
        assert_eq!(sizes.counts(), None);
    }
}
