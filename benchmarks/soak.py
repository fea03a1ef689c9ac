"""Soak: does memory stay flat over a long batch?

    .venv/bin/python benchmarks/soak.py [--plain 3000] [--rendered 500] [--every 100] [--workers 2]
        [--pipeline pipelines/procedural.yaml] [--recycle-after N] [--json benchmarks/results/soak.json]

Runs `scenegen generate` twice as a user would (a subprocess, 2 pool workers): ``--plain`` scenes
without rendering, then ``--rendered`` scenes with rendering (two 640x480 cameras). Every ``--every``
accepted scenes (counted from index.jsonl) it samples the resident memory (VmRSS, /proc) of the
coordinator and of each worker. Reported per run: the table of samples, and the growth of each process
kind from the sample at 500 scenes (or the first sample, for a run shorter than that) to the last
(goal: under 5 %), and the fitted trend from 500 scenes on. ``--recycle-after N`` passes the same flag
to `scenegen generate` (each pool worker replaced by a fresh process after N proposals). Prints the
tables and saves JSON in benchmarks/results/soak.json. ``--recycle-cost N --plain 300 --json F``
instead measures what recycling costs (:func:`recycle_cost`).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WARM = 500  # growth is measured after this many scenes (start-up, caches and first allocations)


def _status(pid: int) -> tuple[int, int] | None:
    """(parent pid, resident kB) of a live process, or None."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    if fields.get("State", "").strip().startswith("Z"):
        return None
    return int(fields["PPid"]), int(fields.get("VmRSS", "0 kB").split()[0])


def resident(root: int) -> dict[str, float]:
    """MB resident: the coordinator ``root``, its pool workers together (and the largest one), and
    everything else under it (multiprocessing's resource tracker)."""
    status = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            found = _status(int(entry.name))
            if found:
                status[int(entry.name)] = found
    tree, frontier = [], {root}
    while frontier:
        frontier = {pid for pid, (ppid, _) in status.items() if ppid in frontier and pid not in tree}
        tree += sorted(frontier)
    workers, other = [], 0.0
    for pid in tree:
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if b"resource_tracker" in command:
            other += status[pid][1] / 1024
        else:
            workers.append(status[pid][1] / 1024)
    return {
        "coordinator": status.get(root, (0, 0))[1] / 1024,
        "workers": sum(workers),
        "largest worker": max(workers, default=0.0),
        "other": other,
    }


