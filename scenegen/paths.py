"""Where the project's bundled files live."""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parents[1]
ASSETS_DIR = Path(os.environ.get("SCENEGEN_ASSETS", PROJECT_ROOT / "assets"))
PIPELINES_DIR = PROJECT_ROOT / "pipelines"
USER_CATALOG = Path("user_assets") / "catalog.yaml"  # `scenegen assets add`: default, in the working dir


def cache_dir() -> Path:
    """Where derived, rebuildable files are kept between runs (the realism scorer's arrays):
    $SCENEGEN_CACHE, else $XDG_CACHE_HOME/scenegen, else ~/.cache/scenegen. Deleting it is safe."""
    if os.environ.get("SCENEGEN_CACHE"):
        return Path(os.environ["SCENEGEN_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "scenegen"
