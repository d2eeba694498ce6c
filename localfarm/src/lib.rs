//! A farm of real `tessera coordinator` and `tessera worker` child processes on this
//! machine, on loopback, with a temporary data directory: what `tessera up`, `tessera
//! studio` and the farm benchmarks (`tessera-bench`) run on.
//!
//! The executable is given, not taken to be the running one: `tessera` passes its own,
//! the benchmark the `tessera` beside it, which is what lets the benchmarks live outside
//! the shipped binary.
//!
//! The children are stopped when the farm is dropped; should this process be killed,
//! they notice that their standard input (a pipe from it) has closed and exit, so no
//! process is ever left behind.
//!
//! A farm of unequal machines is made the way an operator would slow a machine, from
//! outside the worker: [`CpuLimit`] puts one of its processes in a cgroup limited to a
//! share of a core. A worker whose rendering hangs while the rest of it runs is made the
//! same way: [`FrozenThreads`] stops its render threads alone, with ptrace.

mod cpu_limit;
mod freeze;
mod privileged;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, ExitStatus, Stdio};
use std::sync::Mutex;
use std::time::Duration;

use coordinator::client::Client;
use transport::Endpoint;

pub use cpu_limit::CpuLimit;
pub use freeze::FrozenThreads;
pub use privileged::{privileges_required, unprivileged};

/// What can go wrong starting, watching or limiting a local farm's processes.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot create a temporary directory")]
    TempDir(#[source] std::io::Error),
    #[error("cannot start {}", exe.display())]
    Spawn {
        exe: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the local coordinator did not start: {0}")]
    CoordinatorDidNotStart(String),
    #[error("the local coordinator did not serve HTTP: {0}")]
    NoHttp(String),
    /// A process exited on its own, which the farm cannot finish without.
    #[error("the local {name} stopped ({status}): {log}")]
    Stopped {
        name: String,
        status: ExitStatus,
        /// The last line of its log.
        log: String,
    },
    #[error("{count} local workers did not register within {timeout:?}")]
    WorkersLate { count: usize, timeout: Duration },
    /// Talking to the local coordinator failed.
    #[error(transparent)]
    Coordinator(anyhow::Error),
    /// Reading a child's output or writing its log.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The one line [`CpuLimit`] gives: what could not be done, and that it takes root
    /// where that is the reason.
    #[error("cannot limit a process's CPU: {0}")]
    CpuLimit(String),
    /// [`FrozenThreads`] found no thread to stop.
    #[error("process {pid} has no thread named {prefix}*")]
    NoSuchThreads { pid: u32, prefix: String },
    /// [`FrozenThreads`] could not stop or resume threads: what failed, and that it
    /// takes root where that is the reason.
    #[error("cannot freeze threads of process {pid}: {reason}")]
    Freeze { pid: u32, reason: String },
}

/// One worker process of a local farm.
#[derive(Clone, Debug)]
pub struct WorkerSpec {
    pub threads: usize,
    /// More arguments for `tessera worker` (benchmarks of its settings, such as
    /// `--cache-dir`).
    pub args: Vec<String>,
}

impl Default for WorkerSpec {
    fn default() -> Self {
        WorkerSpec {
            threads: 1,
            args: Vec::new(),
        }
    }
}

/// The limits of the coordinator `tessera up` starts: whatever `tessera render` renders
/// (its size and antialiasing), not the defaults that guard a shared farm.
pub fn up_limits() -> Vec<String> {
    use render::limits::{MAX_AA, MAX_SIDE};
    vec![
        "--max-aa".into(),
        MAX_AA.to_string(),
        "--max-pixels".into(),
        (u64::from(MAX_SIDE) * u64::from(MAX_SIDE)).to_string(),
        "--max-objects".into(),
        u64::MAX.to_string(),
    ]
}

/// The `TESSERA_*` variables of this process's environment: settings meant for other
/// daemons (a config file, an HTTP port), which a process the farm or a benchmark
/// starts must not inherit.
pub fn tessera_variables() -> impl Iterator<Item = std::ffi::OsString> {
    std::env::vars_os()
        .map(|(key, _)| key)
        .filter(|key| key.to_string_lossy().starts_with("TESSERA_"))
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
    pub async fn first_exit(&self) -> Error {
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
                return Error::Stopped { name, status, log };
            }
        }
    }

    /// Starts the coordinator (`exe coordinator ...`, `exe` being a `tessera`
    /// executable), waits for its address, then starts the workers.
    pub fn start(exe: &Path, workers: &[WorkerSpec]) -> Result<LocalFarm, Error> {
        Self::start_with(exe, workers, &[])
    }

    /// [`LocalFarm::start`] with more arguments for the coordinator (benchmarks of its
    /// settings).
    pub fn start_with(
        exe: &Path,
        workers: &[WorkerSpec],
        coordinator_args: &[&str],
    ) -> Result<LocalFarm, Error> {
        let dir = tempfile::Builder::new()
            .prefix("tessera-up-")
            .tempdir()
            .map_err(Error::TempDir)?;
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
        let mut coordinator = farm.spawn(exe, "coordinator", &args, true)?;
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
            None => {
                return Err(Error::CoordinatorDidNotStart(last_line(
                    &farm.dir.path().join("coordinator.log"),
                )))
            }
        };
        // With --http, its address is the next line.
        if coordinator_args.contains(&"--http") {
            line.clear();
            stdout.read_line(&mut line)?;
            farm.http = match line.trim().strip_prefix("http on ") {
                Some(addr) => Some(addr.to_string()),
                None => {
                    return Err(Error::NoHttp(last_line(
                        &farm.dir.path().join("coordinator.log"),
                    )))
                }
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
            args.extend(spec.args.iter().map(std::ffi::OsStr::new));
            let mut child = farm.spawn(exe, &name, &args, false)?;
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
    pub async fn wait_for_workers(&self, n: usize, timeout: Duration) -> Result<(), Error> {
        let deadline = tokio::time::Instant::now() + timeout;
        let endpoint = Endpoint::plain(self.address.clone());
        loop {
            let mut client = Client::connect(&endpoint)
                .await
                .map_err(Error::Coordinator)?;
            let workers = client.workers().await.map_err(Error::Coordinator)?;
            if workers.len() >= n {
                return Ok(());
            }
            if tokio::time::Instant::now() >= deadline {
                return Err(Error::WorkersLate { count: n, timeout });
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
    ) -> Result<Child, Error> {
        let log_path = self.dir.path().join(format!("{log}.log"));
        let log_file = std::fs::File::create(&log_path)?;
        let mut command = Command::new(exe);
        // The farm is this command's own: settings meant for other daemons (a config
        // file, an HTTP port) must not reach its processes.
        for key in tessera_variables() {
            command.env_remove(key);
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
            .map_err(|source| Error::Spawn {
                exe: exe.to_path_buf(),
                source,
            })
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
