"""Kill anywhere: SIGKILL each long-running command at random moments, then rerun it.

For every command (generate with 2 workers, reference, label, proposals label, export, audit, and the transfer
experiment's tiny configuration) an uninterrupted run gives the expected output, and a second one
(warm: per-machine caches filled) its wall time T;
then, at each of POINTS moments drawn uniformly from (0, T) (seeded by the command's name), a fresh run
is started, its coordinator SIGKILLed, and it is checked that:

- no process of the run is left after 15 s (the workers die with their coordinator);
- every file the killed run left visible is whole (temporary files are dot- or .tmp-named);
- a rerun of the same command completes, equals the uninterrupted output (bytes, wall-clock timings
  aside), and leaves no temporary file behind; no row is lost or duplicated.

CI runs POINTS = 2 per command (SCENEGEN_KILL_POINTS) and none for the transfer experiment;
``make kill`` runs 20 per command and 5 for the transfer experiment (SCENEGEN_KILL_TRANSFER_POINTS),
and writes the table to runs/kill/report.json.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pyarrow.parquet as pq
import pytest
import yaml
from processes import group_members
from scenes import project_with, small_recipe

from scenegen.paths import PROJECT_ROOT

POINTS = int(os.environ.get("SCENEGEN_KILL_POINTS", "2"))
TRANSFER_POINTS = int(os.environ.get("SCENEGEN_KILL_TRANSFER_POINTS", "0"))
NOT_COMPARED = {"timings.json"}  # wall-clock times
REPORT: dict[str, dict] = {}  # command -> its row of the table (tests/kill/conftest.py prints it)


def scenegen(*args) -> list[str]:
    return [sys.executable, "-m", "scenegen.cli", *map(str, args)]


# the commands render through EGL (an in-process `main` of a GL-free command sets MUJOCO_GL=disable)
ENV = {**os.environ, "MUJOCO_GL": "egl"}


def files_of(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` (relative path -> digest); wall-clock files aside."""
    if root.is_file():
        return {root.name: hashlib.sha256(root.read_bytes()).hexdigest()}
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name not in NOT_COMPARED
    }


def temporary(root: Path) -> list[str]:
    """Temporary files and folders (dot-named or .tmp) anywhere under ``root``."""
    return sorted(
        p.relative_to(root).as_posix() for p in root.rglob("*") if p.name.startswith(".") or ".tmp" in p.name
    )


def _jsonl_whole(path: Path) -> list[str]:
    for number, line in enumerate(path.read_text().splitlines(), 1):
        try:
            if line.strip():
                json.loads(line)
        except ValueError:
            return [f"{path.name}: line {number} torn"]
    return []


def batch_whole(batch: Path) -> list[str]:
    """A (possibly killed) batch's visible files are whole: each scene folder's scene.json parses and
    lists files that exist with its digests; the logs' lines parse; no proposal is logged twice."""
    problems = []
    if not batch.exists():
        return problems
    for log in ("index.jsonl", "rejections.jsonl"):
        if (batch / log).exists():
            problems += _jsonl_whole(batch / log)
    rows = (
        [json.loads(line) for line in (batch / "index.jsonl").read_text().splitlines() if line.strip()]
        if (batch / "index.jsonl").exists()
        else []
    )
    indices = [row["proposal_index"] for row in rows]
    if len(indices) != len(set(indices)):
        problems.append("index.jsonl: a proposal logged twice")
    for scene in sorted(p for p in batch.glob("scene_*") if ".tmp" not in p.name):
        try:
            record = json.loads((scene / "scene.json").read_text())
        except (OSError, ValueError):
            problems.append(f"{scene.name}/scene.json: missing or torn")
            continue
        for name, digest in record["files"].items():
            path = scene / name
            if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != digest:
                problems.append(f"{scene.name}/{name}: missing or not the listed bytes")
    for name in ("manifest.yaml", "pipeline.yaml"):
        if (batch / name).exists():
            try:
                yaml.safe_load((batch / name).read_text())
            except yaml.YAMLError:
                problems.append(f"{name}: torn")
    return problems


def parquet_whole(path: Path) -> list[str]:
    problems = []
    if path.exists():
        try:
            pq.read_table(path)
        except Exception as exc:  # noqa: BLE001 - any unreadable table is a partial file
            problems.append(f"{path.name}: unreadable ({type(exc).__name__})")
    rows = path.with_name(path.name + ".rows.jsonl")
    if rows.exists():
        problems += _jsonl_whole(rows)
    return problems


def export_whole(out: Path) -> list[str]:
    """An export folder is absent or complete (export.json and the shards it lists, same digests)."""
    if not out.exists():
        return []
    try:
        description = json.loads((out / "export.json").read_text())
    except (OSError, ValueError):
        return ["export folder visible without a whole export.json"]
    return [
        f"{name}: not the listed bytes"
        for name, digest in description["shards"].items()
        if not (out / name).is_file() or hashlib.sha256((out / name).read_bytes()).hexdigest() != digest
    ]


