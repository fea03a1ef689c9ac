"""Transfer version 2 end to end at its tiny size (tests/fixtures/transfer_v2_tiny.yaml): each arm and
seed trains its own retrieval head and its chooser through that head's masks (real rendering, real
training, real labelling and closed-loop episodes), is evaluated through its head and through true
masks on the validation side of the version 2 panels; a run stopped after its first evaluation and
continued gives what an uninterrupted one gives."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from scenegen.core.files import load_rows
from scenegen.env.mixture import scene_weights
from scenegen.env.scenes import reference_scene
from scenegen.experiment.transfer_config import TransferConfigError, TransferConfigV2, load_transfer_config
from scenegen.experiment.transfer_v2 import arm_mixture, read_episodes, run_transfer_v2, runs_v2
from scenegen.paths import PROJECT_ROOT

TINY = PROJECT_ROOT / "tests" / "fixtures" / "transfer_v2_tiny.yaml"
REFERENCE = PROJECT_ROOT / "assets" / "reference" / "reference.parquet"


def tiny_config(root: Path, shared: Path) -> TransferConfigV2:
    """The tiny configuration writing into ``root`` (its artifact and a project manifest the outcome
    goes into); the label and sequence stores in ``shared``."""
    from scenegen.data.project_manifest import DATASHEET, TRANSFER
    from scenegen.manifest.io import write_manifest
    from scenegen.manifest.schema import Manifest

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
            "out": str(root / "result"),
            "manifest": str(manifest),
        },
    )


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> tuple:
    base = tmp_path_factory.mktemp("transfer_v2")
    config = tiny_config(base / "whole", base / "shared")
    return config, run_transfer_v2(config, progress=False), base


def test_each_run_trains_its_own_head_and_chooser_and_is_scored_through_both_sights(tiny_run):
    config, metrics, _ = tiny_run
    cache, out = Path(config.cache), Path(config.out)
    names = [r["name"] for r in runs_v2(config)]
    assert names == ["A+_s0", "A+_s1", "C_s0", "C_s1"]
    for run in metrics["runs"]:  # cache folders named by the run and a digest of what decides it
        assert run["parts"].startswith(run["name"] + "-")
        assert run["head"].startswith(run["name"] + "-")
        assert (cache / "heads" / run["head"] / "separator.safetensors").is_file()
        assert (cache / "policies" / run["parts"] / "model.safetensors").is_file()
    heads = {r["head_sha256"] for r in metrics["runs"]}
    assert len(heads) == len(names), "every arm and seed has a head of its own"
    # oracle rows for seed 0 only; the depth-noise shift for C_s0 on the rare panel only
    expected = {
        "toppled": {n: ["head"] for n in names} | {"A+_s0": ["head", "oracle"]}
        | {"C_s0": ["head", "oracle", "head@depth_noise", "oracle@depth_noise"]},
        "common": {n: ["head"] for n in names} | {"A+_s0": ["head", "oracle"], "C_s0": ["head", "oracle"]},
    }  # fmt: skip
    for panel, runs in expected.items():
        files = sorted(p.name for p in (out / "episodes" / panel).iterdir())
        assert files == sorted(f"{n}_{c}.jsonl" for n, cs in runs.items() for c in cs)
        for path in (out / "episodes" / panel).iterdir():
            rows = path.read_text().splitlines()
            assert [json.loads(x)["layout"] for x in rows] == metrics["panels"][panel]
    assert len(metrics["panels"]["toppled"]) == 2 and len(metrics["panels"]["common"]) == 1  # panel_sizes
    assert metrics["plan_grid"] == {"metres": 0.005, "degrees": 5.0}
    rates, contrasts = metrics["head"]["rates"], metrics["head"]["contrasts"]
    assert set(rates["rare"]) == {"A+", "C"} and list(contrasts["rare"]) == ["C - A+"]
    c = contrasts["rare"]["C - A+"]
    assert c["low"] <= c["mean"] <= c["high"] and c["seeds"] == 2 and c["scenes"] == 2
    assert set(metrics["head"]["per_seed"]["rare"]) == set(names)
    assert metrics["oracle"]["contrasts"]["rare"]["C - A+"]["seeds"] == 1
    assert set(metrics["oracle"]["per_seed"]["common"]) == {"A+_s0", "C_s0"}
    exact, noisy = (read_episodes(out, "toppled", "C_s0", c) for c in ("oracle", "oracle@depth_noise"))
    assert [r["plans"] for r in exact] != [r["plans"] for r in noisy]  # the sensor's noise was applied
    for shifted in ("head@depth_noise", "oracle@depth_noise"):
        assert list(metrics[shifted]["rates"]) == ["rare", "toppled"]  # the rare panels only
        assert set(metrics[shifted]["rates"]["rare"]) == {"C"} and not metrics[shifted]["contrasts"]["rare"]


def test_the_report_and_the_manifests_version_2_outcome_pass_the_audit(tiny_run):
    """report.md leads with the positive control; the manifest's transfer outcome is version 2 (the
    positive control, the primary endpoint, each arm's rates, the artifact's checksum) and the
    audit verifies it."""
    from scenegen.audit.manifest import audit
    from scenegen.core.files import folder_sha256
    from scenegen.manifest.io import read_manifest

    config, metrics, _ = tiny_run
    out = Path(config.out)
    text = (out / "report.md").read_text()
    assert (
        text.index("Positive control C - A+") < text.index("Primary endpoint D - A+") < text.index("Per arm")
    )
    assert "Failure labels" in text and "Generation CPU-s" in text
    # what was run, the cuts showing (oracle rows on seed 0, the shift on C's seed 0 only)
    assert "- arms and training seeds: A+ [0, 1]; C [0, 1]" in text and "toppled 2, common 1" in text
    assert "\n- oracle: A+_s0, C_s0\n" in text and "\n- head@depth_noise: C_s0\n" in text
    toppled = metrics["head"]["contrasts"]["toppled"]["C - A+"]
    assert f"| toppled | {toppled['mean']:+.3f} [" in text.split("## Contrasts per panel")[1]
    # every condition's pooled contrasts, "not run" where its arms do not allow one
    by_condition = text.split("## Contrasts per condition")[1].split("\n## ")[0]
    oracle = metrics["oracle"]["contrasts"]["rare"]["C - A+"]
    assert f"| oracle | {oracle['mean']:+.3f} [" in by_condition
    assert "| head@depth_noise | not run |" in by_condition
    # what it cost, summed from costs.jsonl: every part trained, every episode evaluated
    spent = text.split("## What the run cost")[1]
    assert "- heads: 4 trained" in spent and "- choosers: 4 trained" in spent
    assert "- 12 episodes head: " in spent and "- 2 episodes oracle@shift: " in spent
    rows = [json.loads(line) for line in (out / "costs.jsonl").read_text().splitlines()]
    attempts = sum(r["attempts"] for r in rows if "condition" in r)
    shared = sum(r["shared"] for r in rows if "condition" in r)
    assert f"the store served {shared / attempts:.0%} of {attempts:,} attempts" in spent
    outcome = read_manifest(Path(config.manifest)).transfer
    assert outcome.status == "measured" and outcome.metrics["version"] == 2
    control = outcome.metrics["positive_control"]
    assert control["mean"] == metrics["head"]["contrasts"]["rare"]["C - A+"]["mean"]
    assert set(outcome.metrics["arms"]) == {"A+", "C"} and outcome.metrics["arms"]["C"]["seeds"] == [0, 1]
    assert outcome.artifact_sha256 == folder_sha256(out) == metrics["artifact_sha256"]
    report = audit(Path(config.manifest))
    assert not report.violations, report.violations


def test_episodes_through_another_machines_parts_are_compared_pair_by_pair(tiny_run, tmp_path):
    """The report's last section: the same folder agrees with itself in every episode; a copy with one
    rare-panel outcome flipped agrees in all but that one, and the rates differ by exactly it."""
    import shutil

    from scenegen.experiment.transfer_report_v2 import machine_effect, report

    config, metrics, _ = tiny_run
    out = Path(config.out)
    same = machine_effect(out, out)
    assert same["arms"] and all(r["agree"] == 1.0 and r["here"] == r["there"] for r in same["arms"].values())
    other = tmp_path / "first_machine"
    shutil.copytree(out / "episodes", other / "episodes")
    path = next(
        p for p in sorted((other / "episodes").glob("*/A+_s0_head.jsonl")) if p.parent.name != "common"
    )
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    rows[0]["success"] = not rows[0]["success"]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    moved = machine_effect(out, other)
    pooled = moved["arms"]["A+ head"]
    assert pooled["agree"] == round(1 - 1 / pooled["paired"], 3)
    assert abs(pooled["here"] - pooled["there"]) == pytest.approx(1 / pooled["paired"], abs=1e-3)
    assert moved["arms"]["C head"] == same["arms"]["C head"]
    sources = json.loads((out / "sources.json").read_text())
    assert "Another machine's parts" in report(metrics, out, sources, other)
    assert "Another machine's parts" not in report(metrics, out, sources)


def test_ds_share_of_cs_gain_is_the_ratio_of_the_gains_with_its_interval():
    import numpy as np

    from scenegen.experiment.transfer_stats import share

    scenes = np.arange(100)
    base, c, d = ((scenes < k).astype(float)[None].repeat(2, 0) for k in (50, 70, 60))
    measured = share(c, base, d, 500, seed=0)
    assert measured["mean"] == 0.5 and measured["low"] <= 0.5 <= measured["high"]
    assert share(base, base, d, 100, seed=0)["mean"] is None  # no gain to share


def test_a_chooser_is_trained_on_its_own_heads_masks(tiny_run):
    """The observations a chooser trained on are keyed by its head: two heads, two sets of inputs."""
    config, metrics, _ = tiny_run
    from scenegen.experiment.sequences import NOMINAL, sight

    heads = [Path(config.cache) / "heads" / r["head"] for r in metrics["runs"]]
    assert len({sight(h, NOMINAL) for h in heads}) == len(heads)


def test_a_stopped_and_continued_run_gives_the_same_outcome(tiny_run):
    """On the whole run's trained parts (``parts``, as a fresh machine resumes on the committed ones;
    that training gives the same bytes is the next test's): stopped after C_s0's evaluation, whose
    noisy conditions are evaluated, and continued from there."""
    config, metrics, base = tiny_run
    resumed = tiny_config(base / "resumed", base / "shared").model_copy(update={"parts": Path(config.cache)})
    assert run_transfer_v2(resumed, progress=False, stop_after="evaluation:3") == {}
    again = run_transfer_v2(resumed, progress=False)
    # (the artifact's checksum covers costs.jsonl: CPU seconds differ between runs, episodes do not)
    drop = lambda m: {k: v for k, v in m.items() if k not in ("timings", "artifact_sha256")}  # noqa: E731
    assert drop(again) == drop(metrics)
    for path in sorted((Path(config.out) / "episodes").rglob("*.jsonl")):
        twin = Path(resumed.out) / path.relative_to(config.out)
        assert twin.read_bytes() == path.read_bytes(), path.name


def test_heads_trained_two_at_a_time_are_the_bytes_of_heads_trained_alone(tiny_run):
    """``workers: 2`` trains two heads at once (each at one thread, in its own process; the seed 0
    runs, A+'s and C's): the same weights as the tiny run's heads, trained one after another, and
    each head's wall in the costs with how many ran at once."""
    from scenegen.experiment.transfer_ledger import measured
    from scenegen.experiment.transfer_v2 import weights_sha256

    config, metrics, base = tiny_run
    seed_0 = config.training.model_copy(update={"seeds": (0,)})
    two = tiny_config(base / "two_at_a_time", base / "shared")
    two = two.model_copy(update={"workers": 2, "training": seed_0})
    assert run_transfer_v2(two, progress=False, stop_after="training") == {}
    runs = [r for r in metrics["runs"] if r["name"].endswith("_s0")]
    assert [r["name"] for r in runs] == ["A+_s0", "C_s0"]
    for run in runs:
        assert weights_sha256(Path(two.cache) / "heads" / run["head"]) == run["head_sha256"], run["name"]
    costs = [json.loads(x) for x in (Path(two.out) / "costs.jsonl").read_text().splitlines()]
    heads = [c for c in costs if c.get("stage") == "head"]
    assert len(heads) == len(runs) and all(c["parallel"] == 2 for c in heads)
    per_run = measured([two.out])["training"]["head"]["wall_s"]  # a head's share of the run's wall
    assert per_run == pytest.approx(sum(c["wall_s"] / 2 for c in heads) / len(heads), abs=0.1)


