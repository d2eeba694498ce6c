//! The rules a coordinator's settings must follow before it accepts anyone: the two
//! roles' secrets must differ, and a coordinator that other machines can reach must
//! ask both roles for proof, unless its operator says otherwise.

use std::fmt;
use std::net::SocketAddr;

use thiserror::Error;

use crate::server::Config;

/// Settings under which peers could do what their role does not allow. The messages
/// name the command line's flags, which is where an operator fixes them.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum Unsafe {
    /// A client's credential would also let it join as a worker, and render tiles.
    #[error(
        "the worker token and the client token are the same secret, so any client could \
         join as a worker: give two different secrets (e.g. each from `openssl rand \
         -hex 32`)"
    )]
    SameSecret,
    /// Anyone who can reach the address could submit jobs or pose as a worker.
    #[error(
        "refusing to listen on {listen} without {missing}: anyone who can reach it could \
         submit jobs or pose as a worker. Give --worker-token-file FILE and \
         --client-token-file FILE (or pass --insecure to accept peers without proof)"
    )]
    Unproven {
        listen: SocketAddr,
        missing: MissingTokens,
    },
}

/// Which roles' tokens a coordinator lacks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MissingTokens {
    Both,
    Worker,
    Client,
}

impl fmt::Display for MissingTokens {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            MissingTokens::Both => "a token for workers and one for clients",
            MissingTokens::Worker => "a token for workers",
            MissingTokens::Client => "a token for clients",
        })
    }
}

impl Config {
    /// Checks the secrets against each other and against the address listened on.
    /// On a loopback address only this machine's users can connect, so no token is
    /// needed there; elsewhere both roles need one, unless `insecure` accepts the
    /// roles without a token as they are.
    pub fn check_security(&self, insecure: bool) -> Result<(), Unsafe> {
        let (worker, client) = (&self.worker_secret, &self.client_secret);
        if worker.is_some() && worker == client {
            return Err(Unsafe::SameSecret);
        }
        let missing = match (worker.is_some(), client.is_some()) {
            (true, true) => return Ok(()),
            (false, false) => MissingTokens::Both,
            (false, true) => MissingTokens::Worker,
            (true, false) => MissingTokens::Client,
        };
        if self.listen.ip().is_loopback() || insecure {
            return Ok(());
        }
        Err(Unsafe::Unproven {
            listen: self.listen,
            missing,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(listen: &str, worker: Option<&str>, client: Option<&str>) -> Config {
        let mut config = Config::new(listen.parse().unwrap(), "unused".into());
        config.worker_secret = worker.map(|s| s.as_bytes().to_vec());
        config.client_secret = client.map(|s| s.as_bytes().to_vec());
        config
    }

    #[test]
    fn loopback_needs_no_token() {
        for listen in ["127.0.0.1:7878", "[::1]:0"] {
            assert_eq!(config(listen, None, None).check_security(false), Ok(()));
            assert_eq!(
                config(listen, Some("w"), None).check_security(false),
                Ok(())
            );
        }
    }

    #[test]
    fn another_address_needs_both_tokens_or_insecure() {
        let error = |worker, client| {
            config("0.0.0.0:7878", worker, client)
                .check_security(false)
                .unwrap_err()
                .to_string()
        };
        assert_eq!(
            error(None, None),
            "refusing to listen on 0.0.0.0:7878 without a token for workers and one for \
             clients: anyone who can reach it could submit jobs or pose as a worker. Give \
             --worker-token-file FILE and --client-token-file FILE (or pass --insecure to \
             accept peers without proof)"
        );
        assert!(error(None, Some("c")).contains(" without a token for workers: "));
        assert!(error(Some("w"), None).contains(" without a token for clients: "));
        let both = config("10.1.2.3:7878", Some("w"), Some("c"));
        assert_eq!(both.check_security(false), Ok(()));
        let open = config("0.0.0.0:7878", None, Some("c"));
        assert_eq!(open.check_security(true), Ok(()));
    }

    #[test]
    fn the_roles_secrets_must_differ_on_any_address() {
        for (listen, insecure) in [("127.0.0.1:7878", false), ("0.0.0.0:7878", true)] {
            let same = config(listen, Some("s"), Some("s"));
            assert_eq!(same.check_security(insecure), Err(Unsafe::SameSecret));
        }
        assert_eq!(
            Unsafe::SameSecret.to_string(),
            "the worker token and the client token are the same secret, so any client could \
             join as a worker: give two different secrets (e.g. each from `openssl rand -hex \
             32`)"
        );
    }
}
