//! How commands show renders and jobs: the one-line summaries of a finished render,
//! job or sequence, a job's state and frames, and the JSON objects of `--json`.

use std::path::Path;

use protocol::{FrameProgress, JobStatus};
use render::RenderSettings;

/// A figure with its noun, singular for exactly one: `1 thread`, `4 threads`, `1
/// sample/pixel`, `0.5 levels`. One helper for every figure printed, so that none says
/// `1 threads`. `noun` is the singular; a noun with a `/` (`sample/pixel`) takes its
/// plural before it.
pub fn counted(figure: impl std::fmt::Display, noun: &str) -> String {
    let figure = figure.to_string();
    if figure == "1" {
        return format!("1 {noun}");
    }
    match noun.split_once('/') {
        Some((counted, per)) => format!("{figure} {counted}s/{per}"),
        None => format!("{figure} {noun}s"),
    }
}

/// A size in bytes as listings show it, in decimal units: `812 bytes`, `4.2 kB`,
/// `33.7 MB`, `1.50 GB`.
pub fn bytes(n: u64) -> String {
    match n {
        0..=999 => counted(n, "byte"),
        1_000..=999_999 => format!("{:.1} kB", n as f64 / 1e3),
        1_000_000..=999_999_999 => format!("{:.1} MB", n as f64 / 1e6),
        _ => format!("{:.2} GB", n as f64 / 1e9),
    }
}

/// A job's files in a listing: `, 3 files (33.7 MB)`; nothing for a job without.
pub fn assets_summary(a: &protocol::JobAssets) -> String {
    if a.files == 0 {
        return String::new();
    }
    format!(", {} ({})", counted(a.files, "file"), bytes(a.bytes))
}

/// What a render spent and how wrong it may be, for the summary lines of `render`,
/// `up` and `submit --wait`: `4 samples/pixel (grid 2x2, 96000 in all), estimated
/// error 0.842 levels`. The mean is exact for the grid and jittered samplers, a
/// fraction of the budget for adaptive sampling.
pub fn sampling_summary(settings: &RenderSettings, samples: u64, error: Option<f64>) -> String {
    let n = settings.aa;
    let pixels = settings.pixel_count().max(1);
    let mean = if samples.is_multiple_of(pixels) {
        (samples / pixels).to_string()
    } else {
        format!("{:.2}", samples as f64 / pixels as f64)
    };
    let pattern = match settings.sampling {
        render::Sampling::Adaptive { .. } if settings.sampling.time_decides() => {
            format!("adaptive up to {n}x{n}, no target")
        }
        render::Sampling::Adaptive { .. } => format!(
            "adaptive up to {n}x{n}, target {}",
            counted(
                settings.sampling.target_error().unwrap_or_default(),
                "level"
            )
        ),
        other => format!("{} {n}x{n}", other.name()),
    };
    let error = match error {
        Some(e) => format!("estimated error {e:.3} levels"),
        None if n == 1 => "no error estimate from 1 sample/pixel".to_string(),
        None => "no error estimate".to_string(),
    };
    format!(
        "{} ({pattern}, {samples} in all), {error}",
        counted(mean, "sample/pixel")
    )
}

/// The one-line summary of a finished job: size, samples spent, estimated error, tiles,
/// time.
pub fn summary(output: &Path, status: &JobStatus) -> String {
    // The time rendering took: the queue's wait is not the farm's speed.
    let queued = status.queued_ms.unwrap_or(0).min(status.elapsed_ms);
    let secs = (status.elapsed_ms - queued) as f64 / 1000.0;
    let wait = if queued > 0 {
        format!(" after {:.1} s in the queue", queued as f64 / 1000.0)
    } else {
        String::new()
    };
    let settings = verify::render_settings(&status.settings);
    // As `tessera render` says it: whether the time limit, not the target, ended it.
    let note = match (
        status.stopped_on_time_limit,
        settings.sampling.time_decides(),
    ) {
        (false, _) => "",
        (true, false) => "; stopped by the time limit before the target",
        (true, true) => "; as far as the time limit allowed",
    };
    format!(
        "{}: {}x{}, {}{note}, {}, rendered in {:.3} s{wait}, {:.1} M rays/s",
        output.display(),
        status.settings.width,
        status.settings.height,
        sampling_summary(&settings, status.samples, status.estimated_error),
        counted(status.tiles_total, "tile"),
        secs,
        status.rays as f64 / secs.max(1e-9) / 1e6
    )
}

/// The one-line summary of a finished sequence.
pub fn sequence_summary(dir: &Path, status: &JobStatus) -> String {
    let frames = status.frames.as_ref().map_or(0, |f| f.done);
    let queued = status.queued_ms.unwrap_or(0).min(status.elapsed_ms);
    let secs = (status.elapsed_ms - queued) as f64 / 1000.0;
    format!(
        "{}: {frames} frames of {}x{}, {}, rendered in {:.3} s ({:.2} frames/s), {:.1} M rays/s",
        dir.display(),
        status.settings.width,
        status.settings.height,
        sampling_summary(
            &verify::render_settings(&status.settings),
            status.samples / u64::from(frames.max(1)),
            status.estimated_error
        ),
        secs,
        f64::from(frames) / secs.max(1e-9),
        status.rays as f64 / secs.max(1e-9) / 1e6
    )
}

pub use coordinator::json::{shown_state, status_json};

/// The frames line of `tessera status` for a sequence.
pub fn frames_summary(f: &FrameProgress) -> String {
    let total = f.last - f.first + 1;
    let mut line = format!("frames {}-{}: {}/{total} done", f.first, f.last, f.done);
    if f.active > 0 {
        line.push_str(&format!(", {} rendering", f.active));
    }
    if f.cancelled > 0 {
        line.push_str(&format!(", {} cancelled", f.cancelled));
    }
    if f.failed > 0 {
        let listed: Vec<String> = f.failures.iter().map(|x| x.frame.to_string()).collect();
        line.push_str(&format!(", {} failed ({})", f.failed, listed.join(", ")));
    }
    line
}

/// A Unix time in milliseconds as `YYYY-MM-DD HH:MM:SS` UTC (the civil calendar from
/// days since the epoch; no time zone database needed).
pub fn utc(unix_ms: u64) -> String {
    let secs = unix_ms / 1000;
    let (days, rest) = ((secs / 86_400) as i64, secs % 86_400);
    // Howard Hinnant's days-to-civil algorithm.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02}:{:02}",
        rest / 3600,
        rest % 3600 / 60,
        rest % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_is_singular_and_every_other_figure_plural() {
        assert_eq!(counted(1, "thread"), "1 thread");
        assert_eq!(counted(2, "thread"), "2 threads");
        assert_eq!(counted(0, "tile"), "0 tiles");
        assert_eq!(counted(1.0, "level"), "1 level");
        assert_eq!(counted(0.5, "level"), "0.5 levels");
        assert_eq!(counted("1", "sample/pixel"), "1 sample/pixel");
        assert_eq!(counted("1.50", "sample/pixel"), "1.50 samples/pixel");
    }

    #[test]
    fn utc_times_are_the_calendar() {
        assert_eq!(utc(0), "1970-01-01 00:00:00");
        assert_eq!(utc(951_782_400_000), "2000-02-29 00:00:00");
        assert_eq!(utc(1_795_000_000_123), "2026-11-18 11:06:40");
    }
}
