"""The batch realism checks of the diffusion generator at several guidance weights w.

    .venv/bin/python benchmarks/realism_guidance.py [--weights 1 4] [--n 60] [--workers 2]
        [--request "retrieve the spoon"] [--out runs/realism_guidance]

For each w, one rendered batch of pipelines/demo.yaml (the shipped checkpoint, its cost guidance and
its per-scene `unrealistic` filter) with `proposer.guidance` = w, into OUT/w<w>; each batch's
manifest then holds its realism checks (scenegen/manifest/realism_checks.py: layout C2ST and MMD
against reference layouts of the same request, image statistics against the committed reference
renders), which this prints side by side with the batch's pass rate and its `unrealistic`
rejections, and audits. Resumable: rerun the same command to continue a killed batch. Saves a
Markdown table next to the batches (OUT/realism_guidance.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scenegen.audit.manifest import audit
from scenegen.manifest import read_manifest
from scenegen.runner.config import load_pipeline
from scenegen.runner.pipeline import run_batch


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", type=float, nargs="+", default=[1.0, 4.0], help="guidance weights w")
    parser.add_argument("--n", type=int, default=60, help="accepted scenes per batch (default 60)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--request", help="free-text request laid over the demo recipe's condition")
    parser.add_argument("--recipe", type=Path, default=Path("pipelines/demo.yaml"))
    parser.add_argument("--out", type=Path, default=Path("runs/realism_guidance"))
    args = parser.parse_args()

    header = (
        "| w | scenes / proposals | unrealistic | layout C2ST | layout MMD^2 (p) | image stats | audit |\n"
        "|---|---|---|---|---|---|---|"
    )
    lines = [header]
    for w in args.weights:
        base = load_pipeline(args.recipe)
        proposer = {**base.proposer.model_dump(mode="json"), "guidance": w}
        config = load_pipeline(
            args.recipe,
            {"n": args.n, "seed": args.seed, "proposer": proposer, "max_proposals": 20 * args.n},
            request=args.request,
        )
        out = args.out / f"w{w:g}"
        summary = run_batch(config, out, workers=args.workers, progress=True)
        (source,) = read_manifest(out / "manifest.yaml").sources
        checks = {c.metric: c for c in source.realism}
        c2st, kernel = checks["layout_c2st"], checks["layout_mmd"]
        image = checks.get("image_stats")
        report = audit(out / "manifest.yaml")
        lines.append(
            f"| {w:g} | {summary.accepted} / {summary.proposals} | "
            f"{source.rejections_by_label.get('unrealistic', 0)} | "
            f"{c2st.value:.3f} {c2st.status} (CI {c2st.details['ci'][0]:.2f}-{c2st.details['ci'][1]:.2f}) | "
            f"{kernel.value:.4f} {kernel.status} (p {kernel.details['p_value']:.3f}) | "
            f"{f'{image.value:.2f} {image.status}' if image else '-'} | "
            f"{'passed' if report.ok else f'{len(report.violations)} violations'} |"
        )
        print("\n".join(lines), flush=True)
    reference = checks["layout_c2st"].reference
    note = (
        f"\nRequest: {config.condition.model_dump(mode='json')}; reference subset: {reference.subset} "
        f"({checks['layout_c2st'].samples['reference']} layouts); thresholds: C2ST <= {c2st.threshold}, "
        f"MMD^2 <= {kernel.threshold}, image stats <= {image.threshold if image else '-'}.\n"
    )
    (args.out / "realism_guidance.md").write_text("\n".join(lines) + "\n" + note)
    print(note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
