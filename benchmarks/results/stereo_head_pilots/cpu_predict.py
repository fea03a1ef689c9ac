import time, numpy as np, torch
from pathlib import Path
from scenegen.policy.panels_v2 import load_panels_v2, panel_scenes
from scenegen.perception.retrieval.frames import scene_frames
from scenegen.perception.retrieval.candidates import CandidatePicker, robot_pixels
from scenegen.env.scenes import target_category
torch.set_num_threads(1)
panel = panel_scenes(load_panels_v2(Path("assets/panels/v2/panels.json")), "validation")
scenes = panel["common"][:20]
for head, sensor in (("assets/retrieval/instances", "exact"), ("runs/stereo/pilot_learned_w5", "active_stereo")):
    picker = CandidatePicker(Path(head))
    frames = list(scene_frames(scenes, Path("runs/cache/frames"), sensor=sensor))
    picker.predict(frames[0], scenes[0].cameras, target_category(scenes[0]), robot_pixels(frames[0], scenes[0]))
    t = time.process_time()
    for s, f in zip(scenes, frames):
        picker.predict(f, s.cameras, target_category(s), robot_pixels(f, s))
    print(head, sensor, round((time.process_time() - t) / len(scenes), 3), "CPU-s per decision (2 cameras)")
