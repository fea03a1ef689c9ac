"""Workers and resume: a batch is the same bytes whatever the number of workers and wherever it was killed.

Every batch here is made by the real command line in a fresh process (``python -m scenegen.cli
generate``), with the demo recipe's cameras shrunk to 160x120 to keep rendering cheap. A killed
batch is killed the hard way, SIGKILL to the whole process group (coordinator and pool workers), at
several points, then resumed by running the same command again; the result must equal an
uninterrupted run byte for byte (timings.json aside, which holds wall-clock times).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from processes import group_members
from scenes import small_recipe

from scenegen.cli import main

N = 6
SEED = 1  # a seed whose first proposals include rejections
NOT_COMPARED = {"timings.json"}  # wall-clock times
USAGE_ERROR = 2
PREFIX = "scenegen: error: "


# ---------------------------------------------------------------- helpers


def generate_cmd(recipe: Path, out: Path, workers: int, n: int = N, seed: int = SEED) -> list[str]:
    return [
        sys.executable,
        "-m",
        "scenegen.cli",
        "generate",
        str(recipe),
        "--n",
        str(n),
        "--seed",
        str(seed),
        "--out",
        str(out),
        "--workers",
        str(workers),
        "--quiet",
    ]


def run_to_completion(cmd: list[str]) -> subprocess.CompletedProcess:
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f"{' '.join(cmd)} exited {result.returncode}:\n{result.stderr}"
    assert "Traceback" not in result.stderr, result.stderr
    return result


def snapshot(batch: Path) -> dict[str, str]:
    """sha256 of every file under the batch (relative path -> digest), timings.json aside."""
    return {
        str(p.relative_to(batch)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(batch.rglob("*"))
        if p.is_file() and p.name not in NOT_COMPARED
    }


def tree(batch: Path) -> list[str]:
    """Every path under the batch, directories included."""
    return sorted(str(p.relative_to(batch)) + ("/" if p.is_dir() else "") for p in batch.rglob("*"))


def leftovers(batch: Path) -> list[str]:
    return [p for p in tree(batch) if ".tmp" in Path(p).name]


def read_rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def assert_same_batch(got: Path, expected: Path) -> None:
    """Same files with the same bytes (timings.json aside), nothing else, no duplicate rows."""
    assert not leftovers(got), f"temporary files left: {leftovers(got)}"
    scenes = sorted(p.name for p in got.iterdir() if p.name.startswith("scene_"))
    assert scenes == sorted(p.name for p in expected.iterdir() if p.name.startswith("scene_"))
    assert len(scenes) == N
    for log in ("index.jsonl", "rejections.jsonl"):
        indices = [row["proposal_index"] for row in read_rows(got / log)]
        assert len(indices) == len(set(indices)), f"{log}: duplicate rows {indices}"
    assert tree(got) == tree(expected), (
        f"only in {got.name}: {sorted(set(tree(got)) - set(tree(expected)))}; "
        f"only in {expected.name}: {sorted(set(tree(expected)) - set(tree(got)))}"
    )
    a, b = snapshot(got), snapshot(expected)
    differ = sorted(k for k in a if a[k] != b.get(k))
    assert not differ, f"files differ from the uninterrupted run: {differ}"


def count_rows(path: Path) -> int:
    try:
        return path.read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def start_and_kill(cmd: list[str], ready, timeout: float = 180.0) -> dict:
    """Start ``cmd`` in its own process group, SIGKILL the whole group once ``ready()`` holds.

    Returns where the kill landed; fails if the group is not entirely dead afterwards.
    """
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    pgid = proc.pid
    deadline = time.monotonic() + timeout
    try:
        while not ready() and proc.poll() is None:
            assert time.monotonic() < deadline, "kill point never reached"
            time.sleep(0.01)
        finished_first = proc.poll() is not None
        os.killpg(pgid, signal.SIGKILL)
    except ProcessLookupError:
        finished_first = True
    finally:
        if proc.poll() is None:
            try:
                os.killpg(pgid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    proc.wait(timeout=30)
    if not finished_first and proc.returncode == 0:
        # it ended on its own between the last poll and the kill (the command exits at once once its
        # batch is written: cli.entry): the kill found a finished process
        finished_first = True
    if not finished_first:
        assert proc.returncode == -signal.SIGKILL, proc.returncode
    deadline = time.monotonic() + 15
    while group_members(pgid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not group_members(pgid), f"processes of the killed group still alive: {group_members(pgid)}"
    return {"finished_before_kill": finished_first}


# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def recipe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # Crowded enough that some proposals are rejected.
    return small_recipe(tmp_path_factory.mktemp("recipe") / "small.yaml", n_objects=[5, 8])


@pytest.fixture(scope="module")
def reference(recipe: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The uninterrupted batch: N scenes, 2 workers."""
    out = tmp_path_factory.mktemp("reference") / "batch"
    run_to_completion(generate_cmd(recipe, out, workers=2))
    return out


