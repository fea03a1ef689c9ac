"""Stage render: off-screen RGB, depth and instance segmentation per camera (offscreen.py)."""
