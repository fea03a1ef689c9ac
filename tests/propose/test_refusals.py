"""Each refusal rule of ``propose/base.py`` ``impossible_request`` derived from the assets and the
predicates themselves, on settled scenes measured by the real predicates: a request is refused only
where no scene can hold it."""

from __future__ import annotations

import pytest

from scenegen.propose.base import impossible_request
from scenegen.runner.config import ConfigError, load_pipeline
from scenegen.runner.process import process_proposal
from scenegen.schema.condition import Condition


@pytest.fixture(scope="module")
def config():
    return load_pipeline("pipelines/procedural.yaml", {"render": False}, "retrieve the spoon")


def settled_tags(config, proposal):
    result = process_proposal(proposal, config, config.catalog(), False)
    assert result.record is not None, result.rejection
    return result.record.tags


def test_a_toppled_target_without_a_non_upright_pose_is_refused_and_never_toppled(config):
    """The spoon (every spoon asset) has only upright resting poses: settled in each, the toppled
    predicate never holds, and the request is refused; a mug, which has one, is not refused."""
    from scenegen.propose.procedural import ProceduralProposer

    catalog = config.catalog()
    assert impossible_request(
        Condition(task="retrieve", target="spoon", tags={"toppled": "required"}), catalog
    )
    assert not impossible_request(
        Condition(task="retrieve", target="mug", tags={"toppled": "required"}), catalog
    )
    proposer = ProceduralProposer(config.proposer, catalog)
    seen = set()
    for proposal in proposer.propose(config.condition, range(30), 0):
        target = next(o for o in proposal.objects if o.name == proposal.target)
        if (target.asset, target.resting_pose) in seen or target.support != "table":
            continue
        result = process_proposal(proposal, config, catalog, False)
        if result.record is None:
            continue
        seen.add((target.asset, target.resting_pose))
        assert not result.record.tags["toppled"].holds
    poses = {(a.name, i) for a in catalog.of_category("spoon") for i in range(len(a.resting_poses))}
    assert seen and seen <= poses


def test_near_edge_and_on_floor_together_are_refused_and_never_hold_together(config):
    """A target at the table's edge is not on the floor, and one moved to the floor strip is not
    near_edge (the predicate asks for a target on the table top), however close to the edge it lies."""
    from scenegen.core import layout
    from scenegen.propose.procedural import ProceduralProposer
    from scenegen.propose.tag_projection import edge_margin, near_edge, on_floor

    catalog = config.catalog()
    both = Condition(task="retrieve", target="mug", tags={"near_edge": "required", "on_floor": "required"})
    assert "near_edge and on_floor" in impossible_request(both, catalog)
    with pytest.raises(ConfigError, match="near_edge and on_floor"):
        load_pipeline("pipelines/procedural.yaml", {"render": False}, "retrieve the mug near edge on floor")
    mug = load_pipeline("pipelines/procedural.yaml", {"render": False}, "retrieve the mug")
    proposer = ProceduralProposer(mug.proposer, catalog)
    proposal = next(
        p
        for p in proposer.propose(mug.condition, range(40), 1)
        if next(o for o in p.objects if o.name == p.target).support == "table"
        and process_proposal(p, mug, catalog, False).record is not None
    )
    target = next(o for o in proposal.objects if o.name == proposal.target)
    edge, _ = near_edge(proposal, "required", edge_margin(catalog, target) + 0.01, 0.03, catalog)  # 2 cm past
    tags = settled_tags(mug, edge)
    assert tags["near_edge"].holds and not tags["on_floor"].holds
    floor, _ = on_floor(proposal, "required", 0.0, 0.3, catalog)
    target = next(o for o in floor.objects if o.name == floor.target)
    assert target.support == "floor" and layout.FLOOR.margin(target.position[:2]) >= 0
    tags = settled_tags(mug, floor)
    assert tags["on_floor"].holds and not tags["near_edge"].holds
