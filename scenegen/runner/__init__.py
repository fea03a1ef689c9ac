"""The batch runner above the stages: the recipe (config.py) and the worker pool that runs
check -> settle -> tag -> render and commits in proposal order (pipeline.py)."""
