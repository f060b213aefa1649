//! Reading the scene recordings of `road serve` (`crates/road-serve/src/record.rs`) for
//! `road render`, `road replay` and `road demo`, including files cut off by a killed server.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// A recording's topics (`road_serve::record::topics`).
pub use road_serve::record::topics;

/// Every message of one recording file, in file order.
#[derive(Debug)]
pub struct Recording {
    pub path: PathBuf,
    pub messages: Vec<mcap::Message<'static>>,
    /// Why reading stopped before the end of the file (a server killed mid-scene leaves no
    /// summary and may end mid-chunk); `None` when the file ended cleanly.
    pub cut_off: Option<String>,
}

impl Recording {
    /// Reads the whole file; a file that stops mid-way keeps the messages before the break.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path)
            .with_context(|| format!("cannot read the recording {}", path.display()))?;
        anyhow::ensure!(
            bytes.starts_with(mcap::MAGIC),
            "not an MCAP file (it does not start with the MCAP magic): {}",
            path.display()
        );
        // Without the end magic check the stream stops at the data end record, or at the
        // first broken record of a file that was never finished.
        let stream = mcap::MessageStream::new_with_options(
            &bytes,
            mcap::read::Options::IgnoreEndMagic.into(),
        )
        .with_context(|| format!("not a readable MCAP file: {}", path.display()))?;
        let mut messages = Vec::new();
        let mut cut_off = None;
        for message in stream {
            match message {
                Ok(m) => messages.push(m),
                Err(e) if messages.is_empty() => {
                    return Err(anyhow::Error::new(e))
                        .with_context(|| format!("not a readable MCAP file: {}", path.display()));
                }
                Err(e) => {
                    cut_off = Some(e.to_string());
                    break;
                }
            }
        }
        if let Some(reason) = &cut_off {
            tracing::warn!(
                "{} ends early ({reason}; a server killed mid-scene leaves such a file): using its first {} messages",
                path.display(),
                messages.len()
            );
        }
        Ok(Self {
            path: path.to_owned(),
            messages,
            cut_off,
        })
    }

    /// The messages on `topic`.
    pub fn on<'a>(&'a self, topic: &'a str) -> impl Iterator<Item = &'a mcap::Message<'static>> {
        self.messages
            .iter()
            .filter(move |m| m.channel.topic == topic)
    }

    /// The scene's id: from the creation reply, else from the first NPC tick.
    pub fn scene_id(&self) -> Option<u64> {
        [topics::CREATED, topics::NPC].iter().find_map(|topic| {
            self.on(topic).find_map(|m| {
                serde_json::from_slice::<serde_json::Value>(&m.data)
                    .ok()?
                    .get("scene")?
                    .as_u64()
            })
        })
    }

    /// The scene's client id: from the creation request, else from an ego tick that names it.
    pub fn client_id(&self) -> Option<String> {
        [topics::CREATE, topics::EGO].iter().find_map(|topic| {
            self.on(topic).find_map(|m| {
                Some(
                    serde_json::from_slice::<serde_json::Value>(&m.data)
                        .ok()?
                        .get("client")?
                        .as_str()?
                        .to_owned(),
                )
            })
        })
    }
}
