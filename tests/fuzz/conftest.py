"""The fuzz targets' tally, printed at the end of the run (tests/fuzzing.py)."""

from __future__ import annotations


def pytest_terminal_summary(terminalreporter) -> None:
    from fuzzing import PROFILE, write_report

    table = write_report()
    if table:
        terminalreporter.write_sep("-", f"fuzzing ({PROFILE} profile): answers per target")
        terminalreporter.write_line(table)