def test_parts_kept_beside_the_artifact_let_a_fresh_machine_resume_without_training(tiny_run):
    """``parts``: trained heads and choosers kept in their own (committed) folder; a run on a fresh
    machine (an empty cache) finds them and trains nothing, and the folder is storage, not part of
    the configuration its out folder records."""
    import shutil

    config, metrics, base = tiny_run
    parts = base / "committed_parts"
    for kind in ("heads", "policies"):
        shutil.copytree(Path(config.cache) / kind, parts / kind)
    fresh = tiny_config(base / "fresh", base / "shared").model_copy(update={"parts": parts})
    assert run_transfer_v2(fresh, progress=False, stop_after="training") == {}
    log = Path(fresh.out) / "costs.jsonl"  # a row per trained part; none trained, none written
    assert not log.exists() or "head" not in log.read_text() and "chooser" not in log.read_text()
    assert not (Path(fresh.cache) / "heads").exists()
    assert "parts" not in yaml.safe_load((Path(fresh.out) / "config.yaml").read_text())


def test_the_endpoints_arms_are_evaluated_first_and_each_evaluation_names_its_processor(tiny_run):
    from scenegen.experiment.transfer_v2 import evaluation_order

    runs = [
        {"name": f"{arm}_s{seed}", "arm": arm} for arm in ("A", "A+", "B", "C", "D", "E") for seed in (0, 1)
    ]
    order = [r["name"] for r in evaluation_order(runs)]
    assert order[:6] == ["A+_s0", "A+_s1", "C_s0", "C_s1", "D_s0", "D_s1"]
    assert order[6:] == ["A_s0", "A_s1", "B_s0", "B_s1", "E_s0", "E_s1"]
    config, _, _ = tiny_run
    costs = [json.loads(x) for x in (Path(config.out) / "costs.jsonl").read_text().splitlines()]
    evaluated = [c for c in costs if "panel" in c]
    assert evaluated and all(c["cpu"] for c in evaluated)


