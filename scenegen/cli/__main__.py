"""python -m scenegen.cli: the same as the scenegen command."""

import sys

from scenegen.cli import main

sys.exit(main())
