import sys
import numpy as np
from pathlib import Path
import torch
from scenegen.policy.panels_v2 import load_panels_v2, panel_scenes
from scenegen.perception.retrieval.frames import scene_frames
from scenegen.perception.retrieval.candidates import CandidatePicker, frame_candidates, robot_pixels
from scenegen.env.scenes import target_category
torch.set_num_threads(1)
head, sensor, which = sys.argv[1], sys.argv[2], sys.argv[3]
panel = panel_scenes(load_panels_v2(Path("assets/panels/v2/panels.json")), "validation")
scenes = panel[which][:25]
picker = CandidatePicker(Path(head))
rows = []
for scene, f in zip(scenes, scene_frames(scenes, Path("runs/cache/frames"), sensor=sensor)):
    robot = robot_pixels(f, scene)
    m = picker.rule.mend_frames(f)
    cams = {c.name: c for c in scene.cameras}
    col = 1 + picker.model.categories.index(target_category(scene))
    for k, name in enumerate(f.cameras):
        tgt = f.seg[k] == scene.target_id
        if tgt.sum() < 20: continue
        field, height = picker.rule.foreground(m.depth[k], robot[k], cams[name])
        interior, keep = picker.split.interior(m.rgb[k], m.depth[k], field, height)
        regs = picker.split(m.rgb[k], m.depth[k], robot[k], cams[name])
        crops = [c for kk, r, c in frame_candidates(m, scene.cameras, robot, picker.split) if kk == k]
        with torch.no_grad():
            p = torch.softmax(picker.model(torch.from_numpy(np.stack(crops))), 1).numpy() if crops else np.zeros((0, 10))
        ious = [(float((r & tgt).sum() / (r | tgt).sum()), float(p[i, col])) for i, r in enumerate(regs)]
        best = max(ious, default=(0, 0))
        chosen = max(ious, key=lambda t: t[1], default=(0, 0))
        rows.append(dict(cat=target_category(scene), n=int(tgt.sum()), obj=round(float(keep[tgt].mean()), 2),
                         inter=round(float(interior[tgt].mean()), 2), nreg=len(regs), best_iou=round(best[0], 2), p_best=round(best[1], 2), chosen_iou=round(chosen[0], 2) if chosen[1] > .5 else None))
for r in rows: print(r)
a = lambda k: np.mean([r[k] for r in rows])
print("obj", a("obj"), "best_iou>=.5", np.mean([r["best_iou"] >= .5 for r in rows]), "p>.5|best>=.5", np.mean([r["p_best"] > .5 for r in rows if r["best_iou"] >= .5]))
