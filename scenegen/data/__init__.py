"""Data tools above the runner: the reference set, its renders, real-data import and coverage counts."""
