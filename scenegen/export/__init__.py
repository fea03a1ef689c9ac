"""Exports in the formats other tools read: stored scenes as WebDataset shards (scene_shards.py),
episodes as a LeRobot dataset (lerobot.py). Exporter packages are optional: `pip install
scenegen[export]` (webdataset) and `make install-exporters` (lerobot, which cannot be a pip extra here).
"""
