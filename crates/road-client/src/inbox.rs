//! Hands the samples of a client's one subscription to its scenes, by the scene id in the key.

use std::collections::HashMap;
use std::sync::Mutex;
use std::sync::mpsc::{Receiver, Sender, channel};

use zenoh::sample::Sample;

/// The open scenes' channels: NPC ticks and errors.
#[derive(Debug, Default)]
pub(crate) struct Inbox {
    scenes: Mutex<HashMap<u64, SceneChannels>>,
}

#[derive(Debug)]
struct SceneChannels {
    npc: Sender<Sample>,
    errors: Sender<Sample>,
}

/// What a key under the client's scenes carries.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Topic {
    Npc,
    Error,
}

/// The scene id and topic of a key ending `scene/<id>/npc` or `scene/<id>/error`.
pub(crate) fn scene_topic(key: &str) -> Option<(u64, Topic)> {
    let mut chunks = key.rsplit('/');
    let topic = match chunks.next()? {
        "npc" => Topic::Npc,
        "error" => Topic::Error,
        _ => return None,
    };
    let scene = chunks.next()?.parse().ok()?;
    (chunks.next()? == "scene").then_some((scene, topic))
}

impl Inbox {
    /// Opens scene `id`'s channels: (NPC ticks, errors).
    pub(crate) fn open(&self, id: u64) -> (Receiver<Sample>, Receiver<Sample>) {
        let (npc, npc_rx) = channel();
        let (errors, errors_rx) = channel();
        self.lock().insert(id, SceneChannels { npc, errors });
        (npc_rx, errors_rx)
    }

    /// Closes scene `id`'s channels: later samples for it are dropped.
    pub(crate) fn close(&self, id: u64) {
        self.lock().remove(&id);
    }

    /// Closes every scene's channels (the client is going away): their receivers disconnect.
    pub(crate) fn close_all(&self) {
        self.lock().clear();
    }

    /// Hands `sample` to its scene.
    pub(crate) fn deliver(&self, sample: Sample) {
        let key = sample.key_expr().as_str();
        let Some((scene, topic)) = scene_topic(key) else {
            tracing::warn!(key, "a message on a key this client does not read; dropped");
            return;
        };
        let scenes = self.lock();
        let Some(channels) = scenes.get(&scene) else {
            // A scene this client closed or dropped: its late messages have no reader.
            tracing::debug!(
                scene,
                key,
                "a message for a scene this client no longer holds"
            );
            return;
        };
        let sender = match topic {
            Topic::Npc => &channels.npc,
            Topic::Error => &channels.errors,
        };
        // The receiver lives as long as the entry (the scene removes it when dropped).
        let _ = sender.send(sample);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u64, SceneChannels>> {
        // A panic while holding this lock leaves the map consistent (single inserts/removes).
        self.scenes.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_name_their_scene_and_topic() {
        assert_eq!(
            scene_topic("road/client/ego-1/scene/42/npc"),
            Some((42, Topic::Npc))
        );
        assert_eq!(
            scene_topic("road/a/client/c/scene/7/error"),
            Some((7, Topic::Error))
        );
        for key in [
            "road/client/c/scene/x/npc",
            "road/client/c/scene/1/ego",
            "road/client/c/scenes/1/npc",
            "npc",
            "1/npc",
        ] {
            assert_eq!(scene_topic(key), None, "{key}");
        }
    }
}
