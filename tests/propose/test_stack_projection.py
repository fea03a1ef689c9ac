"""The stack projections (propose/stack_projection.py): a toppled bowl stacked on a soup can falls off
it in MuJoCo; the ``fell_off`` repair sets it on the free plate, the widest top in reach, where it
comes to rest holding both tags; the repair leaves alone what it cannot better."""

from __future__ import annotations

import pytest
from scenes import place, proposal

from scenegen.propose import project as proj
from scenegen.propose.procedural import DEFAULT_CAMERAS
from scenegen.runner.config import load_pipeline
from scenegen.runner.process import process_proposal
from scenegen.schema.condition import Condition
from scenegen.schema.scene import Rejection

ASKED = Condition(task="upright", target="bowl", tags={"toppled": "required", "stacked": "required"})


@pytest.fixture(scope="module")
def config():
    return load_pipeline("pipelines/procedural.yaml", {"render": False}, "upright the bowl toppled stacked")


@pytest.fixture(scope="module")
def on_the_can(config):
    """A bowl on its side (resting pose 0) on an upright soup can, a plate free beside them."""
    catalog = config.catalog()
    can = place(catalog, "can", "soup_can", -0.05, 0.12, pose=1)
    plate = place(catalog, "plate", "plate", -0.05, -0.2, pose=0)
    bowl = place(catalog, "bowl", "bowl", -0.05, 0.12, pose=0, support="can", below=[can])
    return proposal([bowl, can, plate], cameras=DEFAULT_CAMERAS).model_copy(update={"condition": ASKED})


def fell(target: str = "bowl", label: str = "fell_off") -> Rejection:
    return Rejection(proposal_index=0, stage="settle", label=label, check=label, value=0.02, detail=target)


def test_a_toppled_bowl_that_falls_off_a_can_rests_on_the_plate_it_is_moved_to(config, on_the_can):
    catalog = config.catalog()
    first = process_proposal(on_the_can, config, catalog, False)
    assert first.record is None and first.rejection.label in ("fell_off", "unstable"), first.rejection
    assert first.rejection.detail.split(";")[0] == "bowl"
    moved, names = proj.project(on_the_can, first.rejection, catalog)
    bowl = next(o for o in moved.objects if o.name == "bowl")
    assert names == ("bowl",) and bowl.support == "plate" and bowl.resting_pose == 0
    again = process_proposal(moved, config, catalog, False)
    assert again.record is not None, again.rejection
    assert again.record.tags["stacked"].holds and again.record.tags["toppled"].holds


def test_the_repair_moves_nothing_it_cannot_better(config, on_the_can):
    """None: another object fell, the stack is not asked for, or no free base is wider than the can."""
    catalog = config.catalog()
    assert proj.project(on_the_can, fell("plate"), catalog) is None
    unasked = on_the_can.model_copy(update={"condition": Condition(task="upright", target="bowl")})
    assert proj.project(unasked, fell(), catalog) is None
    no_plate = on_the_can.model_copy(update={"objects": on_the_can.objects[:2]})
    assert proj.project(no_plate, fell(label="unstable"), catalog) is None
    assert proj.project(on_the_can, fell(label="unstable"), catalog) is not None
