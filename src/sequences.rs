//! Sequence jobs from the command line: what `tessera submit` and `tessera up` submit
//! for an animated scene, following a sequence while writing its frames as they are
//! done, `tessera fetch` of a sequence into a directory, and `tessera retry JOB
//! --frame K`.

use std::io::IsTerminal;
use std::path::Path;

use anyhow::{anyhow, Result};
use coordinator::client::Client;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use protocol::{FrameProgress, JobId, JobState, JobStatus};
use serde_json::json;

use crate::client_commands::Session;
use crate::output::FramesDir;
use crate::render_command::FrameRange;

/// What a submission renders: one frame (`frame`), or a sequence (`frames`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameChoice {
    pub frame: u32,
    pub frames: Option<protocol::FrameRange>,
}

/// Decides what to submit: `--frame K` one frame; `--frames A-B` (or `all`) a sequence;
/// neither, every frame of an animated scene as a sequence, or frame 1 of a static one.
/// A scene that does not parse goes as frame 1: the coordinator's loader says what is
/// wrong with it, in the words `tessera render` uses.
pub fn choose_frames(
    scene: &str,
    frame: Option<u32>,
    frames: Option<FrameRange>,
) -> Result<FrameChoice> {
    let single = |frame| FrameChoice {
        frame,
        frames: None,
    };
    if let Some(k) = frame {
        return Ok(single(k));
    }
    let count = render::parse_animated(scene)
        .ok()
        .map(|a| (a.frame_count(), a.animation.is_some()));
    let sequence = |first: u64, last: u64| -> Result<FrameChoice> {
        let narrow = |n: u64| u32::try_from(n).map_err(|_| anyhow!("frame {n} is too large"));
        Ok(FrameChoice {
            frame: 1,
            frames: Some(protocol::FrameRange {
                first: narrow(first)?,
                last: narrow(last)?,
            }),
        })
    };
    match (frames, count) {
        (Some(FrameRange::Span { first, last }), _) => sequence(first, last),
        (Some(FrameRange::All), Some((n, _))) | (None, Some((n, true))) => {
            sequence(1, u64::from(n))
        }
        _ => Ok(single(1)),
    }
}

/// Follows a sequence until it ends, with a progress bar of frames on a terminal,
/// writing each frame into `dir` (if given) as soon as it and every frame before it are
/// done. A sequence that fails or is cancelled is an error, after the frames done are
/// written.
pub async fn wait_sequence(
    session: &mut Session,
    job: JobId,
    dir: Option<&FramesDir>,
) -> Result<JobStatus> {
    let bar = if std::io::stderr().is_terminal() {
        ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr())
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} frames {msg}",
        )
        .expect("the template is valid"),
    );
    let mut seen = 0;
    let mut written = 0u32;
    let status = loop {
        let status = session.watch(job, seen).await?;
        seen = status.tiles_done;
        let Some(frames) = status.frames.clone() else {
            return Err(anyhow!("job {job} is not a sequence"));
        };
        bar.set_length(u64::from(frames.last - frames.first + 1));
        bar.set_position(u64::from(frames.done));
        bar.set_message(if frames.failed > 0 {
            format!("({} failed)", frames.failed)
        } else {
            String::new()
        });
        if let Some(dir) = dir {
            written = write_prefix(session, job, &frames, dir, written).await?;
        }
        if status.state.is_final() {
            break status;
        }
    };
    bar.finish_and_clear();
    let frames = status.frames.clone().expect("a sequence");
    if let Some(dir) = dir {
        if status.state != JobState::Done && frames.done > frames.done_prefix {
            // Frames done after a failed or cancelled one are kept too.
            fetch_frames(session.client(), job, &frames, dir).await?;
        }
    }
    crate::client_commands::done_or_why(job, status)
}

/// Writes the frames done one after another from the first that are not written yet;
/// returns how many of them are written.
async fn write_prefix(
    session: &mut Session,
    job: JobId,
    frames: &FrameProgress,
    dir: &FramesDir,
    written: u32,
) -> Result<u32> {
    for i in written..frames.done_prefix {
        let k = frames.first + i;
        let png = session.fetch_frame(job, k).await?;
        dir.frame(u64::from(k), frames.scene_frames)?.write(&png)?;
    }
    Ok(written.max(frames.done_prefix))
}

/// Writes every done frame of a sequence into `dir`; returns how many.
pub async fn fetch_frames(
    client: &mut Client,
    job: JobId,
    frames: &FrameProgress,
    dir: &FramesDir,
) -> Result<u32> {
    let mut written = 0;
    for k in frames.first..=frames.last {
        // The frames done from the first are known to be; after them, a frame not done
        // is answered "has no image" and skipped.
        match client.fetch_frame(job, k).await {
            Ok(png) => {
                dir.frame(u64::from(k), frames.scene_frames)?.write(&png)?;
                written += 1;
            }
            Err(e) if k >= frames.first + frames.done_prefix && is_not_done(&e) => {}
            Err(e) => return Err(e),
        }
    }
    Ok(written)
}

fn is_not_done(e: &anyhow::Error) -> bool {
    format!("{e:#}").contains("has no image: it is")
}

/// `tessera fetch` of a sequence: its done frames into `dir` [default: `job-N/`].
pub async fn run_fetch_sequence(
    client: &mut Client,
    status: &JobStatus,
    dir: Option<&Path>,
    json_out: bool,
) -> Result<()> {
    let job = status.id;
    let frames = status.frames.as_ref().expect("a sequence");
    let default = format!("job-{job}");
    let dir = FramesDir::create(dir.unwrap_or(Path::new(&default)))?;
    let written = fetch_frames(client, job, frames, &dir).await?;
    let total = frames.last - frames.first + 1;
    if json_out {
        println!(
            "{}",
            json!({ "id": job, "output": dir.path().display().to_string(), "frames": written, "of": total })
        );
    } else {
        println!(
            "{}: {written} of {total} frames{}",
            dir.path().display(),
            if written < total {
                " (the others are not done)"
            } else {
                ""
            }
        );
    }
    Ok(())
}

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_animated_scene_goes_whole_unless_a_frame_or_range_is_named() {
        let orbit = include_str!("../scenes/seed-orbit.json");
        let seed = include_str!("../scenes/seed.json");
        let all = Some(protocol::FrameRange {
            first: 1,
            last: 121,
        });
        assert_eq!(choose_frames(orbit, None, None).unwrap().frames, all);
        assert_eq!(
            choose_frames(orbit, None, Some(FrameRange::All))
                .unwrap()
                .frames,
            all
        );
        assert_eq!(
            choose_frames(orbit, Some(17), None).unwrap(),
            FrameChoice {
                frame: 17,
                frames: None
            }
        );
        assert_eq!(
            choose_frames(orbit, None, Some(FrameRange::Span { first: 3, last: 5 }))
                .unwrap()
                .frames,
            Some(protocol::FrameRange { first: 3, last: 5 })
        );
        assert_eq!(choose_frames(seed, None, None).unwrap().frames, None);
        assert_eq!(choose_frames("not json", None, None).unwrap().frame, 1);
    }
}
