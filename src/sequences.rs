//! Following a sequence job while writing its frames as they are done, and fetching
//! a sequence's done frames into a directory.

use std::io::IsTerminal;

use anyhow::{anyhow, Result};
use coordinator::client::Client;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use protocol::{FrameProgress, JobId, JobState, JobStatus};

use crate::output::FramesDir;
use crate::session::{done_or_why, Session};

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
    done_or_why(job, status)
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

/// Whether the coordinator refused a frame for its state (not done yet, failed,
/// cancelled) rather than for anything else.
fn is_not_done(e: &anyhow::Error) -> bool {
    e.downcast_ref::<protocol::Refusal>()
        .is_some_and(|r| r.kind == protocol::RefusalKind::State)
}
