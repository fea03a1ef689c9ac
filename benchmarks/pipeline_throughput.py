"""Pipeline throughput: accepted scenes per second, per-stage time and CPU per accepted scene, for the
code at a baseline commit and the code here, with the local pool and with Ray.

    .venv/bin/python benchmarks/pipeline_throughput.py [--pipelines P ...] [--n 48] [--workers 1 2]
        [--ray-cpus 2] [--baseline 83efef1 | --no-baseline] [--no-ray] [--steady 144]

Every configuration runs the same recipe, seed and n in the same invocation, each in a fresh
process (`run_batch` into a temporary directory, start-up of the worker processes included):
- ``baseline``: the code of the ``--baseline`` commit (default 83efef1, where the throughput issue
  was measured), extracted with `git archive` and run from there with the same virtual environment,
  on that commit's own copy of the recipe;
- ``current``: this checkout, local pool, for each ``--workers``;
- ``ray``: this checkout with ``--backend ray`` on a local cluster of ``--ray-cpus`` CPUs, the
  cluster started before the clock starts (its start is reported separately).
CPU seconds "all processes" are those of the coordinator and every process under it (pool workers,
Ray's raylet, GCS and actors), sampled from /proc every 0.2 s, over the batch only. "own s+r" is the
accepted scenes' settle + render CPU seconds measured inside the workers (time.process_time; the
baseline has only its in-stage wall times, a slight over-estimate of its own CPU, which flatters its
ratio). ``--steady N2`` runs every configuration again at N2 accepted scenes and reports the cost
of the scenes beyond the first n (scenes/s and CPU per scene from the difference of the two runs):
what a long batch pays per scene once start-up (imports, worker start, first compiles) and the batch
manifest's realism checks are paid. Prints tables and saves JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path

from baseline import ROOT, add_child_arguments, baseline_tree, child_main, run_child

STAGES = ("propose", "check", "build", "settle", "tag", "render", "store")
TICK = os.sysconf("SC_CLK_TCK")


# ------------------------------------------------------------------------------ one measurement


class TreeCpu:
    """CPU seconds of this process and every live descendant, sampled every ``period`` seconds.

    A process that exits between two samples loses at most ``period`` of its CPU time."""

    def __init__(self, period: float = 0.2):
        self.period, self.last, self._stop = period, {}, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _children(self) -> dict[int, int]:
        parents = {}
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                text = stat.read_text()
            except OSError:
                continue
            fields = text[text.rfind(")") + 2 :].split()
            parents[int(stat.parent.name)] = (int(fields[1]), int(fields[11]) + int(fields[12]))
        tree, frontier = {}, {os.getpid()}
        while frontier:
            frontier = {pid for pid, (ppid, _) in parents.items() if ppid in frontier and pid not in tree}
            tree.update({pid: parents[pid][1] for pid in frontier})
        return tree

    def _run(self):
        while not self._stop.is_set():
            self.last.update(self._children())
            time.sleep(self.period)

    def start(self) -> TreeCpu:
        self.thread.start()
        return self

    def total(self) -> float:
        """CPU seconds so far: this process plus its descendants' last samples."""
        self.last.update(self._children())
        return time.process_time() + sum(self.last.values()) / TICK

    def stop(self) -> float:
        self._stop.set()
        self.thread.join()
        return self.total()


