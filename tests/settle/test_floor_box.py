"""Issue 64 point 3: the floor as a box, as the table is one. Thin objects laid on robosuite's floor
plane keep turning (a knife at 0.2 rad/s after 2 s, over the 0.05 still limit); on the box they come
to rest. The plane stays what a recipe without ``floor: box`` gets, and a stored scene records its
floor, so the environment rebuilds the floor it settled on."""

from __future__ import annotations

import pytest

from scenegen.env.scenes import stored_scene
from scenegen.propose.base import PROPOSERS
from scenegen.runner.config import load_pipeline
from scenegen.runner.process import process_proposal
from scenegen.sim import world

COUNT = (
    8  # targeted proposals of a knife on the floor (session 57: 6 of 30 settle on the plane, 16 on the box)
)


def _outcomes(floor: str):
    config = load_pipeline(
        "pipelines/procedural.yaml",
        {"render": False, "floor": floor},
        request="retrieve the knife on floor",
        proposer="targeted",
    )
    catalog = config.catalog()
    proposals = PROPOSERS["targeted"](config.proposer, catalog).propose(config.condition, range(COUNT), 0)
    return config, [process_proposal(p, config, catalog, True) for p in proposals]


@pytest.fixture(scope="module")
def outcomes():
    return {floor: _outcomes(floor) for floor in world.FLOORS}


def test_knives_on_the_floor_come_to_rest_on_the_box(outcomes):
    labels = {
        f: [o.rejection.label if o.rejection else "accepted" for o in out] for f, (_, out) in outcomes.items()
    }
    plane, box = labels["plane"], labels["box"]
    assert box.count("accepted") >= plane.count("accepted") + 2, labels
    assert box.count("unstable") < plane.count("unstable"), labels
    assert {label for label in box if label not in plane} <= {"accepted"}, labels  # nothing new rejects


def test_a_knife_standing_on_its_edge_comes_to_rest_on_the_box():
    """A toppled knife touches a box along a line it rolled about (8 of 8 still turning after 2 s
    before the floor's rolling friction); on the box with it, as on the plane, most come to rest."""
    config = load_pipeline(
        "pipelines/procedural.yaml",
        {"render": False, "floor": "box"},
        request="upright the knife toppled on floor",
        proposer="targeted",
    )
    catalog = config.catalog()
    proposals = PROPOSERS["targeted"](config.proposer, catalog).propose(config.condition, range(4), 0)
    labels = [
        o.rejection.label if o.rejection else "accepted"
        for o in (process_proposal(p, config, catalog, True) for p in proposals)
    ]
    assert labels.count("accepted") >= 3, labels


def test_the_box_is_recorded_and_rebuilt(outcomes, tmp_path):
    """scene.json records ``floor: box`` beside the contact options (the plane's record is as before
    floors had a choice); scene.xml holds the box and a plane that touches nothing; the environment's
    scene of that record gets the box back."""
    (config, out), (_, plain) = outcomes["box"], outcomes["plane"]
    accepted = next(o for o in out if o.record is not None)
    assert accepted.record.contact_options == {
        **world.CONTACT_OPTIONS,
        "floor": "box",
        "floor_rolling_friction": world.FLOOR_ROLLING_FRICTION,
    }
    on_plane = next(o for o in plain if o.record is not None)
    assert on_plane.record.contact_options == world.CONTACT_OPTIONS
    assert config.model_dump()["floor"] == "box" and "floor" not in outcomes["plane"][0].model_dump()
    assert f'name="{world.FLOOR_BOX}"' in accepted.xml and world.FLOOR_BOX not in on_plane.xml
    spec = world.build_world(config.catalog(), accepted.record.objects, floor="box")
    compiled = spec.compile()
    floor_geom, plane = compiled.geom(world.FLOOR_BOX), compiled.geom("floor")
    assert floor_geom.size.tolist() == list(world.FLOOR_BOX_HALF) and plane.contype == plane.conaffinity == 0
    scene_dir = tmp_path / "scene_000000"
    scene_dir.mkdir()
    (scene_dir / "scene.json").write_text(accepted.record.model_dump_json())
    assert stored_scene(scene_dir).floor == "box"
    with pytest.raises(ValueError, match="floor 'tiles'"):
        world.build_world(config.catalog(), [], floor="tiles")


def _labels(request: str, overrides: dict, count: int) -> tuple[list[str], list]:
    config = load_pipeline("pipelines/procedural.yaml", {"render": False, **overrides}, request, "targeted")
    catalog = config.catalog()
    proposals = PROPOSERS["targeted"](config.proposer, catalog).propose(config.condition, range(count), 0)
    outcomes = [process_proposal(p, config, catalog, True) for p in proposals]
    return [o.rejection.label if o.rejection else "accepted" for o in outcomes], outcomes


def test_a_knife_toppled_on_the_table_rests_with_the_tables_rolling_friction(tmp_path):
    """On robosuite's table a toppled knife rolls about the line it touches (session 62: 1 of 12 targeted
    "near_edge toppled" knives accepted, 9 unstable); with ``table_rolling_friction: 0.005`` 9 of 12. The
    record holds the value and the environment's scene of it rebuilds the table with it."""
    request = "upright the knife near_edge toppled"
    before, _ = _labels(request, {}, 8)
    after, outcomes = _labels(request, {"table_rolling_friction": 0.005}, 8)
    assert after.count("accepted") >= before.count("accepted") + 3, (before, after)
    assert after.count("unstable") < before.count("unstable"), (before, after)
    record = next(o.record for o in outcomes if o.record is not None)
    assert record.contact_options == {**world.CONTACT_OPTIONS, "table_rolling_friction": 0.005}
    scene_dir = tmp_path / "scene_000000"
    scene_dir.mkdir()
    (scene_dir / "scene.json").write_text(record.model_dump_json())
    scene = stored_scene(scene_dir)
    assert scene.table_rolling_friction == 0.005
    catalog = load_pipeline("pipelines/procedural.yaml").catalog()
    spec = world.build_world(catalog, scene.objects, table_rolling_friction=scene.table_rolling_friction)
    table = spec.compile().geom("table_collision")
    assert table.condim == 6 and table.friction[2] == pytest.approx(0.005)
