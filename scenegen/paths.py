"""Where the project's bundled files live."""

from __future__ import annotations

import os
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parents[1]
ASSETS_DIR = Path(os.environ.get("SCENEGEN_ASSETS", PROJECT_ROOT / "assets"))
PIPELINES_DIR = PROJECT_ROOT / "pipelines"
