"""Layout realism: how far a set of layouts is from the reference set, measured on layout features.

A layout (one reference Parquet row, or a stored scene through :func:`record_row`) becomes a
fixed-length vector by :func:`layout_features`; two sets of vectors are compared by a classifier
two-sample test (:func:`c2st`: held-out accuracy of a classifier telling them apart, 0.5 when it
cannot) and by a kernel distance (:func:`mmd`: unbiased MMD^2 with a permutation p-value).
:func:`distort` and :func:`power` measure how small a change the tests notice. One scene's
typicality is scenegen/analysis/scene_score.py.

Pure numpy/torch: no MuJoCo simulation, no renderer. Features are in world-frame metres and radians
(docs/realism.md lists each one with its unit).
"""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from scenegen.core.files import SPLITS, load_rows  # noqa: F401 - both are part of this module's face
from scenegen.core.layout import FURNITURE, TABLE_TOP_Z

if TYPE_CHECKING:
    import torch  # imported where the classifier is trained: the realism scorer of every worker is numpy

HELDOUT_EVERY = 5  # a layout whose proposal index % 5 == 0 is held out
SUPPORT_KINDS = ("table", "shelf", "bin", "floor", "stacked")
FURNITURE_KINDS = tuple(sorted(FURNITURE))
# Layout features before the per-category counts, and after them (see layout_features).
_HEAD = (
    "n_objects",
    "target_x",
    "target_y",
    "target_height",
    "target_tilt",
    "pair_distance_min",
    "pair_distance_mean",
    "target_nn_distance",
)
_TAIL = (
    *(f"support_{kind}" for kind in SUPPORT_KINDS),
    "mean_abs_x",
    "mean_abs_y",
    "ambient",
    "light_total",
    *(f"has_{kind}" for kind in FURNITURE_KINDS),
)
Z_95 = 1.959963984540054  # two-sided 95 % normal quantile

# The C2ST classifier: a 1-hidden-layer MLP trained full-batch with Adam. Small on purpose: the
# reference sets are hundreds of rows, and a bigger net only memorises its training folds.
C2ST_HIDDEN = 16
C2ST_STEPS = 300
C2ST_LR = 0.01
C2ST_WEIGHT_DECAY = 1e-3
MMD_PERMUTATIONS = 200


# ---------------------------------------------------------------- features


@functools.lru_cache(maxsize=1)
def feature_categories() -> tuple[str, ...]:
    from scenegen.assets.catalog import load_catalog

    return load_catalog().categories


def feature_names(categories: Sequence[str] | None = None) -> tuple[str, ...]:
    """Names of the entries of :func:`layout_features`, in order; ``categories`` defaults to the
    asset catalog's (sorted) categories."""
    categories = feature_categories() if categories is None else tuple(categories)
    return (*_HEAD, *(f"count_{c}" for c in categories), *_TAIL)


def __getattr__(name: str):
    # FEATURE_NAMES depends on the asset catalog; resolving it lazily keeps `import scenegen.analysis.realism`
    # from reading the catalog.
    if name == "FEATURE_NAMES":
        return feature_names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _mean(values: Sequence[float]) -> float:
    # math.fsum is exactly rounded, hence independent of the order of the objects.
    return math.fsum(values) / len(values) if len(values) else 0.0


def _tilt(quat: Sequence[float]) -> float:
    """Angle (rad) between a body's +z axis and world +z, for a wxyz quaternion."""
    w, x, y, z = np.asarray(quat, float) / np.linalg.norm(quat)
    return float(math.acos(min(1.0, max(-1.0, 1.0 - 2.0 * (x * x + y * y)))))


def support_kind(support: str, object_names: Sequence[str]) -> str:
    """The kind (one of ``SUPPORT_KINDS``) of an object's ``support`` name: ``table``, ``floor``, a
    furniture piece (named by its kind, as the proposers name it), or another object (``stacked``)."""
    if support in ("table", "floor") or support in FURNITURE_KINDS:
        return support
    if support in object_names:
        return "stacked"
    raise ValueError(
        f"support {support!r} is neither table, floor, a furniture kind ({', '.join(FURNITURE_KINDS)}) "
        "nor another object of the layout; layout_features knows only these supports"
    )


