"""Command line: ``scenegen generate`` and friends. ``scenegen --help`` lists the commands.

The only place that parses arguments: each command's parser and handler live in ``scenes.py``
(generate, show), ``generator.py`` (train, sweep), ``data.py`` (reference, reference-images,
coverage, import-real, audit, manifest add, manifest refresh), ``export.py`` (export), ``policy.py``
(label, success-table, policy train, eval), ``experiment.py`` (experiment transfer, verifier,
panels, perception-gap), ``assets.py`` (assets add, list, show), ``report.py`` (report),
``retrieval.py`` (retrieval train, eval), ``proposals.py`` (proposals label, train, eval, compare);
handlers call library functions with typed arguments.
"""

from __future__ import annotations

import argparse
import os
import sys

from scenegen.cli import (
    assets,
    data,
    experiment,
    export,
    generator,
    policy,
    proposals,
    report,
    retrieval,
    scenes,
)
from scenegen.cli.common import USAGE_ERROR, fail

DESCRIPTION = """\
scenegen generates physically verified tabletop manipulation scenes for rare cases.

A pipeline recipe (pipelines/*.yaml) names the request (task, target, rare-case tags, robot pose)
and the distributions of the proposer. `generate` proposes scenes, rejects the infeasible ones
(workspace, support, collisions on convex parts, robot clearance, reachability, MuJoCo settling)
and stores each accepted scene as scene.json + scene.xml, with a log of every rejection and a
batch manifest.

Accepted scenes are rendered off-screen (RGB, depth in millimetres, instance segmentation per
camera; MUJOCO_GL=egl works on CPU machines through Mesa). A batch killed at any point resumes
exactly when the same command is run again; the output does not depend on --workers.

examples:
  scenegen generate pipelines/demo.yaml --n 20 --seed 0 --out runs/demo --workers 2
  scenegen show runs/demo            # contact sheet: runs/demo/contact_sheet.png
  scenegen report runs/demo          # the batch as a page: runs/demo/report.html
  scenegen audit runs/demo/manifest.yaml
  scenegen manifest add runs/demo    # into data_manifest.yaml, after auditing it
  scenegen export runs/demo --format webdataset --out runs/demo-wds
  scenegen label runs/demo --out runs/labels.parquet   # every grasp primitive per scene (docs/policy.md)
  scenegen assets add my/lemon.obj --category fruit   # your own objects (docs/assets.md)
  scenegen experiment transfer      # are generated rare scenes worth it in closed loop? (docs/transfer.md)
"""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scenegen", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    scenes.add_commands(sub)
    assets.add_commands(sub)
    data.add_commands(sub)
    generator.add_commands(sub)
    export.add_commands(sub)
    policy.add_commands(sub)
    retrieval.add_commands(sub)
    proposals.add_commands(sub)
    experiment.add_commands(sub)
    report.add_commands(sub)
    return parser


_GL_BACKENDS = (
    "egl",
    "osmesa",
    "glfw",
    "glx",
    "enable",
    "enabled",
    "on",
    "true",
    "1",
    "disable",
    "disabled",
    "off",
    "false",
    "0",
    "",
)


def entry() -> None:
    """The ``scenegen`` command (and ``python -m scenegen.cli``): :func:`main`, then, once the exit
    handlers have run (atexit: logging, multiprocessing's children, Ray, the GL context) and stdout
    and stderr are flushed, the process ends at once. Python's own teardown of every loaded module and
    object (torch, MuJoCo, the reference table) took 1.3 s after a batch and did nothing a user
    needs: every file the command wrote is closed by then (atomic writes). An exception or
    argparse's exit propagates as usual."""
    import atexit

    code = main()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return USAGE_ERROR
    no_gl = args.command in ("train", "sweep", "audit", "manifest", "export", "success-table", "report") or (
        args.command == "generate" and args.no_render
    )
    if no_gl and "mujoco" not in sys.modules:
        os.environ["MUJOCO_GL"] = "disable"  # no GL is touched: a broken GL set-up cannot get in the way
    backend = os.environ.get("MUJOCO_GL", "egl").lower().strip()
    if backend not in _GL_BACKENDS:
        return fail(f"MUJOCO_GL={backend}: not a GL backend mujoco knows; use MUJOCO_GL=egl (or --no-render)")
    try:
        import mujoco  # noqa: F401 - a GL backend that cannot load fails here
    except Exception as exc:  # noqa: BLE001
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return fail(
            f"MUJOCO_GL={backend}: mujoco cannot load this GL backend ({reason}); "
            "use MUJOCO_GL=egl (or --no-render)"
        )
    return args.run(args)
