//! A farm of real `tessera coordinator` and `tessera worker` child processes on this
//! machine, on loopback, with a temporary data directory: what `tessera up` and the
//! farm benchmarks run on.
//!
//! The children are stopped when the farm is dropped; should this process be killed,
//! they notice that their standard input (a pipe from it) has closed and exit, so no
//! process is ever left behind.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::Mutex;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use coordinator::client::Client;
use transport::Endpoint;

/// One worker process of a local farm.
#[derive(Clone, Debug)]
pub struct WorkerSpec {
    pub threads: usize,
    /// Makes the worker this many times slower (benchmarks of uneven farms).
    pub throttle: Option<f64>,
}

impl Default for WorkerSpec {
    fn default() -> Self {
        WorkerSpec {
            threads: 1,
            throttle: None,
        }
    }
}

/// The child processes of a local farm; dropping it stops them all.
pub struct LocalFarm {
    address: String,
    /// The coordinator's HTTP address, when it serves HTTP.
    http: Option<String>,
    children: Mutex<Vec<(Child, Option<ChildStdin>)>>,
    dir: tempfile::TempDir,
}

impl LocalFarm {
    /// Completes when the farm can no longer finish: the coordinator or every worker
    /// has exited on its own. (One worker lost is survivable: its tiles go to the
    /// others.) The error names the process, with the last line of its log.
    pub async fn first_exit(&self) -> anyhow::Error {
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

    /// Starts the coordinator, waits for its address, then starts the workers.
    pub fn start(workers: &[WorkerSpec]) -> Result<LocalFarm> {
        Self::start_with(workers, &[])
    }

    /// [`LocalFarm::start`] with more arguments for the coordinator (benchmarks of its
    /// settings).
    pub fn start_with(workers: &[WorkerSpec], coordinator_args: &[&str]) -> Result<LocalFarm> {
        let exe = std::env::current_exe().context("cannot find the tessera executable")?;
        let dir = tempfile::Builder::new()
            .prefix("tessera-up-")
            .tempdir()
            .context("cannot create a temporary directory")?;
        let mut farm = LocalFarm {
            address: String::new(),
            http: None,
            children: Mutex::new(Vec::new()),
            dir,
        };
        let data = farm.dir.path().join("data");
        let mut args: Vec<&std::ffi::OsStr> = vec![
            "coordinator".as_ref(),
            "--listen".as_ref(),
            "127.0.0.1:0".as_ref(),
            "--data".as_ref(),
            data.as_os_str(),
        ];
        args.extend(coordinator_args.iter().map(std::ffi::OsStr::new));
        let mut coordinator = farm.spawn(&exe, "coordinator", &args, true)?;
        let stdout = coordinator.stdout.take().expect("stdout is piped");
        let stdin = coordinator.stdin.take();
        farm.children
            .get_mut()
            .expect("children lock")
            .push((coordinator, stdin));
        let mut stdout = BufReader::new(stdout);
        let mut line = String::new();
        stdout.read_line(&mut line)?;
        farm.address = match line.trim().strip_prefix("listening on ") {
            Some(addr) => addr.to_string(),
            None => bail!(
                "the local coordinator did not start: {}",
                last_line(&farm.dir.path().join("coordinator.log"))
            ),
        };
        // With --http, its address is the next line.
        if coordinator_args.contains(&"--http") {
            line.clear();
            stdout.read_line(&mut line)?;
            farm.http = match line.trim().strip_prefix("http on ") {
                Some(addr) => Some(addr.to_string()),
                None => bail!(
                    "the local coordinator did not serve HTTP: {}",
                    last_line(&farm.dir.path().join("coordinator.log"))
                ),
            };
        }
        for (i, spec) in workers.iter().enumerate() {
            let name = format!("local-{}", i + 1);
            let threads = spec.threads.to_string();
            let mut args: Vec<&std::ffi::OsStr> = vec![
                "worker".as_ref(),
                "--coordinator".as_ref(),
                farm.address.as_ref(),
                "--threads".as_ref(),
                threads.as_ref(),
                "--name".as_ref(),
                name.as_ref(),
            ];
            let throttle = spec.throttle.map(|t| t.to_string());
            if let Some(throttle) = &throttle {
                args.push("--throttle".as_ref());
                args.push(throttle.as_ref());
            }
            let mut child = farm.spawn(&exe, &name, &args, false)?;
            let stdin = child.stdin.take();
            farm.children
                .get_mut()
                .expect("children lock")
                .push((child, stdin));
        }
        Ok(farm)
    }

    /// The process ids: the coordinator's first, then the workers'.
    pub fn pids(&self) -> Vec<u32> {
        let children = self.children.lock().expect("children lock");
        children.iter().map(|(child, _)| child.id()).collect()
    }

    /// The coordinator's data directory.
    pub fn data_dir(&self) -> std::path::PathBuf {
        self.dir.path().join("data")
    }

    /// The coordinator's address.
    pub fn address(&self) -> &str {
        &self.address
    }

    /// Where the coordinator serves HTTP, when it was started with `--http`.
    pub fn http_address(&self) -> Option<&str> {
        self.http.as_deref()
    }

    /// Waits until `n` workers have registered with the coordinator.
    pub async fn wait_for_workers(&self, n: usize, timeout: Duration) -> Result<()> {
        let deadline = tokio::time::Instant::now() + timeout;
        let endpoint = Endpoint::plain(self.address.clone());
        loop {
            let mut client = Client::connect(&endpoint).await?;
            if client.workers().await?.len() >= n {
                return Ok(());
            }
            if tokio::time::Instant::now() >= deadline {
                bail!("{n} local workers did not register within {timeout:?}");
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
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
        let mut command = Command::new(exe);
        // The farm is this command's own: settings meant for other daemons (a config
        // file, an HTTP port) must not reach its processes.
        for (key, _) in std::env::vars_os() {
            if key.to_string_lossy().starts_with("TESSERA_") {
                command.env_remove(key);
            }
        }
        command
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