def measure(spec: dict) -> dict:
    """One batch in this process (the child): spec has pipeline, n, seed, workers, backend, render."""
    # scenegen from PYTHONPATH only: the editable install's finder would fill in modules the
    # baseline does not have from this checkout.
    sys.meta_path[:] = [f for f in sys.meta_path if "Editable" not in getattr(f, "__name__", "")]
    try:
        from scenegen.runner.config import load_pipeline
        from scenegen.runner.pipeline import run_batch
    except ModuleNotFoundError:  # the flat layout of earlier commits (83efef1)
        from scenegen.config import load_pipeline
        from scenegen.pipeline import run_batch

    overrides = {"n": spec["n"], "seed": spec["seed"], "render": None if spec["render"] else False}
    config = load_pipeline(Path(spec["pipeline"]), overrides)
    kwargs, cluster_start = {}, None
    cpu = TreeCpu().start()
    if spec["backend"] == "ray":
        from scenegen.runner.executors import Backend, connect_ray

        t0 = time.perf_counter()
        connect_ray(None, spec["workers"])
        cluster_start = time.perf_counter() - t0
        kwargs["backend"] = Backend("ray")
    cpu_before = cpu.total()
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_batch(config, Path(tmp) / "batch", workers=spec["workers"], progress=False, **kwargs)
    cpu_all = cpu.stop() - cpu_before
    if spec["backend"] == "ray":
        import ray

        ray.shutdown()
    n = max(summary.accepted, 1)
    own_cpu = getattr(summary, "accepted_cpu", None) or summary.accepted_seconds
    own = (own_cpu["settle"] + own_cpu.get("render", 0.0)) / n
    cams = ", ".join(f"{c.name} {c.width}x{c.height}" for c in config.proposer.cameras)
    return {
        "accepted": summary.accepted,
        "proposals": summary.proposals,
        "wall_s": round(summary.wall, 3),
        "accepted_per_s": round(summary.accepted / summary.wall, 3),
        "cluster_start_s": None if cluster_start is None else round(cluster_start, 2),
        "cpu_all_per_accepted_s": round(cpu_all / n, 4),
        "own_settle_render_cpu_s": round(own, 4),
        "cpu_over_own": round(cpu_all / n / own, 3) if own else None,
        "stage_s_per_accepted": {k: round(v / n, 4) for k, v in summary.seconds.items()},
        "cameras": cams,
        "robot_mesh_detail": getattr(config, "robot_mesh_detail", None),
    }


# ------------------------------------------------------------------------------ the driver


def configurations(args) -> list[dict]:
    runs = []
    for pipeline in args.pipelines:
        for n in (args.n, args.steady) if args.steady else (args.n,):
            base = {"pipeline": str(pipeline), "n": n, "seed": args.seed, "render": not args.no_render}
            if args.baseline:
                runs += [{**base, "code": "baseline", "backend": "local", "workers": w} for w in args.workers]
            runs += [{**base, "code": "current", "backend": "local", "workers": w} for w in args.workers]
            if not args.no_ray:
                runs.append({**base, "code": "current", "backend": "ray", "workers": args.ray_cpus})
    return runs


def _key(r: dict) -> tuple:
    return r["pipeline"], r["code"], r["backend"], r["workers"]


def steady(results: list[dict]) -> list[dict]:
    """Per configuration run at two sizes: the scenes beyond the smaller run, from the difference."""
    out = []
    for long in results:
        short = [r for r in results if _key(r) == _key(long) and r["n"] < long["n"]]
        if not short:
            continue
        short = short[0]
        scenes = long["accepted"] - short["accepted"]
        cpu = (
            long["cpu_all_per_accepted_s"] * long["accepted"]
            - short["cpu_all_per_accepted_s"] * short["accepted"]
        )
        wall = long["wall_s"] - short["wall_s"]
        out.append(
            {
                **{k: long[k] for k in ("pipeline", "code", "backend", "workers")},
                "scenes": scenes,
                "accepted_per_s": round(scenes / wall, 3),
                "cpu_all_per_accepted_s": round(cpu / scenes, 4),
                "own_settle_render_cpu_s": long["own_settle_render_cpu_s"],
                "cpu_over_own": round(cpu / scenes / long["own_settle_render_cpu_s"], 3),
            }
        )
    return out


def report_steady(rows: list[dict]) -> None:
    for pipeline in dict.fromkeys(r["pipeline"] for r in rows):
        mine = [r for r in rows if r["pipeline"] == pipeline]
        print(f"\n{pipeline}: the {mine[0]['scenes']} scenes beyond the first run's (steady state)")
        _print_rows(mine, whole=False)


