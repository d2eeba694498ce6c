//! `tessera up`: a whole farm on this machine for one scene. A coordinator with a
//! temporary data directory and N worker processes on loopback, the scene submitted,
//! progress shown, the image written, and everything shut down again.
//!
//! The children are the real `tessera coordinator` and `tessera worker` processes. They
//! are stopped when `up` ends for any reason; should `up` itself be killed, they notice
//! that their standard input (a pipe from `up`) has closed and exit, so no process is
//! ever left behind.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::Mutex;

use anyhow::{anyhow, bail, Context, Result};
use coordinator::client::Client;
use coordinator::transport::Endpoint;
use protocol::Overrides;

use crate::client_commands::{fetch_to, submit, summary, wait};
use crate::output::default_output;

pub struct Options {
    pub scene: PathBuf,
    pub workers: usize,
    pub threads_per_worker: usize,
    pub output: Option<PathBuf>,
    pub overrides: Overrides,
}

pub async fn run(opts: Options) -> Result<()> {
    // Fail on an unreadable scene before starting anything.
    crate::client_commands::read_scene(&opts.scene)?;
    let (workers, threads) = (opts.workers, opts.threads_per_worker);
    let farm = tokio::task::spawn_blocking(move || LocalFarm::start(workers, threads))
        .await
        .context("starting the local farm")??;
    let result = tokio::select! {
        r = render_on(&farm.address, &opts) => r,
        e = farm.first_exit() => Err(e),
        _ = tokio::signal::ctrl_c() => Err(anyhow!("interrupted")),
    };
    drop(farm);
    result
}

async fn render_on(address: &str, opts: &Options) -> Result<()> {
    let mut client = Client::connect(&Endpoint::plain(address)).await?;
    let job = submit(&mut client, &opts.scene, opts.overrides, 0).await?;
    let status = wait(&mut client, job).await?;
    let output = opts
        .output
        .clone()
        .unwrap_or_else(|| default_output(&opts.scene));
    fetch_to(&mut client, job, &output).await?;
    eprintln!("{} ({} workers)", summary(&output, &status), opts.workers);
    Ok(())
}

/// The child processes of a local farm; dropping it stops them all.
struct LocalFarm {
    address: String,
    children: Mutex<Vec<(Child, Option<ChildStdin>)>>,
    dir: tempfile::TempDir,
}

impl LocalFarm {
    /// Completes when the farm can no longer finish: the coordinator or every worker
    /// has exited on its own. (One worker lost is survivable: its tiles go to the
    /// others.) The error names the process, with the last line of its log.
    async fn first_exit(&self) -> anyhow::Error {
        loop {
            tokio::time::sleep(std::time::Duration::from_millis(200)).await;
            let mut children = self.children.lock().expect("children lock");
            let mut exited = Vec::new();
            for (i, (child, _)) in children.iter_mut().enumerate() {
                if let Ok(Some(status)) = child.try_wait() {
                    exited.push((i, status));
                }
            }
            let workers = children.len() - 1;
            let fatal = exited.iter().find(|(i, _)| *i == 0).or_else(|| {
                (workers > 0 && exited.len() == workers)
                    .then(|| exited.last())
                    .flatten()
            });
            if let Some(&(i, status)) = fatal {
                let name = if i == 0 {
                    "coordinator".to_string()
                } else {
                    format!("local-{i}")
                };
                let log = last_line(&self.dir.path().join(format!("{name}.log")));
                return anyhow!("the local {name} stopped ({status}): {log}");
            }
        }
    }

    fn start(workers: usize, threads: usize) -> Result<LocalFarm> {
        let exe = std::env::current_exe().context("cannot find the tessera executable")?;
        let dir = tempfile::Builder::new()
            .prefix("tessera-up-")
            .tempdir()
            .context("cannot create a temporary directory")?;
        let mut farm = LocalFarm {
            address: String::new(),
            children: Mutex::new(Vec::new()),
            dir,
        };
        let data = farm.dir.path().join("data");
        let mut coordinator = farm.spawn(
            &exe,
            "coordinator",
            &[
                "coordinator".as_ref(),
                "--listen".as_ref(),
                "127.0.0.1:0".as_ref(),
                "--data".as_ref(),
                data.as_os_str(),
            ],
            true,
        )?;
        let stdout = coordinator.stdout.take().expect("stdout is piped");
        let stdin = coordinator.stdin.take();
        farm.children
            .get_mut()
            .expect("children lock")
            .push((coordinator, stdin));
        let mut line = String::new();
        BufReader::new(stdout).read_line(&mut line)?;
        farm.address = match line.trim().strip_prefix("listening on ") {
            Some(addr) => addr.to_string(),
            None => bail!(
                "the local coordinator did not start: {}",
                last_line(&farm.dir.path().join("coordinator.log"))
            ),
        };
        for i in 0..workers {
            let name = format!("local-{}", i + 1);
            let threads = threads.to_string();
            let mut child = farm.spawn(
                &exe,
                &name,
                &[
                    "worker".as_ref(),
                    "--coordinator".as_ref(),
                    farm.address.as_ref(),
                    "--threads".as_ref(),
                    threads.as_ref(),
                    "--name".as_ref(),
                    name.as_ref(),
                ],
                false,
            )?;
            let stdin = child.stdin.take();
            farm.children
                .get_mut()
                .expect("children lock")
                .push((child, stdin));
        }
        Ok(farm)
    }

    fn spawn(
        &self,
        exe: &Path,
        log: &str,
        args: &[&std::ffi::OsStr],
        stdout: bool,
    ) -> Result<Child> {
        let log_path = self.dir.path().join(format!("{log}.log"));
        let log_file = std::fs::File::create(&log_path)?;
        Command::new(exe)
            .args(args)
            .arg("--exit-on-stdin-eof")
            .stdin(Stdio::piped())
            .stdout(if stdout {
                Stdio::piped()
            } else {
                Stdio::null()
            })
            .stderr(log_file)
            .spawn()
            .with_context(|| format!("cannot start {}", exe.display()))
    }
}

impl Drop for LocalFarm {
    fn drop(&mut self) {
        // Workers first, so the coordinator never sees its workers' tiles requeued.
        let children = self.children.get_mut().unwrap_or_else(|e| e.into_inner());
        for (child, stdin) in children.iter_mut().rev() {
            drop(stdin.take());
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

fn last_line(path: &Path) -> String {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|s| s.lines().last().map(str::to_string))
        .unwrap_or_else(|| "no output".into())
}
