//! Finding servers: every `road serve` holds a liveliness token at `<prefix>/alive/server`, so
//! one liveliness query under a root (`road/**/alive/server`) lists the servers behind the
//! zenoh routers a client reaches; each one's status gives its load. A client places a scene on
//! the least-loaded one (`docs/protocol.md`, "Several servers").

use std::time::Duration;

use road_protocol::{Keys, Status};
use zenoh::Wait;

use crate::{Error, Result, parse_reply, query_raw};

/// A server found under a root: its key prefix and the status it answered with.
#[derive(Debug, Clone)]
pub struct ServerInfo {
    pub prefix: String,
    pub status: Status,
}

impl ServerInfo {
    /// Live scenes over capacity: 0 when idle, 1 when full.
    pub fn load(&self) -> f64 {
        self.status.scenes.len() as f64 / self.status.capacity.max(1) as f64
    }

    /// Whether another scene fits.
    pub fn has_room(&self) -> bool {
        self.status.scenes.len() < self.status.capacity
    }
}

/// What [`discover`] found: the servers that answered, and those whose token is there but
/// whose status did not come (each with the reason), so that none is dropped silently.
#[derive(Debug, Default)]
pub struct Discovered {
    pub servers: Vec<ServerInfo>,
    pub unreachable: Vec<(String, Error)>,
}

impl Discovered {
    /// The server with room whose load is lowest (ties: fewer live scenes, then the prefix).
    pub fn least_loaded(&self) -> Option<&ServerInfo> {
        self.servers.iter().filter(|s| s.has_room()).min_by(|a, b| {
            a.load()
                .total_cmp(&b.load())
                .then(a.status.scenes.len().cmp(&b.status.scenes.len()))
                .then(a.prefix.cmp(&b.prefix))
        })
    }
}

/// Every server whose prefix is `root` or lies below it, with its status, sorted by prefix.
/// `timeout` bounds the liveliness query and each status query.
pub fn discover(session: &zenoh::Session, root: &str, timeout: Duration) -> Result<Discovered> {
    let selector = road_protocol::servers_alive_under(root);
    let replies = session
        .liveliness()
        .get(selector.as_str())
        .timeout(timeout)
        .wait()?;
    let mut prefixes = Vec::new();
    // The channel closes when every router has answered or the timeout passed.
    while let Ok(reply) = replies.recv() {
        if let Ok(sample) = reply.result() {
            let key = sample.key_expr().as_str();
            match road_protocol::server_prefix_of(key) {
                Some(prefix) => prefixes.push(prefix.to_owned()),
                None => tracing::warn!(key, "a liveliness token under {selector} is no server's"),
            }
        }
    }
    prefixes.sort();
    prefixes.dedup();
    let mut found = Discovered::default();
    for prefix in prefixes {
        let key = Keys::new(&prefix).status();
        let status = query_raw(session, &key, Vec::new(), timeout).and_then(|reply| {
            let bytes = reply.map_err(Error::Refused)?;
            parse_reply::<Status>(&key, &bytes)
        });
        match status {
            Ok(status) => found.servers.push(ServerInfo { prefix, status }),
            Err(e) => found.unreachable.push((prefix, e)),
        }
    }
    Ok(found)
}
