"""The shipped generator (assets/generator) as a user meets it: trained on the committed reference
set under the current predicates and catalog, and the default recipe (pipelines/demo.yaml) runs on it
end to end through the real checks, MuJoCo settling and tagging."""

from __future__ import annotations

import json
from pathlib import Path

from scenegen.assets.catalog import load_catalog
from scenegen.check.geometry import run_checks
from scenegen.cli import main
from scenegen.diffusion.encoding import ENCODING_VERSION
from scenegen.propose.base import PROPOSERS
from scenegen.runner.config import load_pipeline
from scenegen.store.batch import sha256_file
from scenegen.tags.predicates import PREDICATE_VERSION

ROOT = Path(__file__).resolve().parents[2]
GENERATOR = ROOT / "assets" / "generator"


def test_the_shipped_checkpoint_matches_the_committed_data_predicates_and_catalog():
    config = json.loads((GENERATOR / "config.json").read_text())
    assert config["data"]["sha256"] == sha256_file(ROOT / config["data"]["path"])
    assert config["predicate_version"] == PREDICATE_VERSION
    assert config["catalog_sha256"] == load_catalog().sha256
    assert config["encoding"]["version"] == ENCODING_VERSION
    assert config["step"] == config["train"]["steps"]  # a finished run, not a snapshot
    assert not (GENERATOR / "train_state.safetensors").exists()  # optimizer state is not shipped
    assert (GENERATOR / "model.safetensors").stat().st_size < 8 * 2**20


def test_the_demo_recipe_uses_the_diffusion_generator_and_its_scenes_hold():
    config = load_pipeline(ROOT / "pipelines" / "demo.yaml")
    assert config.proposer.kind == "diffusion"
    catalog = load_catalog()
    proposer = PROPOSERS["diffusion"](config.proposer, catalog)
    proposals = proposer.propose(config.condition, range(16), config.seed)
    passed = sum(run_checks(p, catalog, config.checks)[1] for p in proposals)
    assert all(next(o for o in p.objects if o.name == p.target).category == "spoon" for p in proposals)
    assert passed >= 10, passed  # 16 of 16 on the shipped checkpoint when this test was written


def test_generate_runs_the_demo_recipe_out_of_the_box(tmp_path: Path):
    out = tmp_path / "demo"
    code = main(
        [
            "generate",
            str(ROOT / "pipelines" / "demo.yaml"),
            "--n",
            "2",
            "--no-render",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert code == 0
    scenes = sorted(out.glob("scene_*/scene.json"))
    assert len(scenes) == 2
    for path in scenes:
        record = json.loads(path.read_text())
        assert record["generator"]["kind"] == "diffusion"
        assert record["condition"]["target"] == "spoon"


def test_the_transfer_experiments_generator_is_pinned_to_the_settings_it_was_made_with():
    """pipelines/transfer_v1.yaml's D arm reads pipelines/transfer_generator.yaml: the shipped checkpoint
    pinned by its sha256 (the manifest's), every setting added since at its default (left out of the
    recipe's dump, so its scenes are those of before), while the demo recipe has the v2 settings on."""
    import yaml

    from scenegen.experiment.transfer_config import load_transfer_config
    from scenegen.propose.diffusion import DiffusionSettings

    transfer = load_transfer_config(ROOT / "pipelines" / "transfer_v1.yaml")
    pinned = load_pipeline(ROOT / transfer.generation.diffusion).proposer
    manifest = yaml.safe_load((ROOT / "data_manifest.yaml").read_text())
    model = next(m for m in manifest["models"] if m["name"] == "generator")
    assert pinned.checkpoint == model["checkpoint"]["path"]
    weights = sha256_file(GENERATOR / "model.safetensors")
    assert pinned.checkpoint_sha256 == model["checkpoint"]["sha256"] == weights
    added = set(DiffusionSettings.OMITTED_AT) - {"assets", "checkpoint_sha256"}
    assert all(getattr(pinned, key) == DiffusionSettings.OMITTED_AT[key] for key in added)
    demo = load_pipeline(ROOT / "pipelines" / "demo.yaml").proposer
    assert demo.spacing and demo.upright_off_table and demo.soft_occluded and demo.arm_clearance


def test_transfer_version_2s_generator_is_the_demo_recipes_pinned_by_its_checkpoint():
    """pipelines/transfer.yaml (version 2) reads pipelines/transfer_generator_v2.yaml: the demo
    recipe's proposer as declared (the cost terms of issue 35 on), with the shipped checkpoint's
    sha256, so that a later generator cannot change D's scenes under the declared run."""
    from scenegen.experiment.transfer_config import load_transfer_config

    transfer = load_transfer_config(ROOT / "pipelines" / "transfer.yaml")
    assert transfer.version == 2 and transfer.side == "test"
    pinned = load_pipeline(ROOT / transfer.generation.diffusion).proposer
    assert pinned.checkpoint_sha256 == sha256_file(GENERATOR / "model.safetensors")
    assert pinned.spacing and pinned.upright_off_table and pinned.soft_occluded and pinned.arm_clearance
