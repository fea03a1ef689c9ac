"""python -m scenegen.manifest [MANIFEST]: refresh data_manifest.yaml's derived entries and JSON Schema."""

import sys

from scenegen.manifest.project import main

sys.exit(main(sys.argv[1:]))