def test_c_is_more_real_data_in_version_2():
    """C's extra layouts are drawn with A's per-scene weight (as the curves' rare-rich set), not as a
    second term at alpha: every C scene as likely as every A scene."""
    rows = load_rows(REFERENCE, "train")[:12]
    scenes = {
        "A": [reference_scene(r, "A") for r in rows[:8]],
        "C": [reference_scene(r, "C") for r in rows[8:]],
    }
    data, recipe = arm_mixture("C", 1.0, scenes, ("toppled",))
    weights = scene_weights(recipe, data)
    assert len(data) == 12 and max(weights) - min(weights) < 1e-12


@pytest.mark.parametrize(
    "change, says",
    [
        ({"arms": ["A+", "F"]}, "arms"),
        ({"arms": ["C", "C"]}, "twice"),
        ({"training": {"seeds": [0, 0]}}, "twice"),
        ({"side": "train"}, "side"),
        ({"version": 3}, "version"),
        ({"perturbation": {"name": "dim_light"}}, "not used by version 2"),
        ({"oracle_seeds": [5]}, "oracle_seeds"),
        ({"arm_seeds": {"C": [0, 7]}}, "arm_seeds.C"),
        ({"arm_seeds": {"C": [0, 0]}}, "arm_seeds.C"),
        ({"arm_seeds": {"C": []}}, "arm_seeds.C"),
        ({"perturbations": {"arms": ["D"]}}, "perturbations.arms"),
        ({"perturbations": {"shifts": [{"name": "a"}, {"name": "a"}]}}, "shifts"),
        ({"perturbations": {"shifts": [{"name": "x", "sensor": "lidar"}]}}, "sensor"),
        ({"plan_grid": {"metres": 0.0, "degrees": 5.0}}, "metres"),
    ],
)
def test_a_bad_version_2_configuration_is_one_line_naming_the_key(change, says):
    import yaml

    raw = yaml.safe_load(TINY.read_text()) | change
    with pytest.raises(TransferConfigError, match=says) as info:
        load_transfer_config(None, raw)
    assert "\n" not in str(info.value)


