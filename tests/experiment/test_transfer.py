"""The transfer experiment end to end at its tiny size (tests/fixtures/transfer_tiny.yaml: two tags, two
primitives, a few layouts, real labelling, training and closed-loop evaluation), its outcome in a
manifest that audits clean, a resumed run equal to an uninterrupted one; and its parts: the reference
sets, the arms' mixtures, the bootstrap, the configuration's errors and the artifact checksum."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scenegen.audit.manifest import audit
from scenegen.cli import main
from scenegen.core.files import folder_sha256, load_rows
from scenegen.data.project_manifest import DATASHEET, TRANSFER
from scenegen.env.mixture import scene_weights
from scenegen.experiment.transfer import arm_data, rare, run_transfer
from scenegen.experiment.transfer_config import TransferConfigError, load_transfer_config
from scenegen.experiment.transfer_sources import choose_reference_sets
from scenegen.experiment.transfer_stats import difference, interval
from scenegen.manifest.io import read_manifest, write_manifest
from scenegen.manifest.schema import Manifest
from scenegen.paths import PROJECT_ROOT
from scenegen.policy.panels import PANEL_TAGS

TINY = PROJECT_ROOT / "tests" / "fixtures" / "transfer_tiny.yaml"
REFERENCE = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"


def tiny_config(root: Path, shared: Path):
    """The tiny configuration writing into ``root``; the label and sequence stores (caches keyed by
    content, as a real run shares them between runs) in ``shared``."""
    root.mkdir(parents=True, exist_ok=True)
    manifest = root / "data_manifest.yaml"
    if not manifest.exists():
        write_manifest(manifest, Manifest(kind="project", datasheet=DATASHEET, transfer=TRANSFER))
    return load_transfer_config(
        TINY,
        {
            "label_store": str(shared / "labels.parquet"),
            "path_store": str(shared / "paths.jsonl"),
            "cache": str(root / "cache"),
            "batches": str(root / "batches"),  # D's and E's scenes beside the cache (committed in a real run)
            "out": str(root / "result"),
            "manifest": str(manifest),
        },
    )


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> tuple:
    base = tmp_path_factory.mktemp("transfer")
    config = tiny_config(base / "whole", base / "shared")
    return config, run_transfer(config, progress=False), base


def stable(metrics: dict) -> dict:
    """The metrics a rerun must reproduce: everything but measured CPU-seconds."""
    return {k: v for k, v in metrics.items() if k not in ("cost", "timings", "artifact_sha256")}


def test_the_tiny_configuration_runs_end_to_end(tiny_run):
    config, metrics, _ = tiny_run
    out = Path(config.out)
    for name in ("config.yaml", "sources.json", "metrics.json", "report.md", "transfer.png", "panels.json"):
        assert (out / name).is_file(), name
    records = [json.loads(x) for p in (out / "episodes").glob("*.jsonl") for x in p.read_text().splitlines()]
    runs = {r["name"] for r in metrics["runs"]}
    assert {r["policy"] for r in records} == runs
    for kind in ("D", "E"):  # the generated scenes where `batches` says, not in the cache
        assert list((Path(config.batches) / kind).rglob("scene.json")), kind
    assert not (Path(config.cache) / "batches").exists()
    # every run on both panels; the perturbed panel for its arms only
    panels = json.loads((out / "panels.json").read_text())["scenes"]
    for panel in ("rare", "common"):
        seen = [r for r in records if r["panel"] == panel and r["variant"] == "nominal"]
        assert len(seen) == len(runs) * len(panels[panel])
    shifted = {r["policy"] for r in records if r["variant"] == "dim_light"}
    assert shifted == {
        r["name"]
        for r in metrics["runs"]
        if r["arm"] in ("A+", "D") and r["inputs"] == "rgbd" and r["alpha"] == 1.0
    }
    for r in records:
        assert set(r["choices"]) <= set(config.primitives)
        assert len(r["choices"]) == len(set(r["choices"])) <= 2
        assert (r["failure"] == "") == r["success"]
    for arm in ("A", "A+", "B", "C", "D", "E"):
        m = metrics["arms"][arm]
        assert m["rare"]["low"] <= m["rare"]["mean"] <= m["rare"]["high"]
        assert len(m["seeds"]) == 2
    assert set(metrics["alpha_sweep"]) == {"0.5", "1"}
    assert set(metrics["state_ablation"]) == {"D"}
    sources = json.loads((out / "sources.json").read_text())
    assert all(sources["generation_cpu_s"][k]["cpu_s"] > 0 for k in ("C", "D", "E"))
    assert sources["scenes"]["A"] == 8 and sources["scenes"]["C"] == 2


def test_the_outcome_lands_in_the_manifest_and_audits_clean(tiny_run, capsys):
    config, metrics, _ = tiny_run
    manifest = read_manifest(config.manifest)
    transfer = manifest.transfer
    assert transfer.status == "measured" and transfer.panel == "simulated"
    assert transfer.artifact_sha256 == folder_sha256(config.out) == metrics["artifact_sha256"]
    for arm in ("A", "A+", "B", "C", "D", "E"):
        entry = transfer.metrics["arms"][arm]
        assert entry["rare"]["mean"] == metrics["arms"][arm]["rare"]["mean"]
        assert sum(entry["effective_shares"].values()) == pytest.approx(1.0)
        assert [e["source"] for e in entry["recipe"]["entries"]][0] == "A"
    d_shares = transfer.metrics["arms"]["D"]["effective_shares"]
    assert d_shares == pytest.approx({"A": 0.5, "D": 0.5})  # alpha = 1: the seed's loss
    assert transfer.metrics["arms"]["B"]["recipe"]["entries"][0]["tags"] == ["toppled", "near_edge"]
    assert transfer.metrics["panels"]["panel_origin"] == "reference"
    report = audit(Path(config.manifest))
    assert not report.violations, report.violations
    assert any("artifact" in line and "checksum" in line for line in report.verified)
    # one edited episode: the audit names the artifact's checksum
    episodes = Path(config.out) / "episodes" / "common_nominal.jsonl"
    original = episodes.read_bytes()
    try:
        episodes.write_bytes(original.replace(b'"success": true', b'"success": false', 1) + b"\n")
        assert main(["audit", str(config.manifest)]) == 1
        assert "artifact_sha256" in capsys.readouterr().out
    finally:
        episodes.write_bytes(original)


def test_a_resumed_run_equals_an_uninterrupted_one(tiny_run):
    config, metrics, base = tiny_run
    resumed = tiny_config(base / "resumed", base / "shared")
    for stop in ("sources", "training", "evaluation:1"):
        assert run_transfer(resumed, progress=False, stop_after=stop) == {}
    again = run_transfer(resumed, progress=False)
    assert stable(again) == stable(metrics)
    for name in ("rare_nominal", "common_nominal", "rare_dim_light"):
        first = (Path(config.out) / "episodes" / f"{name}.jsonl").read_bytes()
        assert (Path(resumed.out) / "episodes" / f"{name}.jsonl").read_bytes() == first
    # another configuration may not write into a run's folder
    with pytest.raises(ValueError, match="config.yaml differs"):
        run_transfer(resumed.model_copy(update={"seed": 21}), progress=False)


# --------------------------------------------------------------------------------------------- parts
def test_reference_sets_are_disjoint_deterministic_and_balanced_per_tag():
    rows = load_rows(REFERENCE, "train")
    sets = choose_reference_sets(rows, 60, 100, 35, seed=3)
    assert sets == choose_reference_sets(rows, 60, 100, 35, seed=3)
    assert len(sets.a) == 60 and len(sets.a_plus_extra) == 40 and len(sets.c_extra) == 35
    assert len({*sets.a, *sets.a_plus_extra, *sets.c_extra}) == 135
    by = {r["index"]: r for r in rows}
    assert not any(by[i]["tag_on_floor"] for i in (*sets.a, *sets.c_extra))
    assert [sets.c_tags.count(t) for t in PANEL_TAGS] == [5] * 7
    assert all(by[i][f"tag_{t}"] for i, t in zip(sets.c_extra, sets.c_tags, strict=True))
    assert sum(sets.c_cells(rows).values()) == 35
    with pytest.raises(ValueError, match="near_edge"):
        choose_reference_sets(rows, 60, 100, 7000, seed=3)


def test_arm_b_gets_d_s_effective_rare_share():
    from scenegen.env.scenes import reference_scene

    rows = load_rows(REFERENCE, "train")[:400]
    scenes = {
        "A": [reference_scene(r, source="A") for r in rows[:200]],
        "D": [reference_scene(r, source="D") for r in rows[200:] if any(r[f"tag_{t}"] for t in PANEL_TAGS)],
    }
    for alpha in (0.5, 1.0, 2.0):
        d_scenes, d_recipe = arm_data("D", alpha, scenes, PANEL_TAGS)
        b_scenes, b_recipe = arm_data("B", alpha, scenes, PANEL_TAGS)
        held = np.array([rare(s, PANEL_TAGS) for s in d_scenes])
        d_share = scene_weights(d_recipe, d_scenes)[held].sum()
        b_held = np.array([rare(s, PANEL_TAGS) for s in b_scenes])
        assert scene_weights(b_recipe, b_scenes)[b_held].sum() == pytest.approx(d_share)
        assert b_scenes == scenes["A"]


def test_hierarchical_bootstrap():
    rng = np.random.default_rng(0)
    ones = np.ones((3, 40))
    assert interval(ones, 500, 0) == {"mean": 1.0, "low": 1.0, "high": 1.0, "seeds": 3, "scenes": 40}
    grid = (rng.random((3, 200)) < 0.6).astype(float)
    wide, narrow = interval(grid[:, :20], 1000, 0), interval(grid, 1000, 0)
    assert narrow["high"] - narrow["low"] < wide["high"] - wide["low"]
    assert narrow["low"] < 0.6 < narrow["high"]
    same = difference(grid, grid, 1000, 0)
    assert same["mean"] == 0.0 and same["low"] <= 0 <= same["high"]
    better = difference(np.ones((3, 200)), grid, 1000, 0)
    assert better["low"] > 0.3
    # the seed level counts: seeds that disagree widen the interval over seeds that agree
    split = np.vstack([np.ones(200), np.zeros(200), np.ones(200)])
    agree = np.vstack([grid[0]] * 3)
    assert interval(split, 1000, 0)["high"] - interval(split, 1000, 0)["low"] > 0.3
    assert interval(agree, 1000, 0)["high"] - interval(agree, 1000, 0)["low"] < 0.2


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("sizes: {a: 10, a_plus: 5}\n", "sizes: a_plus (5) must be at least a (10)"),
        ("alpha: .nan\n", "alpha: alpha must be a finite number"),
        ("tags: [on_floor]\n", "tags: ['on_floor']: choose from"),
        ("colour: red\n", "colour: Extra inputs are not permitted"),
        ("training: {seeds: []}\n", "training.seeds"),
        ("- a list\n", "a transfer configuration is a mapping"),
    ],
)
def test_configuration_errors_name_the_key(tmp_path, text, message):
    path = tmp_path / "transfer.yaml"
    path.write_text(text)
    with pytest.raises(TransferConfigError, match=None) as caught:
        load_transfer_config(path)
    assert message in str(caught.value) and str(path) in str(caught.value)
    assert "\n" not in str(caught.value) and len(str(caught.value)) <= 300


def test_a_binary_configuration_is_a_one_line_error(tmp_path):
    path = tmp_path / "transfer.yaml"
    path.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(TransferConfigError, match="cannot read it as a text file"):
        load_transfer_config(path)


def test_the_artifact_checksum_covers_names_and_bytes(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.json").write_text("1")
    first = folder_sha256(tmp_path)
    (tmp_path / "a" / "x.json").write_text("2")
    assert folder_sha256(tmp_path) != first
    (tmp_path / "a" / "x.json").write_text("1")
    assert folder_sha256(tmp_path) == first
    (tmp_path / "a" / "x.json").rename(tmp_path / "a" / "y.json")
    assert folder_sha256(tmp_path) != first
    (tmp_path / "link").symlink_to(tmp_path / "a")
    with pytest.raises(ValueError, match="symlink"):
        folder_sha256(tmp_path)


def test_shared_sequences_replay_what_a_live_episode_does(tiny_run):
    """The closed-loop evaluation from stored sequences chooses and ends as policy/evaluate.py's live
    episode does, on an episode that needed a second attempt (observed from the stored state)."""
    from scenegen.env.robosuite_env import SceneEnv
    from scenegen.experiment.transfer import panel_scenes
    from scenegen.policy.evaluate import run_episode
    from scenegen.policy.labels import CAMERA_SIZE, CAMERAS
    from scenegen.policy.network import PrimitivePolicy

    config, _, _ = tiny_run
    records = [
        json.loads(x)
        for x in (Path(config.out) / "episodes" / "common_nominal.jsonl").read_text().splitlines()
    ]
    records += [
        json.loads(x) for x in (Path(config.out) / "episodes" / "rare_nominal.jsonl").read_text().splitlines()
    ]
    retried = [r for r in records if len(r["choices"]) == 2 and not r["policy"].endswith("_state")]
    assert retried, "the tiny run holds no two-attempt episode"
    record = min(retried, key=lambda r: r["time"])
    scenes = {s.scene_id: s for group in panel_scenes(config).values() for s in group}
    scene = scenes[record["scene_id"]]
    policy = PrimitivePolicy.load(Path(config.cache) / "policies" / record["policy"])
    env = SceneEnv(
        scene, cameras=list(CAMERAS), camera_size=CAMERA_SIZE, render_each_step=False, horizon=6000
    )
    try:
        episode = run_episode(env, policy, scene, "live")
    finally:
        env.close()
    assert [d.choice["primitive"] for d in episode.decisions] == record["choices"]
    assert episode.success == record["success"]


def test_the_command_answers_bad_input_in_one_line(tmp_path, capsys):
    assert main(["experiment", "transfer", str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml: no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("training: {steps: -1}\n")
    assert main(["experiment", "transfer", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "training.steps" in err and len(err.strip().splitlines()) == 1
