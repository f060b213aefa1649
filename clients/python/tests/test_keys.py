"""The client's one subscription hands each message to its scene by the key's scene id."""

from road_client import _scene_topic


def test_scene_keys_name_their_scene_and_topic():
    assert _scene_topic("road/client/ego-1/scene/42/npc") == (42, "npc")
    assert _scene_topic("road/a/client/c/scene/7/error") == (7, "error")
    for key in ["road/client/c/scene/x/npc", "road/client/c/scene/1/ego",
                "road/client/c/scenes/1/npc", "npc", "1/npc"]:
        assert _scene_topic(key) is None, key