def layout_features(row: dict, categories: Sequence[str] | None = None) -> np.ndarray:
    """The feature vector (D,) of one layout, float64, in the order of :func:`feature_names`.

    ``row`` has the shape of a reference Parquet row (``layout_row``): ``target``,
    ``objects`` (name, category, support, position, quat), ``furniture`` (kind), ``ambient`` and
    ``lights`` (colour, intensity). Every feature is a count, a share, a sum, a mean or a minimum
    over objects, so the vector does not depend on the order of the objects; it is defined for any
    number of them. Positions are world-frame metres: the table centre is the origin of x and y, and
    heights are measured from the table top (``layout.TABLE_TOP_Z``).

    - ``n_objects``: number of objects (count).
    - ``target_x``, ``target_y``: the target's centre relative to the table centre (m).
    - ``target_height``: the target's centre above the table top (m; about -0.75 on the floor).
    - ``target_tilt``: angle between the target's body +z axis and world up (rad, 0 to pi).
    - ``pair_distance_min``, ``pair_distance_mean``: smallest and mean xy distance between the
      centres of two objects, over all pairs (m; 0 with fewer than two objects).
    - ``target_nn_distance``: xy distance from the target's centre to the nearest other object's
      (m; 0 when the target is alone).
    - ``count_<category>``: objects of each catalog category, the target included (count).
    - ``support_<kind>``: share of objects resting on the table, the shelf, the bin, the floor, or
      stacked on another object (0-1; they sum to 1 when there is an object).
    - ``mean_abs_x``, ``mean_abs_y``: mean |x| and |y| of the object centres (m).
    - ``ambient``: ambient light, mean over RGB (0-1).
    - ``light_total``: sum over spot lights of intensity x mean colour, i.e. the diffuse strength
      MuJoCo gets (unitless).
    - ``has_<kind>``: whether a furniture piece of that kind is present (0/1).
    """
    categories = feature_categories() if categories is None else tuple(categories)
    objects = row["objects"]
    names = [o["name"] for o in objects]
    target = [o for o in objects if o["name"] == row["target"]]
    if len(target) != 1:
        raise ValueError(f"row target {row['target']!r} must name exactly one object; objects: {names}")
    target = target[0]
    xy = np.array([o["position"][:2] for o in objects], float).reshape(-1, 2)
    dist = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    pairs = dist[np.triu_indices(len(objects), k=1)]
    t = names.index(target["name"])
    others = np.delete(dist[t], t)

    counts = dict.fromkeys(categories, 0)
    for o in objects:
        if o["category"] not in counts:
            raise ValueError(
                f"object {o['name']}: category {o['category']!r} is not among the feature categories "
                f"({', '.join(categories)}); pass the categories of the catalog the layout came from"
            )
        counts[o["category"]] += 1
    kinds = [support_kind(o["support"], names) for o in objects]
    present = {f["kind"] for f in row["furniture"]}
    light_total = math.fsum(light["intensity"] * _mean(light["colour"]) for light in row["lights"])

    values = [
        len(objects),
        target["position"][0],
        target["position"][1],
        target["position"][2] - TABLE_TOP_Z,
        _tilt(target["quat"]),
        float(pairs.min()) if len(pairs) else 0.0,
        _mean(pairs.tolist()),
        float(others.min()) if len(others) else 0.0,
        *(counts[c] for c in categories),
        *(kinds.count(kind) / len(objects) for kind in SUPPORT_KINDS),
        _mean(np.abs(xy[:, 0]).tolist()),
        _mean(np.abs(xy[:, 1]).tolist()),
        row["ambient"],
        light_total,
        *(float(kind in present) for kind in FURNITURE_KINDS),
    ]
    return np.asarray(values, dtype=np.float64)


def feature_matrix(rows: Sequence[dict], categories: Sequence[str] | None = None) -> np.ndarray:
    """Features of many layouts, (N, D) float64, one row per layout."""
    categories = feature_categories() if categories is None else tuple(categories)
    if not rows:
        return np.zeros((0, len(feature_names(categories))))
    return np.stack([layout_features(row, categories) for row in rows])


