"""The command line: bad inputs are usage errors (exit 2, one line naming the problem, nothing written)."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

from scenegen.assets.catalog import load_catalog
from scenegen.cli import main
from scenegen.schema.condition import TAGS

REPO_ROOT = Path(__file__).resolve().parents[2]
DEMO = REPO_ROOT / "pipelines" / "procedural.yaml"
USAGE_ERROR = 2
PREFIX = "scenegen: error: "
TOP_LEVEL_KEYS = ("max_proposals", "condition", "proposer", "checks", "settle")


def demo_recipe() -> dict:
    return yaml.safe_load(DEMO.read_text())


def categories() -> list[str]:
    return list(load_catalog().categories)


def assert_usage_error(code: int, stdout: str, stderr: str, out_dir: Path, needles: list[str]) -> str:
    """Exit 2, exactly one stderr line (no traceback) naming every needle, nothing on stdout or disk."""
    assert code == USAGE_ERROR, (code, stderr)
    lines = stderr.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got:\n{stderr}"
    line = lines[0]
    assert line.startswith(PREFIX), line
    assert "Traceback" not in stderr
    missing = [n for n in needles if n not in line]
    assert not missing, f"error line lacks {missing}: {line}"
    assert stdout == ""
    assert not out_dir.exists(), f"{out_dir} was created"
    return line


def run_subprocess(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "scenegen.cli", *args], capture_output=True, text=True, cwd=cwd, timeout=120
    )


# ---------------------------------------------------------------- bad recipes (in-process)

Mutation = Callable[[dict], None]


def _set(*keys: str, value) -> Mutation:
    def mutate(recipe: dict) -> None:
        node = recipe
        for key in keys[:-1]:
            node = node.setdefault(key, {})
        node[keys[-1]] = value

    return mutate


BAD_RECIPES: dict[str, tuple[Mutation, Callable[[], list[str]]]] = {
    "unknown_top_level_key": (_set("colour", value="red"), lambda: ["colour", *TOP_LEVEL_KEYS]),
    "unknown_nested_key": (
        _set("condition", "colour", value="red"),
        lambda: ["condition.colour", "task", "target", "tags", "robot_pose", "text"],
    ),
    "unknown_task": (
        _set("condition", "task", value="juggle"),
        lambda: ["condition.task", "juggle", "retrieve", "upright", "clear"],
    ),
    "unknown_target": (
        _set("condition", "target", value="unicorn"),
        lambda: ["condition.target", "unicorn", *categories()],
    ),
    "unknown_tag": (
        _set("condition", "tags", value={"sparkly": "required"}),
        lambda: ["condition.tags", "sparkly", *TAGS],
    ),
    "unknown_tag_state": (
        _set("condition", "tags", value={"near_edge": "maybe"}),
        lambda: ["condition.tags", "near_edge", "required", "forbidden", "unspecified"],
    ),
    "robot_pose_out_of_limits": (
        _set("condition", "robot_pose", value=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
        lambda: ["condition.robot_pose", "joint 4", "-3.0718", "-0.0698"],
    ),
    "unknown_robot_pose_name": (
        _set("condition", "robot_pose", value="dance"),
        lambda: ["condition.robot_pose", "dance", "home", "ready"],
    ),
    "unplaceable_text_word": (
        _set("condition", "text", value="retrieve the spoon please"),
        lambda: ["condition", "text", "'please'", "retrieve", "spoon", "near_edge", "home"],
    ),
    "unknown_proposer_kind": (
        _set("proposer", "kind", value="magic"),
        lambda: ["proposer.kind", "procedural"],
    ),
    "unknown_asset_category": (
        _set("proposer", "categories", value=["mug", "teapot"]),
        lambda: ["proposer", "categories", "teapot", *categories()],
    ),
    "impossible_n_objects": (
        _set("proposer", "n_objects", value=[5, 2]),
        lambda: ["proposer.n_objects", "[5, 2]"],
    ),
    "unknown_key_of_targeted_proposer": (
        lambda recipe: recipe["proposer"].update(kind="targeted", occluder=2),
        lambda: ["proposer.occluder", "did you mean occluders", "n_objects", "(26 keys)"],
    ),
    "unknown_occluder_asset": (
        lambda recipe: recipe["proposer"].update(kind="targeted", occluders=["wall"]),
        lambda: ["proposer.occluders", "'wall'", "cereal_box"],
    ),
    "impossible_request": (
        _set("condition", "text", value="retrieve the spoon toppled"),
        lambda: ["condition", "toppled", "spoon", "request another target"],
    ),
    "zero_n": (_set("n", value=0), lambda: ["n: ", "greater than or equal to 1"]),
    "negative_seed": (_set("seed", value=-1), lambda: ["seed", "greater than or equal to 0"]),
    "unknown_support": (
        _set("proposer", "support_weights", value={"table": 0.8, "ceiling": 0.2}),
        lambda: ["proposer", "support_weights", "ceiling", "table", "floor", "stack", "shelf", "bin"],
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_RECIPES))
def test_bad_recipe_is_a_one_line_usage_error(case: str, tmp_path: Path, monkeypatch, capsys):
    mutate, needles = BAD_RECIPES[case]
    recipe = copy.deepcopy(demo_recipe())
    mutate(recipe)
    pipeline = tmp_path / f"{case}.yaml"
    pipeline.write_text(yaml.safe_dump(recipe))
    monkeypatch.chdir(tmp_path)  # a default runs/<name> would land here
    out = tmp_path / "out"
    # named relative to the working folder, as a user types it (an error line holds 300 characters)
    code = main(["generate", pipeline.name, "--max-proposals", "1", "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    assert_usage_error(code, captured.out, captured.err, out, [pipeline.name, *needles()])
    assert sorted(p.name for p in tmp_path.iterdir()) == [pipeline.name]


def test_yaml_list_instead_of_mapping(tmp_path: Path, capsys):
    pipeline = tmp_path / "list.yaml"
    pipeline.write_text("- name: demo\n- n: 3\n")
    out = tmp_path / "out"
    code = main(["generate", str(pipeline), "--out", str(out)])
    captured = capsys.readouterr()
    assert_usage_error(code, captured.out, captured.err, out, [str(pipeline), "mapping"])


def test_binary_recipe_is_named_not_a_traceback(tmp_path: Path, capsys):
    pipeline = tmp_path / "binary.yaml"
    pipeline.write_bytes(bytes(range(256)) * 4)
    out = tmp_path / "out"
    code = main(["generate", str(pipeline), "--out", str(out)])
    captured = capsys.readouterr()
    assert_usage_error(code, captured.out, captured.err, out, [str(pipeline), "not a UTF-8 text file"])


def test_an_override_does_not_hide_a_wrong_recipe_value(tmp_path: Path, capsys):
    recipe = copy.deepcopy(demo_recipe())
    recipe["n"] = "many"
    pipeline = tmp_path / "wrong_n.yaml"
    pipeline.write_text(yaml.safe_dump(recipe))
    out = tmp_path / "out"
    code = main(["generate", str(pipeline), "--n", "1", "--out", str(out)])
    captured = capsys.readouterr()
    assert_usage_error(code, captured.out, captured.err, out, [str(pipeline), "n: ", "valid integer", "--n"])


def test_a_long_unknown_word_is_shortened_in_the_error(tmp_path: Path, capsys):
    out = tmp_path / "out"
    code = main(["generate", str(DEMO), "--request", "retrieve the " + "x" * 5000, "--out", str(out)])
    captured = capsys.readouterr()
    assert_usage_error(code, captured.out, captured.err, out, ["--request", "5000 characters"])
    assert len(captured.err) < 500


@pytest.mark.parametrize(
    ("option", "value", "field", "bound"),
    [
        ("--n", "0", "n: ", "greater than or equal to 1"),
        ("--seed", "-1", "seed", "greater than or equal to 0"),
    ],
)
def test_bad_overrides_are_usage_errors(option, value, field, bound, tmp_path: Path, capsys):
    out = tmp_path / "out"
    code = main(["generate", str(DEMO), option, value, "--out", str(out)])
    captured = capsys.readouterr()
    assert_usage_error(code, captured.out, captured.err, out, [str(DEMO), field, bound])


def test_existing_out_file_is_refused(tmp_path: Path, capsys):
    out = tmp_path / "taken"
    out.write_text("keep me\n")
    code = main(["generate", str(DEMO), "--n", "1", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == USAGE_ERROR
    assert len(captured.err.splitlines()) == 1 and "--out" in captured.err and str(out) in captured.err
    assert out.read_text() == "keep me\n"


# ---------------------------------------------------------------- real processes


def test_missing_pipeline_file(tmp_path: Path):
    result = run_subprocess(["generate", "no_such_recipe.yaml", "--out", "out"], cwd=tmp_path)
    assert_usage_error(
        result.returncode, result.stdout, result.stderr, tmp_path / "out", ["no_such_recipe.yaml"]
    )
    assert list(tmp_path.iterdir()) == []


def test_invalid_yaml(tmp_path: Path):
    (tmp_path / "broken.yaml").write_text("name: demo\ncondition: {task: [retrieve\nn: 3\n")
    result = run_subprocess(["generate", "broken.yaml", "--out", "out"], cwd=tmp_path)
    line = assert_usage_error(
        result.returncode, result.stdout, result.stderr, tmp_path / "out", ["broken.yaml", "YAML"]
    )
    assert "line" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.yaml"]


def test_unknown_task_in_a_real_process(tmp_path: Path):
    recipe = demo_recipe()
    recipe["condition"]["task"] = "juggle"
    (tmp_path / "task.yaml").write_text(yaml.safe_dump(recipe))
    result = run_subprocess(["generate", "task.yaml", "--out", "out"], cwd=tmp_path)
    assert_usage_error(
        result.returncode,
        result.stdout,
        result.stderr,
        tmp_path / "out",
        ["task.yaml", "condition.task", "juggle", "retrieve, upright, clear"],
    )


def test_non_empty_out_is_refused_and_untouched(tmp_path: Path):
    out = tmp_path / "previous"
    (out / "scene_000000").mkdir(parents=True)
    (out / "scene_000000" / "scene.json").write_text('{"keep": true}\n')
    (out / "index.jsonl").write_text("old row\n")
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    result = run_subprocess(["generate", str(DEMO), "--n", "1", "--out", str(out), "--quiet"], cwd=tmp_path)
    assert result.returncode == USAGE_ERROR, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(PREFIX), result.stderr
    assert "--out" in lines[0] and str(out) in lines[0]
    assert result.stdout == ""
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in out.iterdir()) == ["index.jsonl", "scene_000000"]


# ---------------------------------------------------------------- help


def test_help_lists_generate(tmp_path: Path):
    result = run_subprocess(["--help"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "generate" in result.stdout
    assert "usage: scenegen" in result.stdout


def test_generate_help_documents_options(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["generate", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for option in ("--n", "--seed", "--out", "--max-proposals", "pipeline"):
        assert option in text, option


def test_the_command_ends_with_mains_code_and_all_its_output(tmp_path: Path):
    """`scenegen` (cli.entry) ends the process right after the exit handlers: stdout still arrives
    whole (a JSON report, held in the block buffer of a pipe until flushed) and the exit code is
    main's."""
    result = run_subprocess(["audit", str(REPO_ROOT / "data_manifest.yaml"), "--json"], cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["ok"] and report["verified"] and result.stdout.endswith("}\n")


def test_a_batch_short_for_its_realism_filter_says_so(tmp_path: Path, capsys):
    """Every scene settled and tagged, then thrown out by a realism filter no layout passes: the
    warning names the filter and the keys that relax it, besides the cap."""
    recipe = yaml.safe_load((REPO_ROOT / "pipelines" / "procedural.yaml").read_text())
    recipe.update({"n": 1, "render": False, "realism": {"min_score": 1.0}})
    pipeline = tmp_path / "strict.yaml"
    pipeline.write_text(yaml.safe_dump(recipe))
    code = main(["generate", str(pipeline), "--max-tries", "6", "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1
    assert "try cap (6 tries)" in err and "4 of 6 rejections are unrealistic" in err
    assert "realism.min_score" in err
