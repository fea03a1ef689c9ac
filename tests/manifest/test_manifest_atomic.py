"""A manifest is never half-written: a run killed at any point (SIGKILL) leaves the previous manifest
or the new one.

Two levels: the real `scenegen generate` killed at spread-out moments of a batch (before, during and
after the scenes, while the manifest's realism checks are computed and written), and a writer process
killed while it rewrites a large manifest as fast as it can, alternating two versions.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from scenegen.audit.manifest import audit
from scenegen.manifest import read_manifest
from scenegen.paths import PROJECT_ROOT

RECIPE = PROJECT_ROOT / "pipelines" / "procedural.yaml"


def start(cmd: list[str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)


def kill_after(process: subprocess.Popen, seconds: float) -> bool:
    """SIGKILL the process group after ``seconds``; whether it was still running. A run that ended
    on its own must have succeeded (a killed run must never leave a folder the next one refuses)."""
    try:
        process.wait(timeout=seconds)
        assert process.returncode == 0, process.stderr.read().decode()[-2000:]
        return False
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        return True


@pytest.mark.slow
def test_a_killed_generate_leaves_no_manifest_or_a_whole_one(tmp_path: Path):
    out = tmp_path / "batch"
    cmd = [sys.executable, "-m", "scenegen.cli", "generate", str(RECIPE), "--n", "4", "--seed", "2"]
    cmd += ["--out", str(out), "--no-render", "--quiet"]
    seen: set[bytes] = set()
    killed = 0
    for delay in (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0, 7.0):
        killed += kill_after(start(cmd), delay)
        manifest = out / "manifest.yaml"
        if manifest.exists():
            read_manifest(manifest)  # a whole, valid manifest (raises otherwise)
            seen.add(manifest.read_bytes())
    assert killed >= 3, "the runs ended before they could be killed: raise the delays"
    assert subprocess.run(cmd, capture_output=True, timeout=300).returncode == 0
    final = (out / "manifest.yaml").read_bytes()
    assert seen <= {final}, "a killed run left a manifest other than the one the batch ends with"
    assert not [p.name for p in out.iterdir() if ".tmp" in p.name]
    report = audit(out / "manifest.yaml")
    assert report.ok, report.to_text()


WRITER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from scenegen.manifest import read_manifest, write_manifest

    path, a, b = (Path(p) for p in sys.argv[1:])
    versions = [read_manifest(a), read_manifest(b)]
    i = 0
    while True:
        write_manifest(path, versions[i % 2])
        i += 1
    """
)


def test_a_writer_killed_midway_leaves_one_version_or_the_other(tmp_path: Path):
    from scenegen.data.project_manifest import project_manifest
    from scenegen.manifest import dump_manifest

    base = project_manifest()
    # two versions of different sizes: one with a long datasheet, so a torn write would show
    long = base.model_copy(
        update={"datasheet": base.datasheet.model_copy(update={"intended_use": "x " * 200_000})}
    )
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    a.write_text(dump_manifest(base))
    b.write_text(dump_manifest(long))
    target = tmp_path / "data_manifest.yaml"
    target.write_bytes(a.read_bytes())
    allowed = {a.read_bytes(), b.read_bytes()}
    env = {**os.environ, "PYTHONPATH": str(PROJECT_ROOT)}
    for delay in (1.5, 1.7, 1.9, 2.1, 2.3, 2.6):
        writer = subprocess.Popen(
            [sys.executable, "-c", WRITER, str(target), str(a), str(b)], env=env, start_new_session=True
        )
        time.sleep(delay)
        assert writer.poll() is None, "the writer died on its own"
        os.killpg(writer.pid, signal.SIGKILL)
        writer.wait()
        assert target.read_bytes() in allowed
