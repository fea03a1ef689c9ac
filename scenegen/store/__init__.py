"""Stage store: the batch directory, written atomically and resumable (batch.py)."""
