"""The pool worker's entry point, :func:`scenegen.runner.process.work`."""

from __future__ import annotations

from pathlib import Path

import pytest

from scenegen.assets.catalog import load_catalog
from scenegen.propose.base import PROPOSERS
from scenegen.runner import process
from scenegen.runner.config import load_pipeline

PROJECT = Path(__file__).resolve().parents[2]


def test_a_stage_raising_stopiteration_fails_naming_the_proposal(monkeypatch: pytest.MonkeyPatch):
    """Inside the pool's map() a StopIteration would end the batch silently, as if out of proposals:
    work() turns it into an error that names the proposal (it once named a field that does not exist)."""
    config = load_pipeline(PROJECT / "pipelines" / "procedural.yaml", {"render": False})
    catalog = load_catalog()
    proposal = next(
        iter(PROPOSERS[config.proposer.kind](config.proposer, catalog).propose(config.condition, [7], 0))
    )

    def stage_runs_dry(*_):
        raise StopIteration

    monkeypatch.setattr(process, "_WORKER", (config, catalog, True))
    monkeypatch.setattr(process, "process_proposal", stage_runs_dry)
    with pytest.raises(RuntimeError, match="proposal 7: StopIteration in a stage"):
        process.work(proposal)
