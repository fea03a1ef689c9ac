"""User assets with the generators: acceptance with a user asset in a category the model knows, and
a new category through a generator trained to know it, each against its baseline in the same run.

    .venv/bin/python benchmarks/user_assets.py [--n 30] [--known-catalog runs/robosuite_known/catalog.yaml]
        [--new-catalog runs/robosuite_objects/catalog.yaml --checkpoint runs/generator_grocery]

Known category (``--known-catalog``: robosuite's can, bottle, cereal and milk imported as ``can``,
``bottle``, ``box``, ``box``; docs/assets.md): the shipped generator asked for each of those targets,
placing the bundled assets (baseline) or, through ``proposer.assets``, the user assets of those
categories (each decoded object of the category becomes one, in the resting pose matched by
uprightness and height). New category (``--checkpoint``, trained on ``scenegen reference`` with the new
catalog): "retrieve the grocery toppled" from that generator against the procedural proposer
(rejection sampling on the tag). Every arm: ``--n`` accepted scenes (or 20 x n proposals), unrendered,
one process; reported: accepted / proposals, adherence (proposals that settled with the request met,
among those that settled), CPU seconds per accepted scene (this process and its children). Saves JSON
to benchmarks/results/user_assets.json.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import torch  # noqa: E402

torch.set_num_threads(1)

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

from scenegen.paths import PROJECT_ROOT  # noqa: E402
from scenegen.runner.config import validate_config  # noqa: E402
from scenegen.runner.pipeline import run_batch  # noqa: E402

BUNDLED_OTHERS = ("teaspoon", "tablespoon", "fork", "knife", "mug", "bowl", "plate")
KNOWN = {"can": "rs_can", "bottle": "rs_bottle", "box": "rs_cereal"}  # target category -> a user asset
SETTLED_LABELS = ("condition_unmet",)  # rejected after settling because the request was not met


def cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def arm(name: str, recipe: dict, n: int) -> dict:
    """One batch of ``recipe`` (a mapping) in a temporary directory: counts and CPU."""
    batch = re.sub(r"[^A-Za-z0-9_.-]+", "_", name)
    config = validate_config({**recipe, "name": batch, "n": n, "max_proposals": 20 * n, "render": False})
    with tempfile.TemporaryDirectory() as tmp:
        start = cpu_seconds()
        summary = run_batch(config, Path(tmp) / "batch", workers=1, progress=False)
        cpu = cpu_seconds() - start
        targets: dict[str, int] = {}
        for scene in sorted((Path(tmp) / "batch").glob("scene_*/scene.json")):
            record = json.loads(scene.read_text())
            asset = next(o["asset"] for o in record["objects"] if o["name"] == record["target"])
            targets[asset] = targets.get(asset, 0) + 1
    unmet = sum(summary.rejections.get(label, 0) for label in SETTLED_LABELS)
    settled = summary.accepted + unmet
    row = {
        "arm": name,
        "accepted": summary.accepted,
        "proposals": summary.proposals,
        "acceptance": round(summary.accepted / max(summary.proposals, 1), 3),
        "adherence": round(summary.accepted / settled, 3) if settled else None,
        "cpu_per_accepted": round(cpu / max(summary.accepted, 1), 2),
        "rejections": dict(sorted(summary.rejections.items())),
        "targets": targets,
    }
    print(
        f"{name:34s} {row['accepted']:3d}/{row['proposals']:<4d} acceptance {row['acceptance']:.3f} "
        f"adherence {row['adherence']} CPU/accepted {row['cpu_per_accepted']:.2f} s  targets {targets}"
    )
    return row


def known_category(catalog: str, n: int) -> list[dict]:
    rows = []
    for category, user_asset in KNOWN.items():
        base = {"seed": 0, "condition": {"task": "retrieve", "target": category, "robot_pose": "home"}}
        bundled = {**base, "proposer": {"kind": "diffusion"}}
        users = sorted({*KNOWN.values(), "rs_milk", *BUNDLED_OTHERS})
        user = {**base, "catalogs": [catalog], "proposer": {"kind": "diffusion", "assets": users}}
        rows.append(arm(f"diffusion {category}: bundled", bundled, n))
        rows.append(arm(f"diffusion {category}: user ({user_asset})", user, n))
    return rows


def new_category(catalog: str, checkpoint: str, n: int) -> list[dict]:
    request = {"task": "retrieve", "target": "grocery", "tags": {"toppled": "required"}, "robot_pose": "home"}
    base = {"seed": 0, "catalogs": [catalog], "condition": request}
    procedural = {**base, "proposer": {"kind": "procedural"}}
    diffusion = {**base, "proposer": {"kind": "diffusion", "checkpoint": checkpoint}}
    return [arm("procedural grocery toppled", procedural, n), arm("diffusion grocery toppled", diffusion, n)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=30, help="accepted scenes per arm (default 30)")
    parser.add_argument("--known-catalog", default="runs/robosuite_known/catalog.yaml")
    parser.add_argument("--new-catalog", default="runs/robosuite_objects/catalog.yaml")
    parser.add_argument(
        "--checkpoint", help="a generator that knows the new catalog's category (skipped if absent)"
    )
    args = parser.parse_args()
    os.chdir(PROJECT_ROOT)  # recipes name catalogs relative to the working directory
    rows = known_category(args.known_catalog, args.n)
    if args.checkpoint:
        rows += new_category(args.new_catalog, args.checkpoint, args.n)
    out = PROJECT_ROOT / "benchmarks" / "results" / "user_assets.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {"machine": platform.processor() or platform.machine(), "n": args.n, "arms": rows}, indent=1
        )
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
