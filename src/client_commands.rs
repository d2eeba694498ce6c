//! `tessera submit`, `status`, `list`, `cancel`, `fetch` and `workers`.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, Context, Result};
use coordinator::client::Client;
use transport::Endpoint;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use protocol::{JobId, JobSpec, JobState, JobStatus, Overrides, Sampling, Settings, WorkerStatus};
use render::RenderSettings;
use serde_json::{json, Value};

use crate::output::{default_output, write_atomically};
use crate::render_command::sampling_summary;

/// Reads a scene file for submission.
pub fn read_scene(path: &Path) -> Result<String> {
    std::fs::read_to_string(path)
        .with_context(|| format!("cannot read scene file {}", path.display()))
}

/// Submits; a refused scene's message is prefixed with the file name, exactly as
/// `tessera render` reports it.
pub async fn submit(
    client: &mut Client,
    scene_path: &Path,
    overrides: Overrides,
    priority: i32,
) -> Result<JobId> {
    let scene = read_scene(scene_path)?;
    client
        .submit(JobSpec {
            scene,
            overrides,
            priority,
        })
        .await
        .map_err(|e| anyhow!("{}: {e}", scene_path.display()))
}

/// Follows a job until it ends, with a progress bar on a terminal, and returns its
/// final status. A job that fails or is cancelled is an error.
pub async fn wait(client: &mut Client, job: JobId) -> Result<JobStatus> {
    let bar = if std::io::stderr().is_terminal() {
        ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr())
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} tiles {msg}",
        )
        .expect("the template is valid"),
    );
    let mut seen = 0;
    let status = loop {
        let status = client.watch(job, seen).await?;
        seen = status.tiles_done;
        bar.set_length(u64::from(status.tiles_total));
        bar.set_position(u64::from(status.tiles_done));
        let rate = status.rays as f64 / (status.elapsed_ms.max(1) as f64 / 1000.0) / 1e6;
        let eta = status.eta_ms.map_or(String::new(), |ms| {
            format!(", {:.1} s left", ms as f64 / 1000.0)
        });
        bar.set_message(format!("{rate:.1} M rays/s{eta}"));
        if status.state.is_final() {
            break status;
        }
    };
    bar.finish_and_clear();
    match status.state {
        JobState::Done => Ok(status),
        JobState::Failed => Err(anyhow!(
            "job {job} failed: {}",
            status.error.as_deref().unwrap_or("no reason given")
        )),
        other => Err(anyhow!("job {job} is {}", other.as_str())),
    }
}

/// Fetches a finished job's image and writes it.
pub async fn fetch_to(client: &mut Client, job: JobId, output: &Path) -> Result<usize> {
    let png = client.fetch(job).await?;
    write_atomically(output, &png)?;
    Ok(png.len())
}

/// The one-line summary of a finished job: size, samples spent, estimated error, tiles,
/// time.
pub fn summary(output: &Path, status: &JobStatus) -> String {
    let secs = status.elapsed_ms as f64 / 1000.0;
    format!(
        "{}: {}x{}, {}, {} tiles, {:.3} s, {:.1} M rays/s",
        output.display(),
        status.settings.width,
        status.settings.height,
        sampling_summary(
            &render_settings(&status.settings),
            status.samples,
            status.estimated_error
        ),
        status.tiles_total,
        secs,
        status.rays as f64 / secs.max(1e-9) / 1e6
    )
}

/// The renderer's view of a job's settings, for the summary.
fn render_settings(s: &Settings) -> RenderSettings {
    RenderSettings {
        width: s.width,
        height: s.height,
        aa: s.aa,
        max_depth: s.max_depth,
        sampling: match s.sampling {
            Sampling::Grid => render::Sampling::Grid,
            Sampling::Jittered => render::Sampling::Jittered,
            Sampling::Adaptive { target_milli } => render::Sampling::Adaptive { target_milli },
        },
    }
}

/// `tessera submit`.
pub async fn run_submit(
    coordinator: &Endpoint,
    scene: &Path,
    overrides: Overrides,
    priority: i32,
    wait_for_it: bool,
    output: Option<PathBuf>,
    json_out: bool,
) -> Result<()> {
    let mut client = Client::connect(coordinator).await?;
    let job = submit(&mut client, scene, overrides, priority).await?;
    if !wait_for_it {
        if json_out {
            println!("{}", json!({ "id": job, "state": "queued" }));
        } else {
            println!("{job}");
        }
        return Ok(());
    }
    let status = wait(&mut client, job).await?;
    let output = output.unwrap_or_else(|| default_output(scene));
    fetch_to(&mut client, job, &output).await?;
    if json_out {
        let mut v = status_json(&status);
        v["output"] = json!(output.display().to_string());
        println!("{v}");
    } else {
        eprintln!("{}", summary(&output, &status));
    }
    Ok(())
}

