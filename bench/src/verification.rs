//! What verifying the workers' results costs: the seed scene at 1920 × 1080, aa 2, on a
//! local farm of two one-thread workers, with the checks off, with the default sampled
//! verification (spot checks and audits) and with full verification (every tile
//! rendered by both workers). Farms are started fresh for each setting and the settings
//! interleaved, so that the machine's drift hits them alike; throughput is the ratio of
//! median wall times measured side by side in this run.

use std::fmt::Write as _;
use std::path::Path;
use std::time::Duration;

use anyhow::{Context, Result};
use protocol::{JobSpec, Overrides, Verification};

use super::scenes;
use super::Options;
use localfarm::{LocalFarm, WorkerSpec};

/// One way of checking results.
struct Setting {
    name: &'static str,
    coordinator_args: &'static [&'static str],
    verification: Verification,
}

const SETTINGS: [Setting; 3] = [
    Setting {
        name: "checks off (--spot-pixels 0 --audit-share 0)",
        coordinator_args: &["--spot-pixels", "0", "--audit-share", "0"],
        verification: Verification::Sampled,
    },
    Setting {
        name: "sampled (default: 16 spot pixels, audit share 0.01)",
        coordinator_args: &[],
        verification: Verification::Sampled,
    },
    Setting {
        name: "full (every tile on both workers)",
        coordinator_args: &[],
        verification: Verification::Full,
    },
];

/// Runs the suite; writes `verification.md` and `verification.csv`.
pub async fn run(opts: &Options, out: &Path) -> Result<()> {
    let (width, height, aa) = if opts.quick {
        (320, 180, 2)
    } else {
        (1920, 1080, 2)
    };
    let (rounds, jobs_per_farm) = if opts.quick { (1, 1) } else { (5, 4) };
    let mut walls: Vec<Vec<f64>> = vec![Vec::new(); SETTINGS.len()];
    // CPU seconds of the coordinator and of the workers, summed over the jobs.
    let mut cpu = vec![(0.0, 0.0); SETTINGS.len()];
    let mut csv = String::from("setting,round,job,wall_s\n");
    for round in 0..rounds {
        for (s, setting) in SETTINGS.iter().enumerate() {
            let args = setting.coordinator_args;
            let exe = opts.tessera.clone();
            let farm = tokio::task::spawn_blocking(move || {
                LocalFarm::start_with(&exe, &[WorkerSpec::default(), WorkerSpec::default()], args)
            })
            .await
            .context("starting a farm")??;
            farm.wait_for_workers(2, Duration::from_secs(20)).await?;
            let pids = farm.pids();
            let before: Vec<f64> = pids
                .iter()
                .map(|&p| cpu_seconds(p))
                .collect::<Result<_>>()?;
            for job in 0..jobs_per_farm {
                let spec = JobSpec {
                    scene: scenes::seed().json,
                    overrides: Overrides {
                        width: Some(width),
                        height: Some(height),
                        aa: Some(aa),
                        ..Overrides::default()
                    },
                    priority: 0,
                    verification: setting.verification,
                    time_limit_ms: None,
                    name: "bench".into(),
                    submitter: "tessera-bench".into(),
                    frame: 1,
                    frames: None,
                    assets: Vec::new(),
                    after: Vec::new(),
                    require: Vec::new(),
                };
                let (wall, _) = super::latency::run_job(farm.address(), spec).await?;
                eprintln!("verification: {}: {wall:.3} s", setting.name);
                writeln!(csv, "{:?},{round},{job},{wall:.4}", setting.name)?;
                walls[s].push(wall);
            }
            let after: Vec<f64> = pids
                .iter()
                .map(|&p| cpu_seconds(p))
                .collect::<Result<_>>()?;
            let used: Vec<f64> = after.iter().zip(&before).map(|(a, b)| a - b).collect();
            cpu[s].0 += used[0];
            cpu[s].1 += used[1..].iter().sum::<f64>();
        }
    }
    let mut md = String::new();
    writeln!(md, "## What verification costs\n")?;
    writeln!(
        md,
        "The seed scene at {width} × {height}, aa {aa}, on a local farm of two one-thread \
         workers; {rounds} rounds, each starting a fresh farm per setting and running \
         {jobs_per_farm} jobs on it, settings interleaved. Wall time from submission to \
         `done` as the client sees it. CPU: {}.\n",
        super::latency::cpu_model()
    )?;
    writeln!(
        md,
        "| setting | jobs | wall (s), median | range | throughput vs checks off | cost |"
    )?;
    writeln!(md, "|---|---:|---:|---|---:|---:|")?;
    let base = median(&walls[0]);
    for (setting, w) in SETTINGS.iter().zip(&walls) {
        let m = median(w);
        let (lo, hi) = w
            .iter()
            .fold((f64::MAX, f64::MIN), |(lo, hi), &x| (lo.min(x), hi.max(x)));
        writeln!(
            md,
            "| {} | {} | {m:.3} | {lo:.3}–{hi:.3} | {:.3} | {:+.1} % |",
            setting.name,
            w.len(),
            base / m,
            100.0 * (m / base - 1.0)
        )?;
    }
    writeln!(
        md,
        "\nCPU time, which the machine's other load disturbs far less than wall time: \
         the processes' user and system time over all the jobs of a setting (from \
         `/proc/PID/stat`, in clock ticks).\n"
    )?;
    writeln!(
        md,
        "| setting | coordinator CPU (s) | workers' CPU (s) | total | work vs checks off |"
    )?;
    writeln!(md, "|---|---:|---:|---:|---:|")?;
    let base_cpu = cpu[0].0 + cpu[0].1;
    for (setting, &(coordinator, workers)) in SETTINGS.iter().zip(&cpu) {
        let total = coordinator + workers;
        writeln!(
            md,
            "| {} | {coordinator:.2} | {workers:.2} | {total:.2} | {:+.1} % |",
            setting.name,
            100.0 * (total / base_cpu - 1.0)
        )?;
    }
    std::fs::write(out.join("verification.md"), &md)?;
    std::fs::write(out.join("verification.csv"), csv)?;
    println!("{md}");
    Ok(())
}

fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => (v[n / 2 - 1] + v[n / 2]) / 2.0,
    }
}

/// The unit of `/proc`'s times: Linux reports them in 1/100 s whatever the kernel's
/// own tick rate (USER_HZ is part of its interface).
const USER_HZ: f64 = 100.0;

/// User plus system CPU seconds of a process so far, from `/proc/PID/stat`.
pub(super) fn cpu_seconds(pid: u32) -> Result<f64> {
    stat_seconds(&pid.to_string(), 11)
}

/// User plus system CPU seconds of this process's children waited for so far, from
/// `/proc/self/stat`: around one child's run, its own.
pub(super) fn children_cpu_seconds() -> Result<f64> {
    stat_seconds("self", 13)
}

/// This process's own CPU seconds so far (all its threads).
pub(super) fn own_cpu_seconds() -> Result<f64> {
    stat_seconds("self", 11)
}

/// Two adjacent times of `/proc/PID/stat` added, in seconds: `first` counts the fields
/// after the command name (11 and 12 are utime and stime, 13 and 14 cutime and cstime).
fn stat_seconds(pid: &str, first: usize) -> Result<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .with_context(|| format!("cannot read /proc/{pid}/stat"))?;
    // The command name may hold spaces: the fields start after its closing parenthesis.
    let fields: Vec<&str> = stat
        .rsplit_once(')')
        .map_or("", |(_, rest)| rest)
        .split_whitespace()
        .collect();
    let ticks = |i: usize| -> Result<f64> {
        fields
            .get(i)
            .and_then(|f| f.parse::<f64>().ok())
            .with_context(|| format!("unreadable /proc/{pid}/stat"))
    };
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name (11
    // and 12 counted from 0); cutime and cstime the two after them.
    Ok((ticks(first)? + ticks(first + 1)?) / USER_HZ)
}
