"""The diffusion proposer behind the pipeline: a tiny checkpoint trained here, proposals that depend
only on (request, seed, index), targets of the requested category, and a batch through the real
check, settle and tag stages."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

from scenegen.assets.catalog import load_catalog
from scenegen.cli import main
from scenegen.diffusion.train import TrainSettings, train
from scenegen.propose.base import PROPOSERS
from scenegen.runner.config import ConfigError, load_pipeline

REFERENCE = Path(__file__).resolve().parents[2] / "assets" / "reference" / "reference.parquet"


@pytest.fixture(scope="module")
def recipe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("diffusion")
    settings = TrainSettings(
        steps=60, batch_size=64, d_model=32, layers=2, heads=2, checkpoint_every=60, split="heldout"
    )
    train(REFERENCE, root / "ckpt", settings, progress=False)
    path = root / "recipe.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "name": "diffusion-test",
                "render": False,
                "condition": {"task": "retrieve", "target": "mug", "tags": {"near_edge": "required"}},
                "proposer": {
                    "kind": "diffusion",
                    "checkpoint": str(root / "ckpt"),
                    "guidance": 2.0,
                    "steps": 5,
                },
            }
        )
    )
    return path


def test_a_checkpoint_of_another_scene_encoding_is_refused(recipe: Path, tmp_path: Path):
    config = load_pipeline(recipe)
    old = tmp_path / "old"
    shutil.copytree(config.proposer.checkpoint, old)
    meta = json.loads((old / "config.json").read_text())
    meta["encoding"]["version"] = 1
    (old / "config.json").write_text(json.dumps(meta))
    settings = config.proposer.model_copy(update={"checkpoint": str(old)})  # model_copy: no validation
    with pytest.raises(ValueError, match="encoding v1.*retrain"):
        PROPOSERS["diffusion"](settings, load_catalog())
    recipe_old = tmp_path / "old.yaml"
    raw = yaml.safe_load(recipe.read_text())
    raw["proposer"]["checkpoint"] = str(old)
    recipe_old.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=r"proposer.checkpoint: .*encoding v1.*retrain"):
        load_pipeline(recipe_old)


def test_a_recipe_pinned_to_a_checkpoint_loads_only_that_checkpoint(recipe: Path, tmp_path: Path):
    """``checkpoint_sha256``: the recipe loads while the checkpoint's weights have that sha256, and is
    refused with a one-line error naming the key once they are replaced (a retrained checkpoint)."""
    from scenegen.store.batch import sha256_file

    raw = yaml.safe_load(recipe.read_text())
    ckpt = tmp_path / "ckpt"
    shutil.copytree(raw["proposer"]["checkpoint"], ckpt)
    raw["proposer"].update(checkpoint=str(ckpt), checkpoint_sha256=sha256_file(ckpt / "model.safetensors"))
    pinned = tmp_path / "pinned.yaml"
    pinned.write_text(yaml.safe_dump(raw))
    assert load_pipeline(pinned).proposer.checkpoint_sha256 == raw["proposer"]["checkpoint_sha256"]
    with open(ckpt / "model.safetensors", "ab") as f:
        f.write(b"\0")
    with pytest.raises(ConfigError, match=r"proposer: checkpoint_sha256: .*safetensors has sha256") as err:
        load_pipeline(pinned)
    assert "\n" not in str(err.value)


def test_proposals_depend_only_on_request_seed_and_index(recipe: Path):
    config = load_pipeline(recipe)
    proposer = PROPOSERS["diffusion"](config.proposer, load_catalog())
    batch = proposer.propose(config.condition, [0, 1, 2, 3], seed=7)
    again = proposer.propose(config.condition, [3, 2], seed=7)
    assert batch[3] == again[0] and batch[2] == again[1]
    walk = proposer.propose(config.condition, range(20), seed=7)  # groups of 8 sampled together
    fresh = PROPOSERS["diffusion"](config.proposer, load_catalog())
    assert fresh.propose(config.condition, [13, 9], seed=7) == [walk[13], walk[9]]
    assert fresh.propose(config.condition, [17], seed=7) == [walk[17]]
    assert batch[0] != batch[1]
    for p in batch:
        target = next(o for o in p.objects if o.name == p.target)
        assert target.category == "mug"


def test_a_batch_runs_through_the_pipeline(recipe: Path, tmp_path: Path):
    out = tmp_path / "batch"
    code = main(["generate", str(recipe), "--n", "1", "--max-proposals", "12", "--out", str(out), "--quiet"])
    assert code in (0, 1)  # a 60-step model may not reach an accepted scene with its tag in 12 tries
    scenes = list(out.glob("scene_*"))
    rejections = [json.loads(line) for line in (out / "rejections.jsonl").read_text().splitlines()]
    assert len(scenes) + len(rejections) == (
        12 if code == 1 else json.loads((scenes[0] / "scene.json").read_text())["proposal_index"] + 1
    )
    assert all(r["label"] for r in rejections)
    manifest = yaml.safe_load((out / "manifest.yaml").read_text())
    assert manifest["sources"][0]["generator"]["kind"] == "diffusion"


def test_missing_checkpoint_is_a_recipe_error(tmp_path: Path):
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump({"name": "x", "proposer": {"kind": "diffusion", "checkpoint": "nowhere"}}))
    with pytest.raises(ConfigError, match="proposer.checkpoint: nowhere: no checkpoint there"):
        load_pipeline(path)


def test_null_condition_samples_keep_their_own_target(recipe: Path):
    config = load_pipeline(recipe)
    settings = config.proposer.model_copy(update={"unconditional": True})
    proposer = PROPOSERS["diffusion"](settings, load_catalog())
    categories = set()
    for p in proposer.propose(config.condition, range(12), seed=0):
        target = next(o for o in p.objects if o.name == p.target)
        assert p.condition.target == target.category  # the record names the sample's own target
        assert p.condition.tags == config.condition.tags
        categories.add(target.category)
    assert len(categories) > 1  # not forced to the recipe's mug


def test_separation_only_moves_objects_apart(recipe: Path):
    config = load_pipeline(recipe)
    catalog = load_catalog()
    raw = PROPOSERS["diffusion"](config.proposer.model_copy(update={"separate": False}), catalog)
    pushed = PROPOSERS["diffusion"](config.proposer, catalog)
    for i in range(6):
        a, b = raw.decoded(config.condition, i, 0), pushed.decoded(config.condition, i, 0)
        assert [o.name for o in a.proposal.objects] == [o.name for o in b.proposal.objects]
        for before, after in zip(a.proposal.objects, b.proposal.objects, strict=True):
            moved = (
                (after.position[0] - before.position[0]) ** 2 + (after.position[1] - before.position[1]) ** 2
            ) ** 0.5
            assert after.position[2] == before.position[2]
            assert moved <= config.proposer.max_shift + 1e-6
            assert after.projection_distance >= before.projection_distance - 1e-9
        assert b.projection == tuple(o.projection_distance for o in b.proposal.objects)


def test_sweep_writes_its_table_plot_and_numbers(recipe: Path, tmp_path: Path):
    out = tmp_path / "sweep"
    args = ["sweep", str(recipe), "--proposals", "3", "--tags", "on_floor", "--weights", "0", "2"]
    assert main([*args, "--out", str(out), "--quiet"]) == 0
    result = json.loads((out / "sweep.json").read_text())
    cells = {c["cell"]: c for c in result["cells"]}
    assert list(cells) == ["null", "null +cost", "w=0", "w=0 +cost", "w=2", "w=2 +cost"]
    assert (
        set(result["targets"]) == {"on_floor"} and result["targets"]["on_floor"] in load_catalog().categories
    )
    for c in cells.values():
        assert c["proposals"] == 3  # one request per guided cell; the null cells as many proposals
        rejected = sum(c["rejections"].values()) * 3
        assert round(rejected) + c["accepted"] == 3
        passed = c["accepted"] + c["rejections"].get("condition_unmet", 0) * 3
        assert c["pass_rate"] == pytest.approx(passed / 3)
        assert c["cpu_s_per_proposal"] > 0 and c["proposals_per_s"] > 0
    for null in ("null", "null +cost"):
        assert cells[null]["adherence"] in (None, 1.0)  # nothing is required of the null condition
    assert set(cells["null"]["tag_rates"]) == set(cells["null"]["reference_rates"])
    table = (out / "sweep.md").read_text()
    summary, per_request = table.split("\n\naccepted / proposals (adherence) per request:\n\n")
    assert summary.startswith("| cell |") and summary.count("\n") == 1 + 6
    assert per_request.splitlines()[2].startswith("| retrieve ") and per_request.count("\n") == 2 + 1
    for c in cells.values():
        assert sum(r["accepted"] for r in c["requests"]) == c["accepted"]
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_sweep_needs_a_diffusion_recipe(capsys):
    procedural = Path(__file__).resolve().parents[2] / "pipelines" / "procedural.yaml"
    assert main(["sweep", str(procedural), "--quiet"]) == 2
    assert "the sweep needs kind: diffusion" in capsys.readouterr().err


def test_draw_spread_conditions_requests_without_required_tags(recipe: Path, tmp_path: Path):
    """``draw_spread``: refused (one line, naming the key) for a checkpoint trained without spread;
    with one, a request that requires no tag gets each proposal's spread from its own stream (the
    same whatever group it is sampled in, only bins the data holds), and it changes the samples; a
    request with a required tag leaves the spread null."""
    raw = yaml.safe_load(recipe.read_text())
    raw["proposer"]["draw_spread"] = True
    refused = tmp_path / "refused.yaml"
    refused.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match=r"draw_spread: .*--spread-bins") as err:
        load_pipeline(refused)
    assert "\n" not in str(err.value)
    config = load_pipeline(recipe)
    with pytest.raises(ValueError, match=r"draw_spread: .*--spread-bins"):  # settings made without validation
        PROPOSERS["diffusion"](config.proposer.model_copy(update={"draw_spread": True}), load_catalog())

    settings = TrainSettings(
        steps=40,
        batch_size=64,
        d_model=32,
        layers=2,
        heads=2,
        checkpoint_every=40,
        split="heldout",
        spread_bins=4,
    )
    train(REFERENCE, tmp_path / "spread", settings, progress=False)
    drawn = config.proposer.model_copy(update={"checkpoint": str(tmp_path / "spread"), "draw_spread": True})
    proposer = PROPOSERS["diffusion"](drawn, load_catalog())
    nominal = config.condition.model_copy(update={"tags": {}})
    group = proposer._conditions(nominal, range(8), seed=7).spread
    assert group is not None and group[3] == proposer._conditions(nominal, [3], seed=7).spread[0]
    counts = proposer.config["spread"]["counts"]
    assert all(counts[int(b)] > 0 for b in group) and len(set(group.tolist())) > 1
    assert proposer._conditions(config.condition, range(8), seed=7).spread is None  # near_edge required
    undrawn = PROPOSERS["diffusion"](drawn.model_copy(update={"draw_spread": False}), load_catalog())
    a, b = proposer.propose(nominal, range(4), seed=7), undrawn.propose(nominal, range(4), seed=7)
    assert a != b and proposer.propose(nominal, [2], seed=7) == [a[2]]
