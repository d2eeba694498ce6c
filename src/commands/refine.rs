//! `tessera refine`: go on from an adaptive render to a lower error target or a larger
//! cap, taking only the samples it lacks. From a state file saved by `tessera render
//! --state`, on this machine; from a finished adaptive job, as a new job of the
//! coordinator that kept the job's tile states.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, bail, Result};
use protocol::JobId;
use render::adaptive::Region;
use render::limits::MAX_AA;
use render::{
    parse_scene_with, validate_settings, Image, MeshFiles, RenderSettings, Sampling,
    SamplingChoiceError, Tracer,
};
use serde_json::json;

use crate::args::{limit_ms, ClientArgs};
use crate::config;
use crate::local_render::{thread_pool, Job, SceneSource};
use crate::output::{FileOutput, ImageOutput};
use crate::render_state;
use crate::report::{status_json, summary};
use crate::session::{naming_job, wait_and_fetch, Session};

/// Go on from a saved adaptive render to a lower error or a larger cap.
#[derive(clap::Args)]
#[command(
    long_about = "Go on from a render saved with `tessera render --state FILE` to a lower \
        error target or a larger --aa, taking only the samples it lacks. The image is \
        byte for byte the one a direct render with the final settings gives. The state \
        file is updated in place, so refining can go on again. The scene's mesh files \
        are read again from where the render read them, and refused if one has changed \
        since. Given the id of a finished adaptive job instead, a coordinator starts a \
        new job from the tile states it kept for that job, with the same bytes a direct \
        job would give.",
    after_help = "Examples:\n  \
        tessera render scenes/seed.json --sampler adaptive --target-error 4 --state seed.state\n  \
        tessera refine seed.state --target-error 1 -o seed.png\n  \
        tessera refine 12 --target-error 0.5 --aa 16 --wait -o seed.png"
)]
pub struct Args {
    /// A render state saved by `tessera render --state FILE`, or the id of a finished
    /// adaptive job on a coordinator (a new job goes on from its stored samples).
    state: PathBuf,
    /// The new error target, in 8-bit levels [default: the saved one].
    #[arg(long, value_name = "LEVELS", allow_negative_numbers = true)]
    target_error: Option<f64>,
    /// A new cap: at most the largest power of two not above N x N samples per pixel
    /// [default: the saved one].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_AA)))]
    aa: Option<u32>,
    /// Refine for about this long, at most.
    #[arg(long, value_name = "TIME", value_parser = config::parse_duration)]
    time_limit: Option<Duration>,
    /// Where to write the PNG [default: the state's file name with .png].
    #[arg(short, long, value_name = "OUT.png")]
    output: Option<PathBuf>,
    /// Rendering threads [default: one per core].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
    /// For a job id: wait for the new job, showing progress, and write its image.
    #[arg(long)]
    wait: bool,
    #[command(flatten)]
    common: ClientArgs,
}

pub fn run(args: Args) -> Result<()> {
    match refines_a_job(&args.state)? {
        None => refine_file(args),
        Some(job) => super::block_on(refine_job(job, args)),
    }
}

/// What `tessera refine X` refines: the job X on a coordinator if X is all digits and
/// names no file, else a saved render state (whose reading reports a missing file).
fn refines_a_job(state: &Path) -> Result<Option<JobId>> {
    let text = state.to_string_lossy();
    if state.exists() || text.is_empty() || !text.bytes().all(|b| b.is_ascii_digit()) {
        return Ok(None);
    }
    let job = text
        .parse()
        .map_err(|_| anyhow!("refine: job id {text} is too large"))?;
    Ok(Some(job))
}

/// `tessera refine FILE`: the image is the one a direct render with the final settings
/// gives, byte for byte; the state file is updated in place.
fn refine_file(args: Args) -> Result<()> {
    let saved = render_state::load(&args.state)?;
    let pool = thread_pool(args.threads)?;
    let scene = saved_scene(&pool, &saved).map_err(|e| anyhow!("{}: {e}", args.state.display()))?;
    let target = match args.target_error {
        Some(levels) => Sampling::adaptive(levels).map_err(SamplingChoiceError::Target)?,
        None => Sampling::Adaptive {
            target_milli: saved.target_milli,
        },
    };
    let settings = RenderSettings {
        width: saved.width,
        height: saved.height,
        aa: args.aa.unwrap_or(saved.aa),
        max_depth: saved.max_depth,
        sampling: target,
    };
    validate_settings(&settings, "").map_err(|e| anyhow!("command line: {e}"))?;
    let path = match &args.output {
        Some(path) => path.clone(),
        None => {
            let path = args.state.with_extension("png");
            if path.exists() && !is_image_of(&pool, &scene, &saved, &path)? {
                bail!(
                    "{path}: a file of that name exists, and it is not the image of {state}: \
                     give -o {path} to replace it, or -o another name",
                    path = path.display(),
                    state = args.state.display()
                );
            }
            path
        }
    };
    let output = ImageOutput::create(&path)?;
    let job = Job {
        scene: &scene,
        source: Some(SceneSource {
            text: &saved.scene,
            mesh_dir: &saved.mesh_dir,
        }),
        settings,
        output,
        pool: &pool,
        time_limit: args.time_limit,
        state: Some(FileOutput::create(&args.state)?),
        resume: Some((args.state.clone(), saved.blocks)),
    };
    job.run()
}

