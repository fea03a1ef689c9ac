"""The predicate panel: every tag's output on a fixed set of settled reference scenes, pinned to
``tags.PREDICATE_VERSION``.

``tests/fixtures/predicate_panel.json`` holds, for each panel scene (a proposal index of the reference recipe,
pipelines/reference.yaml), the proposal, its settled state (qpos, ctrl) and every tag's measurement
(holds, value, threshold, unit), with the predicate version and the default TagSettings it was recorded
under. The test rebuilds each scene at its stored settled state (no proposer, no settling, so only the
predicates and what they measure are under test) and measures its tags again. An output that differs
while PREDICATE_VERSION is unchanged fails: bump the constant in scenegen/tags/predicates.py, then
re-record the panel. A bumped constant fails until the panel is re-recorded:

    PYTHONPATH=. MUJOCO_GL=egl .venv/bin/python tests/tags/test_predicate_panel.py

which re-runs the recipe's proposals for the panel indices through build, settle and tag (checking that
the stored state measures the same tags as ``pipeline.process_proposal``) and rewrites the JSON. The
panel is a tripwire, not a proof: a change whose effect no panel scene shows still needs a bump.

The panel is anchored to the committed reference set: while that set is stamped with the panel's
version, each scene's tags and settled object poses equal its row in assets/reference/reference.parquet.
"""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import pytest

from scenegen.assets.catalog import Catalog, load_catalog
from scenegen.data.reference import read_reference
from scenegen.schema.condition import TAGS
from scenegen.schema.scene import SceneProposal, TagValue
from scenegen.settle.physics import contact_configuration
from scenegen.sim import world
from scenegen.tags.predicates import PREDICATE_VERSION, TagSettings, scene_tags

REPO_ROOT = Path(__file__).resolve().parents[2]
PANEL_FILE = REPO_ROOT / "tests" / "fixtures" / "predicate_panel.json"
RECIPE = REPO_ROOT / "pipelines" / "reference.yaml"
REFERENCE = REPO_ROOT / "assets" / "reference" / "reference.parquet"
RECORD = "PYTHONPATH=. MUJOCO_GL=egl .venv/bin/python tests/tags/test_predicate_panel.py"

# Reference proposal indices and what each shows (at f571cb9bb73d1d5d). Every rare tag holds in at
# least two scenes; several sit within a hair of a threshold, on either side.
PANEL = {
    0: "nominal",
    9: "clutter at its threshold (3 objects)",
    265: "nominal, target on the shelf top",
    371: "near_edge just inside its threshold (0.029996 m), clutter",
    387: "nominal, under_overhang short of its threshold (0.3375)",
    830: "near_edge, toppled, occluded at its threshold (0.5); shelf and bin",
    1203: "under_overhang, toppled, low_light",
    1481: "toppled, on_floor",
    1858: "nominal, target in the bin",
    2055: "near_edge, occluded, stacked",
    2490: "nominal, near_edge just outside its threshold (0.030005 m)",
    2831: "low_light just below its threshold (0.2495)",
    3400: "clutter, stacked, low_light",
    3550: "nominal, occluded short of its threshold (0.479167)",
    6334: "under_overhang, stacked, low_light; shelf and bin",
    7076: "under_overhang near its threshold (0.569)",
    7453: "nominal, low_light just above its threshold (0.2531)",
    9094: "toppled, low_light, on_floor",
    10933: "low_light, target on the shelf top",
}


# ---------------------------------------------------------------- measuring a stored scene


def replay(proposal: SceneProposal, qpos, ctrl, catalog: Catalog) -> tuple[dict[str, TagValue], dict]:
    """Tags (default TagSettings) of ``proposal`` at the settled state (qpos, ctrl), measured as
    pipeline.process_proposal does, and each object's settled pose (position, wxyz quat) rounded to 6
    decimals as a reference row stores it."""
    spec = world.build_world(
        catalog, proposal.objects, proposal.furniture, proposal.lighting, proposal.cameras
    )
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:], data.ctrl[:] = qpos, ctrl
    mujoco.mj_forward(model, data)
    names = [o.name for o in proposal.objects]
    contacts = contact_configuration(model, data.qpos.copy(), names)
    poses = {}
    for name in names:
        adr = model.joint(f"{name}_joint").qposadr[0]
        poses[name] = [round(float(v), 6) for v in data.qpos[adr : adr + 7]]
    return scene_tags(model, data, catalog, proposal, contacts, TagSettings()), poses


def record(path: Path = PANEL_FILE) -> dict:
    """Re-run the reference recipe's proposals for the PANEL indices (check, build, settle, tag) and
    write their settled states and tags to ``path`` under today's PREDICATE_VERSION."""
    from scenegen.data.reference import request_for
    from scenegen.propose.base import PROPOSERS
    from scenegen.runner.config import load_pipeline
    from scenegen.runner.process import process_proposal
    from scenegen.settle.physics import settle

    config = load_pipeline(RECIPE, {"render": False})
    if config.tags != TagSettings():
        raise ValueError(f"{RECIPE} overrides tag thresholds; the panel records the defaults")
    catalog = load_catalog()
    proposer = PROPOSERS[config.proposer.kind](config.proposer, catalog)
    scenes = []
    for index in sorted(PANEL):
        proposal = proposer.propose(request_for(config, index, catalog.categories), [index], config.seed)[0]
        accepted = process_proposal(proposal, config, catalog, export=False).record
        if accepted is None:
            raise ValueError(f"reference proposal {index} is rejected today; choose another panel scene")
        model = world.build_world(
            catalog, proposal.objects, proposal.furniture, proposal.lighting, proposal.cameras
        ).compile()
        qpos0, ctrl = world.initial_state(model, proposal.condition.robot_pose, proposal.objects)
        settled = settle(model, proposal, qpos0, ctrl, config.settle, catalog)
        qpos, ctrl = [float(v) for v in settled.qpos], [float(v) for v in settled.ctrl]
        tags, _ = replay(proposal, qpos, ctrl, catalog)
        if tags != accepted.tags:
            raise RuntimeError(
                f"scene {index}: the replayed settled state measures other tags than the pipeline"
            )
        scenes.append(
            {
                "index": index,
                "shows": PANEL[index],
                "tags": {t: v.model_dump() for t, v in tags.items()},
                "proposal": proposal.model_dump(mode="json"),
                "qpos": qpos,
                "ctrl": ctrl,
            }
        )
    panel = {
        "predicate_version": PREDICATE_VERSION,
        "tag_settings": TagSettings().model_dump(),
        "recipe": "pipelines/reference.yaml",
        "scenes": scenes,
    }
    text = _dumps(panel)
    if json.loads(text) != panel:
        raise RuntimeError("the panel does not round-trip through JSON")
    path.write_text(text)
    return panel


