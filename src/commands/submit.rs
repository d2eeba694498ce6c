//! `tessera submit`: a scene to a coordinator. Prints the job's id; with `--wait`,
//! follows the job and writes its image to `-o` [default: the scene's file name with
//! .png], or a sequence's frames into the directory `-o` [default: the scene's file
//! name without .json] as they are done.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Result;
use protocol::{JobId, Verification};
use serde_json::json;

use crate::args::{parse_job_id, parse_priority, ClientArgs, FramesArg, ImageArgs};
use crate::config;
use crate::output::JobOutput;
use crate::report::{sequence_summary, status_json, summary};
use crate::scene_file::{read_scene, scene_dir};
use crate::sequences::wait_sequence;
use crate::session::{naming_job, wait_and_fetch, Session};
use crate::signals::StopSignals;
use crate::submission::{choose_frames, submit, JobChoices, Label};

/// Submit a scene to a coordinator; print the job id, or with --wait, write the image.
#[derive(clap::Args)]
#[command(after_help = "Examples:\n  \
    tessera submit scenes/seed.json                  prints the job id\n  \
    tessera submit scenes/seed.json --wait -o seed.png --aa 4\n  \
    tessera submit scenes/seed-orbit.json --frame 17 --wait -o orbit17.png")]
pub struct Args {
    /// The scene file (JSON).
    scene: PathBuf,
    /// Render frame K of an animated scene only (frames are numbered from 1; a scene
    /// without animation has frame 1 only): the image is `tessera render --frame K`'s.
    #[arg(long, value_name = "K", value_parser = clap::value_parser!(u32).range(1..),
          conflicts_with = "frames")]
    frame: Option<u32>,
    // One sequence job; without --frame or --frames, an animated scene's every frame.
    #[command(flatten)]
    frames: FramesArg,
    #[command(flatten)]
    image: ImageArgs,
    /// Adaptive sampling for about this long (500ms, 30s, 2m) of the farm's rendering:
    /// the job stops at the end of the pass that reaches it, with the error it reached.
    /// Implies --sampler adaptive; with --target-error, whichever comes first.
    #[arg(long, value_name = "TIME", value_parser = config::parse_duration)]
    time_limit: Option<Duration>,
    /// Tile side in pixels [default: chosen from the image size and aa].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(8..=512))]
    tile: Option<u32>,
    /// Priority: higher runs first; equal priorities share the farm.
    #[arg(long, default_value_t = 0, allow_negative_numbers = true, value_parser = parse_priority)]
    priority: i32,
    /// How results are checked. `sampled`: 16 pixels of every tile rendered again by
    /// the coordinator, and 1 % of the tiles by a second machine; it catches a tile
    /// that is wrong in many pixels (noise, a broken build) almost surely, but lets a
    /// few subtly altered pixels through: a tile with one pixel off by one level
    /// survives with probability 0.99. `full`: every tile rendered by two different
    /// machines, which must agree byte for byte (twice the rendering; needs two
    /// workers): nothing altered survives unless both machines lie alike.
    #[arg(long, value_enum, default_value_t = VerifyArg::Sampled, value_name = "MODE")]
    verify: VerifyArg,
    /// Render only on workers tagged NAME (`tessera worker --tag NAME`); repeat to
    /// require several tags, all of which a worker must have. With none connected the
    /// job waits (and says so); with --verify full it needs two such machines.
    #[arg(long, value_name = "NAME", action = clap::ArgAction::Append,
          value_parser = crate::args::parse_tag)]
    require: Vec<String>,
    /// Wait for the job, showing progress, and write its image.
    #[arg(long)]
    wait: bool,
    /// With --wait: where to write the PNG [default: the scene's file name with .png],
    /// or for a sequence the directory of its frames [default: the scene's file name].
    #[arg(short, long, value_name = "OUT.png|DIR", requires = "wait")]
    output: Option<PathBuf>,
    /// What listings call the job [default: the scene file's name without .json].
    #[arg(long, value_name = "NAME")]
    name: Option<String>,
    /// Who submitted the job, shown in listings [default: $USER@hostname]. The
    /// client's claim, not checked: the coordinator records the address the
    /// submission came from beside it.
    #[arg(long, value_name = "WHO")]
    submitter: Option<String>,
    /// Start only once job JOB is done (repeatable: once every one is). Until then the
    /// job is `waiting`; if one fails or is cancelled, this one fails, naming it.
    #[arg(long, value_name = "JOB", value_parser = parse_job_id)]
    after: Vec<protocol::JobId>,
    #[command(flatten)]
    common: ClientArgs,
}

