"""python -m scenegen.cli: the same as the scenegen command."""

from scenegen.cli import entry

entry()
