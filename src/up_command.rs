//! `tessera up`: a whole farm on this machine for one scene. A coordinator with a
//! temporary data directory and N worker processes on loopback, the scene submitted,
//! progress shown, the image written, and everything shut down again.
//!
//! The children are the real `tessera coordinator` and `tessera worker` processes of a
//! [`LocalFarm`], stopped when `up` ends for any reason.

use std::path::PathBuf;

use anyhow::{Context, Result};
use localfarm::{up_limits, LocalFarm, WorkerSpec};
use protocol::Overrides;
use transport::Endpoint;

use crate::client_commands::{sequence_summary, submit, summary, wait, JobChoices, Session};
use crate::output::{default_output, FramesDir, ImageOutput};
use crate::render_command::FrameRange;
use crate::sequence_commands::{choose_frames, wait_sequence, FrameChoice};

pub struct Options {
    pub scene: PathBuf,
    pub workers: usize,
    pub threads_per_worker: usize,
    pub output: Option<PathBuf>,
    /// `--frames`: a sequence of an animated scene, into the directory `output`.
    pub frames: Option<FrameRange>,
    /// The image settings and the time limit (ms), if any.
    pub job: (Overrides, Option<u64>),
}

pub async fn run(opts: Options) -> Result<()> {
    // Caught from now on, so that the farm and its temporary directory always go.
    let mut stop = StopSignals::new()?;
    // Fail on an unreadable scene or an image that cannot be written before starting
    // anything.
    let text = crate::client_commands::read_scene(&opts.scene)?;
    let frames = choose_frames(&text, opts.frames.is_none().then_some(1), opts.frames)?;
    let output = match frames.frames {
        None => Output::Image(ImageOutput::create(
            &opts
                .output
                .clone()
                .unwrap_or_else(|| default_output(&opts.scene)),
        )?),
        Some(_) => Output::Frames(FramesDir::create(
            &opts
                .output
                .clone()
                .unwrap_or_else(|| default_output(&opts.scene).with_extension("")),
        )?),
    };
    let specs = vec![
        WorkerSpec {
            threads: opts.threads_per_worker,
        };
        opts.workers
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
        r = render_on(farm.address(), &opts, frames, output) => r,
        e = farm.first_exit() => Err(e.into()),
        signal = stop.next() => Err(signal.into()),
    };
    drop(farm);
    result
}

/// `tessera up` stopped by a signal: the process exits with 128 + its number, as a
/// shell reports a command killed by it, once the farm is stopped and its temporary
/// directory removed.
#[derive(Debug)]
pub struct Interrupted {
    pub name: &'static str,
    /// The exit status: 130 for SIGINT (Ctrl-C), 143 for SIGTERM, 129 for SIGHUP.
    pub exit_code: u8,
}

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "interrupted by {}: the local farm is stopped, no image written",
            self.name
        )
    }
}

impl std::error::Error for Interrupted {}

/// Ctrl-C, SIGTERM and SIGHUP, caught from their creation on.
pub struct StopSignals {
    #[cfg(unix)]
    signals: [(tokio::signal::unix::Signal, Interrupted); 3],
}

impl StopSignals {
    pub fn new() -> Result<StopSignals> {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{signal, SignalKind};
            let catch = |kind: SignalKind, name, exit_code| -> Result<_> {
                Ok((
                    signal(kind).with_context(|| format!("cannot catch {name}"))?,
                    Interrupted { name, exit_code },
                ))
            };
            Ok(StopSignals {
                signals: [
                    catch(SignalKind::interrupt(), "SIGINT", 130)?,
                    catch(SignalKind::terminate(), "SIGTERM", 143)?,
                    catch(SignalKind::hangup(), "SIGHUP", 129)?,
                ],
            })
        }
        #[cfg(not(unix))]
        Ok(StopSignals {})
    }

    /// The next signal caught.
    pub async fn next(&mut self) -> Interrupted {
        #[cfg(unix)]
        {
            let [(int, _), (term, _), (hup, _)] = &mut self.signals;
            let i = tokio::select! {
                _ = int.recv() => 0,
                _ = term.recv() => 1,
                _ = hup.recv() => 2,
            };
            let (_, what) = &self.signals[i];
            Interrupted {
                name: what.name,
                exit_code: what.exit_code,
            }
        }
        #[cfg(not(unix))]
        {
            let _ = tokio::signal::ctrl_c().await;
            Interrupted {
                name: "Ctrl-C",
                exit_code: 130,
            }
        }
    }
}

/// Where `up` writes: an image, or a sequence's frames.
enum Output {
    Image(ImageOutput),
    Frames(FramesDir),
}

async fn render_on(
    address: &str,
    opts: &Options,
    frames: FrameChoice,
    output: Output,
) -> Result<()> {
    let mut session = Session::connect(&Endpoint::plain(address)).await?;
    let job = submit(
        session.client(),
        &opts.scene,
        JobChoices {
            overrides: opts.job.0,
            priority: 0,
            verification: protocol::Verification::default(),
            time_limit_ms: opts.job.1,
            label: Default::default(),
            frames,
        },
    )
    .await
    // The one limit left (the scene's size) is not of a coordinator the user started.
    .map_err(|e| {
        anyhow::anyhow!(
            "{}",
            format!("{e:#}").replace("this coordinator's limit", "the limit of `tessera up`")
        )
    })?;
    let output = match output {
        Output::Image(output) => output,
        Output::Frames(dir) => {
            let status = wait_sequence(&mut session, job, Some(&dir)).await?;
            eprintln!(
                "{} ({} workers)",
                sequence_summary(dir.path(), &status),
                opts.workers
            );
            return Ok(());
        }
    };
    let status = wait(&mut session, job).await?;
    let path = output.path().to_path_buf();
    // The farm and its copy of the image go with this command: no `tessera fetch`.
    let png = session.fetch(job).await?;
    output.write(&png)?;
    eprintln!("{} ({} workers)", summary(&path, &status), opts.workers);
    Ok(())
}
