"""The real-data importer on tests/fixtures/real_example.json: tags recomputed at the measured poses,
rows in the reference layout, and every malformed variant refused with one line naming the record and
field."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from scenegen.assets.catalog import load_catalog
from scenegen.cli import main
from scenegen.core import layout
from scenegen.data.coverage import coverage_table
from scenegen.data.importer import ImportFormatError, import_real, measure_record, read_records
from scenegen.data.reference import file_sha256, layout_row
from scenegen.schema.condition import ROBOT_POSES, TAGS
from scenegen.settle.physics import SettleSettings, passive_test
from scenegen.sim import world
from scenegen.tags.predicates import PREDICATE_VERSION

EXAMPLE = Path(__file__).resolve().parents[1] / "fixtures" / "real_example.json"
MUG, SPOON, CAN = "kitchen_mug_at_edge", "kitchen_spoon_under_shelf", "kitchen_can_on_floor"


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    out = tmp_path_factory.mktemp("real") / "real.parquet"
    stats = import_real(EXAMPLE, out)
    table = pq.read_table(out)
    return stats, table, {row["id"]: row for row in table.to_pylist()}


def held(row: dict) -> set[str]:
    return {t for t in TAGS if row[f"tag_{t}"]}


def test_tags_are_recomputed_at_the_measured_poses(imported):
    _, _, rows = imported
    assert held(rows[MUG]) == {"near_edge"}
    # The mug (yawed 90 deg: its body is 8 cm wide along x) stands 4.5 cm from the front edge x = 0.4.
    assert rows[MUG]["value_near_edge"] == pytest.approx(0.4 - 0.345 - 0.04, abs=1e-3)
    assert held(rows[SPOON]) == {"under_overhang"}
    assert rows[SPOON]["value_under_overhang"] == 1.0  # entirely under the shelf board
    assert held(rows[CAN]) == {"on_floor"}
    assert rows[CAN]["value_on_floor"] == pytest.approx(layout.TABLE_TOP_Z - 0.05)
    # No record gives lighting but the mug's: the default is a well-lit room, never low_light.
    assert rows[SPOON]["value_low_light"] >= 0.25 and rows[CAN]["value_low_light"] >= 0.25


def test_moving_an_object_changes_its_tags(tmp_path):
    records = json.loads(EXAMPLE.read_text())[:1]
    records[0]["objects"][0]["position"][0] = 0.1  # the mug, off the edge
    (tmp_path / "moved.json").write_text(json.dumps(records))
    stats = import_real(tmp_path / "moved.json", tmp_path / "moved.parquet")
    assert stats["tags"]["near_edge"] == 0 and stats["tags"]["nominal"] == 1


def test_robot_pose_by_name_or_joint_angles(tmp_path):
    records = json.loads(EXAMPLE.read_text())[2:]
    records.append({**records[0], "id": "ready", "robot_pose": "ready"})
    records.append({**records[0], "id": "angles", "robot_pose": list(ROBOT_POSES["ready"])})
    (tmp_path / "poses.json").write_text(json.dumps(records))
    import_real(tmp_path / "poses.json", tmp_path / "poses.parquet")
    rows = pq.read_table(tmp_path / "poses.parquet").to_pylist()
    assert [held(r) for r in rows] == [{"on_floor"}] * 3


def test_rows_have_the_reference_layout_and_origin_real(imported):
    stats, table, rows = imported
    assert stats["rows"] == table.num_rows == 3 and stats["unsupported"] == []
    assert stats["tags"] == {t: sum(t in held(r) for r in rows.values()) for t in TAGS}
    assert table.column_names[:2] == ["origin", "id"]
    assert set(table.column("origin").to_pylist()) == {"real"}
    assert [r["id"] for r in table.to_pylist()] == [MUG, SPOON, CAN]  # file order
    assert table.column("index").to_pylist() == [0, 1, 2]
    record = read_records(EXAMPLE)[0]
    scene = measure_record(record, 0, load_catalog(), source=EXAMPLE.name)
    assert table.column_names[2:] == list(layout_row(scene))  # the columns of the reference table
    meta = {k.decode(): v.decode() for k, v in table.schema.metadata.items()}
    assert meta["predicate_version"] == PREDICATE_VERSION
    assert meta["source_sha256"] == file_sha256(EXAMPLE) and meta["scenegen.origin"] == "real"
    assert rows[MUG]["task"] == "retrieve" and rows[MUG]["target_category"] == "mug"
    assert rows[SPOON]["target_asset"] == "teaspoon" and rows[SPOON]["furniture"][0]["kind"] == "shelf"
    supports = {r["id"]: {o["name"]: o["support"] for o in r["objects"]} for r in rows.values()}
    assert supports[SPOON] == {"spoon": "table", "plate": "table", "fork": "plate"}  # fork lies on the plate
    assert supports[CAN] == {"can": "floor", "box": "bin", "mug": "table"}
    poses = {o["name"]: o["resting_pose"] for o in rows[MUG]["objects"]}
    assert poses["mug"] == load_catalog().get("mug").upright_pose()


def test_the_example_is_physically_plausible():
    """Measured poses are imported unsettled; the hand-written ones rest: 2 s of passive simulation
    moves no object more than 5 mm, and nothing penetrates more than 1 mm."""
    catalog = load_catalog()
    for i, record in enumerate(read_records(EXAMPLE)):
        scene = measure_record(record, i, catalog)
        model = world.build_world(catalog, scene.objects, scene.furniture, scene.lighting).compile()
        qpos, ctrl = world.initial_state(model, ROBOT_POSES["home"], scene.objects)
        results = passive_test(model, qpos, ctrl, SettleSettings())
        assert all(r.passed for r in results), (record.id, results)


def test_coverage_reads_the_real_table(imported):
    stats, _, _ = imported
    table = coverage_table(stats["out"])
    assert table.total == 3 and table.count("retrieve", "near_edge") == 1
    assert table.count("retrieve", "on_floor") == 1 and table.count("retrieve", "nominal") == 0


def _set(path: list, value):
    def edit(records):
        node = records
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return edit


def _drop(path: list):
    def edit(records):
        node = records
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]

    return edit


# name -> (edit of the example's records, text the one-line error must hold)
MALFORMED = {
    "missing field": (
        _drop([1, "objects", 0, "quat"]),
        f"record 1 (id '{SPOON}'): objects[0].quat: required",
    ),
    "missing id": (_drop([2, "id"]), "record 2: id: required field missing"),
    "unknown asset": (
        _set([1, "objects", 2, "asset"], "teapot"),
        f"record 1 (id '{SPOON}'): objects[2].asset: unknown asset 'teapot'; valid assets: bottle,",
    ),
    "NaN position": (
        _set([0, "objects", 0, "position", 2], math.nan),
        f"record 0 (id '{MUG}'): objects[0].position[2]: Input should be a finite number",
    ),
    "infinite yaw": (
        _set([1, "furniture", 0, "yaw"], math.inf),
        f"record 1 (id '{SPOON}'): furniture[0].yaw: Input should be a finite number",
    ),
    "number as text": (
        _set([0, "objects", 1, "position", 0], "0.1"),
        f"record 0 (id '{MUG}'): objects[1].position[0]: Input should be a valid number",
    ),
    "unknown task": (
        _set([2, "task"], "juggle"),
        f"record 2 (id '{CAN}'): task: unknown task 'juggle'; valid tasks: retrieve, upright, clear",
    ),
    "table size": (
        _set([1, "table", "size"], [1.2, 1.0]),
        f"record 1 (id '{SPOON}'): table.size: 1.2 x 1 m does not match the simulated table 0.8 x 1 m",
    ),
    "table height": (
        _set([0, "table", "top_z"], 0.75),
        f"record 0 (id '{MUG}'): table.top_z: 0.75 m does not match the simulated table top 0.8 m",
    ),
    "unknown field": (_set([0, "tags"], ["near_edge"]), f"record 0 (id '{MUG}'): tags: unknown field"),
    "target not an object": (
        _set([2, "target"], "cup"),
        f"record 2 (id '{CAN}'): target: 'cup' is not an object of this record",
    ),
    "duplicate id": (_set([2, "id"], MUG), f"record 2 (id '{MUG}'): id: duplicate of record 0"),
    "duplicate object": (
        _set([0, "objects", 1, "name"], "mug"),
        f"record 0 (id '{MUG}'): objects[1].name: duplicate object name 'mug'",
    ),
    "name of the world": (
        _set([0, "objects", 2, "name"], "table"),
        f"record 0 (id '{MUG}'): objects[2].name: 'table' is a body of the simulated table or robot",
    ),
    "not a unit quaternion": (
        _set([0, "objects", 0, "quat"], [1.0, 1.0, 0.0, 0.0]),
        f"record 0 (id '{MUG}'): objects[0].quat: not a unit quaternion (norm 1.414)",
    ),
    "record not an object": (_set([1], "mug"), "record 1: a record must be a JSON object"),
    "robot pose out of range": (
        _set([0, "robot_pose"], [0.0] * 7),
        f"record 0 (id '{MUG}'): robot_pose: joint 4 angle 0.0 rad is outside the Panda's range",
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_records_are_refused_with_one_line(tmp_path, case):
    edit, message = MALFORMED[case]
    records = json.loads(EXAMPLE.read_text())
    edit(records)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(records))  # json writes NaN and Infinity as Python reads them
    out = tmp_path / "new" / "real.parquet"
    with pytest.raises(ImportFormatError) as info:
        import_real(bad, out)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(f"{bad}: ") and message in text, text
    assert not out.exists() and not out.parent.exists()


@pytest.mark.parametrize(
    "text, message",
    [
        (
            '[{"id": "a",',
            "not valid JSON: Expecting property name enclosed in double quotes at line 1 column 13",
        ),
        ("", "not valid JSON: Expecting value at line 1 column 1"),
        ('{"id": "a"}', "the top level must be a list of records"),
        ("[]", "no records"),
    ],
)
def test_a_file_that_is_not_a_list_of_records_is_refused(tmp_path, text, message):
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    with pytest.raises(ImportFormatError, match=message) as info:
        import_real(bad, tmp_path / "real.parquet")
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == [bad]


def test_a_failed_import_leaves_an_earlier_output_alone(tmp_path):
    out = tmp_path / "real.parquet"
    out.write_bytes(b"earlier")
    (tmp_path / "bad.json").write_text("[1]")
    with pytest.raises(ImportFormatError):
        import_real(tmp_path / "bad.json", out)
    assert out.read_bytes() == b"earlier"


def test_main_prints_a_summary(tmp_path, capsys):
    records = json.loads(EXAMPLE.read_text())[2:]
    (tmp_path / "one.json").write_text(json.dumps(records))
    out = tmp_path / "one.parquet"
    assert main(["import-real", str(tmp_path / "one.json"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"1 real scenes from {tmp_path / 'one.json'} -> {out}" in text and "on_floor 1" in text
    assert pq.read_table(out).num_rows == 1


def test_main_on_a_bad_file_returns_2_with_one_line(tmp_path, capsys):
    (tmp_path / "bad.json").write_text("[1, 2")
    assert main(["import-real", str(tmp_path / "bad.json"), "--out", str(tmp_path / "x.parquet")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("scenegen: error: ") and err.count("\n") == 1 and "not valid JSON" in err
    assert not (tmp_path / "x.parquet").exists()


def test_example_poses_rest_on_the_catalog_heights():
    """The hand-written z of each object is its support's height plus its resting pose's height."""
    catalog = load_catalog()
    heights = {"table": layout.TABLE_TOP_Z, "floor": 0.0, "bin": layout.TABLE_TOP_Z + 0.01}
    for i, record in enumerate(read_records(EXAMPLE)):
        scene = measure_record(record, i, catalog)
        for obj in scene.objects:
            if obj.support in heights:
                rest = catalog.get(obj.asset).resting_poses[obj.resting_pose].height
                assert obj.position[2] == pytest.approx(heights[obj.support] + rest, abs=1e-5), obj.name
                assert obj.projection_distance == pytest.approx(0.0, abs=1e-5)