def proposals_whole(folder: Path) -> list[str]:
    """The sequence store may end in a torn line (its reader cuts it off); every line before it and
    every proposed decision point's JSON must be whole."""
    problems = []
    store = folder / "paths.jsonl"
    if store.exists():
        lines = store.read_bytes().split(b"\n")[:-1]  # the part after the last newline may be torn
        for number, line in enumerate(lines, 1):
            try:
                json.loads(line)
            except ValueError:
                problems.append(f"paths.jsonl: line {number} torn")
    for path in sorted((folder / "views").glob("*.json")):
        try:
            json.loads(path.read_text())
        except ValueError:
            problems.append(f"views/{path.name} torn")
    return problems


@dataclass
class Case:
    """One command of the harness: its command line in a run folder, the output that a rerun must
    reproduce, and the check of what a killed run left visible."""

    argv: Callable[[Path], list[str]]
    output: Callable[[Path], Path]
    whole: Callable[[Path], list[str]]
    stdout: bool = False  # compare the rerun's stdout (audit) instead of files
    digest: Callable[[Path], dict] = files_of  # what of the output must be equal


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """The harness's inputs: a small recipe, a batch of it (also the uninterrupted output of the
    generate case is compared against its own run), and a project manifest holding a copy."""
    root = tmp_path_factory.mktemp("kill_inputs")
    recipe = small_recipe(root / "small.yaml", n_objects=[5, 8])
    batch = root / "batch"
    argv = scenegen("generate", recipe, "--n", 3, "--seed", 1, "--out", batch, "--quiet")
    result = subprocess.run(argv, capture_output=True, env=ENV)
    assert result.returncode == 0, result.stderr.decode()
    manifest = project_with(batch, root / "project")
    transfer = root / "transfer.yaml"
    return {"recipe": recipe, "batch": batch, "manifest": manifest, "transfer": transfer}


def cases(inputs: dict[str, Path]) -> dict[str, Case]:
    recipe, batch, manifest = inputs["recipe"], inputs["batch"], inputs["manifest"]
    return {
        "generate": Case(
            lambda run: scenegen(
                "generate", recipe, "--n", 4, "--seed", 1, "--out", run / "batch", "--workers", 2, "--quiet"
            ),
            lambda run: run / "batch",
            lambda run: batch_whole(run / "batch"),
        ),
        "reference": Case(
            lambda run: scenegen(
                "reference",
                PROJECT_ROOT / "pipelines" / "reference.yaml",
                "--n",
                10,
                "--seed",
                5,
                "--out",
                run / "reference.parquet",
                "--workers",
                2,
                "--quiet",
            ),
            lambda run: run / "reference.parquet",
            lambda run: parquet_whole(run / "reference.parquet"),
        ),
        "label": Case(
            lambda run: scenegen(
                "label",
                batch,
                "--out",
                run / "labels.parquet",
                "--primitives",
                "top_grasp",  # one primitive x 3 scenes: the slowest case, kept within the hour's budget
                "--workers",
                2,
                "--quiet",
            ),
            lambda run: run / "labels.parquet",
            lambda run: parquet_whole(run / "labels.parquet"),
        ),
        "proposals": Case(
            lambda run: scenegen(
                "proposals",
                "label",
                "--layouts",
                "validation",
                "--limit",
                1,
                "--sampler",
                2,
                0,
                0,
                0,
                "--out",
                run / "proposals",
                "--workers",
                2,
                "--quiet",
            ),
            lambda run: run / "proposals",
            lambda run: proposals_whole(run / "proposals"),
        ),
        "export": Case(
            lambda run: scenegen("export", batch, "--format", "webdataset", "--out", run / "wds"),
            lambda run: run / "wds",
            lambda run: export_whole(run / "wds"),
        ),
        "audit": Case(
            lambda run: scenegen("audit", manifest, "--json"),
            lambda run: manifest.parent,
            lambda run: (
                [] if files_of(manifest.parent) == inputs["project_files"] else ["the project changed"]
            ),
            stdout=True,
        ),
    }