def _dumps(panel: dict) -> str:
    """JSON with one line per tag (readable diffs) and the proposal and state each on one line."""
    one = json.dumps
    lines = ["{"]
    lines += [f"  {one(k)}: {one(v)}," for k, v in panel.items() if k != "scenes"]
    lines.append('  "scenes": [')
    for i, scene in enumerate(panel["scenes"]):
        tags = ",\n".join(f"      {one(t)}: {one(v)}" for t, v in scene["tags"].items())
        lines += [
            "    {",
            f'     "index": {one(scene["index"])}, "shows": {one(scene["shows"])},',
            f'     "tags": {{\n{tags}\n     }},',
            f'     "proposal": {one(scene["proposal"])},',
            f'     "qpos": {one(scene["qpos"])},',
            f'     "ctrl": {one(scene["ctrl"])}',
            "    }" + ("," if i < len(panel["scenes"]) - 1 else ""),
        ]
    lines += ["  ]", "}", ""]
    return "\n".join(lines)


# ---------------------------------------------------------------- tests


@pytest.fixture(scope="module")
def panel() -> dict:
    return json.loads(PANEL_FILE.read_text())


@pytest.fixture(scope="module")
def measured(panel) -> dict[int, tuple[dict[str, TagValue], dict]]:
    catalog = load_catalog()
    return {
        s["index"]: replay(SceneProposal.model_validate(s["proposal"]), s["qpos"], s["ctrl"], catalog)
        for s in panel["scenes"]
    }


def test_panel_covers_every_tag_both_ways(panel):
    assert sorted(s["index"] for s in panel["scenes"]) == sorted(PANEL), f"PANEL changed: {RECORD}"
    for tag in TAGS:
        held = [s["tags"][tag]["holds"] for s in panel["scenes"]]
        assert any(held) and not all(held), f"{tag} does not both hold and fail in the panel"


def test_predicates_reproduce_the_panel(panel, measured):
    recorded = panel["predicate_version"]
    if PREDICATE_VERSION != recorded:
        pytest.fail(
            f"PREDICATE_VERSION is {PREDICATE_VERSION}, the panel was recorded under {recorded}: "
            f"re-record tests/fixtures/predicate_panel.json ({RECORD})"
        )
    defaults = TagSettings().model_dump()
    changed = [
        f"default TagSettings.{k}: {v} -> {defaults.get(k)}"
        for k, v in panel["tag_settings"].items()
        if defaults.get(k) != v
    ] + [f"default TagSettings.{k}: new" for k in defaults.keys() - panel["tag_settings"].keys()]
    for scene in panel["scenes"]:
        tags, _ = measured[scene["index"]]
        for tag, was in scene["tags"].items():
            now = tags[tag].model_dump()
            if now != was:
                changed.append(f"scene {scene['index']} {tag}: {was} -> {now}")
    if changed:
        pytest.fail(
            f"predicate outputs changed under an unchanged PREDICATE_VERSION ({recorded}):\n  "
            + "\n  ".join(changed)
            + "\nBump PREDICATE_VERSION in scenegen/tags/predicates.py (a predicate's output or default "
            "threshold changed; if predicates.py did not change, the world, catalog or MuJoCo it "
            "measures did), then "
            f"re-record the panel ({RECORD}) and regenerate the data stamped with the old version.",
            pytrace=False,
        )


def test_panel_is_the_committed_reference(panel, measured):
    table, meta = read_reference(REFERENCE)
    if meta["predicate_version"] != panel["predicate_version"]:
        pytest.skip(
            f"reference stamped {meta['predicate_version']}, panel {panel['predicate_version']}: "
            "regenerate the reference set (tests/data/test_reference.py)"
        )
    rows = {r["index"]: r for r in table.to_pylist() if r["index"] in PANEL}
    for scene in panel["scenes"]:
        row = rows[scene["index"]]
        assert row["target"] == scene["proposal"]["target"], scene["index"]
        for tag in TAGS:
            stored = {"holds": row[f"tag_{tag}"], "value": row[f"value_{tag}"]}
            recorded = {k: scene["tags"][tag][k] for k in stored}
            assert recorded == stored, f"scene {scene['index']} {tag}"
        _, poses = measured[scene["index"]]
        assert poses == {o["name"]: [*o["position"], *o["quat"]] for o in row["objects"]}, scene["index"]


if __name__ == "__main__":
    written = record()
    print(f"{PANEL_FILE}: {len(written['scenes'])} scenes under {written['predicate_version']}")
