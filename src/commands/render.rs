//! `tessera render`: load a scene, render it on this machine, write the PNG.
//!
//! An animated scene renders its frame 1, or the frame `--frame K` names, or with
//! `--frames A-B` a sequence of frames into a directory, one file per frame, each
//! written atomically. Every choice is checked against the scene before anything is
//! rendered or written.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use render::{parse_animated_with, validate_settings, AnimatedScene, MeshFiles, RenderSettings};

use crate::args::{FrameRange, FramesArg, ImageArgs};
use crate::config;
use crate::local_render::{thread_pool, Job, SceneSource};
use crate::output::{default_output, FileOutput, FramesDir, ImageOutput};
use crate::scene_file::{is_archive, read_archive, read_in_parallel, scene_dir};

/// Render a scene file to a PNG image on this machine.
#[derive(clap::Args)]
#[command(
    long_about = "Render a scene file to a PNG image on this machine, using all cores.\n\n\
        The scene is a JSON file (see docs/scene-format.md); its optional \"image\" \
        settings give the size and antialiasing, and the flags below override them. \
        The image is written only when the whole render succeeds.\n\n\
        An animated scene renders its frame 1, or frame K with --frame K; --frames \
        renders a sequence into a directory, one PNG per frame, each written whole.",
    after_help = "Examples:\n  \
        tessera render scenes/seed.json                 writes seed.png here\n  \
        tessera render scenes/seed.json -o big.png --width 1920 --height 1080 --aa 4\n  \
        tessera render scenes/seed-orbit.json --frame 17 -o orbit17.png\n  \
        tessera render scenes/seed-orbit.json --frames 1-120 -o orbit/"
)]
pub struct Args {
    /// The scene file (JSON), or a scene saved with its mesh files as a .tar archive
    /// (the studio's Save).
    scene: PathBuf,
    /// Where to write the PNG [default: the scene's file name with .png, here].
    #[arg(short, long, value_name = "OUT.png")]
    output: Option<PathBuf>,
    #[command(flatten)]
    image: ImageArgs,
    /// Rendering threads [default: one per core].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
    /// Adaptive sampling for about this long (500ms, 30s, 2m): the best image
    /// reachable, and the error it reached. Implies --sampler adaptive; with
    /// --target-error it stops at whichever comes first.
    #[arg(long, value_name = "TIME", value_parser = config::parse_duration)]
    time_limit: Option<Duration>,
    /// Save every sample taken (adaptive sampling) to FILE, so that `tessera refine
    /// FILE` can go on to a lower error or a larger --aa without taking them again.
    #[arg(long, value_name = "FILE")]
    state: Option<PathBuf>,
    /// Render frame K of an animated scene (frames are numbered from 1; a scene
    /// without animation has frame 1 only) [default: 1].
    #[arg(long, value_name = "K", value_parser = clap::value_parser!(u64).range(1..), conflicts_with = "frames")]
    frame: Option<u64>,
    #[command(flatten)]
    frames: FramesArg,
}