def layout_row(record) -> dict:
    """One reference Parquet row of a ``SceneRecord``: the request, the settled layout, the lighting and
    every tag's measurement (``tag_<tag>``, ``value_<tag>``); the columns of the reference set."""
    from scenegen.schema.condition import TAGS

    target = next(o for o in record.objects if o.name == record.target)
    row = {
        "index": record.proposal_index,
        "split": "heldout" if record.proposal_index % HELDOUT_EVERY == 0 else "train",
        "task": record.condition.task,
        "target_category": target.category,
        "target_asset": target.asset,
        "target": record.target,
        "robot_pose": list(record.condition.robot_pose),
        "n_objects": len(record.objects),
        "objects": [
            {
                "name": o.name,
                "asset": o.asset,
                "category": o.category,
                "support": o.support,
                "resting_pose": o.resting_pose,
                "position": list(o.position),
                "quat": list(o.quat),
            }
            for o in record.objects
        ],
        "furniture": [
            {"kind": f.kind, "x": f.position[0], "y": f.position[1], "yaw": f.yaw} for f in record.furniture
        ],
        "ambient": float(np.mean(record.lighting.ambient)),
        "lights": [
            {
                "position": list(light.position),
                "direction": list(light.direction),
                "colour": list(light.colour),
                "intensity": light.intensity,
                "cast_shadow": light.cast_shadow,
            }
            for light in record.lighting.lights
        ],
    }
    for tag in TAGS:
        row[f"tag_{tag}"] = record.tags[tag].holds
        row[f"value_{tag}"] = record.tags[tag].value
    return row


def record_row(record) -> dict:
    """A stored scene (``SceneRecord``) as a reference Parquet row, so its features can be compared.

    It is :func:`layout_row`; a record without the full tag set (tags are not features)
    gets NaN tag values instead of failing.
    """
    from scenegen.schema.condition import TAGS
    from scenegen.schema.scene import TagValue

    missing = [tag for tag in TAGS if tag not in record.tags]
    if missing:
        blank = TagValue(holds=False, value=float("nan"), threshold=float("nan"), unit="")
        record = record.model_copy(update={"tags": {**record.tags, **dict.fromkeys(missing, blank)}})
    return layout_row(record)


def reference_features(path: Path, split: str | None = "train") -> np.ndarray:
    """Feature matrix (N, D) of the layouts of one split of a reference Parquet file."""
    return feature_matrix(load_rows(path, split))


def distort(rows: Sequence[dict], fraction: float = 0.3, shift: float = 0.02, *, seed: int) -> list[dict]:
    """Copies of ``rows`` with, in each layout, ``floor(fraction * n + 0.5)`` of its n objects (drawn
    uniformly) moved ``shift`` metres in xy in a uniformly random direction.

    A perturbation of the features only: nothing is re-settled, and objects stacked on a moved one
    stay where they were. Layout i draws from ``SeedSequence([seed, i])``.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction {fraction}: give the share of objects to move, between 0 and 1")
    out = []
    for i, row in enumerate(rows):
        rng = np.random.default_rng(np.random.SeedSequence([seed, i]))
        row = copy.deepcopy(row)
        objects = row["objects"]
        k = int(math.floor(fraction * len(objects) + 0.5))
        for j in rng.choice(len(objects), size=k, replace=False):
            angle = rng.uniform(0.0, 2.0 * math.pi)
            position = list(objects[j]["position"])
            position[0] += shift * math.cos(angle)
            position[1] += shift * math.sin(angle)
            objects[j]["position"] = position
        out.append(row)
    return out


# ---------------------------------------------------------------- two-sample tests


def _check_samples(a: np.ndarray, b: np.ndarray, least: int) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"samples must be (N, D) with the same D; got {a.shape} and {b.shape}")
    if min(len(a), len(b)) < least:
        raise ValueError(f"each sample needs at least {least} rows; got {len(a)} and {len(b)}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ValueError("samples contain NaN or infinite features")
    return a, b


def wilson_interval(successes: int, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (95 % for the default z)."""
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


