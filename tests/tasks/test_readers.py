"""tasks/readers.py: the one scene resolver of ``navcrafter view``, ``export`` and ``render``."""

from __future__ import annotations

import numpy as np
import pytest

from navcrafter.schemas.layout import INGEST
from navcrafter.schemas.store import Store
from navcrafter.tasks.readers import SceneNotFound, resolve_scene, scene_choices

ROOM, STREET, STAIRS = "ab12" + "0" * 60, "ab34" + "1" * 60, "cd56" + "2" * 60


def ingested(store: Store, scene_id: str, source: str) -> None:
    """A scene whose ingest step recorded ``source`` (all the resolver reads besides the manifest)."""
    w = store.scene(scene_id).begin(INGEST, None, "k", "simulation")
    w.write("image", np.zeros((4, 4, 3), np.uint8))
    w.write("work_image", np.zeros((4, 4, 3), np.uint8))
    w.commit(0.0, source=source, sha256=scene_id, original_size=[4, 4], original_mode="RGB", exif_orientation=1,
             crop_box=[0, 0, 4, 4], normalised_size=[4, 4], work_size=[4, 4])


@pytest.fixture()
def store(tmp_path) -> Store:
    st = Store(str(tmp_path / "store"))
    ingested(st, ROOM, "/photos/room-0.png")
    ingested(st, STREET, "/photos/street-0.png")
    ingested(st, STAIRS, "/photos/stairs-0.jpg")
    return st


def test_exact_id_unique_prefix_and_photo_name(store):
    assert resolve_scene(store, ROOM) == ROOM
    assert resolve_scene(store, "cd") == STAIRS  # a unique prefix
    assert resolve_scene(store, "ab3") == STREET
    assert resolve_scene(store, "street-0.png") == STREET  # the photo's file name, stem or path
    assert resolve_scene(store, "room-0") == ROOM
    assert resolve_scene(store, "/photos/stairs-0.jpg") == STAIRS
    assert list(scene_choices(store)) == ["room-0.png (ab1200000000)", "stairs-0.jpg (cd5622222222)",
                                          "street-0.png (ab3411111111)"]


def test_no_scene_given(store, tmp_path):
    assert resolve_scene(store, None, default="first") == ROOM  # first by photo name
    with pytest.raises(SceneNotFound, match=r"holds 3 scenes; choose one with --scene .*room-0.png \(ab1200000000\)"):
        resolve_scene(store, None, option="--scene")
    one = Store(str(tmp_path / "one"))
    ingested(one, STAIRS, "stairs.png")
    assert resolve_scene(one, None) == STAIRS  # the only scene
    with pytest.raises(SceneNotFound, match="has no scenes yet; run `navcrafter explore PHOTOS --store"):
        resolve_scene(Store(str(tmp_path / "empty")), None)


def test_ambiguous_prefix_names_the_candidates(store):
    with pytest.raises(SceneNotFound) as exc:
        resolve_scene(store, "ab")
    msg = str(exc.value)
    assert "SCENE 'ab' matches 2 scenes" in msg
    assert "room-0.png (ab1200000000)" in msg and "street-0.png (ab3411111111)" in msg and "stairs" not in msg
    assert "give more characters of the id" in msg


def test_unknown_scene_lists_close_names_or_the_scenes(store):
    with pytest.raises(SceneNotFound) as exc:
        resolve_scene(store, "strete-0.png", option="--scene")
    msg = str(exc.value)
    assert msg.startswith("--scene 'strete-0.png' names no scene of ")
    assert "did you mean street-0.png (ab3411111111)?" in msg and f"`navcrafter status {store.uri}`" in msg
    with pytest.raises(SceneNotFound) as exc:
        resolve_scene(store, "zz-nothing-like-it")
    msg = str(exc.value)  # nothing close: the store's scenes are listed
    assert "its scenes: room-0.png (ab1200000000), stairs-0.jpg (cd5622222222), street-0.png (ab3411111111)" in msg
    with pytest.raises(SceneNotFound, match="names no scene"):
        resolve_scene(store, "")