pub async fn run_status(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
    let status = Client::connect(coordinator).await?.status(job).await?;
    if json_out {
        println!("{}", status_json(&status));
    } else {
        println!("{}", status_line(&status));
    }
    Ok(())
}

pub async fn run_list(coordinator: &Endpoint, json_out: bool) -> Result<()> {
    let jobs = Client::connect(coordinator).await?.list().await?;
    if json_out {
        println!("{}", Value::Array(jobs.iter().map(status_json).collect()));
    } else if jobs.is_empty() {
        println!("no jobs");
    } else {
        for status in &jobs {
            println!("{}", status_line(status));
        }
    }
    Ok(())
}

pub async fn run_cancel(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
    Client::connect(coordinator).await?.cancel(job).await?;
    if json_out {
        println!("{}", json!({ "id": job, "state": "cancelled" }));
    } else {
        println!("job {job} cancelled");
    }
    Ok(())
}

pub async fn run_fetch(
    coordinator: &Endpoint,
    job: JobId,
    output: Option<PathBuf>,
    json_out: bool,
) -> Result<()> {
    let output = output.unwrap_or_else(|| PathBuf::from(format!("job-{job}.png")));
    let mut client = Client::connect(coordinator).await?;
    let bytes = fetch_to(&mut client, job, &output).await?;
    if json_out {
        println!(
            "{}",
            json!({ "id": job, "output": output.display().to_string(), "bytes": bytes })
        );
    } else {
        println!("{}", output.display());
    }
    Ok(())
}

pub async fn run_workers(coordinator: &Endpoint, json_out: bool) -> Result<()> {
    let workers = Client::connect(coordinator).await?.workers().await?;
    if json_out {
        println!(
            "{}",
            Value::Array(workers.iter().map(worker_json).collect())
        );
    } else if workers.is_empty() {
        println!("no workers");
    } else {
        for w in &workers {
            println!(
                "worker {} {}: {} threads, {} tiles in flight, {} tiles done, {:.1} M rays/s",
                w.id,
                w.name,
                w.threads,
                w.tiles_in_flight,
                w.tiles_done,
                w.rays_per_second / 1e6
            );
        }
    }
    Ok(())
}

fn status_line(s: &JobStatus) -> String {
    let mut line = format!(
        "job {}: {}, {}/{} tiles, {}x{} aa {} {}, {} samples, {:.1} s",
        s.id,
        s.state.as_str(),
        s.tiles_done,
        s.tiles_total,
        s.settings.width,
        s.settings.height,
        s.settings.aa,
        s.settings.sampling.name(),
        s.samples,
        s.elapsed_ms as f64 / 1000.0
    );
    if let Some(e) = s.estimated_error {
        line.push_str(&format!(", estimated error {e:.3} levels"));
    }
    if let Some(eta) = s.eta_ms {
        line.push_str(&format!(", about {:.1} s left", eta as f64 / 1000.0));
    }
    if let Some(e) = &s.error {
        line.push_str(&format!(": {e}"));
    }
    line
}

fn status_json(s: &JobStatus) -> Value {
    json!({
        "id": s.id,
        "state": s.state.as_str(),
        "width": s.settings.width,
        "height": s.settings.height,
        "aa": s.settings.aa,
        "max_depth": s.settings.max_depth,
        "priority": s.priority,
        "tiles_done": s.tiles_done,
        "tiles_total": s.tiles_total,
        "rays": s.rays,
        "elapsed_ms": s.elapsed_ms,
        "eta_ms": s.eta_ms,
        "error": s.error,
        "sampler": s.settings.sampling.name(),
        "target_error": s.settings.sampling.target_error(),
        "samples": s.samples,
        // The mean over the whole image, known once every tile is in.
        "samples_per_pixel": (s.state == JobState::Done).then(|| {
            s.samples as f64 / (u64::from(s.settings.width) * u64::from(s.settings.height)) as f64
        }),
        "estimated_error": s.estimated_error,
    })
}

fn worker_json(w: &WorkerStatus) -> Value {
    json!({
        "id": w.id,
        "name": w.name,
        "threads": w.threads,
        "tiles_in_flight": w.tiles_in_flight,
        "tiles_done": w.tiles_done,
        "rays": w.rays,
        "connected_ms": w.connected_ms,
        "rays_per_second": w.rays_per_second,
    })
}
