"""A batch through a depth sensor (recipe ``sensor:``, ``generate --sensor``): each camera's sensor
depth stored beside the exact one and listed in scene.json, its checksums and the manifest; the same
bytes from one worker, two, and a run killed and resumed; the audit passes it and names a scene whose
sensor disagrees with the manifest; the contact sheet shows it; and a sensor without rendering is
refused with the field named."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from scenes import small_recipe

from scenegen.cli import main

N = 2
SENSOR = "active_stereo"


def _cmd(recipe: Path, out: Path, workers: int) -> list[str]:
    return [sys.executable, "-m", "scenegen.cli", "generate", str(recipe), "--n", str(N), "--seed", "1",
            "--sensor", SENSOR, "--out", str(out), "--workers", str(workers), "--quiet"]  # fmt: skip


def _run(cmd: list[str]) -> None:
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr


def _snapshot(batch: Path) -> dict[str, str]:
    return {
        str(p.relative_to(batch)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(batch.rglob("*"))
        if p.is_file() and p.name != "timings.json"
    }


@pytest.fixture(scope="module")
def recipe(tmp_path_factory) -> Path:
    return small_recipe(tmp_path_factory.mktemp("recipe") / "small.yaml", (320, 240))


@pytest.fixture(scope="module")
def batch(recipe: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sensor") / "batch"
    _run(_cmd(recipe, out, workers=2))
    return out


def test_each_camera_stores_the_sensors_depth_beside_the_exact_one(batch: Path):
    from scenegen.render.sensor import SENSORS

    manifest = (batch / "manifest.yaml").read_text()
    assert f"name: {SENSOR}" in manifest
    scenes = sorted(batch.glob("scene_*"))
    assert len(scenes) == N
    for scene in scenes:
        record = json.loads((scene / "scene.json").read_text())
        assert record["render"]["sensor"] == {"name": SENSOR, "version": SENSORS[SENSOR].key()}
        for cam in record["cameras"]:
            name = cam["images"]["sensor_depth"]
            assert name == f"{cam['name']}_depth_{SENSOR}.png"
            data = (scene / name).read_bytes()
            assert record["files"][name] == hashlib.sha256(data).hexdigest()
            sensed = cv2.imread(str(scene / name), cv2.IMREAD_UNCHANGED)
            exact = cv2.imread(str(scene / cam["images"]["depth"]), cv2.IMREAD_UNCHANGED)
            assert sensed.dtype == np.uint16 and sensed.shape == exact.shape
            both = (sensed > 0) & (exact > 0) & (exact < 2000)  # the table and what stands on it
            assert 0.5 < both.sum() / ((exact > 0) & (exact < 2000)).sum() < 1.0
            assert np.median(np.abs(sensed[both].astype(int) - exact[both])) <= 10  # mm


def test_one_worker_and_a_killed_then_resumed_run_give_the_same_bytes(
    recipe: Path, batch: Path, tmp_path: Path
):
    single = tmp_path / "single"
    assert main(_cmd(recipe, single, workers=1)[3:]) == 0
    assert _snapshot(single) == _snapshot(batch)

    resumed = tmp_path / "resumed"
    cmd = _cmd(recipe, resumed, workers=2)
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    index = resumed / "index.jsonl"
    while proc.poll() is None and not (index.exists() and index.read_bytes().count(b"\n") >= 1):
        assert time.monotonic() < deadline, "the first scene never came"
        time.sleep(0.01)
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    _run(cmd)
    assert _snapshot(resumed) == _snapshot(batch)


def test_the_audit_passes_it_and_names_a_scene_of_another_sensor(batch: Path, tmp_path: Path, capsys):
    import shutil

    assert main(["audit", str(batch / "manifest.yaml")]) == 0
    capsys.readouterr()
    copy = tmp_path / "batch"
    shutil.copytree(batch, copy)
    scene = sorted(copy.glob("scene_*"))[0]
    record = json.loads((scene / "scene.json").read_text())
    record["render"]["sensor"]["name"] = "structured_light"
    text = json.dumps(record, indent=1) + "\n"
    (scene / "scene.json").write_text(text)
    assert main(["audit", str(copy / "manifest.yaml")]) == 1
    out = capsys.readouterr().out
    assert f"{scene.name}/scene.json" in out and "render.sensor: structured_light" in out


def test_the_contact_sheet_shows_the_sensors_depth(batch: Path, tmp_path: Path):
    plain, both = tmp_path / "plain.png", tmp_path / "depth.png"
    assert main(["show", str(batch), "--out", str(plain)]) == 0
    assert main(["show", str(batch), "--depth", "--out", str(both)]) == 0
    # colour + exact depth + the sensor's depth: three thumbnails a tile instead of one
    assert cv2.imread(str(both)).shape[1] == 3 * cv2.imread(str(plain)).shape[1]


def test_a_sensor_needs_rendering(recipe: Path, tmp_path: Path, capsys):
    import yaml

    broken = tmp_path / "broken.yaml"
    broken.write_text(
        yaml.safe_dump({**yaml.safe_load(recipe.read_text()), "render": False, "sensor": SENSOR})
    )
    assert main(["generate", str(broken), "--out", str(tmp_path / "never"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "sensor" in err and "render" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "never").exists()
    # --no-render turns the sensor off with it
    assert main(["generate", str(recipe), "--n", "1", "--sensor", SENSOR, "--no-render", "--out",
                 str(tmp_path / "plain"), "--quiet"]) == 0  # fmt: skip
