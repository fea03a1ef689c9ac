"""The generator's own distribution: N accepted scenes sampled under the null condition, compared with
the held-out reference layouts (tag rates, classifier two-sample test, MMD).

    .venv/bin/python benchmarks/null_condition.py [--n 2000] [--workers 2] [--out runs/null_condition]

The batch is `scenegen generate` of the reference recipe (pipelines/reference.yaml: its checks,
settling and tags) with the proposer of --generator (pipelines/demo.yaml: the shipped checkpoint and
its settings) sampling the null condition (`unconditional: true`; nothing required, so nothing is
rejected as condition_unmet). It is resumable: a killed run continues when the same command is run
again. Every tag is then read from the stored scene.json files and compared with the held-out
split of the reference set: each tag's rate must lie within max(1 point, 30 % of the reference
rate), and the C2ST accuracy (scenegen.analysis.realism.c2st, 5 folds) must be at most 0.60. Prints a table,
saves JSON; exit code 1 when a criterion fails.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from scenegen.analysis.realism import c2st, feature_matrix, feature_names, load_rows, mmd, record_row
from scenegen.runner.config import load_pipeline
from scenegen.runner.pipeline import run_batch
from scenegen.schema.condition import TAGS
from scenegen.schema.scene import SceneRecord

C2ST_MAX = 0.60


def tolerance(rate: float) -> float:
    return max(0.01, 0.3 * rate)


def separating_features(a, b, top: int = 8) -> list[dict]:
    """The ``top`` features whose marginals differ most between generated ``a`` and reference ``b``:
    two-sample Kolmogorov-Smirnov statistic and both means, largest statistic first. A reading aid
    for the C2ST (which sees the features jointly), not a criterion."""
    from scipy.stats import ks_2samp

    rows = [
        {
            "feature": name,
            "ks": float(ks_2samp(a[:, i], b[:, i]).statistic),
            "generated": float(a[:, i].mean()),
            "reference": float(b[:, i].mean()),
        }
        for i, name in enumerate(feature_names())
        if a[:, i].std() + b[:, i].std() > 1e-12
    ]
    return sorted(rows, key=lambda r: -r["ks"])[:top]


def count_matched(a, b, seed: int, draws: int = 5) -> dict:
    """What a generator whose object count followed the data's would reach: the C2ST of subsamples of
    ``a`` drawn without replacement in ``b``'s count histogram (as large as ``a``'s scarcest count
    allows), beside subsamples of ``a`` of the same size drawn at random (the C2ST falls with n
    alone), each averaged over ``draws`` seeded draws. A reading aid, not a criterion."""
    import numpy as np

    count_a, count_b = a[:, 0].astype(int), b[:, 0].astype(int)  # feature 0 is n_objects
    share = np.bincount(count_b) / len(count_b)
    held = np.bincount(count_a, minlength=len(share))[: len(share)]
    size = int(min(held[k] / share[k] for k in range(len(share)) if share[k] > 0))
    matched, unmatched = [], []
    for draw in range(draws):
        rng = np.random.default_rng([seed, draw])
        pick = [
            rng.choice(np.flatnonzero(count_a == k), size=int(share[k] * size), replace=False)
            for k in range(len(share))
            if share[k] > 0
        ]
        rows = np.concatenate(pick)
        matched.append(c2st(a[rows], b, seed=seed + draw).accuracy)
        random = rng.choice(len(a), size=len(rows), replace=False)
        unmatched.append(c2st(a[random], b, seed=seed + draw).accuracy)
    return {"n": int(len(rows)), "matched": float(np.mean(matched)), "unmatched": float(np.mean(unmatched))}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="accepted scenes (default 2000)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/null_condition"))
    parser.add_argument("--recipe", type=Path, default=Path("pipelines/reference.yaml"))
    parser.add_argument("--generator", type=Path, default=Path("pipelines/demo.yaml"))
    parser.add_argument("--reference", type=Path, default=Path("assets/reference/reference.parquet"))
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/null_condition.json"))
    parser.add_argument(
        "--cost-weight",
        type=float,
        help="cost guidance of the null samples (default: the generator recipe's)",
    )
    args = parser.parse_args()

    generator = load_pipeline(args.generator).proposer
    proposer = {**generator.model_dump(mode="json"), "unconditional": True}
    if args.cost_weight is not None:
        proposer["cost_weight"] = args.cost_weight
    config = load_pipeline(
        args.recipe,
        {"name": "null_condition", "n": args.n, "seed": args.seed, "render": False, "proposer": proposer},
    )
    existing = sum(1 for _ in args.out.glob("scene_*/scene.json")) if args.out.is_dir() else 0
    if existing:
        print(
            f"resuming the batch in {args.out}: {existing} scenes are already there, made by the code "
            "that ran then; delete the folder (or pass another --out) to measure the current code"
        )
    summary = run_batch(config, args.out, workers=args.workers)
    records = [
        SceneRecord.model_validate_json(p.read_text()) for p in sorted(args.out.glob("scene_*/scene.json"))
    ]
    heldout = load_rows(args.reference, "heldout")
    rows = []
    ok = True
    for tag in TAGS:
        rate = sum(r.tags[tag].holds for r in records) / len(records)
        ref = sum(bool(h[f"tag_{tag}"]) for h in heldout) / len(heldout)
        within = abs(rate - ref) <= tolerance(ref) + 1e-12
        ok &= within
        rows.append(
            {"tag": tag, "rate": rate, "reference": ref, "tolerance": tolerance(ref), "within": within}
        )
    a, b = feature_matrix([record_row(r) for r in records]), feature_matrix(heldout)
    test = c2st(a, b, seed=args.seed)
    kernel = mmd(a, b, seed=args.seed)
    ok &= test.accuracy <= C2ST_MAX
    print(
        f"\n{len(records)} accepted of {summary.proposals} proposals ({len(records) / summary.proposals:.0%})"
    )
    print("rejections: " + ", ".join(f"{k} {v}" for k, v in summary.rejections.most_common()))
    print("\n| tag | generated | held-out reference | allowed difference | within |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['tag']} | {r['rate']:.2%} | {r['reference']:.2%} | {r['tolerance']:.2%} "
            f"| {'yes' if r['within'] else 'NO'} |"
        )
    print(
        f"\nC2ST {test.accuracy:.3f} [{test.ci[0]:.3f}, {test.ci[1]:.3f}] (n {test.n}; at most {C2ST_MAX}), "
        f"MMD^2 {kernel.mmd2:.4f} p {kernel.p_value:.3f}"
    )
    separating = separating_features(a, b)
    print("\nfeatures whose marginals differ most (KS statistic; generated mean / reference mean):")
    for r in separating:
        print(f"  {r['feature']:22s} {r['ks']:.3f}  {r['generated']:.3f} / {r['reference']:.3f}")
    counts = count_matched(a, b, seed=args.seed)
    print(
        f"\nthe data's object counts ({counts['n']} scenes drawn in its histogram, 5 draws): C2ST "
        f"{counts['matched']:.3f} against {counts['unmatched']:.3f} for as many drawn at random"
    )
    result = {
        "args": {k: str(v) for k, v in vars(args).items()},
        "accepted": len(records),
        "proposals": summary.proposals,
        "rejections": dict(summary.rejections),
        "tags": rows,
        "c2st": {"accuracy": test.accuracy, "ci": test.ci, "n": test.n, "max": C2ST_MAX},
        "mmd": {"mmd2": kernel.mmd2, "p_value": kernel.p_value},
        "separating_features": separating,
        "count_matched": counts,
        "passed": bool(ok),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    print(f"{'passed' if ok else 'FAILED'}; saved {args.json}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