def report(results: list[dict]) -> None:
    for pipeline, n in dict.fromkeys((r["pipeline"], r["n"]) for r in results):
        rows = [r for r in results if r["pipeline"] == pipeline and r["n"] == n]
        print(f"\n{pipeline}: n={n} cameras: {rows[0]['cameras']}")
        _print_rows(rows, whole=True)
        print("stage wall seconds per accepted scene (all proposals, summed over workers):")
        print(
            f"{'stage':<10}"
            + "".join(f"{r['code'][:4] + '/' + r['backend'][:1] + str(r['workers']):>10}" for r in rows)
        )
        for stage in STAGES:
            print(f"{stage:<10}" + "".join(f"{r['stage_s_per_accepted'].get(stage, 0):>10.3f}" for r in rows))


def _print_rows(rows: list[dict], whole: bool) -> None:
    """One line per configuration, "vs base" against the first code's local run with as many
    workers; ``whole``: a whole batch's row (with its wall time and Ray's cluster start)."""
    columns = [("code", 9), ("backend", 8), ("workers", 8), ("scenes/s", 9), ("vs base", 8)]
    columns += [("wall s", 8)] * whole + [("cpu/scene", 10), ("own s+r", 8), ("ratio", 6)]
    columns += [("start s", 8)] * whole
    print("".join(f"{h:>{w}}" for h, w in columns))
    base = {r["workers"]: r for r in rows if r["code"] == rows[0]["code"] and r["backend"] == "local"}
    for r in rows:
        ref = base.get(r["workers"])
        vs = r["accepted_per_s"] / ref["accepted_per_s"] if ref else float("nan")
        cells = [r["code"], r["backend"], r["workers"], f"{r['accepted_per_s']:.2f}", f"{vs:.2f}"]
        if whole:
            cells.append(f"{r['wall_s']:.1f}")
        cells += [f"{r['cpu_all_per_accepted_s']:.3f}", f"{r['own_settle_render_cpu_s']:.3f}"]
        cells += [f"{r['cpu_over_own']:.2f}"]
        if whole:
            cells.append(f"{r['cluster_start_s']:.1f}" if r["cluster_start_s"] is not None else "-")
        print("".join(f"{c:>{w}}" for c, (_, w) in zip(cells, columns, strict=True)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--pipelines",
        type=Path,
        nargs="+",
        default=[Path("pipelines/demo.yaml"), Path("pipelines/procedural.yaml")],
    )
    parser.add_argument("--n", type=int, default=48, help="accepted scenes per configuration (default 48)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--ray-cpus", type=int, default=2, help="Ray actors (1 CPU each) of the ray run")
    parser.add_argument("--baseline", default="83efef1", help="commit whose code is the baseline")
    parser.add_argument("--no-baseline", dest="baseline", action="store_const", const=None)
    parser.add_argument("--no-ray", action="store_true")
    parser.add_argument("--no-render", action="store_true")
    parser.add_argument(
        "--steady",
        type=int,
        metavar="N2",
        help="also run every configuration at N2 > n accepted scenes: the cost per scene beyond n",
    )
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/pipeline_throughput.json"))
    add_child_arguments(parser)
    args = parser.parse_args()
    if args.steady is not None and args.steady <= args.n:
        parser.error(f"--steady {args.steady}: give more accepted scenes than --n ({args.n})")
    if child_main(args, measure):
        return

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        code = {"current": ROOT}
        if args.baseline:
            code["baseline"] = baseline_tree(args.baseline, Path(tmp) / "baseline")
        for spec in configurations(args):
            print(
                f"running {spec['code']} {spec['backend']} workers={spec['workers']} {spec['pipeline']} ...",
                flush=True,
            )
            results.append({**spec, **run_child(__file__, spec, code[spec["code"]])[0]})
    report(results)
    beyond = steady(results)
    if beyond:
        report_steady(beyond)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
        },
        "baseline": args.baseline,
        "results": results,
        "steady": beyond,
    }
    args.json.write_text(json.dumps(payload, indent=1) + "\n")
    print(f"\nsaved {args.json}")


if __name__ == "__main__":
    main()
