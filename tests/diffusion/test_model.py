"""The denoiser: permutation equivariance over slots, the guidance formula, the null condition."""

from __future__ import annotations

import pytest
import torch

from scenegen.diffusion.model import (
    NULL,
    REQUIRED,
    UNSPECIFIED,
    ConditionBatch,
    Denoiser,
    DenoiserConfig,
    guided_eps,
    predict_eps,
)

ALPHAS = torch.linspace(0.9999, 1e-4, 1000)  # any cumulative-alpha table
CONFIG = DenoiserConfig(
    object_width=28, scene_width=34, slots=8, n_tasks=3, n_targets=9, n_tags=8, d_model=32, layers=2
)


@pytest.fixture
def model():
    torch.manual_seed(0)
    net = Denoiser(CONFIG)
    for head in (net.object_out, net.scene_out):  # zero-initialised for training; random here
        torch.nn.init.normal_(head.weight, std=0.2)
    return net.eval()


def batch(n: int = 5, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    c = ConditionBatch(
        task=torch.randint(0, CONFIG.n_tasks, (n,), generator=g),
        target=torch.randint(0, CONFIG.n_targets, (n,), generator=g),
        tags=torch.randint(0, 3, (n, CONFIG.n_tags), generator=g),
        pose=torch.randn(n, 7, generator=g),
        pose_null=torch.zeros(n, dtype=torch.bool),
    )
    x = torch.randn(n, CONFIG.slots, CONFIG.object_width, generator=g)
    s = torch.randn(n, CONFIG.scene_width, generator=g)
    t = torch.randint(0, 1000, (n,), generator=g)
    return x, s, t, c


def test_permuting_the_slots_permutes_the_prediction(model):
    x, s, t, c = batch()
    perm = torch.randperm(CONFIG.slots, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        eps_o, eps_s = model(x, s, t, c)
        eps_o_p, eps_s_p = model(x[:, perm], s, t, c)
    assert torch.allclose(eps_o_p, eps_o[:, perm], atol=1e-5)
    assert torch.allclose(eps_s_p, eps_s, atol=1e-5)


@pytest.mark.parametrize("w", [0.0, 0.5, 1.0, 4.0])
def test_guidance_matches_the_formula(model, w: float):
    x, s, t, c = batch()
    with torch.no_grad():
        cond_o, cond_s = predict_eps(model, x, s, t, c, ALPHAS)
        null_o, null_s = predict_eps(model, x, s, t, c.null_like(CONFIG), ALPHAS)
        guided_o, guided_s = guided_eps(model, x, s, t, c, w, ALPHAS)
    assert torch.allclose(guided_o, (1 + w) * cond_o - w * null_o, atol=1e-5)
    assert torch.allclose(guided_s, (1 + w) * cond_s - w * null_s, atol=1e-5)


def test_eps_is_recovered_from_the_velocity(model):
    """The network predicts v = sqrt(a) eps - sqrt(1 - a) x0; predict_eps inverts it given x_t."""
    x, s, t, c = batch()
    a = ALPHAS[t][:, None, None]
    with torch.no_grad():
        v_o, _ = model(x, s, t, c)
        eps_o, _ = predict_eps(model, x, s, t, c, ALPHAS)
    x0 = (x - (1 - a).sqrt() * eps_o) / a.sqrt()
    assert torch.allclose(a.sqrt() * eps_o - (1 - a).sqrt() * x0, v_o, atol=1e-4)


def test_null_condition_is_its_own_input(model):
    """Null differs from 'every tag unspecified' and from any task or target."""
    x, s, t, c = batch()
    null = c.null_like(CONFIG)
    assert (null.tags == NULL).all() and (null.task == CONFIG.n_tasks).all() and null.pose_null.all()
    unspecified = ConditionBatch(c.task, c.target, torch.full_like(c.tags, UNSPECIFIED), c.pose, c.pose_null)
    with torch.no_grad():
        a, _ = model(x, s, t, null)
        b, _ = model(x, s, t, unspecified)
        required = ConditionBatch(c.task, c.target, torch.full_like(c.tags, REQUIRED), c.pose, c.pose_null)
        r, _ = model(x, s, t, required)
    assert not torch.allclose(a, b) and not torch.allclose(b, r)


def test_rows_do_not_interact(model):
    x, s, t, c = batch()
    with torch.no_grad():
        full, _ = model(x, s, t, c)
        first, _ = model(x[:1], s[:1], t[:1], c.index(slice(0, 1)))
    assert torch.allclose(full[:1], first, atol=1e-5)


def test_the_spread_token_conditions_only_where_it_is_given():
    """A model with ``n_spread``: a row's spread bin changes its prediction; a missing spread, -1 and
    the null index are the same null input; the null condition has the null spread; batches with
    and without spread concatenate, the latter null."""
    torch.manual_seed(0)
    net = Denoiser(CONFIG.model_copy(update={"n_spread": 4})).eval()
    torch.nn.init.normal_(net.object_out.weight, std=0.2)
    x, s, t, c = batch(4)
    null = ConditionBatch(*(getattr(c, f) for f in ConditionBatch.FIELDS[:-1]), spread=torch.full((4,), 4))
    with torch.no_grad():
        base = net(x, s, t, c)[0]
        assert torch.equal(base, net(x, s, t, null)[0])
        assert torch.equal(base, net(x, s, t, ConditionBatch.cat([c.index([0, 1]), null.index([2, 3])]))[0])
        given = net(
            x, s, t, ConditionBatch(*(getattr(c, f) for f in ConditionBatch.FIELDS[:-1]), torch.arange(4))
        )
        assert not torch.allclose(base, given[0])
    assert c.null_like(net.config).spread is None  # null
