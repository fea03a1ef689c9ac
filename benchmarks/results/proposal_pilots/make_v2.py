"""The v2 features (features_v2.py) of every labelled natural:600 candidate, in examples() order -> v2.npz."""
import sys
from pathlib import Path
import numpy as np
sys.path.insert(0, str(Path(__file__).parent))
from features_v2 import candidate_features_v2
from scenegen.env.physics import physics_named
from scenegen.env.scenes import scene_sha256
from scenegen.experiment.closed_loop import episode_env
from scenegen.experiment.proposal_data import examples
from scenegen.experiment.proposal_labels import label_layouts, open_labels
from scenegen.manipulation.proposals import Candidate
from scenegen.perception.observation import observe

labels = Path("runs/proposals")
config, store, views = open_labels(labels)
scenes = list(label_layouts(["natural:600"], None)["natural:600"])
data = examples(scenes, store, views, labels / "crops", config)
by_sha = {scene_sha256(s): s for s in scenes}
physics = physics_named(config.physics)
out = np.zeros((len(data), 18), np.float32)
done = {}
for i, (sha, c) in enumerate(zip(data.scene, data.candidates)):
    if sha not in done:
        env = episode_env(by_sha[sha], physics); env.reset_to(by_sha[sha])
        done[sha] = observe(env, None, image=False)[1]
        if len(done) % 25 == 0: print(len(done), flush=True)
    if done[sha] is not None:
        out[i] = candidate_features_v2(Candidate.from_dict(c), done[sha])
assert np.allclose(out[:, :13], data.features, atol=1e-4), np.abs(out[:, :13] - data.features).max()
np.savez("runs/proposals_pilot/v2.npz", features=out)
print("ok", out.shape)
