"""A user's request (issue 64 point 4): each request goes to its own folder unless --out says
otherwise, a default try cap stated in --help, and the summary counts tries."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from scenegen.cli import main
from scenegen.cli.scenes import TRIES_PER_SCENE, request_folder

REPO_ROOT = Path(__file__).resolve().parents[2]
PROCEDURAL = REPO_ROOT / "pipelines" / "procedural.yaml"


def test_a_request_names_its_folder():
    words = "retrieve the mug near edge, not clutter"
    assert request_folder(words) == "retrieve_the_mug_near_edge_not_clutter"
    assert request_folder("Retrieve the MUG -- toppled!") == "retrieve_the_mug_toppled"
    assert len(request_folder("retrieve the spoon " * 20)) <= 80
    assert request_folder("!!!") == "request"


def test_two_requests_of_one_recipe_land_in_two_folders(tmp_path: Path, monkeypatch, capsys):
    """Before issue 64 the second request failed: its default folder held a batch of another recipe.
    Each batch's pipeline.yaml holds its own request, and the summary counts tries."""
    monkeypatch.chdir(tmp_path)
    requests = ("retrieve the mug", "retrieve the bowl not clutter")
    for request in requests:
        code = main(["generate", str(PROCEDURAL), "--request", request, "--n", "1", "--no-render", "--quiet"])
        out = capsys.readouterr().out
        assert code == 0, out
        folder = Path("runs") / "requests" / "procedural" / request_folder(request)
        assert f"-> {folder}" in out and " tries in " in out and "proposals" not in out
        recipe = yaml.safe_load((folder / "pipeline.yaml").read_text())
        assert recipe["condition"]["target"] == request.split()[2]
        assert recipe["max_tries"] == TRIES_PER_SCENE  # the default cap, recorded with the recipe
    assert not (tmp_path / "runs" / "procedural").exists()  # the recipe's own batch folder is untouched


def test_the_default_try_cap_is_stated_and_a_recipes_own_wins(tmp_path: Path, capsys):
    with pytest.raises(SystemExit):
        main(["generate", "--help"])
    assert f"{TRIES_PER_SCENE} x n" in " ".join(capsys.readouterr().out.split())
    assert main(["generate", str(PROCEDURAL), "--n", "3", "--check"]) == 0
    assert f"at most {3 * TRIES_PER_SCENE} tries" in capsys.readouterr().out
    recipe = yaml.safe_load(PROCEDURAL.read_text()) | {"max_tries": 7}
    (tmp_path / "capped.yaml").write_text(yaml.safe_dump(recipe))
    assert main(["generate", str(tmp_path / "capped.yaml"), "--n", "3", "--check"]) == 0
    assert "at most 7 tries" in capsys.readouterr().out