def test_the_command_prints_every_condition_with_its_contrasts(tiny_run):
    from scenegen.cli.experiment import _v2_summary

    _, metrics, _ = tiny_run
    text = _v2_summary(metrics)
    for condition in ("head", "oracle", "head@depth_noise", "oracle@depth_noise"):
        assert f"\n{condition}: rare panels pooled\n" in text
    assert text.count("C - A+:") == 2  # the shifted conditions hold C alone


def test_the_cost_of_a_configuration_is_projected_from_what_a_run_measured(tiny_run, capsys):
    """--estimate counts the configuration's work (runs; episodes per condition class) and multiplies
    it by the rates the run wrote to costs.jsonl; every trained part and evaluated file is there."""
    from scenegen.cli import main
    from scenegen.experiment.transfer_cost import planned, project
    from scenegen.experiment.transfer_ledger import measured

    config, _, _ = tiny_run
    work = planned(config)
    episodes = {"head": 12, "oracle": 6, "head@shift": 2, "oracle@shift": 2}
    assert work["runs"] == 4 and work["episodes"] == episodes
    rates = measured([config.out])
    assert rates["training"]["head"]["n"] == 4 and rates["training"]["chooser"]["n"] == 4
    assert {k: v["n"] for k, v in rates["episodes"].items()} == episodes
    assert all(0 <= v["served"] <= 1 and v["cpu_s"] >= 0 for v in rates["episodes"].values())
    assert rates["episodes"]["head"]["cpu_s"] > 0  # (a class may be served whole by the stores)
    projection = project(config, rates)
    assert not projection["assumed_like_head"] and projection["total_hours"] > 0
    assert main(["experiment", "transfer", str(TINY), "--estimate", str(config.out)]) == 0
    assert "4 runs (a head and a chooser each)" in capsys.readouterr().out
    assert main(["experiment", "transfer", str(TINY), "--estimate", str(config.cache)]) == 2
    assert "costs.jsonl" in capsys.readouterr().err


