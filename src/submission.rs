//! What a job is before it goes to a coordinator: its scene file, the frames it
//! renders, its name and submitter and the choices of its submission; and submitting
//! it.

use std::path::Path;

use anyhow::{anyhow, Context, Result};
use coordinator::client::Client;
use protocol::{JobId, JobSpec, Overrides, Verification};

use crate::args::FrameRange;
use crate::scene_file::{read_scene, scene_files};

/// What a submission chooses besides its scene.
pub struct JobChoices {
    pub overrides: Overrides,
    pub priority: i32,
    pub verification: Verification,
    /// Milliseconds of rendering an adaptive job may take, if limited.
    pub time_limit_ms: Option<u64>,
    pub label: Label,
    /// The frame of the scene, from 1, or a sequence of frames.
    pub frames: FrameChoice,
    /// The jobs it waits for.
    pub after: Vec<protocol::JobId>,
    /// The worker tags the job requires (checked by the command line's parser).
    pub require: Vec<String>,
}

/// What a job is called and who submitted it; `None` takes the default.
#[derive(Clone, Debug, Default)]
pub struct Label {
    /// Default: the scene file's stem.
    pub name: Option<String>,
    /// Default: [`default_submitter`].
    pub submitter: Option<String>,
}

/// `$USER@hostname`: who a job says submitted it unless told. It is the client's
/// claim, not checked by anyone; the coordinator records the address the submission
/// came from beside it.
pub fn default_submitter() -> String {
    let user = ["USER", "USERNAME", "LOGNAME"]
        .iter()
        .find_map(|v| std::env::var(v).ok().filter(|u| !u.is_empty()))
        .unwrap_or_else(|| "unknown".into());
    let host = ["/proc/sys/kernel/hostname", "/etc/hostname"]
        .iter()
        .find_map(|p| {
            std::fs::read_to_string(p)
                .ok()
                .map(|h| h.trim().to_string())
                .filter(|h| !h.is_empty())
        })
        .or_else(|| std::env::var("COMPUTERNAME").ok())
        .unwrap_or_else(|| "localhost".into());
    format!("{user}@{host}")
}

/// What a submission renders: one frame (`frame`), or a sequence (`frames`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameChoice {
    pub frame: u32,
    pub frames: Option<protocol::FrameRange>,
}

/// Decides what to submit: `--frame K` one frame; `--frames A-B` (or `all`) a sequence;
/// neither, every frame of an animated scene as a sequence, or frame 1 of a static one.
/// A scene that does not parse goes as frame 1: the coordinator's loader says what is
/// wrong with it, in the words `tessera render` uses. The scene is read with the mesh
/// files `files` gives (those beside its file).
pub fn choose_frames(
    scene: &str,
    files: &render::MeshFiles,
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
    let count = render::parse_animated_with(scene, files)
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

/// Submits; a refused scene's message is prefixed with the file name, exactly as
/// `tessera render` reports it.
pub async fn submit(client: &mut Client, scene_path: &Path, job: JobChoices) -> Result<JobId> {
    let JobChoices {
        overrides,
        priority,
        verification,
        time_limit_ms,
        label,
        frames,
        after,
        require,
    } = job;
    let scene = read_scene(scene_path)?;
    let files = scene_files(scene_path, &scene)?;
    // On a terminal only: a script reading stderr gets an error as one line.
    if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        client.on_upload(upload_shown());
    }
    let name = label.name.unwrap_or_else(|| {
        scene_path
            .file_stem()
            .map_or_else(String::new, |s| s.to_string_lossy().into_owned())
    });
    client
        .submit_with_files(
            JobSpec {
                scene,
                overrides,
                priority,
                verification,
                time_limit_ms,
                name,
                submitter: label.submitter.unwrap_or_else(default_submitter),
                frame: frames.frame,
                frames: frames.frames,
                assets: Vec::new(),
                after,
                require,
            },
            &files,
        )
        .await
        // As context, not flattened: a refused upload's reason is in the chain (one
        // line with `{:#}`), and a refusal keeps its kind for `--json`.
        .with_context(|| scene_path.display().to_string())
}

/// Shows a submission's upload on stderr: when it starts, every few seconds while it
/// goes, and when it ends. Files the coordinator has already are not uploaded, and
/// not shown.
fn upload_shown() -> impl FnMut(coordinator::client::UploadProgress) + Send + 'static {
    use crate::report::{bytes, counted};
    use std::time::{Duration, Instant};
    let started = Instant::now();
    let mut shown = started;
    move |p| {
        let now = Instant::now();
        if p.finished {
            let secs = now.duration_since(started).as_secs_f64();
            eprintln!(
                "uploaded {} ({}) in {secs:.1} s",
                counted(p.files, "file"),
                bytes(p.total)
            );
        } else if p.sent == 0 {
            eprintln!(
                "uploading {} the coordinator lacks ({})",
                counted(p.files, "file"),
                bytes(p.total)
            );
        } else if now.duration_since(shown) >= Duration::from_secs(3) {
            shown = now;
            eprintln!("uploading: {} of {}", bytes(p.sent), bytes(p.total));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_animated_scene_goes_whole_unless_a_frame_or_range_is_named() {
        let none = render::MeshFiles::none();
        let orbit = include_str!("../scenes/seed-orbit.json");
        let seed = include_str!("../scenes/seed.json");
        let all = Some(protocol::FrameRange {
            first: 1,
            last: 121,
        });
        assert_eq!(choose_frames(orbit, &none, None, None).unwrap().frames, all);
        assert_eq!(
            choose_frames(orbit, &none, None, Some(FrameRange::All))
                .unwrap()
                .frames,
            all
        );
        assert_eq!(
            choose_frames(orbit, &none, Some(17), None).unwrap(),
            FrameChoice {
                frame: 17,
                frames: None
            }
        );
        assert_eq!(
            choose_frames(
                orbit,
                &none,
                None,
                Some(FrameRange::Span { first: 3, last: 5 })
            )
            .unwrap()
            .frames,
            Some(protocol::FrameRange { first: 3, last: 5 })
        );
        assert_eq!(choose_frames(seed, &none, None, None).unwrap().frames, None);
        assert_eq!(
            choose_frames("not json", &none, None, None).unwrap().frame,
            1
        );
    }
}