def accepted(batch: Path) -> int:
    try:
        return (batch / "index.jsonl").read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def soak(
    pipeline: Path,
    n: int,
    render: bool,
    every: int,
    workers: int,
    out: Path,
    recycle_after: int | None = None,
) -> dict:
    """One batch of ``n`` scenes, sampled every ``every`` accepted scenes."""
    cmd = [sys.executable, "-m", "scenegen.cli", "generate", str(pipeline), "--n", str(n), "--seed", "0"]
    cmd += ["--out", str(out), "--workers", str(workers), "--quiet", "--max-proposals", str(60 * n)]
    if recycle_after is not None:
        cmd += ["--recycle-after", str(recycle_after)]
    if not render:
        cmd.append("--no-render")
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    samples, next_at = [], every
    while proc.poll() is None:
        count = accepted(out)
        if count >= next_at:
            memory = resident(proc.pid)
            if not memory["workers"]:  # the batch is done and its pool already stopped
                next_at = float("inf")
                continue
            samples.append({"scenes": count, "wall_s": round(time.perf_counter() - start, 1), **memory})
            print(f"  {count} scenes: " + ", ".join(f"{k} {v:.0f} MB" for k, v in memory.items()), flush=True)
            next_at = (count // every + 1) * every
        time.sleep(0.2)
    if proc.returncode != 0:
        raise SystemExit(f"generate exited {proc.returncode}: {proc.stderr.read().decode()[-2000:]}")
    wall = time.perf_counter() - start
    return {
        "n": n,
        "render": render,
        "recycle_after": recycle_after,
        "wall_s": round(wall, 1),
        "samples": samples,
        "growth": growth(samples),
        "trend": trend(samples),
    }


def live(samples: list[dict]) -> list[dict]:
    """The samples taken while the pool ran (a sample after the batch's end finds no worker)."""
    return [s for s in samples if s.get("workers", 1) > 0]


def growth(samples: list[dict], window: int = 3) -> dict[str, float]:
    """Per column: the mean of the last ``window`` samples against the mean of the ``window`` samples
    from WARM scenes on (from the first sample when the run is shorter), in %. Means over a few samples,
    because a worker's memory moves by ~10 % from one scene to the next (each scene is its own model)."""
    samples = live(samples)
    if len(samples) < 2 * window:
        return {}
    first = next((i for i, s in enumerate(samples) if s["scenes"] >= WARM), 0)
    first = min(first, len(samples) - 2 * window)
    base, last = samples[first : first + window], samples[-window:]
    keys = [k for k in last[-1] if k not in ("scenes", "wall_s")]

    def mean(rows, key):
        return sum(r[key] for r in rows) / len(rows)

    out = {
        k: round(100 * (mean(last, k) - mean(base, k)) / mean(base, k), 1) for k in keys if mean(base, k) > 0
    }
    return out | {"from_scenes": base[0]["scenes"], "to_scenes": last[-1]["scenes"]}


def trend(samples: list[dict]) -> dict[str, dict]:
    """Per column: a least-squares line through the samples from WARM scenes on, its slope (MB per
    1,000 scenes, with a 95 % interval from the residuals, t with n - 2 degrees of freedom) and the
    growth it implies from the first such sample to the last, in % of the line's value at the first:
    the trend, which the jumps between adjacent samples (each scene is its own model) do not move much."""
    import numpy as np
    from scipy import stats

    rows = [r for r in live(samples) if r["scenes"] >= WARM]
    if len(rows) < 4:
        return {}
    x = np.array([r["scenes"] for r in rows], float)
    out = {}
    for key in (k for k in rows[-1] if k not in ("scenes", "wall_s")):
        y = np.array([r[key] for r in rows], float)
        if y.mean() <= 0:
            continue
        fit = stats.linregress(x, y)
        half = stats.t.ppf(0.975, len(x) - 2) * fit.stderr
        start = fit.intercept + fit.slope * x[0]
        out[key] = {
            "slope_mb_per_1000": round(1000 * fit.slope, 2),
            "slope_ci95": [round(1000 * (fit.slope - half), 2), round(1000 * (fit.slope + half), 2)],
            "fitted_growth_pct": round(100 * fit.slope * (x[-1] - x[0]) / start, 2),
            "from_scenes": int(x[0]),
            "to_scenes": int(x[-1]),
        }
    return out


def recycle_cost(pipeline: Path, n: int, recycle_after: int, workers: int, repeats: int) -> dict:
    """What recycling costs: the same ``n``-scene batch (no rendering) without recycling and with
    ``--recycle-after``, alternated ``repeats`` times; wall and CPU seconds (the process and its pool,
    RUSAGE_CHILDREN) of each, and the extra CPU per worker start (starts: proposals / N)."""
    import resource
    import statistics

    cmd = [sys.executable, "-m", "scenegen.cli", "generate", str(pipeline), "--n", str(n), "--seed", "0"]
    cmd += ["--workers", str(workers), "--quiet", "--no-render"]
    runs: dict[str, list[tuple[float, float]]] = {"kept": [], "recycled": []}
    proposals = 0
    with tempfile.TemporaryDirectory(prefix="recycle") as tmp:
        for repeat in range(repeats):
            for kind in ("kept", "recycled") if repeat % 2 == 0 else ("recycled", "kept"):
                out = Path(tmp) / f"{kind}_{repeat}"
                extra = ["--recycle-after", str(recycle_after)] if kind == "recycled" else []
                before, began = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
                subprocess.run([*cmd, "--out", str(out), *extra], check=True, capture_output=True)
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
                runs[kind].append((time.perf_counter() - began, cpu))
                proposals = sum(1 for _ in open(out / "index.jsonl")) + sum(
                    1 for _ in open(out / "rejections.jsonl")
                )
    median = {k: [statistics.median(v[i] for v in rs) for i in (0, 1)] for k, rs in runs.items()}
    starts = proposals / recycle_after
    return {
        "n": n,
        "recycle_after": recycle_after,
        "proposals": proposals,
        "worker_starts": round(starts, 1),
        "runs": runs,
        "median_wall_s": {k: round(v[0], 2) for k, v in median.items()},
        "median_cpu_s": {k: round(v[1], 2) for k, v in median.items()},
        "cpu_per_start_s": round((median["recycled"][1] - median["kept"][1]) / starts, 3),
        "wall_ratio": round(median["recycled"][0] / median["kept"][0], 3),
    }


def table(run: dict) -> str:
    keys = [k for k in run["samples"][-1] if k not in ("scenes", "wall_s")] if run["samples"] else []
    lines = ["| scenes | wall s | " + " | ".join(f"{k} MB" for k in keys) + " |"]
    lines.append("|---" * (len(keys) + 2) + "|")
    for s in run["samples"]:
        cells = " | ".join(f"{s.get(k, 0):.0f}" for k in keys)
        lines.append(f"| {s['scenes']} | {s['wall_s']} | {cells} |")
    g = run["growth"]
    if g:
        shown = ", ".join(f"{k} {v:+.1f} %" for k, v in g.items() if k not in ("from_scenes", "to_scenes"))
        lines.append(f"growth, mean of 3 samples from {g['from_scenes']} scenes to the last 3: {shown}")
    for key, t in run.get("trend", {}).items():
        lines.append(
            f"trend of {key}: {t['fitted_growth_pct']:+.1f} % fitted from {t['from_scenes']} to "
            f"{t['to_scenes']} scenes ({t['slope_mb_per_1000']:+.1f} MB per 1,000 scenes, "
            f"95 % {t['slope_ci95']})"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--pipeline", type=Path, default=ROOT / "pipelines" / "procedural.yaml")
    parser.add_argument("--plain", type=int, default=3000, help="scenes without rendering (default 3000)")
    parser.add_argument("--rendered", type=int, default=500, help="scenes with rendering (default 500)")
    parser.add_argument("--every", type=int, default=100, help="sample every this many scenes (default 100)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--recycle-after", type=int, default=None, help="replace workers after N proposals")
    parser.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "soak.json")
    parser.add_argument(
        "--report", action="store_true", help="only report the runs saved in --json again, trends fitted"
    )
    parser.add_argument(
        "--recycle-cost",
        type=int,
        metavar="N",
        help="only measure what recycling costs: --plain scenes without and with --recycle-after N",
    )
    args = parser.parse_args(argv)
    if args.recycle_cost:
        os.environ.setdefault("MUJOCO_GL", "egl")
        cost = recycle_cost(args.pipeline, args.plain, args.recycle_cost, args.workers, 2)
        print(json.dumps(cost, indent=1))
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(cost, indent=1) + "\n")
        return 0
    if args.report:
        results = json.loads(args.json.read_text())
        for run in results["runs"]:
            run["trend"] = trend(run["samples"])
            print(f"{run['n']} scenes, {'rendered' if run['render'] else 'no rendering'}:")
            print(table(run))
        args.json.write_text(json.dumps(results, indent=1) + "\n")
        return 0
    os.environ.setdefault("MUJOCO_GL", "egl")
    results = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs", "runs": []}
    with tempfile.TemporaryDirectory(prefix="soak") as tmp:
        for n, render in ((args.plain, False), (args.rendered, True)):
            if n <= 0:
                continue
            kind = "rendered" if render else "no rendering"
            print(f"{n} scenes, {kind}, {args.workers} workers:", flush=True)
            batch = Path(tmp) / f"batch_{int(render)}"
            run = soak(args.pipeline, n, render, args.every, args.workers, batch, args.recycle_after)
            results["runs"].append(run)
            print(table(run), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(results, indent=1) + "\n")
    print(f"-> {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
