"""Shared fixtures: one small demo batch, generated once per test session through the real CLI."""

from __future__ import annotations

import os
from pathlib import Path

# Off-screen rendering through EGL; this must be set before any test module imports mujoco.
os.environ.setdefault("MUJOCO_GL", "egl")

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--full", action="store_true", help="also run the full-size regenerations (-m full)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--full"):
        return
    skip = pytest.mark.skip(reason="full-size regeneration: run with pytest --full (make test-full)")
    for item in items:
        if "full" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def demo_batch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A stored batch of 6 accepted scenes of pipelines/procedural.yaml (the demo request with the
    procedural proposer), seed 0 (real MuJoCo, ~10 s)."""
    from scenegen.cli import main

    out = tmp_path_factory.mktemp("demo_batch") / "batch"
    pipeline = PROJECT_ROOT / "pipelines" / "procedural.yaml"
    code = main(["generate", str(pipeline), "--n", "6", "--seed", "0", "--out", str(out), "--quiet"])
    assert code == 0, f"scenegen generate exited {code}"
    return out
