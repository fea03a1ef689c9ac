"""Pilot: top grasps drawn antipodally on the seen footprint (a closing axis at random; the grasp
centre midway between the extremes, along that axis, of the visible points on a 1 cm line through a
random visible point) against sampler 2's (a random visible point, a random axis), on the first N
labelled natural:600 layouts, 6 draws each, executed from the settled state under dt5."""
import json, sys, time
from pathlib import Path
import numpy as np
from scenegen.env.physics import physics_named
from scenegen.env.scenes import scene_sha256
from scenegen.experiment.closed_loop import episode_env, _init_worker
from scenegen.experiment.proposal_labels import label_layouts, open_labels, point_rng, simulate_candidates
from scenegen.manipulation.proposals import Candidate, TABLE_CLEARANCE, _unit
from scenegen.perception.observation import observe

n = int(sys.argv[1]) if len(sys.argv) > 1 else 20
skip = int(sys.argv[2]) if len(sys.argv) > 2 else 0
_init_worker()
config, store, views = open_labels(Path("runs/proposals"))
physics = physics_named(config.physics)
scenes = list(label_layouts(["natural:600"], n)["natural:600"])[skip:]
old = {}
for line in open("runs/proposals/paths.jsonl"):
    r = json.loads(line)
    c = r["candidate"]
    if len(r["tokens"]) == 1 and c.get("approach") == "top" and c["action"] == "grasp":
        old.setdefault(r["scene_sha256"], []).append(r["success"])
rows = []
t0 = time.process_time()
for scene in scenes:
    sha = scene_sha256(scene)
    env = episode_env(scene, physics); env.reset_to(scene)
    _, view = observe(env, image=False)
    if view is None:
        continue
    pts = np.asarray(view.target_points, float)
    low = float(np.percentile(pts[:, 2], 2)) + TABLE_CLEARANCE
    rng = point_rng(0, sha, ["sampler3"])
    wins = []
    for _ in range(6):
        theta = rng.uniform(0, np.pi); axis = np.array(_unit(theta)); across = np.array([-axis[1], axis[0]])
        p = pts[rng.integers(len(pts))]
        line = pts[np.abs((pts[:, :2] - p[:2]) @ across) < 0.01]
        u = line[:, :2] @ axis
        centre = p[:2] + axis * (0.5 * (u.min() + u.max()) - p[:2] @ axis)
        z = float(max(low, np.percentile(line[:, 2], 98) - rng.uniform(0.0, 0.04)))
        c = Candidate("grasp", {"approach": "top", "position": [float(centre[0]), float(centre[1]), z], "heading": axis.tolist()})
        c = Candidate(c.action, config.grid.snap(c.params))
        wins.append(bool(simulate_candidates(scene, [c], physics)[-1]["success"]))
    rows.append((sha, wins, old.get(sha, [])))
    print(f"{len(rows)}: sampler3 {sum(wins)}/6, sampler2 {sum(old.get(sha, []))}/{len(old.get(sha, []))}", flush=True)
new = [w for _, ws, _ in rows for w in ws]; prev = [w for _, _, ws in rows for w in ws]
print(f"per draw: sampler3 {np.mean(new):.3f} ({len(new)}), sampler2 {np.mean(prev):.3f} ({len(prev)})")
print(f"layouts with a lifting top grasp: sampler3 {np.mean([any(w) for _, w, _ in rows]):.3f}, sampler2 {np.mean([any(w) for _, _, w in rows]):.3f}")
print(f"{time.process_time() - t0:.0f} CPU-s")
