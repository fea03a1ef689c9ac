"""scenegen: physically verified synthetic scenes for robot manipulation, with their bookkeeping."""

import os

# Off-screen rendering goes through EGL (Mesa's software EGL on CPU machines) unless the user chose
# another backend; this must be set before mujoco is first imported.
os.environ.setdefault("MUJOCO_GL", "egl")

__version__ = "0.1.0"
