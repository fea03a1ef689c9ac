"""The committed retrieval heads are the bytes their pins name (assets/retrieval/heads.json: the
sha256 of each whole folder), the default is the instances design, and every one loads."""

from __future__ import annotations

import json

from scenegen.core.files import folder_sha256
from scenegen.paths import ASSETS_DIR
from scenegen.perception.retrieval import DEFAULT_HEAD, HEADS_FILE


def test_every_committed_head_is_pinned_by_its_folder_and_loads():
    from scenegen.perception.retrieval.perceive import RetrievalPerception

    pins = json.loads(HEADS_FILE.read_text())
    folders = {p.name for p in (ASSETS_DIR / "retrieval").iterdir() if p.is_dir()}
    assert set(pins["heads"]) == folders
    for name, pin in pins["heads"].items():
        assert folder_sha256(ASSETS_DIR / "retrieval" / name) == pin["sha256"], name
        config = json.loads((ASSETS_DIR / "retrieval" / name / "config.json").read_text())
        assert config["kind"] == pin["kind"]
        RetrievalPerception.load(ASSETS_DIR / "retrieval" / name)
    assert DEFAULT_HEAD.name == pins["default"] == "instances"
    assert pins["heads"]["instances"]["kind"] == "instances"


def test_through_the_active_stereo_sensor_the_default_head_is_the_one_trained_through_it():
    from scenegen.perception.retrieval import default_head
    from scenegen.perception.retrieval.perceive import RetrievalPerception

    assert default_head() == default_head("structured_light") == DEFAULT_HEAD
    head = RetrievalPerception.load(default_head("active_stereo"))
    config = json.loads((default_head("active_stereo") / "config.json").read_text())
    assert config["depth_rule"]["learned"] is True and config["separator"]["training"]["steps"] == 12000
    assert head is not None
