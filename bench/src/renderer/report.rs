//! What the report says of the run as a whole rather than of one case: its head (how
//! to regenerate it, the machine, the programs, the date and the load) and the CSV of
//! every program's runs on every case, sphere and mesh alike.

use std::fmt::Write as _;
use std::path::PathBuf;

use super::image::ImageDiff;
use super::{cpu_model, AnchorKind, CaseResult, Runs, NOT_GIVEN};
use crate::Options;

/// Today's date (UTC) as YYYY-MM-DD.
fn utc_date() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    civil_date(secs / 86_400)
}

/// The proleptic Gregorian date `days` days after 1970-01-01.
pub(super) fn civil_date(days: u64) -> String {
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
pub(super) fn load_average() -> String {
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
pub(super) fn header_markdown(opts: &Options, load: &str) -> String {
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

/// Every program's runs on every case, sphere and mesh cases alike; the anchor's rows
/// also give its image's difference from Tessera's as numbers.
pub(super) fn comparison_csv(results: &[&CaseResult]) -> String {
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
