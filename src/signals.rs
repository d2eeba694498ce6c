//! The signals that end a command: Ctrl-C, SIGTERM and SIGHUP for the commands that
//! run a farm on this machine (`up`, `studio`), which must stop it and remove its
//! files before they exit; and for the daemons, the same or their parent gone. The
//! coordinator takes SIGHUP as the daemons' usual request to reload ([`Hangups`]): its
//! token files. And SIGPIPE, which ends the short-lived commands whose output is closed
//! ([`end_quietly_on_a_closed_pipe`]).

use anyhow::{Context, Result};
use tracing::info;

/// The subcommands that keep running, serving others: the daemons, and the commands
/// that run a farm on this machine. They write to sockets and to their children's
/// pipes, where a reader gone must stay an error they handle (`EPIPE`), never their
/// death; `--print-config` only prints, then exits.
pub fn keeps_running(subcommand: &str, print_config: bool) -> bool {
    ["coordinator", "worker", "up", "studio"].contains(&subcommand) && !print_config
}

/// Lets a closed standard output end the process by SIGPIPE, as it ends `ls` or
/// `grep`: `tessera events 7 | head -1` stops quietly, with the shell's status for it
/// (141), once `head` has its line.
///
/// Rust ignores SIGPIPE, so a write to a closed pipe fails, and `println!` panics on
/// that failure (`failed printing to stdout: Broken pipe`, exit 101). Restoring the
/// default action would end the command on any closed pipe or socket alike: the
/// standard library sends with `MSG_NOSIGNAL`, but vectored writes (`writev`, which
/// TLS uses) raise SIGPIPE too, and a coordinator that closes the connection must stay
/// an error the command reports. So the handler installed here asks which it was: if
/// standard output is a pipe whose reader is gone (`poll` says `POLLERR`), the default
/// action is restored and the signal raised again, ending the process; otherwise it
/// returns, and the write fails with `EPIPE` as before. One handler covers every
/// `println!` of the binary, where routing stdout through a writer that exits on
/// `BrokenPipe` would have to be kept up by each new line printed.
pub fn end_quietly_on_a_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: `sigaction` installs `on_sigpipe`, which calls only async-signal-safe
    // functions (`poll`, `signal`, `raise`); it is called from `main` before the command
    // starts any thread or installs any other handler, and its failure leaves the
    // signal ignored, as it was.
    unsafe {
        let mut action: libc::sigaction = std::mem::zeroed();
        action.sa_sigaction = on_sigpipe as extern "C" fn(libc::c_int) as libc::sighandler_t;
        action.sa_flags = libc::SA_RESTART;
        libc::sigemptyset(&mut action.sa_mask);
        libc::sigaction(libc::SIGPIPE, &action, std::ptr::null_mut());
    }
}

/// SIGPIPE's handler of [`end_quietly_on_a_closed_pipe`]: ends the process by the
/// signal if standard output is closed, and otherwise lets the write fail.
#[cfg(unix)]
extern "C" fn on_sigpipe(_: libc::c_int) {
    let mut stdout = libc::pollfd {
        fd: libc::STDOUT_FILENO,
        events: libc::POLLOUT,
        revents: 0,
    };
    // SAFETY: `poll` on one descriptor with no wait, `signal` and `raise` are
    // async-signal-safe; `stdout` lives for the call.
    unsafe {
        if libc::poll(&mut stdout, 1, 0) == 1 && stdout.revents & libc::POLLERR != 0 {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
            libc::raise(libc::SIGPIPE);
        }
    }
}

/// A command stopped by a signal: the process exits with 128 + its number, as a
/// shell reports a command killed by it, once the command has left things as its
/// line says (`tessera up`: the farm stopped and its temporary directory removed;
/// `submit --wait`: the job left running on the farm).
#[derive(Debug)]
pub struct Interrupted {
    pub name: &'static str,
    /// The exit status: 130 for SIGINT (Ctrl-C), 143 for SIGTERM, 129 for SIGHUP.
    pub exit_code: u8,
    /// What the interruption leaves, said after its name.
    left: String,
}

impl Interrupted {
    /// The same signal, leaving what `left` says instead.
    pub fn leaving(self, left: String) -> Interrupted {
        Interrupted { left, ..self }
    }
}

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "interrupted by {}: {}", self.name, self.left)
    }
}

impl std::error::Error for Interrupted {}

/// What an interrupted `tessera up` leaves.
const LOCAL_FARM_STOPPED: &str = "the local farm is stopped, no image written";

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
                    Interrupted {
                        name,
                        exit_code,
                        left: String::new(),
                    },
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

    /// The next signal caught, said of a local farm (`up`, `studio`); another command
    /// says what it leaves with [`Interrupted::leaving`].
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
                left: LOCAL_FARM_STOPPED.to_owned(),
            }
        }
        #[cfg(not(unix))]
        {
            let _ = tokio::signal::ctrl_c().await;
            Interrupted {
                name: "Ctrl-C",
                exit_code: 130,
                left: LOCAL_FARM_STOPPED.to_owned(),
            }
        }
    }
}

/// The SIGHUPs a daemon receives, caught from their creation on (so that one no
/// longer ends the process).
pub struct Hangups {
    #[cfg(unix)]
    signal: tokio::signal::unix::Signal,
}

impl Hangups {
    pub fn new() -> Result<Hangups> {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{signal, SignalKind};
            Ok(Hangups {
                signal: signal(SignalKind::hangup()).context("cannot catch SIGHUP")?,
            })
        }
        #[cfg(not(unix))]
        Ok(Hangups {})
    }

    /// Waits for the next SIGHUP; `false` if none can come any more.
    pub async fn next(&mut self) -> bool {
        #[cfg(unix)]
        {
            let received = self.signal.recv().await.is_some();
            if received {
                info!("SIGHUP: reloading the token files");
            }
            received
        }
        #[cfg(not(unix))]
        {
            std::future::pending::<()>().await;
            false
        }
    }
}

/// Completes on Ctrl-C, on SIGTERM, or (for processes started by `tessera up`) when
/// standard input reaches its end because the parent is gone.
pub async fn shutdown_signal(exit_on_stdin_eof: bool) {
    let stdin_closed = async {
        if exit_on_stdin_eof {
            let _ = tokio::task::spawn_blocking(|| {
                let mut sink = Vec::new();
                let _ = std::io::Read::read_to_end(&mut std::io::stdin(), &mut sink);
            })
            .await;
        } else {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = tokio::signal::ctrl_c() => info!("interrupted"),
        () = terminate => info!("terminated"),
        () = stdin_closed => info!("parent gone"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_commands_that_print_and_exit_die_of_sigpipe() {
        for daemon in ["coordinator", "worker", "up", "studio"] {
            assert!(keeps_running(daemon, false), "{daemon}");
        }
        assert!(!keeps_running("coordinator", true));
        assert!(!keeps_running("worker", true));
        for client in [
            "list", "events", "status", "submit", "render", "refine", "simulate",
        ] {
            assert!(!keeps_running(client, false), "{client}");
        }
    }
}
