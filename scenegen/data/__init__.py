"""Data tools above the runner: the reference set, its renders, real-data import and coverage counts.

The coverage command's defaults live here, not in coverage.py, so that `scenegen --help` names them
without importing the schema and numpy (0.13 s)."""

SPARSE_COUNT = 20  # a (task x tag) cell with fewer scenes than this is sparse
CHART_NAME = "coverage.png"