def test_version_2_draws_its_rare_data_for_the_tags_that_have_a_panel():
    """C's extra layouts and D's and E's requests cover the six version 2 panel tags: under_overhang
    has no panel, so scenes drawn for it would dilute what the panels measure."""
    from scenegen.policy.panels_v2 import load_panels_v2, panel_scenes

    config = load_transfer_config(None, {"version": 2})
    panels = panel_scenes(load_panels_v2(config.panels), "validation")
    assert set(config.tags) == set(panels) - {"common"} and "under_overhang" not in config.tags


def _digests(folder: Path) -> dict:
    import hashlib

    return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*.*")}


def test_the_status_of_a_run_counts_what_is_done_and_shows_only_whole_arms(tiny_run, tmp_path, capsys):
    """--status reads the out folder: with one of C's files gone C is not whole, its episodes are
    left at the folder's measured rate, and the rates shown (A+'s, whole) are the finished run's
    figures; it writes nothing, and refuses a folder with no run or another configuration's."""
    import shutil

    from scenegen.cli import main
    from scenegen.experiment.transfer_cost import status
    from scenegen.experiment.transfer_ledger import measured

    config, metrics, _ = tiny_run
    whole = status(config)
    assert not whole["left"] and whole["whole_arms"] == ["A+", "C"]
    assert whole["metrics"]["head"]["contrasts"] == metrics["head"]["contrasts"]
    copy = tmp_path / "result"
    shutil.copytree(config.out, copy)
    gone = copy / "episodes" / "toppled" / "C_s1_head.jsonl"
    lost = len(gone.read_text().splitlines())
    gone.unlink()
    before = _digests(copy)
    part = status(config.model_copy(update={"out": str(copy)}))
    assert part["arms"]["C"]["whole"] == part["arms"]["C"]["runs"] - 1
    assert part["arms"]["C"]["episodes"] - part["arms"]["C"]["done"] == lost
    assert part["left"] == {"head": lost} and not part["assumed_like_head"]
    rate = measured([copy])["episodes"]["head"]  # the folder's own rate, what the left work costs
    assert part["hours_left"]["wall"] == pytest.approx(lost * rate["wall_s"] / 3600)
    assert part["whole_arms"] == ["A+"] and "C" not in part["metrics"]["head"]["rates"]["rare"]
    assert part["metrics"]["head"]["rates"]["rare"]["A+"] == metrics["head"]["rates"]["rare"]["A+"]
    assert main(["experiment", "transfer", str(TINY), "--out", str(copy), "--status"]) == 0
    said = capsys.readouterr().out
    assert f"evaluation left: {lost} episodes" in said and "whole arms: A+" in said and "C - A+" not in said
    assert _digests(copy) == before
    assert main(["experiment", "transfer", str(TINY), "--out", str(tmp_path), "--status"]) != 0
    assert "no run here yet" in capsys.readouterr().err
    changed = tmp_path / "changed.yaml"  # what is run differs (the seed), the folder is the same
    changed.write_text(yaml.safe_dump(yaml.safe_load(TINY.read_text()) | {"seed": 29}))
    assert main(["experiment", "transfer", str(changed), "--out", str(copy), "--status"]) != 0
    assert "another configuration's run (config.yaml differs in seed)" in capsys.readouterr().err


