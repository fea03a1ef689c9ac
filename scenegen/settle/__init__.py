"""Stage settle: MuJoCo settling of a checked proposal and the passive stability test (physics.py)."""
