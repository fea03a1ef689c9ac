"""What the benchmarks that compare this checkout with a baseline commit share (audit_scale.py,
pipeline_throughput.py, primitives.py, proposer_cpu.py): the commit's files, and a measurement run in
a fresh interpreter that imports scenegen from one tree or the other with this virtual environment.

A benchmark script calls :func:`run_child` with a spec; the child is the same script run with
``--child SPEC --child-out FILE`` from the chosen tree, which calls its own ``measure(spec)`` and writes
the JSON result (:func:`child_main`).
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def baseline_tree(ref: str, into: Path) -> Path:
    """The files of commit ``ref`` (git archive), extracted under ``into``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref], capture_output=True, check=True).stdout
    with tempfile.TemporaryFile() as f:
        f.write(archive)
        f.seek(0)
        with tarfile.open(fileobj=f) as tar:
            tar.extractall(into, filter="data")
    return into


def run_child(script: str, spec: dict, code: Path, timeout: int = 7200) -> tuple[dict, float, float]:
    """``measure(spec)`` of benchmark ``script`` (its ``__file__``) in a fresh interpreter importing
    scenegen from ``code`` (cwd ``code``): its result, and the wall seconds and CPU seconds (the child
    and its own children, ``RUSAGE_CHILDREN``) it took. A failed child ends the benchmark with its
    stderr's tail."""
    env = {**os.environ, "PYTHONPATH": str(code), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    began = time.perf_counter()
    with tempfile.NamedTemporaryFile(suffix=".json") as out:
        cmd = [
            sys.executable,
            str(Path(script).resolve()),
            "--child",
            json.dumps(spec),
            "--child-out",
            out.name,
        ]
        result = subprocess.run(cmd, cwd=code, env=env, capture_output=True, text=True, timeout=timeout)
        wall = time.perf_counter() - began
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if result.returncode != 0:
            raise SystemExit(f"{spec}: exited {result.returncode}\n{result.stderr[-3000:]}")
        found = json.loads(Path(out.name).read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return found, wall, cpu


def child_main(args, measure) -> bool:
    """In a child (``args.child`` set): ``measure`` of its spec, written to ``args.child_out``. Returns
    whether this process was a child (then the caller returns)."""
    if not getattr(args, "child", None):
        return False
    Path(args.child_out).write_text(json.dumps(measure(json.loads(args.child))))
    return True


def add_child_arguments(parser) -> None:
    """The hidden ``--child`` and ``--child-out`` options :func:`run_child` passes."""
    import argparse

    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--child-out", help=argparse.SUPPRESS)
