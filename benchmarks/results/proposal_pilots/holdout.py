"""Pilot (validation-free, natural:600 only): does the proposal model rank held-out layouts' candidates
above chance? Train on the first 80 % of the labelled natural:600 layouts, score the rest offline."""
import json, sys, time
from pathlib import Path
import numpy as np
from scenegen.env.scenes import scene_sha256
from scenegen.experiment.proposal_data import Examples, examples
from scenegen.experiment.proposal_labels import label_layouts, open_labels
from scenegen.experiment.proposal_offline import first_ranked, train_on

steps = int(sys.argv[1]) if len(sys.argv) > 1 else 3000
width = int(sys.argv[2]) if len(sys.argv) > 2 else 16
labels = Path("runs/proposals")
config, store, views = open_labels(labels)
scenes = list(label_layouts(["natural:600"], None)["natural:600"])
t0 = time.process_time()
data = examples(scenes, store, views, labels / "crops", config)
print(f"{len(data)} candidates on {len(set(data.scene))} layouts, crops {time.process_time() - t0:.0f} CPU-s", flush=True)
order = list(dict.fromkeys(data.scene))
cut = int(0.8 * len(order))
train_set = set(order[:cut])
def subset(keep):
    idx = [i for i, s in enumerate(data.scene) if s in keep]
    return Examples(data.crops[idx], data.features[idx], data.labels[idx], [data.scene[i] for i in idx], [data.candidates[i] for i in idx])
train, test = subset(train_set), subset(set(order[cut:]))
t0 = time.process_time()
model = train_on(train, steps=steps, width=width)
print(f"train {len(train)} ex, {time.process_time() - t0:.0f} CPU-s", flush=True)
for name, d in (("train", train), ("held-out", test)):
    picks = first_ranked(model, d)
    succ = np.mean([p["success"] for p in picks.values()])
    ceil = np.mean([p["any"] for p in picks.values()])
    chance = np.mean([np.mean([d.labels[i] for i, s in enumerate(d.scene) if s == sha]) for sha in picks])
    print(f"{name}: {len(picks)} layouts, first-ranked {succ:.3f}, chance {chance:.3f}, ceiling {ceil:.3f}", flush=True)