/// The saved scene, its mesh files read again from the directory the render read them
/// from, and each file the very one the samples were taken of: a file that changed or
/// is gone since is refused in one line naming it, before anything is rendered.
fn saved_scene(pool: &rayon::ThreadPool, saved: &render_state::Saved) -> Result<render::Scene> {
    let files = MeshFiles::beside(&saved.mesh_dir);
    match pool.install(|| parse_scene_with(&saved.scene, &files)) {
        Ok(scene) => {
            render_state::check_meshes(saved, &scene)?;
            Ok(scene)
        }
        Err(e) => {
            // A mesh file that no longer reads (gone, or changed into another) is named
            // as such rather than by what is wrong with it now.
            render_state::check_mesh_files(saved)?;
            bail!("the saved scene: {e}")
        }
    }
}

/// Whether the file at `path` is the image the render or refine that saved `saved`
/// wrote (rendering is deterministic: its samples at its rung paint the same bytes).
/// The name refine chooses by itself (the state's, with .png) replaces only that
/// image, never another file that happens to have the name.
fn is_image_of(
    pool: &rayon::ThreadPool,
    scene: &render::Scene,
    saved: &render_state::Saved,
    path: &Path,
) -> Result<bool> {
    let Ok(existing) = std::fs::read(path) else {
        return Ok(false);
    };
    let settings = RenderSettings {
        width: saved.width,
        height: saved.height,
        aa: saved.aa,
        max_depth: saved.max_depth,
        sampling: Sampling::Adaptive {
            target_milli: saved.target_milli,
        },
    };
    let png = pool.install(|| -> Option<Vec<u8>> {
        let tracer = Tracer::new(scene, settings);
        let full = render::Rect {
            x: 0,
            y: 0,
            width: saved.width,
            height: saved.height,
        };
        let footprints = Region::footprints(&tracer);
        let region = Region::new(&tracer, footprints, full, Some(saved.blocks.clone())).ok()?;
        let mut image = Image::black(saved.width, saved.height);
        region.paint(saved.rung, &mut image);
        Some(image.to_png())
    });
    Ok(png.is_some_and(|png| png == existing))
}

/// `tessera refine JOB`: a new job going on from a finished adaptive job's samples;
/// prints its id, or with `--wait`, follows it and writes its image.
async fn refine_job(old: JobId, args: Args) -> Result<()> {
    let target_milli = match args.target_error.map(Sampling::adaptive).transpose()? {
        Some(Sampling::Adaptive { target_milli }) => Some(target_milli),
        _ => None,
    };
    let coordinator = args.common.target()?;
    let json_out = args.common.json;
    // A file named is checked before the farm spends anything on it.
    let checked = match (args.wait, &args.output) {
        (true, Some(path)) => Some(ImageOutput::create(path)?),
        _ => None,
    };
    let mut session = Session::connect(&coordinator).await?;
    let target_milli = match target_milli {
        Some(t) => t,
        None => saved_target(&mut session, old).await?,
    };
    let job = session
        .client()
        .refine(old, target_milli, args.aa, args.time_limit.map(limit_ms))
        .await?;
    if !args.wait {
        if json_out {
            println!(
                "{}",
                json!({ "id": job, "state": "queued", "refines": old })
            );
        } else {
            println!("{job}");
        }
        return Ok(());
    }
    eprintln!("refining job {old} as job {job}");
    let output = match checked {
        Some(output) => output,
        None => ImageOutput::create(&PathBuf::from(format!("job-{job}.png")))
            .map_err(|e| naming_job(job, e))?,
    };
    let output_path = output.path().to_path_buf();
    let status = wait_and_fetch(&mut session, job, output).await?;
    if json_out {
        let mut v = status_json(&status);
        v["output"] = json!(output_path.display().to_string());
        v["refines"] = json!(old);
        println!("{v}");
    } else {
        eprintln!("{}", summary(&output_path, &status));
    }
    Ok(())
}

/// The target a finished job was rendered to: what a refinement without a new one
/// keeps. Only adaptive jobs keep the tile states a refinement goes on from.
async fn saved_target(session: &mut Session, old: JobId) -> Result<u32> {
    match session.client().status(old).await?.settings.sampling {
        protocol::Sampling::Adaptive { target_milli } => Ok(target_milli),
        other => anyhow::bail!(
            "cannot refine job {old}: it was rendered with {} sampling: only adaptive \
             jobs keep their tile states",
            other.name()
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn digits_that_name_no_file_are_a_job() {
        assert_eq!(refines_a_job(Path::new("12")).unwrap(), Some(12));
        for state in ["seed.state", "", "-1", "1.5", "/tmp/12"] {
            assert_eq!(refines_a_job(Path::new(state)).unwrap(), None, "{state:?}");
        }
        assert_eq!(
            refines_a_job(Path::new("99999999999999999999999"))
                .unwrap_err()
                .to_string(),
            "refine: job id 99999999999999999999999 is too large"
        );
    }
}