@dataclass(frozen=True)
class C2STResult:
    """Classifier two-sample test: pooled held-out ``accuracy`` over ``n`` predictions (both samples
    together, balanced), its 95 % Wilson interval ``ci``; 0.5 means indistinguishable."""

    accuracy: float
    ci: tuple[float, float]
    n: int

    @property
    def distinguishes(self) -> bool:
        """Whether the whole interval lies above chance (0.5)."""
        return self.ci[0] > 0.5


def _torch_seed(seed: int, *key: int) -> int:
    return int(np.random.SeedSequence([seed, *key]).generate_state(1, np.uint64)[0]) >> 1


def _train_classifier(x: torch.Tensor, y: torch.Tensor, generator: torch.Generator) -> torch.nn.Module:
    """A 1-hidden-layer MLP (D -> C2ST_HIDDEN -> 1 logit) fitted full-batch; init drawn from
    ``generator`` (PyTorch's default Linear init, uniform +-1/sqrt(fan_in))."""
    import torch

    model = torch.nn.Sequential(
        torch.nn.Linear(x.shape[1], C2ST_HIDDEN), torch.nn.Tanh(), torch.nn.Linear(C2ST_HIDDEN, 1)
    )
    with torch.no_grad():
        for layer in (model[0], model[2]):
            bound = 1.0 / math.sqrt(layer.in_features)
            layer.weight.uniform_(-bound, bound, generator=generator)
            layer.bias.uniform_(-bound, bound, generator=generator)
    optimiser = torch.optim.Adam(model.parameters(), lr=C2ST_LR, weight_decay=C2ST_WEIGHT_DECAY)
    loss_fn = torch.nn.BCEWithLogitsLoss()
    for _ in range(C2ST_STEPS):
        optimiser.zero_grad()
        loss_fn(model(x).squeeze(1), y).backward()
        optimiser.step()
    return model


def c2st(a: np.ndarray, b: np.ndarray, seed: int, folds: int = 5) -> C2STResult:
    """Classifier two-sample test of feature matrices ``a`` (N_a, D) and ``b`` (N_b, D).

    The larger sample is subsampled (drawn with ``seed``) to the size n of the smaller; the 2n rows
    are split into ``folds`` folds, each holding the same number of rows of each sample (+-1). For
    each fold a small MLP is trained on the other folds, standardized by the training folds' mean
    and standard deviation, and predicts the held-out fold. The accuracy over all 2n held-out
    predictions and its Wilson interval are returned (the interval treats the predictions as
    independent, which cross-validation only approximates). Deterministic for a seed: weights come
    from a seeded ``torch.Generator`` and torch runs on one thread inside this call.
    """
    a, b = _check_samples(a, b, least=folds)
    if folds < 2:
        raise ValueError(f"folds={folds}: cross-validation needs at least 2 folds")
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0]))
    n = min(len(a), len(b))
    a = a[rng.permutation(len(a))[:n]]
    b = b[rng.permutation(len(b))[:n]]
    x = np.concatenate([a, b])
    y = np.concatenate([np.zeros(n), np.ones(n)])
    fold_of = np.concatenate([np.arange(n) % folds, np.arange(n) % folds])

    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one thread: reductions in a fixed order, the same numbers every run
    try:
        correct = 0
        for fold in range(folds):
            train, test = fold_of != fold, fold_of == fold
            mean, std = x[train].mean(axis=0), x[train].std(axis=0)
            std = np.where(std > 1e-12, std, 1.0)  # a constant feature carries no information
            xt = torch.as_tensor((x[train] - mean) / std, dtype=torch.float32)
            yt = torch.as_tensor(y[train], dtype=torch.float32)
            generator = torch.Generator().manual_seed(_torch_seed(seed, 1, fold))
            model = _train_classifier(xt, yt, generator)
            with torch.no_grad():
                logits = model(torch.as_tensor((x[test] - mean) / std, dtype=torch.float32)).squeeze(1)
            correct += int(((logits > 0).numpy() == (y[test] == 1)).sum())
    finally:
        torch.set_num_threads(threads)
    return C2STResult(accuracy=correct / (2 * n), ci=wilson_interval(correct, 2 * n), n=2 * n)


@dataclass(frozen=True)
class MMDResult:
    """Unbiased MMD^2 (RBF kernel of ``bandwidth``, in standardized feature units) and the share of
    ``n_permutations`` label permutations with an MMD^2 as large (+1 smoothed): ``p_value``."""

    mmd2: float
    p_value: float
    bandwidth: float
    n_permutations: int


