"""``scenegen audit``: a data manifest verified against its files. manifest.py checks the manifest
itself (models, recipes, realism presence); files.py walks a source's files (the checksum chain,
recounts, the source re-derived and its realism recomputed). docs/manifest.md."""

IMAGE_SAMPLE = 64  # scenes of a batch whose images' statistics the audit re-measures from the pixels
