"""Pilot: sampler version 3's top grasps against two changes, paired draw by draw (the same closing
axis and visible point in each variant), on natural:600 layouts chosen by target category (training
side only), executed from the settled state under dt5:

- ``v3``: the committed draw (centre midway between the visible extremes along the axis on a 1 cm
  line; grip site 0-4 cm under the line's top, never under the lowest visible point + 1 cm);
- ``end``: where the line is wider than the hand spans (primitives.MAX_GRASP_WIDTH), the centre goes
  EDGE_IN inside the end of the line nearer the drawn point (a rim, an edge) instead of the middle;
- ``end_mid``: ``end``, and the grip site never under the line's mid-height (not the lowest visible
  point + 1 cm: a flat utensil's whole body lies under that clearance).

    python benchmarks/results/proposal_pilots/sampler4.py PER_THIN PER_OTHER DRAWS
"""
import collections
import sys
import time

import numpy as np

from scenegen.env.physics import physics_named
from scenegen.env.scenes import scene_sha256
from scenegen.experiment.closed_loop import _init_worker, episode_env
from scenegen.experiment.proposal_labels import GRID, label_layouts, point_rng, simulate_candidates
from scenegen.manipulation.primitives import MAX_GRASP_WIDTH
from scenegen.manipulation.proposals import STRIP, TABLE_CLEARANCE, Candidate, _unit
from scenegen.perception.observation import observe

EDGE_IN = 0.015
THIN = ("fork", "spoon", "bowl", "knife")
OTHER = ("bottle", "can", "box", "mug")


def draw(pts, rng, variant):
    low = float(np.percentile(pts[:, 2], 2)) + TABLE_CLEARANCE
    axis = np.array(_unit(rng.uniform(0, np.pi)))
    across = np.array([-axis[1], axis[0]])
    p = pts[rng.integers(len(pts))]
    line = pts[np.abs((pts[:, :2] - p[:2]) @ across) < STRIP]
    along = line[:, :2] @ axis
    lo, hi = along.min(), along.max()
    mid = 0.5 * (lo + hi)
    if variant != "v3" and hi - lo > MAX_GRASP_WIDTH:
        u = p[:2] @ axis
        mid = lo + EDGE_IN if u - lo <= hi - u else hi - EDGE_IN
    centre = p[:2] + axis * (mid - p[:2] @ axis)
    top = float(np.percentile(line[:, 2], 98))
    floor = low if variant != "end_mid" else 0.5 * (float(np.percentile(line[:, 2], 2)) + top)
    z = max(floor, top - rng.uniform(0.0, 0.04))
    c = Candidate("grasp", {"approach": "top", "position": [float(centre[0]), float(centre[1]), float(z)],
                            "heading": axis.tolist()})
    return Candidate(c.action, GRID.snap(c.params))


per_thin, per_other, draws = (int(a) for a in sys.argv[1:4])
_init_worker()
physics = physics_named("dt5")
scenes = label_layouts(["natural:600"])["natural:600"]
chosen, counts = [], collections.Counter()
for s in scenes:
    cat = next(o.category for o in s.objects if o.name == s.target)
    want = per_thin if cat in THIN else per_other if cat in OTHER else 0
    if counts[cat] < want:
        counts[cat] += 1
        chosen.append((cat, s))
wins = collections.defaultdict(lambda: collections.defaultdict(list))
t0 = time.process_time()
for cat, scene in chosen:
    sha = scene_sha256(scene)
    env = episode_env(scene, physics)
    env.reset_to(scene)
    _, view = observe(env, image=False)
    if view is None:
        continue
    pts = np.asarray(view.target_points, float)
    line = []
    for variant in ("v3", "end", "end_mid"):
        results = []
        for i in range(draws):
            c = draw(pts, point_rng(0, sha, [f"sampler4:{i}"]), variant)
            results.append(bool(simulate_candidates(scene, [c], physics)[-1]["success"]))
        wins[cat][variant].append(results)
        line.append(f"{variant} {sum(results)}/{draws}")
    print(cat, sha[:8], ", ".join(line), flush=True)
print("category: per draw (layouts with a lift) for v3 / end / end_mid")
for cat, by in wins.items():
    print(cat, " / ".join(f"{np.mean(sum(by[v], [])):.2f} ({sum(any(r) for r in by[v])}/{len(by[v])})"
                          for v in ("v3", "end", "end_mid")))
for v in ("v3", "end", "end_mid"):
    every = [r for by in wins.values() for r in by[v]]
    print(v, f"per draw {np.mean(sum(every, [])):.3f}, layouts with a lift {np.mean([any(r) for r in every]):.3f}")
print(f"{time.process_time() - t0:.0f} CPU-s")