def test_a_contrast_of_whole_arms_does_not_depend_on_the_arms_beside_it(tiny_run, tmp_path):
    """What --status shows before the last arm lands is the finished figure: metrics over A+ and C
    equal those over A+, C and a third arm (C's episodes copied as D's), contrasts and per-seed rates."""
    import shutil

    from scenegen.experiment.transfer_v2 import metrics_v2, panels_v2

    config, _, _ = tiny_run
    copy = tmp_path / "result"
    shutil.copytree(config.out, copy)
    for path in list((copy / "episodes").rglob("C_s*.jsonl")):
        run = path.name.split("_")[0] + "_" + path.name.split("_")[1]  # C_s0
        twin = path.with_name("D" + path.name[1:])
        twin.write_text(path.read_text().replace(f'"policy": "{run}"', f'"policy": "D{run[1:]}"'))
    two = config.model_copy(update={"out": str(copy)})
    three = two.model_copy(update={"arms": ("A+", "C", "D")})
    panels = panels_v2(two)
    small, big = metrics_v2(two, runs_v2(two), panels, copy), metrics_v2(three, runs_v2(three), panels, copy)
    for condition in ("head", "oracle"):
        assert big[condition]["contrasts"]["rare"]["D - C"]["mean"] == 0  # the copy is C's own
        for group, contrasts in small[condition]["contrasts"].items():
            assert big[condition]["contrasts"][group]["C - A+"] == contrasts["C - A+"]
        for group, rates in small[condition]["rates"].items():
            assert {a: big[condition]["rates"][group][a] for a in rates} == rates


def test_version_2_keeps_its_physics_and_resolves_as_it_ran(monkeypatch):
    """The declared configuration runs under ``exact`` and resolves to the committed artifact's
    config.yaml byte for byte (the physics key added since is left out where it holds exact);
    another physics is part of what the run is, and of what decides its choosers."""
    from scenegen.env.mixture import MixtureRecipe
    from scenegen.env.physics import PHYSICS
    from scenegen.experiment.transfer_v2 import parts_digest, resolved_config

    declared = load_transfer_config(PROJECT_ROOT / "pipelines" / "transfer.yaml")
    committed = PROJECT_ROOT / "assets" / "transfer" / "v2" / "result" / "config.yaml"
    assert declared.physics == "exact"
    assert resolved_config(declared) == committed.read_text()
    monkeypatch.setitem(PHYSICS, "coarse", PHYSICS["exact"].with_changes("coarse", timestep=0.005))
    coarse = declared.model_copy(update={"physics": "coarse"})
    assert "physics: coarse" in resolved_config(coarse)
    run = {"seed": 0, "alpha": 1.0}
    scenes = [reference_scene(r) for r in load_rows(REFERENCE, "train")[:3]]
    recipe = MixtureRecipe.seed_loss({"A": 3}, {}, 0.0)
    assert parts_digest(run, declared, scenes, recipe) != parts_digest(run, coarse, scenes, recipe)
    assert parts_digest(run, declared, scenes, recipe, head=True) == parts_digest(
        run, coarse, scenes, recipe, head=True
    )  # a head sees frames: the physics does not decide it
    with pytest.raises(TransferConfigError, match="physics"):
        load_transfer_config(PROJECT_ROOT / "pipelines" / "transfer.yaml", {"physics": "fast"})
