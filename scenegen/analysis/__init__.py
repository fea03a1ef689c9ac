"""Analysis of layouts and renders: realism features and tests (realism.py), per-scene scores
(scene_score.py), image statistics (image_stats.py) and contact sheets (contact_sheet.py)."""
