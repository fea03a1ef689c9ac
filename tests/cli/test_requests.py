"""Requests and proposer overrides on the command line: `--request` and `--proposer` override the
recipe, and a request no scene can meet, a malformed request or an unknown proposer is a one-line
usage error before any work."""

from __future__ import annotations

from pathlib import Path

import pytest
from scenes import REFERENCE
from scenes import generate_request as generate

from scenegen.cli import main
from scenegen.runner.config import ConfigError, load_pipeline

USAGE_ERROR = 2


def test_request_and_proposer_override_the_recipe():
    config = load_pipeline(REFERENCE, request="upright the bowl toppled not clutter", proposer="targeted")
    assert config.proposer.kind == "targeted"
    assert config.proposer.n_objects == load_pipeline(REFERENCE).proposer.n_objects
    assert (config.condition.task, config.condition.target) == ("upright", "bowl")
    assert config.condition.required() == ["toppled"] and config.condition.forbidden() == ["clutter"]


def test_unreachable_request_is_refused_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture):
    """No spoon asset has a non-upright resting pose: asking for a toppled spoon is an error, not a
    run that rejects every proposal."""
    with pytest.raises(ConfigError, match="toppled: no spoon asset"):
        load_pipeline(REFERENCE, request="retrieve the spoon toppled")
    out = tmp_path / "never"
    assert generate(out, "retrieve the spoon toppled", "procedural") == USAGE_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "toppled" in err[0] and "request another target" in err[0]
    assert err[0].startswith("scenegen: error: --request over ")  # the request made it impossible
    assert not out.exists()


@pytest.mark.parametrize(
    ("request_text", "named"), [("retrieve the mug sideways", "'sideways'"), ("mug not", "'not'")]
)
def test_bad_request_is_one_line(
    request_text: str, named: str, tmp_path: Path, capsys: pytest.CaptureFixture
):
    out = tmp_path / "never"
    assert main(["generate", str(REFERENCE), "--request", request_text, "--out", str(out)]) == USAGE_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("scenegen: error: --request:") and named in err[0]
    assert not out.exists()


def test_unknown_proposer_kind_lists_the_valid_ones(tmp_path: Path, capsys: pytest.CaptureFixture):
    with pytest.raises(SystemExit) as exit_info:
        main(["generate", str(REFERENCE), "--proposer", "magic", "--out", str(tmp_path / "never")])
    assert exit_info.value.code == USAGE_ERROR
    assert "choose from 'diffusion', 'procedural', 'targeted'" in capsys.readouterr().err
    with pytest.raises(
        ConfigError, match="--proposer magic: unknown kind; valid: procedural, targeted, diffusion"
    ):
        load_pipeline(REFERENCE, proposer="magic")


@pytest.mark.parametrize("listed", ["assets/catalog.yaml", "assets"])
def test_a_recipe_listing_the_bundled_catalog_is_refused_before_any_scene(
    listed: str, tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
):
    """The bundled catalog is always in use; listed among a recipe's ``catalogs`` its folder would be
    audited as a user catalog's (every other folder of assets/ a violation), so the recipe is refused."""
    import yaml

    from scenegen.paths import PROJECT_ROOT

    monkeypatch.chdir(PROJECT_ROOT)
    recipe = yaml.safe_load(Path(REFERENCE).read_text()) | {"catalogs": [listed]}
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(recipe))
    refused = f"catalogs: {listed} is the bundled catalog, always in use"
    with pytest.raises(ConfigError, match=refused) as caught:
        load_pipeline(path)
    assert str(caught.value).startswith(f"{path}: catalogs: ") and str(caught.value).count(str(path)) == 1
    assert "leave catalogs out" in str(caught.value)
    out = tmp_path / "never"
    assert main(["generate", str(path), "--out", str(out), "--quiet"]) == USAGE_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "always in use" in err[0] and not out.exists()
