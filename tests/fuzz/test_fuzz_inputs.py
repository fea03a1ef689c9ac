"""Fuzzing the files and text a user hands to scenegen: recipes, transfer configurations, requests and
checkpoints (tests/fuzzing.py states what every answer must be)."""

from __future__ import annotations

import copy
import io
import pickle
import shutil
from pathlib import Path

import yaml
from fuzzing import (
    PROJECT_ROOT,
    RAW_FILES,
    dump_yaml,
    example_dir,
    mutated_mapping,
    run_cli,
)
from hypothesis import example, given
from hypothesis import strategies as st

PIPELINES = PROJECT_ROOT / "pipelines"
RECIPES = {p.stem: p.read_text() for p in sorted(PIPELINES.glob("*.yaml")) if p.stem != "transfer"}


@st.composite
def edited_text(draw, text: str) -> bytes:
    """``text`` with a few bytes inserted, deleted or the rest cut off (YAML syntax errors, mostly)."""
    data = bytearray(text.encode("utf-8"))
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, len(data)))
        action = draw(st.sampled_from(["insert", "delete", "cut"]))
        if action == "insert":
            data[at:at] = draw(
                st.binary(min_size=1, max_size=8) | st.sampled_from([b":", b"\n  - ", b"{", b"'"])
            )
        elif action == "delete":
            del data[at : at + draw(st.integers(1, 20))]
        else:
            del data[at:]
    return bytes(data)


def recipe_files(recipes: dict[str, str]):
    """A recipe's bytes: a mapping with odd values, edited text, or not a recipe at all."""
    name = st.sampled_from(sorted(recipes))
    return st.one_of(
        name.flatmap(lambda n: mutated_mapping(yaml.safe_load(recipes[n]))).map(dump_yaml),
        name.flatmap(lambda n: edited_text(recipes[n])),
        RAW_FILES,
    )


@given(recipe_files(RECIPES))
@example(raw=b"\r?")  # YAML's complex-key marker: a mapping whose key is not a string (was a TypeError)
@example(raw=b"n: 4\n1: 2\n")
def test_recipes(raw: bytes):
    with example_dir() as root:
        recipe = root / "recipe.yaml"
        recipe.write_bytes(raw)
        run_cli(
            "generate RECIPE", ["generate", recipe, "--check", "--out", root / "out"], root, ["recipe.yaml"]
        )


def _transfer_base(root: Path) -> dict:
    """pipelines/transfer.yaml with its inputs made absolute and its outputs under ``root``."""
    config = yaml.safe_load((PIPELINES / "transfer.yaml").read_text())
    for key in ("reference", "panels"):
        config[key] = str(PROJECT_ROOT / config[key])
    config["reuse_labels"] = [str(PROJECT_ROOT / p) for p in config["reuse_labels"]]
    config["generation"] = {**config["generation"]}
    for key in ("recipe", "diffusion"):
        config["generation"][key] = str(PROJECT_ROOT / config["generation"][key])
    for key in ("label_store", "path_store", "cache", "parts", "out", "manifest", "batches"):
        if key in config:  # version 2 names no manifest yet
            config[key] = str(root / key)
    return config


TRANSFER_TEXT = (PIPELINES / "transfer.yaml").read_text()


@given(st.data())
def test_transfer_configurations(data):
    with example_dir() as root:
        base = _transfer_base(root)
        raw = data.draw(
            st.one_of(mutated_mapping(base).map(dump_yaml), edited_text(TRANSFER_TEXT), RAW_FILES),
            label="config",
        )
        config = root / "transfer.yaml"
        config.write_bytes(raw)
        run_cli(
            "experiment transfer CONFIG",
            ["experiment", "transfer", config, "--check"],
            root,
            ["transfer.yaml"],
        )


WORDS = st.sampled_from(
    "retrieve pick place the a mug spoon bowl can box near edge near_edge toppled clutter under_shelf "
    "occluded on_floor not no without dim_light home tucked, and with".split()
)
REQUESTS = st.one_of(
    st.text(max_size=200),
    st.lists(WORDS | st.text(min_size=1, max_size=12), max_size=12).map(" ".join),
    st.text(min_size=1000, max_size=6000),
)


