"""``scenegen audit``: a data manifest verified against its files. manifest.py checks the manifest
itself (models, recipes, realism presence); files.py walks a source's files (the checksum chain,
recounts, the source re-derived and its realism recomputed). docs/manifest.md."""

# Scenes of a rendered batch whose images the audit decodes for the image check (a larger batch is
# judged on a seeded sample of this many, by audit/scenes.py's stated rule; a smaller one, exactly).
IMAGE_SAMPLE = 200
