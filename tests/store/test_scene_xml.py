"""scene.xml is written with stand-in meshes (store/batch.py, scene_xml): the same bytes as MuJoCo's
writer gives with the real mesh files, and the spec is left as it was."""

from __future__ import annotations

from itertools import islice
from pathlib import Path

import pytest

from scenegen.assets.catalog import load_catalog
from scenegen.propose.base import PROPOSERS
from scenegen.runner.config import load_pipeline
from scenegen.runner.pipeline import proposal_stream
from scenegen.settle.physics import free_bodies
from scenegen.sim import world
from scenegen.store.batch import scene_xml

PIPELINES = Path(__file__).resolve().parents[2] / "pipelines"


@pytest.mark.parametrize("recipe", ["demo.yaml", "procedural.yaml"])  # generator; shelves and bins
def test_stand_in_meshes_write_the_same_scene_xml(recipe: str):
    catalog = load_catalog()
    config = load_pipeline(PIPELINES / recipe, {"seed": 3})
    proposer = PROPOSERS[config.proposer.kind](config.proposer, catalog)
    for proposal in islice(proposal_stream(proposer, config, 0), 5):
        spec = world.build_world(
            catalog, proposal.objects, proposal.furniture, proposal.lighting, proposal.cameras
        )
        model = spec.compile()
        qpos, ctrl = world.initial_state(model, proposal.condition.robot_pose, proposal.objects)
        files = {mesh.name: mesh.file for mesh in spec.meshes}
        objects = dict(free_bodies(model))
        fast = scene_xml(spec, qpos, ctrl, objects)
        assert {mesh.name: mesh.file for mesh in spec.meshes} == files  # put back
        assert "stand_in" not in fast
        assert fast == scene_xml(spec, qpos, ctrl, objects, stand_ins=False)
