"""Issue 62: the target as seen (footprint, top, bottom, other objects near it) on exact depth, through the
stereo sensor under the simulator's masks and through the pinned stereo head, on every 9th validation layout
from the 14th (docs/sensor.md, "The closed loop through the sensor").

    .venv/bin/python benchmarks/results/stereo_head_pilots/view_estimates.py
"""

import numpy as np

from scenegen.env.physics import DEFAULT_PHYSICS, physics_named
from scenegen.env.scenes import scene_sha256
from scenegen.experiment.closed_loop import episode_env, loaded_perception
from scenegen.experiment.proposal_labels import label_layouts
from scenegen.experiment.sequences import NOMINAL, Variant, path_key
from scenegen.perception.observation import observe
from scenegen.perception.retrieval import SENSOR_HEAD

phys = physics_named(DEFAULT_PHYSICS)
scenes = label_layouts(["validation"])["validation"]
stereo = Variant("sensor_active_stereo", 1.0, "active_stereo")
SIGHTS = (("exact", NOMINAL, None), ("stereo-oracle", stereo, None), ("stereo-head", stereo, SENSOR_HEAD))
for s in scenes[13:140:9]:
    out = []
    for name, variant, head in SIGHTS:
        env = episode_env(s, phys)
        perception = loaded_perception(head)
        env.reset_to(variant.apply(s) if perception is not None else s)
        variant.sense(env, path_key(scene_sha256(s), ()))
        _, view = observe(env, perception, image=perception is not None)
        if view is None:
            out.append(f"{name}: unseen")
            continue
        t = view.target
        near = np.linalg.norm(view.others[:, :2] - t.centre[:2], axis=1) < 0.15
        size = f"top {t.top_z:.3f} bot {t.bottom_z:.3f} ext {t.extent[0]:.3f},{t.extent[1]:.3f}"
        out.append(f"{name}: {size} others {len(view.others)} near {near.sum()}")
    print(s.target, " | ".join(out), flush=True)
