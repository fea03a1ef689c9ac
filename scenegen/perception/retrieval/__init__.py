"""The retrieval head: a learned, category-conditioned target localiser (RGB-D frames + the requested
category -> the target's pixels), its training data (frames rendered and cached by content), training
and offline evaluation.

The committed heads are pinned by their folders' sha256 in ``assets/retrieval/heads.json``
(``core.files.folder_sha256``); ``DEFAULT_HEAD`` is the one the closed loop sees through unless
told otherwise (issue 43: the ``instances`` design); through the active stereo sensor it is
``SENSOR_HEAD`` (issue 62: the same design trained through the sensor under its depth rule)."""

from pathlib import Path

from scenegen.paths import ASSETS_DIR

HEADS_FILE = ASSETS_DIR / "retrieval" / "heads.json"
DEFAULT_HEAD = ASSETS_DIR / "retrieval" / "instances"
SENSOR_HEAD = ASSETS_DIR / "retrieval" / "instances_stereo"


def default_head(sensor: str = "exact") -> Path:
    """The committed head a closed loop sees through when its depth comes from ``sensor``."""
    return SENSOR_HEAD if sensor == "active_stereo" else DEFAULT_HEAD
