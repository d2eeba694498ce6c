//! Which name a worker joining gets. Names are unique among the connected workers, since
//! operators name workers to drain, disable and enable them, and a name is a machine's
//! (failed attempts, blocks and disabling are kept per name).
//!
//! A worker that comes back under its name from the same host (its IP address) is the
//! same machine restarted (by systemd, say) before its old connection timed out: it
//! supersedes that connection, which is closed at once and its tiles put back. One from
//! another host is another machine given the same name by mistake: it joins under the
//! name with the first free suffix, `NAME-2`, `NAME-3`..., and both hosts are named in
//! the coordinator's log. A suffixed name held by the same host is superseded in turn,
//! so that a renamed worker restarting keeps its suffix.

use std::net::IpAddr;

use protocol::WorkerId;

/// A connected worker, as naming sees it.
#[derive(Clone, Copy, Debug)]
pub struct Holder<'a> {
    pub id: WorkerId,
    pub name: &'a str,
    pub host: IpAddr,
}

/// What a joining worker's name comes to.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Naming {
    /// No connected worker has the name asked for: it is the worker's.
    Free,
    /// A connected worker of the same host holds `name` (the name asked for, or a
    /// suffixed one it was given): the new connection takes its place.
    Supersedes { name: String, old: WorkerId },
    /// The name asked for is held by a worker of another host (`holder`, on `host`):
    /// the joining worker is `name`, the first suffixed name free (or superseded, as
    /// `old`, when the same host holds it).
    Suffixed {
        name: String,
        holder: WorkerId,
        host: IpAddr,
        old: Option<WorkerId>,
    },
}

impl Naming {
    /// The name the joining worker gets, given the one it asked for.
    pub fn name<'a>(&'a self, asked: &'a str) -> &'a str {
        match self {
            Naming::Free => asked,
            Naming::Supersedes { name, .. } | Naming::Suffixed { name, .. } => name,
        }
    }

    /// The connection the joining worker replaces, if any.
    pub fn superseded(&self) -> Option<WorkerId> {
        match self {
            Naming::Free => None,
            Naming::Supersedes { old, .. } => Some(*old),
            Naming::Suffixed { old, .. } => *old,
        }
    }
}

/// The name a worker asking for `asked` from `host` gets among the `connected` ones.
pub fn place<'a>(
    connected: impl IntoIterator<Item = Holder<'a>> + Clone,
    asked: &str,
    host: IpAddr,
) -> Naming {
    let holder = |name: &str| connected.clone().into_iter().find(|h| h.name == name);
    let Some(first) = holder(asked) else {
        return Naming::Free;
    };
    if first.host == host {
        return Naming::Supersedes {
            name: asked.to_owned(),
            old: first.id,
        };
    }
    // One more suffix than there are workers is always enough to find a free one.
    let mut n = 2;
    loop {
        let name = format!("{asked}-{n}");
        match holder(&name) {
            None => {
                return Naming::Suffixed {
                    name,
                    holder: first.id,
                    host: first.host,
                    old: None,
                }
            }
            Some(h) if h.host == host => {
                return Naming::Suffixed {
                    name,
                    holder: first.id,
                    host: first.host,
                    old: Some(h.id),
                }
            }
            Some(_) => n += 1,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 0, 1));
    const B: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 0, 2));
    const C: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 0, 3));

    fn holders<'a>(list: &'a [(WorkerId, &'a str, IpAddr)]) -> Vec<Holder<'a>> {
        list.iter()
            .map(|&(id, name, host)| Holder { id, name, host })
            .collect()
    }

    #[test]
    fn a_name_nobody_holds_is_the_workers() {
        let connected = [(1, "render-1", A)];
        assert_eq!(place(holders(&connected), "render-2", B), Naming::Free);
        assert_eq!(place(holders(&[]), "", A), Naming::Free);
        assert_eq!(Naming::Free.name("render-2"), "render-2");
    }

    #[test]
    fn the_same_host_under_the_same_name_supersedes_its_old_connection() {
        let connected = [(1, "render-1", A), (2, "render-2", B)];
        let naming = place(holders(&connected), "render-2", B);
        assert_eq!(
            naming,
            Naming::Supersedes {
                name: "render-2".into(),
                old: 2
            }
        );
        assert_eq!(naming.name("render-2"), "render-2");
        assert_eq!(naming.superseded(), Some(2));
    }

    #[test]
    fn another_host_gets_the_first_free_suffix() {
        let connected = [(1, "render-2", A)];
        let naming = place(holders(&connected), "render-2", B);
        assert_eq!(
            naming,
            Naming::Suffixed {
                name: "render-2-2".into(),
                holder: 1,
                host: A,
                old: None
            }
        );
        assert_eq!(naming.name("render-2"), "render-2-2");
        assert_eq!(naming.superseded(), None);
        // A third host skips the suffix taken.
        let connected = [(1, "render-2", A), (2, "render-2-2", B)];
        assert_eq!(
            place(holders(&connected), "render-2", C).name("render-2"),
            "render-2-3"
        );
    }

    #[test]
    fn a_suffixed_worker_restarting_keeps_its_suffix() {
        let connected = [
            (1, "render-2", A),
            (2, "render-2-2", B),
            (3, "render-2-3", C),
        ];
        let naming = place(holders(&connected), "render-2", C);
        assert_eq!(
            naming,
            Naming::Suffixed {
                name: "render-2-3".into(),
                holder: 1,
                host: A,
                old: Some(3)
            }
        );
        assert_eq!(naming.superseded(), Some(3));
    }
}
