"""Same recipe + same seed -> the same stored batch (bar wall-clock fields); another seed -> other scenes.

One run is in-process, the other in a fresh interpreter with a different PYTHONHASHSEED, so the
comparison also covers state cached inside a process and set/dict ordering.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from scenegen.cli import main

REPO_ROOT = Path(__file__).resolve().parents[2]
PIPELINE = REPO_ROOT / "pipelines" / "procedural.yaml"
N = 4
BYTE_EQUAL = ("index.jsonl", "rejections.jsonl", "manifest.yaml", "pipeline.yaml")


def generate_in_process(out: Path, seed: int, n: int = N) -> Path:
    code = main(["generate", str(PIPELINE), "--n", str(n), "--seed", str(seed), "--out", str(out), "--quiet"])
    assert code == 0
    return out


def generate_in_subprocess(out: Path, seed: int, n: int = N) -> Path:
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    cmd = [sys.executable, "-m", "scenegen.cli", "generate", str(PIPELINE), "--n", str(n)]
    cmd += ["--seed", str(seed), "--out", str(out), "--quiet"]
    result = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=out.parent, timeout=300)
    assert result.returncode == 0, result.stderr
    return out


def scene_ids(batch: Path) -> list[str]:
    return sorted(d.name for d in batch.iterdir() if d.is_dir() and d.name.startswith("scene_"))


def record(batch: Path, scene_id: str, drop: tuple[str, ...] = ()) -> dict:
    data = json.loads((batch / scene_id / "scene.json").read_text())
    for key in drop:
        data.pop(key)
    return data


@pytest.fixture(scope="module")
def twin_batches(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("determinism")
    return generate_in_process(root / "a", seed=0), generate_in_subprocess(root / "b", seed=0)


def test_same_seed_gives_identical_scenes(twin_batches):
    a, b = twin_batches
    ids = scene_ids(a)
    assert len(ids) == N
    assert scene_ids(b) == ids
    for scene_id in ids:
        # scene.json holds no wall-clock data, so the files are byte-identical.
        ja, jb = (a / scene_id / "scene.json").read_bytes(), (b / scene_id / "scene.json").read_bytes()
        assert ja == jb, f"{scene_id}: scene.json differs"
        assert (a / scene_id / "scene.xml").read_bytes() == (b / scene_id / "scene.xml").read_bytes(), (
            scene_id
        )


@pytest.mark.parametrize("name", BYTE_EQUAL)
def test_same_seed_gives_identical_logs(twin_batches, name: str):
    a, b = twin_batches
    assert (a / name).read_bytes() == (b / name).read_bytes(), f"{name} differs between identical runs"


def test_same_seed_gives_identical_assets(twin_batches):
    a, b = twin_batches
    assets_a = sorted(p.name for p in (a / "_assets").iterdir())
    assert assets_a == sorted(p.name for p in (b / "_assets").iterdir())
    for name in assets_a:
        assert (a / "_assets" / name).read_bytes() == (b / "_assets" / name).read_bytes(), name


def test_smaller_batch_is_a_prefix_of_a_larger_one(twin_batches, demo_batch: Path):
    """n=4 and n=6 with the same seed: the first 4 scenes and rejections before them are the same."""
    small, _ = twin_batches
    ids = scene_ids(small)
    assert scene_ids(demo_batch)[: len(ids)] == ids
    drop = ("provenance",)  # the recipe hash includes n
    for scene_id in ids:
        assert record(small, scene_id, drop) == record(demo_batch, scene_id, drop), scene_id
        xml_small = (small / scene_id / "scene.xml").read_bytes()
        assert xml_small == (demo_batch / scene_id / "scene.xml").read_bytes(), scene_id
    small_rejections = (small / "rejections.jsonl").read_text().splitlines()
    last = int(ids[-1].removeprefix("scene_"))
    big_rejections = [
        line
        for line in (demo_batch / "rejections.jsonl").read_text().splitlines()
        if json.loads(line)["proposal_index"] < last
    ]
    assert small_rejections == big_rejections


def test_different_seed_gives_different_scenes(twin_batches, tmp_path: Path):
    a, _ = twin_batches
    other = generate_in_process(tmp_path / "other", seed=1, n=2)
    assert (a / "index.jsonl").read_bytes() != (other / "index.jsonl").read_bytes()

    def layouts(batch: Path) -> set[str]:
        return {
            json.dumps([(o["asset"], o["position"]) for o in record(batch, s)["objects"]])
            for s in scene_ids(batch)
        }

    assert not layouts(a) & layouts(other), "a scene of seed 0 reappears with seed 1"
    for scene_id in set(scene_ids(a)) & set(scene_ids(other)):
        ra, ro = record(a, scene_id), record(other, scene_id)
        assert ra["objects"] != ro["objects"] and ra["lighting"] != ro["lighting"], scene_id
