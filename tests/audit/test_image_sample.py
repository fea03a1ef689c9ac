"""`scenegen audit --image-sample N`: a rendered batch of more than N scenes has its image check
judged on N scenes' images, drawn by a seed, by the rule the report states (audit/scenes.py,
``compare_image_sample``); every file's checksum is verified all the same."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

from scenegen.cli import main

TAMPERED = 1


@pytest.fixture
def batch(demo_batch: Path, tmp_path: Path) -> Path:
    """A private copy of the session's rendered demo batch (6 scenes)."""
    return Path(shutil.copytree(demo_batch, tmp_path / "batch"))


def audit(batch: Path, capsys, *flags: str) -> tuple[int, dict]:
    code = main(["audit", str(batch / "manifest.yaml"), "--json", *flags])
    return code, json.loads(capsys.readouterr().out)


def edit_image_check(batch: Path, edit) -> None:
    path = batch / "manifest.yaml"
    data = yaml.safe_load(path.read_text())
    (check,) = [c for c in data["sources"][0]["realism"] if c["metric"] == "image_stats"]
    edit(check)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def test_a_sample_of_the_scenes_passes_a_faithful_batch_and_states_its_rule(batch: Path, capsys):
    code, report = audit(batch, capsys, "--image-sample", "3", "--sample-seed", "5")
    assert code == 0, report["violations"]
    (rule,) = [line for line in report["verified"] if "seeded sample" in line]
    assert "sample of 3 of 6 scenes (seed 5; 6 of 12 images decoded)" in rule
    assert "standard errors of the sample's estimate" in rule and "Student t, 2 degrees" in rule
    code, report = audit(batch, capsys)  # the default sample holds the whole batch: exact, no rule
    assert code == 0 and not [line for line in report["verified"] if "seeded sample" in line]


def test_a_recorded_statistic_far_from_the_pixels_is_caught_by_the_sample(batch: Path, capsys):
    def shift(check):
        check["details"]["per_stat"]["luminance_mean"] += 5.0
        check["value"] = max(abs(v) for v in check["details"]["per_stat"].values())

    edit_image_check(batch, shift)
    code, report = audit(batch, capsys, "--image-sample", "5")
    assert code == TAMPERED
    (found,) = report["violations"]
    assert found["check"] == "realism" and "outside: luminance_mean" in found["message"], found


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda c: c.update(value=c["value"] + 0.5), "is not its largest |per_stat|"),
        (lambda c: c["samples"].update(images=13), "the batch's records give"),
        (lambda c: c.update(threshold=9.0), "threshold differs"),
    ],
)
def test_what_a_sample_can_check_exactly_is_checked_exactly(batch: Path, capsys, edit, says):
    edit_image_check(batch, edit)
    code, report = audit(batch, capsys, "--image-sample", "3")
    assert code == TAMPERED
    assert any(says in v["message"] for v in report["violations"]), report["violations"]


def test_a_sampled_audit_still_verifies_every_checksum(batch: Path, capsys):
    scene = sorted(p for p in batch.iterdir() if p.name.startswith("scene_"))[-1]
    (scene / "front_rgb.png").write_bytes((scene / "side_rgb.png").read_bytes())
    code, report = audit(batch, capsys, "--image-sample", "2")
    assert code == TAMPERED
    assert any(v["check"] == "checksum" and "front_rgb.png" in v["where"] for v in report["violations"])


@pytest.mark.parametrize("value", ["1", "0", "some"])
def test_a_sample_too_small_to_judge_is_refused_in_one_line(batch: Path, capsys, value):
    code = main(["audit", str(batch / "manifest.yaml"), "--image-sample", value])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--image-sample" in err and "'all'" in err and "\n" not in err


def test_unreadable_sampled_images_are_violations_not_a_crash(batch: Path, capsys):
    for image in batch.glob("scene_*/front_rgb.png"):
        image.write_bytes(b"not a png")
    code, report = audit(batch, capsys, "--image-sample", "3")
    assert code == TAMPERED
    checks = {v["check"] for v in report["violations"]}
    assert {"checksum", "realism"} <= checks
    assert any("not a readable image" in v["message"] for v in report["violations"])
