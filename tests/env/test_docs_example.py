"""docs/env.md's example runs as written, on a fresh batch in place of runs/demo."""

from __future__ import annotations

import re
from pathlib import Path

from scenegen.paths import PROJECT_ROOT


def test_the_example_in_docs_env_md_runs(demo_batch: Path, capsys):
    text = (PROJECT_ROOT / "docs" / "env.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len([line for line in code.splitlines() if line.strip()]) <= 10 and '"runs/demo"' in code
    exec(compile(code.replace('"runs/demo"', repr(str(demo_batch))), "docs/env.md", "exec"), {})
    scene_id, *_ = capsys.readouterr().out.split()
    assert (demo_batch / scene_id / "scene.json").is_file()
