"""`scenegen audit` against tampering: each tamper is detected, named and located, with exit code 1.

A clean batch (the session's rendered demo batch, copied) and a clean project manifest (a copy of the
reference set and the shipped checkpoint in a temporary project folder) pass; then one thing at a time
is broken the way a careless hand or a bad copy would break it.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
import yaml

from scenegen.audit.manifest import audit
from scenegen.cli import main
from scenegen.data.project_manifest import project_manifest
from scenegen.manifest import read_manifest
from scenegen.manifest.schema import Manifest
from scenegen.paths import PROJECT_ROOT

TAMPERED = 1


def run_audit(path: Path, capsys) -> tuple[int, dict]:
    code = main(["audit", str(path), "--json"])
    return code, json.loads(capsys.readouterr().out)


def scene_ids(batch: Path) -> list[str]:
    return [json.loads(line)["scene_id"] for line in (batch / "index.jsonl").read_text().splitlines()]


def violations(report: dict, check: str) -> list[dict]:
    return [v for v in report["violations"] if v["check"] == check]


def edit_yaml(path: Path, edit) -> None:
    data = yaml.safe_load(path.read_text())
    edit(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


@pytest.fixture
def batch(demo_batch: Path, tmp_path: Path) -> Path:
    """A private copy of the session's rendered demo batch (6 scenes)."""
    return Path(shutil.copytree(demo_batch, tmp_path / "batch"))


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """A project folder with its own manifest: the reference set and a copy of the shipped checkpoint
    (named by an absolute path, so that replacing it cannot touch assets/)."""
    root = tmp_path / "project"
    (root / "assets" / "reference").mkdir(parents=True)
    (root / "pipelines").mkdir()
    shutil.copy(PROJECT_ROOT / "assets/reference/reference.parquet", root / "assets/reference")
    shutil.copy(PROJECT_ROOT / "pipelines/reference.yaml", root / "pipelines")
    manifest = project_manifest(read_manifest(PROJECT_ROOT / "data_manifest.yaml"))
    # the transfer outcome's artifact, which the audit rehashes (its location is relative)
    artifact = manifest.transfer.artifact
    shutil.copytree(PROJECT_ROOT / artifact, root / artifact)
    checkpoint = Path(shutil.copytree(PROJECT_ROOT / "assets/generator", tmp_path / "generator"))
    data = manifest.model_dump(mode="json", exclude_none=True)
    data["models"][0]["checkpoint"]["path"] = str(checkpoint)
    (root / "data_manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return root / "data_manifest.yaml"


def test_the_clean_batch_and_project_pass(batch: Path, project: Path, capsys):
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == 0 and report["ok"], report["violations"]
    assert {c.metric for c in read_manifest(batch / "manifest.yaml").sources[0].realism} == {
        "layout_c2st",
        "layout_mmd",
        "image_stats",
    }
    code, report = run_audit(project, capsys)
    assert code == 0 and report["ok"], report["violations"]


def test_an_edited_transfer_artifact_fails_its_checksum(project: Path, capsys):
    """The committed transfer outcome names its artifact's sha256: one changed episode record fails."""
    artifact = project.parent / read_manifest(project).transfer.artifact
    episodes = sorted((artifact / "episodes").rglob("*.jsonl"))[0]
    edited = episodes.read_text().replace('"success": true', '"success": false', 1)
    assert edited != episodes.read_text()
    episodes.write_text(edited)
    code, report = run_audit(project, capsys)
    assert code == TAMPERED
    assert [v["where"] for v in report["violations"]] == ["transfer"], report["violations"]


def test_the_committed_project_manifest_passes_and_is_derived_from_the_files(capsys):
    code, report = run_audit(PROJECT_ROOT / "data_manifest.yaml", capsys)
    assert code == 0, report["violations"]
    committed = read_manifest(PROJECT_ROOT / "data_manifest.yaml")
    assert committed == project_manifest(committed), "rerun: scenegen manifest refresh"


# ---------------------------------------------------------------- tampered batches


def test_a_deleted_scene(batch: Path, capsys):
    scene = scene_ids(batch)[1]
    shutil.rmtree(batch / scene)
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    (missing,) = violations(report, "missing_scene")
    assert missing["where"].endswith(scene)
    assert any("counts.scenes 6, 5 scene directories" in v["message"] for v in violations(report, "count"))


def test_one_flipped_byte_in_an_image(batch: Path, capsys):
    scene = scene_ids(batch)[1]
    image = batch / scene / "front_rgb.png"
    data = bytearray(image.read_bytes())
    data[len(data) // 2] ^= 0x01
    image.write_bytes(bytes(data))
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    (bad,) = violations(report, "checksum")
    assert bad["where"].endswith(f"{scene}/front_rgb.png")


def test_an_edited_count(batch: Path, capsys):
    def edit(data):
        counts = data["sources"][0]["counts"]
        counts["scenes"] += 1
        counts["proposals"] += 1  # keep the manifest self-consistent: only the files can tell

    edit_yaml(batch / "manifest.yaml", edit)
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    messages = [v["message"] for v in violations(report, "count")]
    assert any("counts.scenes 7, 6 scene directories" in m for m in messages), messages


def test_a_removed_realism_check(batch: Path, capsys):
    edit_yaml(batch / "manifest.yaml", lambda d: d["sources"][0]["realism"].pop(0))
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    (bad,) = violations(report, "realism")
    assert "layout_c2st is missing" in bad["message"] and bad["where"].startswith("sources[0]")


def test_a_realism_check_copied_from_another_batch(batch: Path, tmp_path: Path, capsys):
    other = tmp_path / "other"
    assert main(["generate", str(PROJECT_ROOT / "pipelines/procedural.yaml"), "--n", "2", "--seed", "5",
                 "--out", str(other), "--no-render", "--quiet"]) == 0  # fmt: skip
    capsys.readouterr()
    theirs = yaml.safe_load((other / "manifest.yaml").read_text())["sources"][0]["realism"]

    def edit(data):
        ours = data["sources"][0]["realism"]
        ours[:2] = theirs  # layout_c2st and layout_mmd of the other batch

    edit_yaml(batch / "manifest.yaml", edit)
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    copied = [v for v in violations(report, "realism") if "computed on another batch" in v["message"]]
    assert {v["where"].split()[-1] for v in copied} == {"layout_c2st", "layout_mmd"}


def test_a_source_pointing_at_a_missing_folder(batch: Path, capsys):
    edit_yaml(batch / "manifest.yaml", lambda d: d["sources"][0].update(location="gone"))
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    (bad,) = violations(report, "location")
    assert "gone does not exist" in bad["message"]
    edit_yaml(batch / "manifest.yaml", lambda d: d["sources"][0].update(location="../../etc"))
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED and "lies outside" in violations(report, "location")[0]["message"]


def test_a_predicate_version_mismatch(batch: Path, capsys):
    edit_yaml(batch / "manifest.yaml", lambda d: d["sources"][0].update(predicate_version="0123456789abcdef"))
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    bad = violations(report, "predicate_version")
    assert any("this scenegen's are" in v["message"] for v in bad)  # against the code
    assert any(v["where"].endswith("scene.json") for v in bad)  # against every scene


# ---------------------------------------------------------------- tampered project manifests


@pytest.mark.parametrize("alpha", [-0.5, float("nan"), "much"])
def test_an_invalid_alpha(project: Path, capsys, alpha):
    edit_yaml(project, lambda d: d["recipes"][0].update(alpha=alpha))
    code, report = run_audit(project, capsys)
    assert code == TAMPERED
    assert any(v["where"] == "recipes[0].alpha" for v in violations(report, "schema")), report


def test_an_alpha_that_disagrees_with_its_shares(project: Path, capsys):
    def edit(data):
        data["recipes"][0]["components"].append({"source": "reference", "role": "synthetic"})
        data["recipes"][0]["alpha"] = 0.5  # reference cannot feed the synthetic term; shares unchanged

    edit_yaml(project, edit)
    code, report = run_audit(project, capsys)
    assert code == TAMPERED
    assert any("cannot feed the synthetic term" in v["message"] for v in violations(report, "recipe"))


def test_a_replaced_checkpoint_file(project: Path, capsys):
    path = Path(yaml.safe_load(project.read_text())["models"][0]["checkpoint"]["path"])
    weights = bytearray((path / "model.safetensors").read_bytes())
    weights[-1] ^= 0xFF
    (path / "model.safetensors").write_bytes(bytes(weights))
    code, report = run_audit(project, capsys)
    assert code == TAMPERED
    (bad,) = violations(report, "provenance")
    assert bad["where"].startswith("models[0] generator") and bad["where"].endswith("model.safetensors")


def test_a_reference_table_edited_behind_the_manifest(project: Path, capsys):
    def edit(data):
        counts = data["sources"][0]["counts"]
        counts.update(scenes=counts["scenes"] - 1, proposals=counts["proposals"] - 1)
        counts["splits"]["train"] -= 1

    edit_yaml(project, edit)
    code, report = run_audit(project, capsys)
    assert code == TAMPERED
    assert any("the table has 10000 rows" in v["message"] for v in violations(report, "count"))


def test_every_violation_is_reported_not_just_the_first(batch: Path, capsys):
    first, second = scene_ids(batch)[:2]
    shutil.rmtree(batch / first)
    image = batch / second / "side_rgb.png"
    image.write_bytes(image.read_bytes()[:-1] + b"\x00")
    edit_yaml(batch / "manifest.yaml", lambda d: d["sources"][0]["realism"].pop())
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    assert {"missing_scene", "checksum", "realism"} <= {v["check"] for v in report["violations"]}
    text = audit(batch / "manifest.yaml").to_text()
    assert "FAILED" in text and f"{second}/side_rgb.png" in text


def test_an_unreadable_manifest_is_a_usage_error(tmp_path: Path, capsys):
    assert main(["audit", str(tmp_path / "none.yaml")]) == 2
    assert "no such manifest" in capsys.readouterr().err
    (tmp_path / "bad.yaml").write_text("schema_version: 1\nkind: batch\n")
    code, report = run_audit(tmp_path / "bad.yaml", capsys)
    assert code == TAMPERED and "schema_version 1" in report["violations"][0]["message"]


# ---------------------------------------------------------------- manifest add


def test_manifest_add_merges_an_audited_batch(project: Path, demo_batch: Path, capsys):
    batch = Path(shutil.copytree(demo_batch, project.parent / "runs" / "demo"))
    assert main(["manifest", "add", str(batch), "--to", str(project), "--name", "demo"]) == 0
    merged = read_manifest(project)
    source = next(s for s in merged.sources if s.name == "demo")
    assert source.location == "runs/demo" and source.counts.scenes == 6
    capsys.readouterr()
    code, report = run_audit(project, capsys)
    assert code == 0, report["violations"]
    # the same name again is refused, and nothing is written
    before = project.read_bytes()
    assert main(["manifest", "add", str(batch), "--to", str(project), "--name", "demo"]) == 2
    assert "already named 'demo'" in capsys.readouterr().err and project.read_bytes() == before


def test_manifest_add_refuses_a_tampered_batch_and_a_batch_outside(project: Path, batch: Path, capsys):
    before = project.read_bytes()
    assert main(["manifest", "add", str(batch), "--to", str(project)]) == 2  # outside the project
    assert "outside" in capsys.readouterr().err and project.read_bytes() == before
    inside = Path(shutil.copytree(batch, project.parent / "runs" / "b"))
    (inside / scene_ids(inside)[0] / "scene.xml").write_text("<mujoco/>")
    assert main(["manifest", "add", str(inside), "--to", str(project)]) == 2
    assert "fails its audit" in capsys.readouterr().err and project.read_bytes() == before


def test_the_json_schema_in_docs_is_current():
    committed = json.loads((PROJECT_ROOT / "docs" / "manifest.schema.json").read_text())
    assert committed == Manifest.model_json_schema(), "rerun: scenegen manifest refresh"


# ---------------------------------------------------------------- a careful forger


def rechain(batch: Path) -> None:
    """Make the checksum chain consistent again after an edit: index rows' scene.json hashes, the
    manifest's file hashes and root, and every realism check's batch_sha256."""
    from scenegen.manifest.derive import batch_checksum

    rows = [json.loads(line) for line in (batch / "index.jsonl").read_text().splitlines()]
    for row in rows:
        text = (batch / row["scene_id"] / "scene.json").read_bytes()
        row["scene_json_sha256"] = hashlib.sha256(text).hexdigest()
    (batch / "index.jsonl").write_text("".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))
    sums = batch_checksum(batch)

    def edit(data):
        source = data["sources"][0]
        source["checksums"] = sums.model_dump(mode="json")
        for check in source["realism"]:
            check["batch_sha256"] = sums.root

    edit_yaml(batch / "manifest.yaml", edit)


def test_a_rechained_edit_of_a_scene_is_caught_by_recomputing(batch: Path, capsys):
    for scene in scene_ids(batch):  # every object 30 cm to the side, in every record
        path = batch / scene / "scene.json"
        record = json.loads(path.read_text())
        for obj in record["objects"]:
            obj["position"][1] += 0.3
        path.write_text(json.dumps(record, indent=1) + "\n")
    rechain(batch)
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    assert not violations(report, "checksum"), "the chain itself is consistent"
    recomputed = [v for v in violations(report, "realism") if "recomputed from the files" in v["message"]]
    assert "layout_mmd" in {v["where"].split()[-1] for v in recomputed}  # 6 scenes: C2ST may tie


@pytest.mark.parametrize(
    "field, value",
    [("threshold", 0.95), ("min_samples", 1000), ("value", 0.5)],
)
def test_a_hand_edited_realism_field_is_caught(batch: Path, capsys, field, value):
    def edit(data):
        check = data["sources"][0]["realism"][0]
        check[field] = value
        if field == "min_samples":
            check["status"] = "insufficient"

    edit_yaml(batch / "manifest.yaml", edit)
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED, report


def test_hiding_a_check_by_saying_not_rendered_is_caught(batch: Path, capsys):
    def edit(data):
        source = data["sources"][0]
        source["rendered"] = False
        source["realism"] = [c for c in source["realism"] if c["metric"] != "image_stats"]

    edit_yaml(batch / "manifest.yaml", edit)
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    assert any(v["where"].endswith(".rendered") for v in violations(report, "provenance"))


def test_malformed_logs_and_stray_files_are_violations_not_tracebacks(batch: Path, capsys):
    (batch / scene_ids(batch)[0] / "notes.txt").write_text("left here")
    with open(batch / "index.jsonl", "a") as f:
        f.write('5\n{"scene_id": ["x"], "proposal_index": 99}\n')
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    assert violations(report, "count") and not violations(report, "unreadable")
    (batch / "rejections.jsonl").write_bytes(b"\xff\xfe not utf-8\n")
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED and any("rejections.jsonl" in v["where"] for v in report["violations"])


def test_an_unlisted_file_in_a_scene_is_named(batch: Path, capsys):
    stray = batch / scene_ids(batch)[0] / "extra_rgb.png"
    stray.write_bytes(b"not listed")
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    (bad,) = violations(report, "unlisted_file")
    assert bad["where"].endswith("extra_rgb.png")


def test_a_batch_added_twice_counts_twice_and_is_refused_by_the_audit(
    project: Path, demo_batch: Path, capsys
):
    batch = Path(shutil.copytree(demo_batch, project.parent / "runs" / "demo"))
    assert main(["manifest", "add", str(batch), "--to", str(project), "--name", "one"]) == 0
    assert main(["manifest", "add", str(batch), "--to", str(project), "--name", "two"]) == 0
    capsys.readouterr()
    code, report = run_audit(project, capsys)
    assert code == TAMPERED
    (dup,) = violations(report, "duplicate")
    assert dup["where"].endswith("two")


# ---------------------------------------------------------------- entries nobody lists


def test_a_scene_folder_copied_under_another_name_is_named(batch: Path, capsys):
    shutil.copytree(batch / scene_ids(batch)[0], batch / "backup_scene")
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    (bad,) = report["violations"]  # named once, as a folder, not file by file
    assert bad["check"] == "unlisted_file" and bad["where"].endswith(": backup_scene"), bad


@pytest.mark.parametrize("name", ["notes.txt", ".DS_Store"])
def test_a_stray_file_at_the_top_of_a_batch_is_named(batch: Path, capsys, name):
    (batch / name).write_bytes(b"left here")
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == TAMPERED
    (bad,) = report["violations"]
    assert bad["check"] == "unlisted_file" and bad["where"].endswith(f": {name}"), bad


def test_the_views_scenegen_writes_into_a_batch_audit_clean(batch: Path, capsys):
    """`scenegen show` and `scenegen coverage` write contact_sheet.png and coverage.png into the batch
    by default (`make demo` shows, then audits): they are not stray files."""
    assert main(["show", str(batch)]) == 0 and main(["coverage", str(batch)]) == 0
    assert (batch / "contact_sheet.png").is_file() and (batch / "coverage.png").is_file()
    capsys.readouterr()
    code, report = run_audit(batch / "manifest.yaml", capsys)
    assert code == 0 and report["ok"], report["violations"]


def test_two_workers_report_what_one_does(batch: Path, capsys):
    """The per-scene checks in a pool of two processes: the same findings, in the same order."""
    scene = scene_ids(batch)[2]
    (batch / scene / "side_depth.png").write_bytes(b"not the depth image")
    (batch / scene_ids(batch)[4] / "front_seg.png").unlink()
    reports = []
    for workers in ("1", "2"):
        assert main(["audit", str(batch / "manifest.yaml"), "--json", "--workers", workers]) == TAMPERED
        reports.append(json.loads(capsys.readouterr().out))
    assert reports[0]["violations"] == reports[1]["violations"]
    assert {v["check"] for v in reports[0]["violations"]} >= {"checksum", "missing_file"}