pub fn run(args: Args) -> Result<()> {
    let sampling = args.image.sampling(args.time_limit)?;
    let scene_path = &args.scene;
    if args.state.is_some() && (args.frame.is_some() || args.frames.frames.is_some()) {
        bail!("--state saves one render of a scene's frame 1: it cannot be used with --frame or --frames");
    }
    // The pool renders, and reads a large scene's file and objects first.
    let pool = thread_pool(args.threads)?;
    // A scene saved with its mesh files (the studio's Save) is read whole from its
    // archive, its files bound by name as a worker's are.
    let archived = is_archive(scene_path)
        .then(|| read_archive(scene_path))
        .transpose()?;
    if archived.is_some() && args.state.is_some() {
        bail!(
            "--state: a render of an archive cannot save its samples (a refine reads the \
             mesh files beside the scene): extract it with tar and render the scene file"
        );
    }
    let (text, bound) = match archived {
        Some(archive) => (archive.text, Some(archive.files)),
        None => (
            pool.install(|| read_in_parallel(scene_path))
                .with_context(|| format!("cannot read scene file {}", scene_path.display()))?,
            None,
        ),
    };
    // A render that saves its samples records where its mesh files are, as an absolute
    // and canonical directory (the one they are then read from), so that a refine from
    // any directory reads the same files.
    let mut mesh_dir = scene_dir(scene_path);
    if args.state.is_some() {
        mesh_dir = std::fs::canonicalize(&mesh_dir)
            .with_context(|| format!("cannot resolve the directory of {}", scene_path.display()))?;
    }
    let files = match bound {
        Some(files) => MeshFiles::bound(files),
        None => MeshFiles::beside(&mesh_dir),
    };
    let animated = pool
        .install(|| parse_animated_with(&text, &files))
        .map_err(|e| anyhow!("{}: {e}", scene_path.display()))?;
    // Only a render that saves its samples needs the text again; otherwise it goes now,
    // before the tracer is built (a large scene's text is larger than the scene).
    let text = args.state.is_some().then_some(text);

    // Image settings are not animated: the same for every frame.
    let mut settings = animated.base.settings;
    let image = args.image;
    settings.width = image.width.unwrap_or(settings.width);
    settings.height = image.height.unwrap_or(settings.height);
    settings.aa = image.aa.unwrap_or(settings.aa);
    settings.max_depth = image.max_depth.unwrap_or(settings.max_depth);
    settings.sampling = sampling.unwrap_or(settings.sampling);
    validate_settings(&settings, "").map_err(|e| anyhow!("command line: {e}"))?;
    if args.state.is_some() && settings.sampling.target_error().is_none() {
        bail!("--state saves the samples of adaptive sampling: add --sampler adaptive");
    }
    if let Some(range) = args.frames.frames {
        return run_sequence(&args, &animated, range, settings, pool);
    }
    let frame = args.frame.unwrap_or(1);
    let scene = animated
        .into_frame(frame)
        .map_err(|e| anyhow!("{}: {e}", scene_path.display()))?;
    let output = ImageOutput::create(
        &args
            .output
            .clone()
            .unwrap_or_else(|| default_output(scene_path)),
    )?;
    let job = Job {
        scene: &scene,
        source: text.as_deref().map(|text| SceneSource {
            text,
            mesh_dir: &mesh_dir,
        }),
        settings,
        output,
        pool: &pool,
        time_limit: args.time_limit,
        state: args.state.as_deref().map(FileOutput::create).transpose()?,
        resume: None,
    };
    job.run()
}

/// `--frames`: checks the range against the scene and every output file, then renders
/// the frames in order, each written atomically into the directory as soon as it is
/// done. An interrupted sequence leaves whole frames only.
fn run_sequence(
    args: &Args,
    animated: &AnimatedScene,
    range: FrameRange,
    settings: RenderSettings,
    pool: rayon::ThreadPool,
) -> Result<()> {
    let scene_path = &args.scene;
    let count = animated.frame_count();
    let (first, last) = match range {
        FrameRange::All => (1, u64::from(count)),
        FrameRange::Span { first, last } => (first, last),
    };
    // The last frame is the largest: if it exists, they all do.
    if let Err(e) = animated.frame(last) {
        bail!("{}: --frames {first}-{last}: {e}", scene_path.display());
    }
    let dir = FramesDir::create(
        &args
            .output
            .clone()
            .unwrap_or_else(|| default_output(scene_path).with_extension("")),
    )?;
    let outputs = (first..=last)
        .map(|k| Ok((k, dir.frame(k, count)?)))
        .collect::<Result<Vec<_>>>()?;
    for (k, output) in outputs {
        let scene = animated
            .frame(k)
            .map_err(|e| anyhow!("{}: frame {k}: {e}", scene_path.display()))?;
        let job = Job {
            scene: &scene,
            source: None,
            settings,
            output,
            pool: &pool,
            time_limit: args.time_limit,
            state: None,
            resume: None,
        };
        job.run()?;
    }
    Ok(())
}
