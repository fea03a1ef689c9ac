"""The retrieval head: a learned, category-conditioned target localiser (RGB-D frames + the requested
category -> the target's pixels), its training data (frames rendered and cached by content), training
and offline evaluation.

The committed heads are pinned by their folders' sha256 in ``assets/retrieval/heads.json``
(``core.files.folder_sha256``); ``DEFAULT_HEAD`` is the one the closed loop sees through unless
told otherwise (issue 43: the ``instances`` design)."""

from scenegen.paths import ASSETS_DIR

HEADS_FILE = ASSETS_DIR / "retrieval" / "heads.json"
DEFAULT_HEAD = ASSETS_DIR / "retrieval" / "instances"
