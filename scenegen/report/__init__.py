"""``scenegen report``: a batch (or the project's data_manifest.yaml) as one HTML page a person
opens from disk: no server, no network, styles and scripts inline, plots drawn by matplotlib as SVG,
thumbnails beside the page (docs/report.md).

- ``facts.py``: what the page says of a batch, recounted from its files (scene folders, the rejection
  log, timings.json, the manifest's realism checks, the reference's tag rates), the audit recomputed;
- ``thumbs.py``: small RGB, colourized depth and segmentation images per scene and camera;
- ``project.py``: what the page says of a project manifest (sources, mixtures, coverage, transfer);
- ``plots.py``: the SVG plots; ``page.py``: the templates filled and written atomically.
"""

from scenegen.store.batch import REPORT, REPORT_FILES  # the batch layout's names (audit/files.py allows them)

__all__ = ["REPORT", "REPORT_FILES"]
