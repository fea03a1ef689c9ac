"""The procedural proposer (domain randomization; rejection sampling is the other baseline of rare-case
generation), run for real through check, settle and tag. Its most frequent tag is exercised here; the
others take minutes each (benchmarks/rare_case_yield.py runs them all and re-measures every stored
scene the same way)."""

from __future__ import annotations

import json
from pathlib import Path

from scenes import REFERENCE, stored_scenes
from scenes import generate_request as generate

from scenegen.assets.catalog import load_catalog
from scenegen.propose.base import PROPOSERS
from scenegen.runner.config import load_pipeline
from scenegen.store.batch import measure_stored_scene


def test_procedural_rejection_sampling_keeps_proposing_until_the_tag_holds(tmp_path: Path):
    out = tmp_path / "low_light"
    assert generate(out, "retrieve the mug low light", "procedural", max_proposals=400) == 0
    (scene,) = stored_scenes(out)
    assert measure_stored_scene(scene)["low_light"].holds
    labels = [json.loads(line)["label"] for line in (out / "rejections.jsonl").read_text().splitlines()]
    # Every proposal before the accepted one was rejected, most because the tag did not hold.
    index = json.loads((scene / "scene.json").read_text())["proposal_index"]
    assert len(labels) == index
    assert labels.count("condition_unmet") > len(labels) / 2


def test_procedural_proposals_are_a_pure_function_of_index_and_seed():
    """A proposal depends on (seed, index) only: not on which batch of indices asked for it."""
    config = load_pipeline(REFERENCE, request="retrieve the bowl")
    proposer = PROPOSERS["procedural"](config.proposer, load_catalog())
    batch = proposer.propose(config.condition, [0, 1, 2, 3], seed=7)
    assert proposer.propose(config.condition, [3], seed=7)[0] == batch[3]
    assert proposer.propose(config.condition, [3], seed=8)[0] != batch[3]
    assert len({p.model_dump_json() for p in batch}) == 4
    for proposal in batch:
        names = [o.name for o in proposal.objects]
        assert len(set(names)) == len(names) and proposal.target in names
        assert proposal.condition.target == "bowl"