def run_case(name: str, case: Case, base: Path, points: int) -> dict:
    """Two uninterrupted runs (the second, warm, gives the wall time T the kill moments are drawn
    from: a first run also fills per-machine caches and is slower), then ``points`` kill-and-rerun
    rounds; returns the table row."""
    start = time.perf_counter()
    outputs, walls = [], []
    for folder in ("uninterrupted", "warm"):
        (base / folder).mkdir(parents=True)
        began = time.perf_counter()
        done = subprocess.run(case.argv(base / folder), capture_output=True, timeout=900, env=ENV)
        walls.append(time.perf_counter() - began)
        assert done.returncode in (0, 1), f"{name}: {done.stderr.decode()[-2000:]}"
        outputs.append(done.stdout if case.stdout else case.digest(case.output(base / folder)))
    expected, wall = outputs[0], walls[1]
    problems: list[str] = [] if outputs[1] == expected else ["two uninterrupted runs differ"]
    rng = random.Random(f"kill-{name}")
    moments = sorted(rng.uniform(0.0, wall) for _ in range(points))
    row = {"points": points, "wall_s": round(wall, 1), "killed_running": 0, "finished_first": 0}
    for i, moment in enumerate(moments):
        run = base / f"point_{i:02d}"
        run.mkdir()
        proc = subprocess.Popen(
            case.argv(run),
            start_new_session=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=ENV,
        )
        time.sleep(moment)
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)  # the coordinator only: its workers must follow
            row["killed_running"] += 1
        else:
            row["finished_first"] += 1
        proc.wait(timeout=60)
        deadline = time.monotonic() + 15
        while group_members(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = group_members(proc.pid)
        if left:
            problems.append(f"point {i} ({moment:.1f} s): processes left: {left}")
            os.killpg(proc.pid, signal.SIGKILL)
        problems += [f"point {i} ({moment:.1f} s): {p}" for p in case.whole(run)]
        again = subprocess.run(case.argv(run), capture_output=True, timeout=900, env=ENV)
        if again.returncode != done.returncode:
            problems.append(f"point {i}: rerun exited {again.returncode}: {again.stderr.decode()[-300:]}")
            continue
        got = again.stdout if case.stdout else case.digest(case.output(run))
        if got != expected:
            differ = sorted(set(got.items()) ^ set(expected.items())) if isinstance(got, dict) else "stdout"
            problems.append(
                f"point {i} ({moment:.1f} s): rerun differs from the uninterrupted run: {differ}"[:400]
            )
        if temporary(run):
            problems.append(f"point {i}: temporary files left after the rerun: {temporary(run)[:3]}")
        if not problems:
            shutil.rmtree(run, ignore_errors=True)  # kept for a look when something is wrong
    row["problems"] = len(problems)
    row["seconds"] = round(time.perf_counter() - start, 1)
    REPORT[name] = row
    assert not problems, "\n".join(problems)
    return row


def _unmeasured(data):
    """``data`` without the CPU seconds a run measured (sources.json's generation costs)."""
    if isinstance(data, dict):
        return {k: _unmeasured(v) for k, v in data.items() if k not in ("cpu_s", "generation_cpu_s")}
    if isinstance(data, list):
        return [_unmeasured(v) for v in data]
    return data


@pytest.mark.slow
@pytest.mark.parametrize("name", ["generate", "reference", "label", "proposals", "export", "audit"])
def test_kill_anywhere_and_rerun(name: str, inputs: dict[str, Path], tmp_path: Path):
    inputs.setdefault("project_files", files_of(inputs["manifest"].parent))
    run_case(name, cases(inputs)[name], tmp_path, POINTS)


@pytest.mark.slow
@pytest.mark.skipif(TRANSFER_POINTS < 1, reason="the transfer experiment's kill points run in `make kill`")
def test_kill_the_tiny_transfer_experiment_anywhere(tmp_path: Path):
    from scenegen.data.project_manifest import DATASHEET, TRANSFER
    from scenegen.manifest import Manifest, write_manifest

    config = yaml.safe_load((PROJECT_ROOT / "tests" / "fixtures" / "transfer_tiny.yaml").read_text())

    def argv(run: Path) -> list[str]:
        if not (run / "data_manifest.yaml").exists():
            write_manifest(
                run / "data_manifest.yaml", Manifest(kind="project", datasheet=DATASHEET, transfer=TRANSFER)
            )
            paths = {k: str(run / k) for k in ("label_store", "path_store", "cache", "out")}
            paths |= {"label_store": str(run / "labels.parquet"), "path_store": str(run / "paths.jsonl")}
            (run / "tiny.yaml").write_text(
                yaml.safe_dump(config | paths | {"manifest": str(run / "data_manifest.yaml")})
            )
        return scenegen("experiment", "transfer", run / "tiny.yaml", "--quiet")

    def whole(run: Path) -> list[str]:
        out = run / "out"
        problems = [] if not (run / "labels.parquet").exists() else parquet_whole(run / "labels.parquet")
        for path in sorted(out.rglob("*.json*")) if out.exists() else []:
            if ".tmp" not in path.name:
                problems += _jsonl_whole(path) if path.suffix == ".jsonl" else []
        return problems

    def results(out: Path) -> dict:
        """What a rerun must reproduce: the episodes, sources and metrics (measured seconds aside)."""
        metrics = json.loads((out / "metrics.json").read_text())
        stable = {k: v for k, v in metrics.items() if k not in ("cost", "timings", "artifact_sha256")}
        sources = _unmeasured(json.loads((out / "sources.json").read_text()))
        kept = {k: v for k, v in files_of(out).items() if k.startswith("episodes/")}
        return kept | {
            "metrics": json.dumps(stable, sort_keys=True),
            "sources": json.dumps(sources, sort_keys=True),
        }

    case = Case(argv, lambda run: run / "out", whole, digest=results)
    run_case("experiment transfer (tiny)", case, tmp_path, TRANSFER_POINTS)
