//! `tessera up`: a whole farm on this machine for one scene. A coordinator with a
//! temporary data directory and N worker processes on loopback, the scene submitted,
//! progress shown, the image written, and everything shut down again.
//!
//! The children are the real `tessera coordinator` and `tessera worker` processes of a
//! [`LocalFarm`], stopped when `up` ends for any reason.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result};
use localfarm::{up_limits, LocalFarm, WorkerSpec};
use transport::Endpoint;

use crate::args::{threads_per_worker, FramesArg, ImageArgs};
use crate::config;
use crate::output::JobOutput;
use crate::report::{counted, sequence_summary, summary};
use crate::scene_file::{read_scene, scene_dir};
use crate::sequences::wait_sequence;
use crate::session::{wait, Session};
use crate::signals::StopSignals;
use crate::submission::{choose_frames, submit, JobChoices};

/// Render a scene on a farm started on this machine for the occasion.
#[derive(clap::Args)]
#[command(
    long_about = "Start a coordinator and worker processes on this machine (loopback \
        only), render the scene on them, write the image and stop them all again.",
    after_help = "Example:\n  tessera up scenes/seed.json --workers 3 -o seed.png"
)]
pub struct Args {
    /// The scene file (JSON).
    scene: PathBuf,
    /// Worker processes to start.
    #[arg(long, value_name = "N", default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=64))]
    workers: u32,
    /// Rendering threads of each worker [default: cores / workers, at least 1].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads_per_worker: Option<u32>,
    /// Where to write the PNG [default: the scene's file name with .png, here]; with
    /// --frames, the directory of the frames [default: the scene's file name].
    #[arg(short, long, value_name = "OUT.png|DIR")]
    output: Option<PathBuf>,
    #[command(flatten)]
    frames: FramesArg,
    #[command(flatten)]
    image: ImageArgs,
    /// Adaptive sampling for about this long (500ms, 30s, 2m): the job stops at the
    /// end of the pass that reaches it. Implies --sampler adaptive.
    #[arg(long, value_name = "TIME", value_parser = config::parse_duration)]
    time_limit: Option<Duration>,
    /// Tile side in pixels [default: chosen from the image size and aa].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(8..=512))]
    tile: Option<u32>,
}

pub fn run(args: Args) -> Result<()> {
    super::block_on(up(args))
}

async fn up(args: Args) -> Result<()> {
    let workers = args.workers as usize;
    let threads = threads_per_worker(workers, args.threads_per_worker);
    let (overrides, time_limit_ms) = args.image.farm_job(args.tile, args.time_limit)?;
    // Caught from now on, so that the farm and its temporary directory always go.
    let mut stop = StopSignals::new()?;
    // Fail on an unreadable scene or an image that cannot be written before starting
    // anything.
    let text = read_scene(&args.scene)?;
    let files = render::MeshFiles::beside(scene_dir(&args.scene));
    let frames = choose_frames(
        &text,
        &files,
        args.frames.frames.is_none().then_some(1),
        args.frames.frames,
    )?;
    let output = JobOutput::create(frames.frames.is_some(), args.output, &args.scene)?;
    let job = JobChoices {
        overrides,
        priority: 0,
        verification: protocol::Verification::default(),
        time_limit_ms,
        label: Default::default(),
        frames,
        after: Vec::new(),
        require: Vec::new(),
    };
    let specs = vec![
        WorkerSpec {
            threads,
            ..WorkerSpec::default()
        };
        workers
    ];
    let exe = std::env::current_exe().context("cannot find the tessera executable")?;
    let starting = tokio::task::spawn_blocking(move || {
        let limits = up_limits();
        let args: Vec<&str> = limits.iter().map(String::as_str).collect();
        LocalFarm::start_with(&exe, &specs, &args)
    });
    let farm = tokio::select! {
        farm = starting => farm.context("starting the local farm")??,
        signal = stop.next() => return Err(signal.into()),
    };
    let result = tokio::select! {
        r = render_on(farm.address(), &args.scene, job, output, workers) => r,
        e = farm.first_exit() => Err(e.into()),
        signal = stop.next() => Err(signal.into()),
    };
    drop(farm);
    result
}

/// Submits the job to the farm at `address`, follows it and writes its result; the
/// summary line says how many `workers` rendered it.
async fn render_on(
    address: &str,
    scene: &Path,
    job: JobChoices,
    output: JobOutput,
    workers: usize,
) -> Result<()> {
    let mut session = Session::connect(&Endpoint::plain(address)).await?;
    let job = submit(session.client(), scene, job)
        .await
        // The one limit left (the scene's size) is not of a coordinator the user started.
        .map_err(|e| {
            anyhow::anyhow!(
                "{}",
                format!("{e:#}").replace("this coordinator's limit", "the limit of `tessera up`")
            )
        })?;
    let output = match output {
        JobOutput::Image(output) => output,
        JobOutput::Frames(dir) => {
            let status = wait_sequence(&mut session, job, Some(&dir)).await?;
            eprintln!(
                "{} ({})",
                sequence_summary(dir.path(), &status),
                counted(workers, "worker")
            );
            return Ok(());
        }
    };
    let status = wait(&mut session, job).await?;
    let path = output.path().to_path_buf();
    // The farm and its copy of the image go with this command: no `tessera fetch`.
    let png = session.fetch(job).await?;
    output.write(&png)?;
    eprintln!(
        "{} ({})",
        summary(&path, &status),
        counted(workers, "worker")
    );
    Ok(())
}