/// `--verify`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum VerifyArg {
    Sampled,
    Full,
}

impl From<VerifyArg> for Verification {
    fn from(v: VerifyArg) -> Self {
        match v {
            VerifyArg::Sampled => Verification::Sampled,
            VerifyArg::Full => Verification::Full,
        }
    }
}

pub fn run(args: Args) -> Result<()> {
    super::block_on(submit_and_follow(args))
}

async fn submit_and_follow(args: Args) -> Result<()> {
    let text = read_scene(&args.scene)?;
    let files = render::MeshFiles::beside(scene_dir(&args.scene));
    let frames = choose_frames(&text, &files, args.frame, args.frames.frames)?;
    let coordinator = args.common.target()?;
    let (overrides, time_limit_ms) = args.image.farm_job(args.tile, args.time_limit)?;
    let choices = JobChoices {
        overrides,
        priority: args.priority,
        verification: args.verify.into(),
        time_limit_ms,
        label: Label {
            name: args.name,
            submitter: args.submitter,
        },
        frames,
        after: args.after,
        require: protocol::check_tags(&args.require)
            .map_err(|e| anyhow::anyhow!("--require: {e}"))?,
    };
    let json_out = args.common.json;
    // The output is checked before the farm spends anything on it.
    let output = if args.wait {
        let sequence = frames.frames.is_some();
        Some(JobOutput::create(sequence, args.output, &args.scene)?)
    } else {
        None
    };
    // With --wait, caught from before the submission: a Ctrl-C then is answered once
    // the job's id is known, with what to do about the job.
    let mut stop = match output {
        Some(_) => Some(StopSignals::new()?),
        None => None,
    };
    let mut session = Session::connect(&coordinator).await?;
    let job = submit(session.client(), &args.scene, choices).await?;
    let (Some(output), Some(stop)) = (output, stop.as_mut()) else {
        print_submitted(job, json_out);
        return Ok(());
    };
    eprintln!("submitted job {job}");
    let output_path = output.path().to_path_buf();
    let waiting = async {
        match output {
            JobOutput::Image(image) => wait_and_fetch(&mut session, job, image).await,
            JobOutput::Frames(dir) => wait_sequence(&mut session, job, Some(&dir))
                .await
                .map_err(|e| naming_job(job, e)),
        }
    };
    // Stopping the wait does not stop the job: the line says so, and how to follow or
    // cancel it.
    let status = tokio::select! {
        status = waiting => status?,
        signal = stop.next() => return Err(signal
            .leaving(format!(
                "job {job} keeps running on the farm: `tessera status {job}` follows it, \
                 `tessera cancel {job}` cancels it"
            ))
            .into()),
    };
    if json_out {
        let mut v = status_json(&status);
        v["output"] = json!(output_path.display().to_string());
        println!("{v}");
    } else if status.frames.is_some() {
        eprintln!("{}", sequence_summary(&output_path, &status));
    } else {
        eprintln!("{}", summary(&output_path, &status));
    }
    Ok(())
}

/// What `tessera submit` without `--wait` prints: the job's id.
fn print_submitted(job: JobId, json_out: bool) {
    if json_out {
        println!("{}", json!({ "id": job, "state": "queued" }));
    } else {
        println!("{job}");
    }
}
