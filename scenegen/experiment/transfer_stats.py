"""Success rates with hierarchical bootstrap intervals: the training seed and the panel scene are both
sources of variation, so each replicate resamples the seeds (with replacement) and, independently, the
panel's scenes, and takes the mean success over the resampled (seed, scene) grid. A difference of two
arms resamples the scenes once for both (the same panel: a paired comparison) and each arm's seeds on
its own. Intervals are the replicates' 2.5 and 97.5 percentiles."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

import numpy as np

from scenegen.policy.success_table import wilson


def success_grid(records: Sequence[dict], runs: Sequence[str], scene_ids: Sequence[str]) -> np.ndarray:
    """(runs, scenes) 0/1 success of each run (one training seed of an arm) on each scene."""
    index = {(r["policy"], r["scene_id"]): r["success"] for r in records}
    missing = [(run, s) for run in runs for s in scene_ids if (run, s) not in index]
    if missing:
        raise ValueError(f"no episode of {missing[0][0]} on {missing[0][1]} ({len(missing)} missing)")
    return np.array([[float(index[(run, s)]) for s in scene_ids] for run in runs])


def _draws(rng: np.random.Generator, n: int, replicates: int) -> np.ndarray:
    return rng.integers(0, n, size=(replicates, n))


def _grid_means(grid: np.ndarray, seeds: np.ndarray, scenes: np.ndarray) -> np.ndarray:
    # mean over the resampled seeds of the mean over the resampled scenes, per replicate
    per_seed = np.stack([grid[:, s].mean(axis=1) for s in scenes])  # (replicates, runs)
    return np.take_along_axis(per_seed, seeds, axis=1).mean(axis=1)


def interval(grid: np.ndarray, replicates: int, seed: int) -> dict:
    """Mean success of a (runs, scenes) grid and its 95 % hierarchical bootstrap interval."""
    rng = np.random.default_rng(seed)
    seeds = _draws(rng, grid.shape[0], replicates)
    scenes = _draws(rng, grid.shape[1], replicates)
    values = _grid_means(grid, seeds, scenes)
    return _summary(grid.mean(), values, grid.shape)


def difference(first: np.ndarray, second: np.ndarray, replicates: int, seed: int) -> dict:
    """``first`` minus ``second`` (grids over the same scenes) and its paired 95 % interval."""
    if first.shape[1] != second.shape[1]:
        raise ValueError("a difference needs both arms on the same panel scenes")
    rng = np.random.default_rng(seed)
    scenes = _draws(rng, first.shape[1], replicates)
    a = _grid_means(first, _draws(rng, first.shape[0], replicates), scenes)
    b = _grid_means(second, _draws(rng, second.shape[0], replicates), scenes)
    return _summary(first.mean() - second.mean(), a - b, first.shape)


def _summary(mean: float, values: np.ndarray, shape: tuple) -> dict:
    low, high = np.percentile(values, [2.5, 97.5])
    return {
        "mean": round(float(mean), 4),
        "low": round(float(low), 4),
        "high": round(float(high), 4),
        "seeds": int(shape[0]),
        "scenes": int(shape[1]),
    }


def share(gain_arm: np.ndarray, base: np.ndarray, arm: np.ndarray, replicates: int, seed: int) -> dict:
    """(arm - base) / (gain_arm - base): the fraction of ``gain_arm``'s gain over ``base`` that ``arm``
    reaches (D's share of C's gain over A+), grids over the same scenes; its 95 % interval with the
    scenes drawn once for all three and each arm's seeds on its own. Replicates where the gain is 0
    are dropped (the share is undefined there, counted in ``undefined``); the point value is None when
    the measured gain is 0."""
    if not gain_arm.shape[1] == base.shape[1] == arm.shape[1]:
        raise ValueError("a share needs the three arms on the same panel scenes")
    rng = np.random.default_rng(seed)
    scenes = _draws(rng, base.shape[1], replicates)
    means = [_grid_means(g, _draws(rng, g.shape[0], replicates), scenes) for g in (gain_arm, base, arm)]
    gain, reached = means[0] - means[1], means[2] - means[1]
    defined = np.abs(gain) > 1e-12
    point_gain = gain_arm.mean() - base.mean()
    low, high = (
        np.percentile(reached[defined] / gain[defined], [2.5, 97.5]) if defined.any() else (np.nan,) * 2
    )
    return {
        "mean": None if abs(point_gain) < 1e-12 else round(float((arm.mean() - base.mean()) / point_gain), 4),
        "low": round(float(low), 4),
        "high": round(float(high), 4),
        "undefined": int((~defined).sum()),
    }


def episodes_block(records: list[dict]) -> dict:
    """Success with a 95 % Wilson interval, perception failures, failure labels and out-of-time
    episodes of ``records`` (episode records of the closed loop or the proposal loop)."""
    n, k = len(records), sum(r["success"] for r in records)
    low, high = wilson(k, n) if n else (None, None)
    perception = sum("perception" in r["attempt_failures"] for r in records)
    first = [r["perception"][0] for r in records if r["perception"] and r["perception"][0]]
    overlap = [s["hit_iou"] for s in first if "hit_iou" in s]  # None unless every decision has it
    return {
        "episodes": n,
        "success": round(k / n, 4) if n else None,
        "interval": [round(low, 4), round(high, 4)] if n else None,
        "perception_failures": perception,
        "first_decision_hit": round(sum(s["hit"] for s in first) / len(first), 4) if first else None,
        "first_decision_hit_iou": (
            round(sum(overlap) / len(overlap), 4) if overlap and len(overlap) == len(first) else None
        ),
        "failures": dict(sorted(Counter(r["failure"] for r in records if not r["success"]).items())),
        "out_of_time": sum(r["out_of_time"] for r in records),
    }