def mmd(a: np.ndarray, b: np.ndarray, seed: int, n_permutations: int = MMD_PERMUTATIONS) -> MMDResult:
    """Kernel two-sample test of feature matrices ``a`` (m, D) and ``b`` (n, D).

    Features are standardized on the pooled sample; the kernel is exp(-d^2 / (2 s^2)) with s the
    median pairwise distance of the pooled sample (median heuristic). MMD^2 is the unbiased
    estimate (diagonal terms left out). The p-value is (1 + #{permuted MMD^2 >= observed}) /
    (1 + n_permutations), the permutations of the sample labels drawn with ``seed``.
    """
    a, b = _check_samples(a, b, least=2)
    x = np.concatenate([a, b])
    std = x.std(axis=0)
    x = (x - x.mean(axis=0)) / np.where(std > 1e-12, std, 1.0)
    sq = np.sum(x * x, axis=1)
    d2 = np.maximum(sq[:, None] + sq[None, :] - 2.0 * x @ x.T, 0.0)
    off = d2[np.triu_indices(len(x), k=1)]
    bandwidth = float(np.sqrt(np.median(off)))
    if bandwidth <= 0.0:  # more than half the pairs coincide: fall back to the mean distance
        bandwidth = float(np.sqrt(off.mean())) or 1.0
    kernel = np.exp(-d2 / (2.0 * bandwidth**2))
    m, n = len(a), len(b)

    def mmd2(labels: np.ndarray) -> np.ndarray:
        """MMD^2 for label rows (P, m+n), 1 = second sample."""
        in_b = labels.astype(np.float64)
        in_a = 1.0 - in_b
        ka, kb = kernel @ in_a.T, kernel @ in_b.T  # (m+n, P)
        aa = (np.einsum("pi,ip->p", in_a, ka) - m) / (m * (m - 1))  # the kernel's diagonal is 1
        bb = (np.einsum("pi,ip->p", in_b, kb) - n) / (n * (n - 1))
        ab = np.einsum("pi,ip->p", in_a, kb) / (m * n)
        return aa + bb - 2.0 * ab

    labels = np.concatenate([np.zeros(m, bool), np.ones(n, bool)])
    observed = float(mmd2(labels[None])[0])
    rng = np.random.default_rng(np.random.SeedSequence([seed, 2]))
    permuted = mmd2(np.stack([rng.permutation(labels) for _ in range(n_permutations)]))
    p_value = (1 + int(np.sum(permuted >= observed))) / (1 + n_permutations)
    return MMDResult(mmd2=observed, p_value=p_value, bandwidth=bandwidth, n_permutations=n_permutations)


# ---------------------------------------------------------------- power


def power(
    rows: Sequence[dict],
    n_trials: int,
    seed: int,
    fraction: float = 0.3,
    shift: float = 0.02,
    folds: int = 5,
) -> float:
    """Share of ``n_trials`` in which :func:`c2st` tells a layout set from a distorted one.

    Each trial splits ``rows`` at random into two disjoint halves, applies :func:`distort`
    (``fraction``, ``shift``) to the second, and counts a detection when the C2ST interval lies
    above 0.5. With ``shift=0`` it measures the false-detection rate instead. Trial t draws from
    ``SeedSequence([seed, t])``.
    """
    if len(rows) < 2 * folds:
        raise ValueError(
            f"power needs at least {2 * folds} rows (two halves of {folds} folds); got {len(rows)}"
        )
    categories = feature_categories()
    half = len(rows) // 2
    detected = 0
    for trial in range(n_trials):
        trial_seed = _torch_seed(seed, 3, trial)
        order = np.random.default_rng(np.random.SeedSequence([seed, trial])).permutation(len(rows))
        first = [rows[i] for i in order[:half]]
        second = distort([rows[i] for i in order[half : 2 * half]], fraction, shift, seed=trial_seed)
        result = c2st(
            feature_matrix(first, categories), feature_matrix(second, categories), trial_seed, folds
        )
        detected += result.distinguishes
    return detected / n_trials
