"""The kill harness's table, printed at the end of the run and written to $SCENEGEN_KILL_REPORT."""

from __future__ import annotations

import json
import os
from pathlib import Path


def pytest_terminal_summary(terminalreporter) -> None:
    from test_kill_anywhere import REPORT

    if not REPORT:
        return
    columns = ["points", "killed_running", "finished_first", "problems", "wall_s", "seconds"]
    terminalreporter.write_sep("-", "kill anywhere: SIGKILL at random moments, then rerun")
    terminalreporter.write_line("| command | " + " | ".join(columns) + " |")
    terminalreporter.write_line("|---" * (len(columns) + 1) + "|")
    for name, row in REPORT.items():
        terminalreporter.write_line(f"| {name} | " + " | ".join(str(row[c]) for c in columns) + " |")
    if os.environ.get("SCENEGEN_KILL_REPORT"):
        Path(os.environ["SCENEGEN_KILL_REPORT"]).write_text(json.dumps(REPORT, indent=1) + "\n")