@given(REQUESTS)
@example(request="--steps")  # as one argument (a separate "--steps" is argparse's usage error)
def test_requests(request: str):
    with example_dir() as root:
        # `--request=TEXT`: how a shell user passes a request that starts with a dash
        argv = [
            "generate",
            PIPELINES / "procedural.yaml",
            "--check",
            f"--request={request}",
            "--out",
            root / "out",
        ]
        run_cli("generate --request", argv, root, ["--request"])


def _torch_pickle() -> bytes:
    import torch

    buffer = io.BytesIO()
    torch.save({"weight": torch.zeros(3)}, buffer)
    return buffer.getvalue()


@st.composite
def broken_checkpoint(draw, source: Path):
    """A function that breaks a copy of the checkpoint folder ``source`` in one way."""
    config = source / "config.json"
    size = (source / "model.safetensors").stat().st_size
    kind = draw(
        st.sampled_from(["truncate", "flip", "pickle", "torch", "encoding", "config", "missing", "file"])
    )
    if kind == "truncate":
        at = draw(st.integers(0, size - 1))
        return kind, lambda d: (d / "model.safetensors").write_bytes(
            (source / "model.safetensors").read_bytes()[:at]
        )
    if kind == "flip":
        at, value = draw(st.integers(0, min(size - 1, 4096))), draw(st.integers(0, 255))

        def flip(d: Path):
            data = bytearray((d / "model.safetensors").read_bytes())
            data[at] = value
            (d / "model.safetensors").write_bytes(bytes(data))

        return kind, flip
    if kind == "pickle":
        return kind, lambda d: (d / "model.safetensors").write_bytes(pickle.dumps({"weight": [0.0] * 3}))
    if kind == "torch":
        return kind, lambda d: (d / "model.safetensors").write_bytes(_torch_pickle())
    if kind == "encoding":
        encoding = draw(st.sampled_from(["utf-16", "utf-32", "latin-1"]))
        text = config.read_text().replace('"', '"\u00e9', 1) if encoding == "latin-1" else config.read_text()
        return kind, lambda d: (d / "config.json").write_bytes(text.encode(encoding))
    if kind == "config":
        import json

        edited = draw(mutated_mapping(json.loads(config.read_text()), edits=2))
        return kind, lambda d: (d / "config.json").write_text(json.dumps(edited))
    if kind == "missing":
        name = draw(st.sampled_from(["config.json", "model.safetensors"]))
        return kind, lambda d: (d / name).unlink()
    return kind, lambda d: (shutil.rmtree(d), d.write_bytes(b"not a folder"))


def _copy_checkpoint(source: Path, to: Path) -> Path:
    to.mkdir()
    for name in ("config.json", "model.safetensors"):
        shutil.copyfile(source / name, to / name)
    return to


@given(broken_checkpoint(PROJECT_ROOT / "assets" / "generator"))
def test_generator_checkpoints(broken):
    _, breaks = broken
    with example_dir() as root:
        checkpoint = _copy_checkpoint(PROJECT_ROOT / "assets" / "generator", root / "ckpt")
        breaks(checkpoint)
        recipe = copy.deepcopy(yaml.safe_load(RECIPES["demo"]))
        recipe["proposer"]["checkpoint"] = str(checkpoint)
        (root / "recipe.yaml").write_bytes(dump_yaml(recipe))
        argv = ["generate", root / "recipe.yaml", "--check", "--out", root / "out"]
        run_cli("generator checkpoint", argv, root, ["ckpt"])


@given(broken_checkpoint(PROJECT_ROOT / "assets" / "policy" / "baseline"))
def test_policy_checkpoints(demo_batch, broken):
    _, breaks = broken
    with example_dir() as root:
        checkpoint = _copy_checkpoint(PROJECT_ROOT / "assets" / "policy" / "baseline", root / "ckpt")
        breaks(checkpoint)
        argv = ["policy", "eval", "--checkpoint", checkpoint, "--scenes", demo_batch, "--n", "0"]
        run_cli(
            "policy eval --checkpoint",
            [*argv, "--out", root / "eval", "--quiet"],
            root,
            ["ckpt", "no feasible"],
        )
