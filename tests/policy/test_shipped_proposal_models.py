"""The committed proposal models are the bytes their pins name (assets/proposals/models.json: the
sha256 of each whole folder), and every one loads as a model of this code's version."""

from __future__ import annotations

import json

from scenegen.core.files import folder_sha256
from scenegen.paths import ASSETS_DIR
from scenegen.policy.proposal_model import MODEL_VERSION, ProposalModel


def test_every_committed_proposal_model_is_pinned_by_its_folder_and_loads():
    root = ASSETS_DIR / "proposals"
    pins = json.loads((root / "models.json").read_text())
    assert set(pins["models"]) == {p.name for p in root.iterdir() if p.is_dir()}
    for name, pin in pins["models"].items():
        assert folder_sha256(root / name) == pin["sha256"], name
        assert pin["version"] == MODEL_VERSION
        ProposalModel.load(root / name)
