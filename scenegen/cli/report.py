"""``scenegen report``: a batch, or the project's data_manifest.yaml, as one HTML page (docs/report.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenegen.cli.common import fail, first_line

HELP = """\
Writes an HTML page that opens from disk with no server and no network (styles, scripts and plots
inline; thumbnails beside it).

For a batch folder: BATCH/report.html, with thumbnails in BATCH/report_files/ (RGB, depth
colourized, segmentation). It shows the request, recipe, generator and checkpoint sha256; the counts
(recounted from the scene folders and rejections.jsonl), tries, wall and CPU seconds per stage; the
rejection funnel with its labels and repairs; the realism checks with the rule each was judged by and
each tag's rate against the reference with 95 % intervals; every accepted scene as a thumbnail,
filterable by tag and target category, its facts (settled poses, tags with their measured values,
provenance, checksums) on a click; and the audit's verdict, recomputed now.

For a project manifest (data_manifest.yaml): report.html beside it (or --out): sources, the training
recipes' alpha mixtures, coverage of task x tag, the transfer outcome with every contrast and arm.

examples:
  scenegen report runs/demo                 # -> runs/demo/report.html
  scenegen report data_manifest.yaml --out runs/project_report.html
"""


def add_commands(sub) -> None:
    parser = sub.add_parser(
        "report",
        help="a batch or the project manifest as an HTML page (opens from disk)",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "path", type=Path, metavar="BATCH|MANIFEST", help="a batch folder or data_manifest.yaml"
    )
    parser.add_argument(
        "--out", type=Path, help="the page to write (a project manifest only; default report.html beside it)"
    )
    parser.add_argument("--no-audit", action="store_true", help="leave the audit out (the page says so)")
    parser.add_argument("--workers", type=int, default=1, help="processes for the audit's scene checks")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(run=_report)


def _report(args) -> int:
    from scenegen.report.facts import ReportError
    from scenegen.report.page import batch_report, project_report

    path = args.path
    if args.workers < 1:
        return fail(f"--workers {args.workers}: must be at least 1")
    try:
        if path.is_dir():
            if args.out is not None:
                return fail(f"--out {args.out}: a batch's report is BATCH/report.html; leave --out out")
            progress = None
            if not args.quiet:
                from tqdm import tqdm

                def progress(items):
                    return tqdm(items, desc="thumbnails", unit="scene")

            page = batch_report(path, audit=not args.no_audit, workers=args.workers, progress=progress)
        elif path.is_file():
            page = project_report(path, args.out, audit=not args.no_audit, workers=args.workers)
        else:
            return fail(f"{path}: no such batch folder or manifest file")
    except (ReportError, OSError) as exc:
        return fail(first_line(exc))
    print(page)
    return 0
