"""scenegen: physically verified synthetic scenes for robot manipulation, with their bookkeeping."""

__version__ = "0.1.0"
