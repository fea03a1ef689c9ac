"""The fuzzing harness (tests/fuzz/): one CLI call in process, and what every answer must be.

A plain module, imported as ``from fuzzing import ...`` (tests/ is on sys.path, see tests/scenes.py).

Every command, given a broken input, answers with one line on stderr that starts with
``scenegen: error:``, is at most 300 characters and names the file or option it read, and exits
non-zero; it never lets an exception out (a traceback) and never leaves a file half-written: on a
failure, nothing under the example's folder changed. Commands that report findings instead of failing
(``audit``: exit 1 with its report) may answer in several lines.

Profiles: ``ci`` (bounded, derandomized, the default) and ``long`` (``SCENEGEN_FUZZ=long``, at least
1,000 examples per target; ``make fuzz``). ``SCENEGEN_FUZZ_EXAMPLES`` overrides either count. The tally
of each target (examples, exit codes, tracebacks, half-written outputs) is printed at the end of the run
and written to ``SCENEGEN_FUZZ_REPORT`` when set.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import tempfile
import time
import traceback
from collections import Counter, defaultdict
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path

import yaml
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st

PROJECT_ROOT = Path(__file__).resolve().parents[1]
MAX_ERROR = 300
PROFILE = os.environ.get("SCENEGEN_FUZZ", "ci")
# no shrinking: a failure's message names the exact command line, and shrinking a CLI run is slow
_COMMON = dict(
    deadline=None,
    database=None,
    suppress_health_check=list(HealthCheck),
    phases=[Phase.explicit, Phase.generate],
)
settings.register_profile(
    "ci", max_examples=int(os.environ.get("SCENEGEN_FUZZ_EXAMPLES", "10")), derandomize=True, **_COMMON
)
settings.register_profile(
    "long", max_examples=int(os.environ.get("SCENEGEN_FUZZ_EXAMPLES", "1000")), **_COMMON
)
settings.load_profile(PROFILE)

TALLY: dict[str, Counter] = defaultdict(Counter)  # target -> examples, exit codes, tracebacks, half-written


@dataclass
class Answer:
    code: int
    stdout: str
    stderr: str


@contextmanager
def example_dir():
    """A fresh, short folder per example (error lines name paths: keep them short)."""
    folder = Path(tempfile.mkdtemp(prefix="fz", dir="/tmp"))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def snapshot(root: Path) -> dict[str, str]:
    """Every entry under ``root``: relative path -> what it is (file digest, link target, folder)."""
    out = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if path.is_symlink():
            out[rel] = "link:" + os.readlink(path)
        elif path.is_file():
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[rel] = "dir"
    return out


def run_cli(target: str, argv: list, root: Path, names: list[str], *, report_ok: bool = False) -> Answer:
    """Run ``scenegen ARGV`` in this process and check its answer (module docstring); count it under
    ``target``. ``root``: the example's folder (nothing in it may change on a failure); ``names``: the
    answer's error line must contain one of these (the file, folder or option given);
    ``report_ok``: exit 1 with a report of findings is a valid answer (audit)."""
    from scenegen.cli import main

    tally = TALLY[target]
    tally["examples"] += 1
    before = snapshot(root)
    out, err = io.StringIO(), io.StringIO()
    argv = [str(a) for a in argv]
    start = time.perf_counter()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse's own usage errors
            code = exc.code if isinstance(exc.code, int) else 2
        except BaseException:  # noqa: BLE001 - what the fuzzing is for
            tally["tracebacks"] += 1
            raise AssertionError(f"scenegen {argv!r} raised:\n{traceback.format_exc()}") from None
    answer = Answer(int(code or 0), out.getvalue(), err.getvalue())
    tally["seconds"] += round(time.perf_counter() - start, 3)
    tally[f"exit {answer.code}"] += 1
    if "Traceback (most recent call last)" in answer.stderr + answer.stdout:
        tally["tracebacks"] += 1
        raise AssertionError(f"scenegen {argv!r} printed a traceback:\n{answer.stderr}")
    if answer.code == 0:
        return answer
    after = snapshot(root)
    if after != before:
        tally["half-written"] += 1
        changed = sorted(set(after.items()) ^ set(before.items()))[:5]
        raise AssertionError(f"scenegen {argv!r} failed (exit {answer.code}) but changed files: {changed}")
    if answer.code == 1 and report_ok:
        return answer
    lines = [line for line in answer.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, f"scenegen {argv!r}: {len(lines)} lines on stderr, one expected:\n{answer.stderr}"
    line = lines[0]
    assert line.startswith("scenegen: error: "), f"scenegen {argv!r}: not an error line: {line!r}"
    assert len(line) <= MAX_ERROR, f"scenegen {argv!r}: {len(line)} characters: {line!r}"
    assert any(str(name) in line for name in names), f"scenegen {argv!r}: names none of {names}: {line!r}"
    return answer


def write_report() -> str:
    """The tally as a table (and as JSON in $SCENEGEN_FUZZ_REPORT when set)."""
    if not TALLY:
        return ""
    keys = sorted({k for c in TALLY.values() for k in c if k.startswith("exit")})
    columns = ["examples", *keys, "tracebacks", "half-written", "seconds"]
    rows = [f"| target | {' | '.join(columns)} |", "|---" * (len(columns) + 1) + "|"]
    for target, tally in sorted(TALLY.items()):
        cells = [f"{tally.get(c, 0):.0f}" if c == "seconds" else str(tally.get(c, 0)) for c in columns]
        rows.append(f"| {target} | " + " | ".join(cells) + " |")
    table = "\n".join(rows)
    report = os.environ.get("SCENEGEN_FUZZ_REPORT")
    if report:
        Path(report).write_text(json.dumps({"profile": PROFILE, "targets": TALLY}, indent=1, sort_keys=True))
    return table


# ---------------------------------------------------------------- strategies shared by the targets

ODD_NUMBERS = st.one_of(
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1e-300, 1e300, 2**63, -(2**63)]),
)
ODD_SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    ODD_NUMBERS,
    st.text(max_size=40),
    st.sampled_from(["", "nan", ".inf", "1e400", "~", "../..", "/etc/passwd", "assets/generator"]),
)
ODD_VALUES = st.one_of(
    ODD_SCALARS,
    st.lists(ODD_SCALARS, max_size=5),
    st.dictionaries(st.text(max_size=10), ODD_SCALARS, max_size=3),
    st.builds(lambda: list(range(20_000))),  # a huge list (a new one each time: edits may go into it)
)
RAW_FILES = st.one_of(
    st.binary(max_size=400),  # binary, mostly not UTF-8
    st.just(b""),
    st.just(b"\xff\xfe\x00\x00binary"),
    st.text(max_size=200).map(lambda t: t.encode("utf-8")),
    st.text(max_size=60).map(lambda t: t.encode("utf-16")),
    st.just(b"- [" * 5000),  # deeply nested YAML
)


def leaf_paths(data, prefix=()) -> list[tuple]:
    """Every key path of a nested dict / list (leaves and inner nodes)."""
    paths = []
    items = data.items() if isinstance(data, dict) else enumerate(data) if isinstance(data, list) else ()
    for key, value in items:
        paths.append((*prefix, key))
        paths.extend(leaf_paths(value, (*prefix, key)))
    return paths


@st.composite
def mutated_mapping(draw, base: dict, edits: int = 3) -> dict:
    """``base`` with 1..edits edits: a value replaced by an odd one, an unknown key added, a key dropped."""
    import copy

    data = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, edits))):
        paths = leaf_paths(data)
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = data
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["replace", "replace", "add", "drop"]))
        if action == "replace":
            parent[path[-1]] = draw(ODD_VALUES)
        elif action == "add" and isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=12))] = draw(ODD_SCALARS)
        elif action == "drop":
            del parent[path[-1]]
    return data


def dump_yaml(data) -> bytes:
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True).encode("utf-8")
