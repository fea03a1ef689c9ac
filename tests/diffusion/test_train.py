"""Training the denoiser at a tiny size on committed reference layouts: the loss goes down, the
checkpoint is safetensors + JSON with provenance, and a resumed run equals an uninterrupted one."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from scenegen.diffusion.train import TrainSettings, train
from scenegen.store.batch import sha256_file
from scenegen.tags.predicates import PREDICATE_VERSION

REFERENCE = Path(__file__).resolve().parents[2] / "assets" / "reference" / "reference.parquet"
TINY = TrainSettings(
    steps=120, batch_size=64, d_model=32, layers=2, heads=2, checkpoint_every=40, split="heldout"
)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ckpt") / "tiny"
    train(REFERENCE, out, TINY, progress=False)
    return out


def test_loss_goes_down(trained: Path):
    losses = json.loads((trained / "config.json").read_text())["losses"]
    assert len(losses) == TINY.steps
    assert np.mean(losses[-20:]) < 0.85 * np.mean(losses[:20])  # measured: 0.76 -> 0.58


def test_checkpoint_records_its_data_and_predicates(trained: Path):
    config = json.loads((trained / "config.json").read_text())
    assert config["data"]["sha256"] == sha256_file(REFERENCE)
    assert config["predicate_version"] == PREDICATE_VERSION
    assert config["step"] == TINY.steps and config["train"] == TINY.model_dump()
    weights = load_file(str(trained / "model.safetensors"))
    assert weights and all(torch.isfinite(v).all() for v in weights.values())
    assert (trained / "loss.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_resumed_training_equals_uninterrupted(trained: Path, tmp_path: Path):
    out = tmp_path / "resumed"
    train(REFERENCE, out, TINY, progress=False, stop_after=40)  # "killed" after the first checkpoint
    assert json.loads((out / "config.json").read_text())["step"] == 40
    train(REFERENCE, out, TINY, progress=False)
    a, b = load_file(str(trained / "model.safetensors")), load_file(str(out / "model.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (
        json.loads((out / "config.json").read_text())["losses"]
        == json.loads((trained / "config.json").read_text())["losses"]
    )


def test_extended_training_equals_training_that_long(trained: Path, tmp_path: Path):
    """The shipped checkpoint was trained this way: N steps, then resumed with a larger --steps."""
    out = tmp_path / "extended"
    train(REFERENCE, out, TINY.model_copy(update={"steps": 40}), progress=False)
    train(REFERENCE, out, TINY, progress=False)
    a, b = load_file(str(trained / "model.safetensors")), load_file(str(out / "model.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    config = json.loads((out / "config.json").read_text())
    assert config["step"] == TINY.steps and config["train"]["steps"] == TINY.steps
    with pytest.raises(ValueError, match="already trained"):
        train(REFERENCE, out, TINY.model_copy(update={"steps": 40}), progress=False)


def test_other_settings_do_not_resume_a_checkpoint(trained: Path):
    with pytest.raises(ValueError, match="another train"):
        train(REFERENCE, trained, TINY.model_copy(update={"lr": 0.5}), progress=False)


def test_train_command(tmp_path: Path, capsys: pytest.CaptureFixture):
    from scenegen.cli import main

    out = tmp_path / "cli"
    args = ["train", "--data", str(REFERENCE), "--out", str(out), "--steps", "10", "--d-model", "16"]
    assert main([*args, "--layers", "1", "--split", "heldout", "--quiet"]) == 0
    assert {"model.safetensors", "config.json", "train_state.safetensors", "loss.png"} <= {
        p.name for p in out.iterdir()
    }
    assert "10 steps" in capsys.readouterr().out
    assert main(["train", "--steps", "0", "--out", str(tmp_path / "never")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("scenegen: error: --steps:")
    assert not (tmp_path / "never").exists()


def test_learning_rate_decays_on_a_half_cosine_over_the_last_share():
    from scenegen.diffusion.train import learning_rate

    s = TrainSettings(steps=100, lr=1e-3, lr_decay=0.5)
    assert [learning_rate(s, i) for i in (0, 49, 50)] == [1e-3, 1e-3, 1e-3]
    assert learning_rate(s, 75) == pytest.approx(0.5e-3)
    assert 0 < learning_rate(s, 99) < 1e-5
    rates = [learning_rate(s, i) for i in range(50, 100)]
    assert all(a > b for a, b in zip(rates[:-1], rates[1:], strict=True))  # falling every step
    assert {learning_rate(TrainSettings(steps=100), i) for i in range(100)} == {1e-3}


def test_a_decaying_run_is_not_extended_and_does_train(tmp_path: Path):
    """With a decaying rate the total steps are part of the schedule: resuming with more is refused.
    The rate reaches the optimizer (the last steps, at a rate near 0, barely move the weights)."""
    out = tmp_path / "decay"
    decay = TINY.model_copy(update={"steps": 40, "lr_decay": 0.5, "checkpoint_every": 20})
    train(REFERENCE, out, decay.model_copy(update={"steps": 40}), progress=False, stop_after=20)
    with pytest.raises(ValueError, match="another train"):
        train(REFERENCE, out, decay.model_copy(update={"steps": 60}), progress=False)
    train(REFERENCE, out, decay, progress=False, stop_after=19)
    before = {k: v.clone() for k, v in load_file(str(out / "train_state.safetensors")).items()}
    train(REFERENCE, out, decay, progress=False)  # the 40th step: lr ~ 1e-6
    after = load_file(str(out / "train_state.safetensors"))
    weights = [k for k in before if k.startswith("model.")]
    change = max(float((after[k] - before[k]).abs().max()) for k in weights)
    assert 0 < change < 1e-4


def test_layout_spread_is_the_mean_pair_distance_of_present_objects():
    from scenegen.assets.catalog import load_catalog
    from scenegen.diffusion.data import layout_spread, spread_bin, spread_edges
    from scenegen.diffusion.encoding import XY_SCALE, SceneEncoding

    encoding = SceneEncoding(load_catalog())
    tokens = -torch.ones(3, encoding.slots, encoding.object_width)
    x = encoding.xyz_cols.start
    for layout, points in enumerate([[(0.0, 0.0), (0.3, 0.4)], [(0, 0), (0.1, 0), (0, 0.1)], [(0.2, 0.2)]]):
        for slot, (px, py) in enumerate(points):
            tokens[layout, slot, 0] = 1.0
            tokens[layout, slot, x : x + 2] = torch.tensor([px, py]) / XY_SCALE
    spread = layout_spread(tokens, encoding)
    assert spread[0] == pytest.approx(0.5) and spread[1] == pytest.approx((0.1 + 0.1 + 0.02**0.5) / 3)
    assert torch.isnan(spread[2])  # one object: no pair
    assert spread_bin(spread, [0.2, 0.4]).tolist() == [2, 0, 3]  # NaN: one past the last bin
    with pytest.raises(ValueError, match="--spread-bins 4: only 2 layouts with two objects or more"):
        spread_edges(spread, 4)
    values = torch.arange(100, dtype=torch.float64)
    edges = spread_edges(values, 4)
    assert torch.bincount(spread_bin(values, edges)).tolist() == [25, 25, 25, 25]


def test_a_spread_conditioned_run_records_its_bins_and_resumes(tmp_path: Path):
    """``spread_bins``: the checkpoint holds the bins' edges and the training layouts' count per bin
    (what a recipe's ``draw_spread`` samples), the model a spread embedding; a run resumes exactly."""
    settings = TINY.model_copy(update={"steps": 40, "checkpoint_every": 20, "spread_bins": 4})
    out = tmp_path / "spread"
    train(REFERENCE, out, settings, progress=False, stop_after=20)
    train(REFERENCE, out, settings, progress=False)
    config = json.loads((out / "config.json").read_text())
    assert len(config["spread"]["edges"]) == 3 and config["denoiser"]["n_spread"] == 5
    counts = config["spread"]["counts"]
    assert sum(counts) == config["data"]["rows"] and max(counts[:4]) - min(counts[:4]) <= 2
    assert "spread.weight" in load_file(str(out / "model.safetensors"))
    once = tmp_path / "once"
    train(REFERENCE, once, settings, progress=False)
    a, b = load_file(str(out / "model.safetensors")), load_file(str(once / "model.safetensors"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="trained with another"):
        train(REFERENCE, out, settings.model_copy(update={"spread_bins": 6}), progress=False)


def test_a_checkpoint_from_before_a_setting_was_added_resumes(trained: Path, tmp_path: Path):
    """A config.json written before ``lr_decay``, ``spread_bins`` and ``n_spread`` existed holds them
    at their defaults: extending such a run is not refused as 'trained with another train'."""
    out = tmp_path / "old"
    shutil.copytree(trained, out)
    config = json.loads((out / "config.json").read_text())
    for key in ("lr_decay", "spread_bins", "p_spread_null"):
        del config["train"][key]
    del config["denoiser"]["n_spread"], config["spread"]
    (out / "config.json").write_text(json.dumps(config))
    extended = train(REFERENCE, out, TINY.model_copy(update={"steps": TINY.steps + 10}), progress=False)
    assert extended["step"] == TINY.steps + 10
    config["train"]["warmup"] = 100  # a setting this scenegen does not know: one line, no traceback
    (out / "config.json").write_text(json.dumps(config))
    with pytest.raises(
        ValueError, match=r"config.json: not a checkpoint this scenegen resumes .*new --out"
    ) as err:
        train(REFERENCE, out, TINY.model_copy(update={"steps": TINY.steps + 20}), progress=False)
    assert "\n" not in str(err.value)


def test_the_cpu_device_writes_the_bytes_of_a_run_without_one(trained: Path, tmp_path: Path):
    """``device="cpu"`` (what ``--device auto`` resolves to without CUDA) moves nothing: every file
    equals the default run's, and config.json names no device."""
    out = tmp_path / "cpu"
    train(REFERENCE, out, TINY, progress=False, device="cpu")
    for name in ("model.safetensors", "train_state.safetensors"):
        assert sha256_file(out / name) == sha256_file(trained / name), name
    config, before = (json.loads((d / "config.json").read_text()) for d in (out, trained))
    assert "device" not in config
    assert {k: v for k, v in config.items() if k != "cpu_seconds"} == {
        k: v for k, v in before.items() if k != "cpu_seconds"
    }


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_a_cuda_run_without_cuda_is_a_one_line_error_before_any_work(tmp_path: Path, capsys):
    from scenegen.cli import main

    out = tmp_path / "cuda"
    assert main(["train", "--steps", "2", "--out", str(out), "--device", "cuda", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--device cuda" in err[0] and "use --device cpu or auto" in err[0]
    assert not out.exists()


def test_the_weighted_loss_is_the_plain_mse_at_unit_weights_and_weighs_what_it_names():
    """Issue 64 point 2: ``tag_loss_weight`` and ``light_loss_weight``. At unit weights the loss is
    the plain MSE to the bit; an error only in the lighting columns counts light_loss_weight times as
    much (relative to the same error elsewhere in the scene token); a layout holding a rare tag counts
    1 + tag_loss_weight times another's."""
    from scenegen.assets.catalog import load_catalog
    from scenegen.diffusion.encoding import SceneEncoding
    from scenegen.diffusion.train import weighted_loss

    encoding = SceneEncoding(load_catalog())
    g = torch.Generator().manual_seed(0)
    err_o = torch.randn(4, encoding.slots, encoding.object_width, generator=g)
    err_s = torch.randn(4, encoding.scene_width, generator=g)
    ones_r, ones_c = torch.ones(4), torch.ones(encoding.scene_width)
    plain = torch.cat([err_o.flatten(1), err_s], dim=1).pow(2).mean()
    assert torch.equal(weighted_loss(err_o, err_s, ones_r, ones_c), plain)
    columns = ones_c.clone()
    columns[encoding.light_cols] = 3.0
    light_only, other_only = torch.zeros_like(err_s), torch.zeros_like(err_s)
    light_only[:, encoding.light_cols.start] = 1.0
    other_only[:, encoding.count_cols.start] = 1.0
    zero_o = torch.zeros_like(err_o)
    ratio = weighted_loss(zero_o, light_only, ones_r, columns) / weighted_loss(
        zero_o, other_only, ones_r, columns
    )
    assert ratio.item() == pytest.approx(3.0)
    rows = torch.tensor([1.0, 5.0, 1.0, 1.0])  # the second layout holds a tag, tag_loss_weight 4
    first, second = torch.zeros_like(err_s), torch.zeros_like(err_s)
    first[0, 0], second[1, 0] = 1.0, 1.0
    ratio = weighted_loss(zero_o, second, rows, ones_c) / weighted_loss(zero_o, first, rows, ones_c)
    assert ratio.item() == pytest.approx(5.0)


def test_a_weighted_run_records_its_weights_and_trains(tmp_path: Path):
    settings = TrainSettings(
        steps=120,
        batch_size=64,
        d_model=32,
        layers=2,
        heads=2,
        checkpoint_every=120,
        split="heldout",
        tag_loss_weight=2.0,
        light_loss_weight=4.0,
    )
    config = train(REFERENCE, tmp_path / "weighted", settings, progress=False)
    saved = json.loads((tmp_path / "weighted" / "config.json").read_text())
    assert saved["train"]["tag_loss_weight"] == 2.0 and saved["train"]["light_loss_weight"] == 4.0
    losses = config["losses"]
    assert np.mean(losses[-10:]) < np.mean(losses[:10])


def test_a_wholly_null_row_is_told_apart_from_a_partly_null_one():
    """The rows that teach the unconditional distribution (``null_rows``) count 1 in the loss
    whatever their tags (train.py), so that tag weighting does not change the null condition's
    tag rates; rows drawn by rare oversampling are never wholly null."""
    from scenegen.assets.catalog import load_catalog
    from scenegen.core.files import load_rows
    from scenegen.diffusion.data import layout_tensors, null_rows, tasks, training_conditions
    from scenegen.diffusion.encoding import SceneEncoding

    encoding = SceneEncoding(load_catalog())
    data = layout_tensors(load_rows(REFERENCE, "heldout")[:32], encoding)
    n_tasks, n_targets = len(tasks()), len(encoding.catalog.categories)
    rows = torch.arange(32)
    rare = torch.zeros(32, dtype=torch.bool)
    rare[:8] = True
    g = torch.Generator().manual_seed(0)
    every = training_conditions(data, rows, rare, n_tasks, n_targets, g, p_null=1.0)
    assert null_rows(every, n_tasks, n_targets).tolist() == [False] * 8 + [True] * 24
    partly = training_conditions(data, rows, rare, n_tasks, n_targets, g, p_null=0.0, p_field=0.3)
    assert (partly.task == n_tasks).any() and partly.pose_null.any()  # some fields nulled, one by one
    assert not null_rows(partly, n_tasks, n_targets).any()  # never all eleven at once here