@pytest.fixture(scope="module")
def single_worker(recipe: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("single") / "batch"
    run_to_completion(generate_cmd(recipe, out, workers=1))
    return out


# ---------------------------------------------------------------- workers


def test_reference_batch_is_complete(reference: Path):
    rows = read_rows(reference / "index.jsonl")
    assert len(rows) == N
    rejected = read_rows(reference / "rejections.jsonl")
    assert rejected, "the recipe should reject some proposals, or resume points are not all covered"
    for row in rows:
        scene = reference / row["scene_id"]
        names = sorted(p.name for p in scene.iterdir())
        images = sorted(f"{c}_{k}.png" for c in ("front", "side") for k in ("rgb", "depth", "seg"))
        assert names == sorted([*images, "scene.json", "scene.xml"]), names
    timings = json.loads((reference / "timings.json").read_text())
    assert timings["workers"] == 2


def test_one_and_two_workers_give_identical_batches(reference: Path, single_worker: Path):
    assert json.loads((single_worker / "timings.json").read_text())["workers"] == 1
    assert_same_batch(single_worker, reference)


def test_recycled_workers_give_the_same_bytes(recipe: Path, reference: Path, tmp_path: Path):
    """--recycle-after 2: each pool worker is replaced by a fresh process after two proposals (its
    memory returned, catalog and GL context made again); the batch is the same, byte for byte."""
    out = tmp_path / "batch"
    run_to_completion([*generate_cmd(recipe, out, workers=2), "--recycle-after", "2"])
    assert_same_batch(out, reference)


def test_recycling_is_refused_for_ray_and_for_zero(tmp_path: Path, capsys: pytest.CaptureFixture):
    recipe = small_recipe(tmp_path / "small.yaml")
    args = ["generate", str(recipe), "--out", str(tmp_path / "out"), "--quiet"]
    for extra in (["--recycle-after", "0"], ["--recycle-after", "5", "--backend", "ray"]):
        assert main([*args, *extra]) == USAGE_ERROR
        err = capsys.readouterr().err
        assert err.startswith(PREFIX) and "--recycle-after" in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- SIGKILL and resume


def test_sigkill_after_two_scenes_resumes_exactly(recipe: Path, reference: Path, tmp_path: Path):
    out = tmp_path / "batch"
    cmd = generate_cmd(recipe, out, workers=2)
    where = start_and_kill(cmd, lambda: count_rows(out / "index.jsonl") >= 2)
    assert not where["finished_before_kill"], "the batch finished before it could be killed"
    stored = count_rows(out / "index.jsonl")
    assert 2 <= stored <= N
    run_to_completion(cmd)
    assert_same_batch(out, reference)


def test_sigkill_right_after_start_resumes_exactly(recipe: Path, reference: Path, tmp_path: Path):
    out = tmp_path / "batch"
    cmd = generate_cmd(recipe, out, workers=2)
    where = start_and_kill(cmd, lambda: (out / "pipeline.yaml").exists())
    assert not where["finished_before_kill"]
    assert (out / "pipeline.yaml").is_file()
    assert count_rows(out / "index.jsonl") == 0, "killed right after start, yet scenes were stored"
    run_to_completion(cmd)
    assert_same_batch(out, reference)


@pytest.mark.slow
def test_repeated_sigkills_at_fixed_delays_resume_exactly(recipe: Path, reference: Path, tmp_path: Path):
    """Killed again and again at fixed delays after each start (points spread over start-up, the first
    rejections and the first commits on this machine), then run to completion."""
    out = tmp_path / "batch"
    cmd = generate_cmd(recipe, out, workers=2)
    landed = []
    for delay in (2.0, 4.2, 5.7, 6.9, 3.3):
        start = time.monotonic()
        where = start_and_kill(cmd, lambda d=delay, s=start: time.monotonic() - s >= d)
        landed.append((delay, count_rows(out / "index.jsonl"), count_rows(out / "rejections.jsonl"), where))
    assert any(not w["finished_before_kill"] for *_, w in landed), landed
    run_to_completion(cmd)
    assert_same_batch(out, reference)


# ---------------------------------------------------------------- resume from a damaged batch


def killed_copy(reference: Path, dst: Path, torn: str) -> Path:
    """A copy of the finished batch as a kill would have left it while writing a row of ``torn``.

    Rows from the cut on are gone, half of the next row of ``torn`` is at the end of that file
    without a newline; scene directories after the cut stay (renamed into place, never indexed);
    a stray temporary scene directory and temporary files lie around; manifest.yaml is stale.
    """
    shutil.copytree(reference, dst)
    index = (dst / "index.jsonl").read_text().splitlines(keepends=True)
    rejections = (dst / "rejections.jsonl").read_text().splitlines(keepends=True)
    rows = sorted(
        [(json.loads(line)["proposal_index"], "index.jsonl", line) for line in index]
        + [(json.loads(line)["proposal_index"], "rejections.jsonl", line) for line in rejections]
    )
    first_scene = min(p for p, name, _ in rows if name == "index.jsonl")
    # The cut: the 4th scene for a torn index row, the first rejection after a scene otherwise.
    if torn == "index.jsonl":
        cut = [p for p, name, _ in rows if name == "index.jsonl"][3]
    else:
        cut = min(p for p, name, _ in rows if name == torn and p > first_scene)
    for name in ("index.jsonl", "rejections.jsonl"):
        kept = "".join(line for p, n, line in rows if n == name and p < cut)
        torn_row = next(line for p, n, line in rows if n == name and p == cut) if name == torn else ""
        (dst / name).write_text(kept + torn_row[: len(torn_row) // 2])
    assert not (dst / torn).read_text().endswith("\n")
    stray = dst / ".tmp_scene_000099"
    stray.mkdir()
    (stray / "scene.json").write_text('{"half": ')
    (dst / ".index.jsonl.tmp4242").write_text("partial")
    asset = next((dst / "_assets").iterdir())
    (dst / "_assets" / f".{asset.name}.tmp").write_bytes(asset.read_bytes()[:100])
    (dst / "manifest.yaml").write_text("stale: true\n")
    unindexed = [
        p.name
        for p in dst.iterdir()
        if p.name.startswith("scene_") and int(p.name.removeprefix("scene_")) >= cut
    ]
    assert unindexed, "the cut should leave scene directories without index rows"
    return dst


@pytest.mark.parametrize("torn", ["index.jsonl", "rejections.jsonl"])
def test_rerun_cleans_up_a_torn_batch_and_completes_it(
    recipe: Path, reference: Path, tmp_path: Path, torn: str
):
    out = killed_copy(reference, tmp_path / "batch", torn)
    run_to_completion(generate_cmd(recipe, out, workers=1))
    assert_same_batch(out, reference)


# ---------------------------------------------------------------- refusing another recipe


@pytest.mark.parametrize(
    "change",
    [["--seed", "2"], ["--n", "5"], ["--no-render"]],
    ids=["other_seed", "other_n", "no_render"],
)
def test_rerun_with_other_settings_is_refused(
    recipe: Path,
    reference: Path,
    tmp_path: Path,
    change: list[str],
    capfd: pytest.CaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
):
    monkeypatch.setenv("MUJOCO_GL", os.environ.get("MUJOCO_GL", "egl"))  # undo any change main makes
    out = tmp_path / "batch"
    shutil.copytree(reference, out)
    before = {**snapshot(out), "timings.json": (out / "timings.json").read_text()}
    mtimes = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    args = generate_cmd(recipe, out, workers=1)[3:]
    flag, *value = change
    if value:
        args[args.index(flag) + 1] = value[0]
    else:
        args.append(flag)
    code = main(args)
    captured = capfd.readouterr()
    assert code == USAGE_ERROR, (code, captured.err)
    lines = captured.err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got:\n{captured.err}"
    assert lines[0].startswith(PREFIX) and "--out" in lines[0] and str(out) in lines[0], lines[0]
    assert captured.out == ""
    assert {**snapshot(out), "timings.json": (out / "timings.json").read_text()} == before
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == mtimes, "the batch was touched"


# ---------------------------------------------------------------- the Ray backend


def test_ray_backend_gives_the_local_pools_bytes(recipe: Path, reference: Path, tmp_path: Path):
    """--backend ray (a local Ray cluster, 2 actors of 1 CPU) writes the local pool's batch byte for byte."""
    pytest.importorskip("ray")  # the `ray` extra: CI installs it (make setup)
    out = tmp_path / "batch"
    run_to_completion([*generate_cmd(recipe, out, workers=2), "--backend", "ray"])
    timings = json.loads((out / "timings.json").read_text())
    assert (timings["backend"], timings["workers"]) == ("ray", 2)
    assert_same_batch(out, reference)


def test_sigkill_of_a_ray_batch_resumes_exactly(recipe: Path, reference: Path, tmp_path: Path):
    pytest.importorskip("ray")
    out = tmp_path / "batch"
    cmd = [*generate_cmd(recipe, out, workers=2), "--backend", "ray"]
    where = start_and_kill(cmd, lambda: count_rows(out / "index.jsonl") >= 2)
    assert not where["finished_before_kill"], "the batch finished before it could be killed"
    run_to_completion(cmd)
    assert_same_batch(out, reference)
    assert json.loads((out / "timings.json").read_text())["backend"] == "ray"


def test_backend_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture):
    recipe = small_recipe(tmp_path / "small.yaml")
    args = ["generate", str(recipe), "--out", str(tmp_path / "out"), "--quiet"]
    assert main([*args, "--address", "auto"]) == USAGE_ERROR
    err = capsys.readouterr().err
    assert err.startswith(PREFIX) and "--backend ray" in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_ray_backend_without_ray_says_how_to_install_it(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` meets where it is not installed
    recipe = small_recipe(tmp_path / "small.yaml")
    code = main(["generate", str(recipe), "--out", str(tmp_path / "out"), "--backend", "ray", "--quiet"])
    err = capsys.readouterr().err
    assert code == USAGE_ERROR and err.count("\n") == 1, err
    assert "pip install 'scenegen[ray]'" in err
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- no orphans


def children_of(pid: int) -> dict[int, str]:
    """Live (not zombie) child processes of ``pid``: pid -> command line."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
            cmdline = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        fields = text[text.rfind(")") + 2 :].split()
        if int(fields[1]) == pid and fields[0] not in ("Z", "X"):
            found[int(stat.parent.name)] = cmdline
    return found


def alive(pid: int) -> bool:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return text[text.rfind(")") + 2 :].split()[0] not in ("Z", "X")


def test_no_pool_worker_outlives_a_killed_coordinator(recipe: Path, tmp_path: Path):
    """SIGKILL of the coordinator alone (not its process group): its spawn workers die with it
    (PR_SET_PDEATHSIG), and so does multiprocessing's resource tracker (its pipe closes)."""
    out = tmp_path / "batch"
    proc = subprocess.Popen(
        generate_cmd(recipe, out, workers=2), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + 120
    workers: dict[int, str] = {}
    while len(workers) < 2 and time.monotonic() < deadline and proc.poll() is None:
        workers = {p: c for p, c in children_of(proc.pid).items() if "spawn_main" in c}
        time.sleep(0.05)
    assert len(workers) == 2, f"the pool did not start: {children_of(proc.pid)}"
    everyone = children_of(proc.pid)
    left = kill_and_wait(proc, everyone, 10)
    assert not left, f"processes of the killed coordinator still alive after 10 s: {left}"


def kill_and_wait(proc: subprocess.Popen, others: dict[int, str], seconds: float) -> dict[int, str]:
    """SIGKILL ``proc`` alone, wait up to ``seconds`` for ``others`` to end; those still alive
    (then killed, so as not to leak into the rest of the run)."""
    proc.kill()
    proc.wait(timeout=30)
    deadline = time.monotonic() + seconds
    while any(alive(p) for p in others) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = {p: others[p] for p in others if alive(p)}
    for p in left:
        os.kill(p, signal.SIGKILL)
    return left


def descendants_of(pid: int) -> dict[int, str]:
    found, frontier = {}, {pid}
    while frontier:
        layer = {}
        for parent in frontier:
            layer.update(children_of(parent))
        frontier = set(layer) - set(found)
        found.update(layer)
    return found


def test_no_ray_actor_outlives_a_killed_coordinator(recipe: Path, tmp_path: Path):
    """SIGKILL of a `--backend ray` coordinator: the actors, the raylet and GCS of the local cluster
    it started exit within seconds (measured: under 5 s); Ray's per-node agents (DashboardAgent,
    RuntimeEnvAgent) exit once their raylet health check gives up (measured: ~65 s)."""
    pytest.importorskip("ray")
    out = tmp_path / "batch"
    cmd = [*generate_cmd(recipe, out, workers=2), "--backend", "ray"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 180
    while count_rows(out / "index.jsonl") < 1 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    everyone = descendants_of(proc.pid)
    assert sum("RayWorker" in c for c in everyone.values()) == 2, everyone
    agents = {p: c for p, c in everyone.items() if "Agent" in c}
    others = {p: c for p, c in everyone.items() if p not in agents}
    left = kill_and_wait(proc, others, 30)
    assert not left, f"actors or cluster processes still alive 30 s after their coordinator: {left}"
    deadline = time.monotonic() + 150
    while any(alive(p) for p in agents) and time.monotonic() < deadline:
        time.sleep(0.5)
    left = {p: agents[p] for p in agents if alive(p)}
    for p in left:
        os.kill(p, signal.SIGKILL)
    assert not left, f"Ray's agents still alive 150 s after their raylet: {left}"


def test_an_unreachable_ray_cluster_is_a_one_line_error_before_any_file(
    tmp_path: Path, capsys: pytest.CaptureFixture
):
    pytest.importorskip("ray")
    recipe = small_recipe(tmp_path / "small.yaml")
    args = ["generate", str(recipe), "--out", str(tmp_path / "out"), "--backend", "ray", "--quiet"]
    assert main([*args, "--address", "127.0.0.1:9"]) == USAGE_ERROR  # the discard port: nothing listens
    err = capsys.readouterr().err
    assert err.startswith(PREFIX) and "127.0.0.1:9" in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()
