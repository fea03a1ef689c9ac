"""The retrieval head's offline metrics (``scenegen retrieval eval``): its prediction
(perceive.py's ``predict_target``) on each camera's frame against the true target mask (the
segmentation, read here for scoring only):

- ``iou``: intersection over union with the true target's pixels;
- ``hit``: the predicted region's centre (the mean of its pixels) lies on a true target pixel;
- ``wrong_object``: most of the predicted region lies on another object instance;
- ``miss``: the target is visible (at least ``MIN_VISIBLE`` pixels) and nothing is predicted;
- ``false_alarm``: the target is not visible in this camera and something is predicted.

A scene is hit (``hit``, the centre rule, version 1) when every camera's prediction that exists hits
and at least one does: the planner back-projects the target's pixels of every camera together, so
one wrong camera spoils the points. The centre rule counts a mask that holds the target and the
object under it as found; the overlap rule (``hit_iou``, version 2, ``PERCEPTION_RULES``) does not:
a scene counts when every camera that sees the target (``MIN_VISIBLE`` pixels or more) predicts a
region with IoU >= ``IOU_HIT`` against the true target mask and every camera that does not see it
predicts nothing. The closed loop's perception failure rule (:func:`perception_missed`) is the
version's scene rule.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from scenegen.env.scenes import EnvScene, target_category
from scenegen.perception.retrieval.frames import Frames
from scenegen.perception.retrieval.model import Prediction, RetrievalHead
from scenegen.perception.retrieval.perceive import predict_target

MIN_VISIBLE = 20  # pixels of the true target for it to count as visible in a camera (as MIN_POINTS)
IOU_HIT = 0.5  # the overlap rule's IoU
# 1: the centre rule (a prediction's centre on the target, none on another object); 2: the overlap rule
PERCEPTION_RULES = 2


def perception_missed(score: dict, rules: int = PERCEPTION_RULES) -> bool:
    """Whether a scored decision (``score_observation``'s scene-level keys) missed the target, by the
    rules' version: 1, no centre hit or mostly another object; 2, not an overlap hit."""
    if rules == 1:
        return not score["hit"] or bool(score["wrong_object"])
    if rules == 2:
        return not score["hit_iou"]
    raise ValueError(f"perception rules {rules}: versions 1 and 2 exist")


def image_metrics(prediction: Prediction, seg: np.ndarray, target_id: int, object_ids: Sequence[int]) -> dict:
    """The metrics of one camera's prediction against its segmentation (H, W) instance ids."""
    true = seg == target_id
    visible = int(true.sum()) >= MIN_VISIBLE
    if prediction.empty:
        nothing = {"iou": 0.0, "hit": False, "wrong_object": False, "false_alarm": False}
        return {"visible": visible, "predicted": False, "miss": visible, "iou_hit": not visible} | nothing
    mask = prediction.mask
    union = np.logical_or(mask, true).sum()
    rows, cols = np.nonzero(mask)
    centre = true[int(round(rows.mean() - 0.5)), int(round(cols.mean() - 0.5))]
    others = np.isin(seg[mask], [i for i in object_ids if i != target_id]).mean()
    iou = float(np.logical_and(mask, true).sum() / union)
    return {
        "visible": visible,
        "predicted": True,
        "iou": iou,
        "iou_hit": visible and iou >= IOU_HIT,
        "hit": bool(centre),
        "wrong_object": bool(others > 0.5),
        "miss": False,
        "false_alarm": not visible,
    }


def scene_metrics(predict, scene: EnvScene, frames: Frames) -> dict:
    """Per camera metrics and the scene's hit, for ``scene`` and its ``frames``; ``predict(frames,
    cameras, category, robot)`` gives a :class:`Prediction` per camera (:func:`head_predictor` for
    the segmenter; the candidate designs' ``CandidatePicker.predict``)."""
    from scenegen.perception.retrieval.candidates import robot_pixels

    category = target_category(scene)
    predictions = predict(frames, scene.cameras, category, robot_pixels(frames, scene))
    ids = [scene.segmentation[o.name] for o in scene.objects]
    per_camera = {
        camera: image_metrics(p, seg, scene.target_id, ids)
        for camera, p, seg in zip(frames.cameras, predictions, frames.seg, strict=True)
    }
    return {
        "scene_id": scene.scene_id,
        "tags": [t for t, held in scene.tags.items() if held and t != "nominal"] or ["nominal"],
        "target_category": category,
        "unique_category": sum(o.category == category for o in scene.objects) == 1,
        "cameras": per_camera,
        **_scene_level(per_camera),
    }


def head_predictor(head: RetrievalHead):
    """``predict(frames, cameras, category, robot)`` of a segmenter: it reads the frames' RGB-D only."""
    return lambda frames, cameras, category, robot: predict_target(head, frames.rgb, frames.depth, category)


def _scene_level(per_camera: dict) -> dict:
    """A scene's hit (every camera's prediction that exists hits, and one does at least), its
    overlap hit (every camera's ``iou_hit``: IoU >= 0.5 where the target is visible, nothing
    predicted where it is not) and whether any camera's prediction lies mostly on another object."""
    predicted = [m for m in per_camera.values() if m["predicted"]]
    return {
        "hit": bool(predicted) and all(m["hit"] for m in predicted),
        "hit_iou": all(m["iou_hit"] for m in per_camera.values()),
        "wrong_object": any(m["wrong_object"] for m in predicted),
    }


def score_observation(env, obs: dict) -> dict:
    """The metrics of a learned observation's predicted target (``<cam>_predicted_target``) against
    the simulator's segmentation, rendered now from the same state: scoring, the only reader of the
    segmentation while a learned policy runs. Per camera metrics, the scene's hit and wrong object."""
    truth = env.camera_observations(image=False)  # the masks only: no colour pass
    scene = env.scene
    ids = [scene.segmentation[o.name] for o in scene.objects]
    per_camera = {}
    for name in env.cameras:
        mask = np.squeeze(obs[f"{name}_predicted_target"], -1)
        seg = np.squeeze(truth[f"{name}_segmentation"], -1)
        per_camera[name] = image_metrics(Prediction(mask, float(mask.sum())), seg, scene.target_id, ids)
    return {"cameras": per_camera, **_scene_level(per_camera)}


def summarise(rows: Sequence[dict]) -> dict:
    """Scene hit rate and per-image means (over the images where the target is visible; false
    alarms over those where it is not), overall and per tag."""

    def block(chosen: Sequence[dict]) -> dict:
        images = [m for r in chosen for m in r["cameras"].values()]
        seen = [m for m in images if m["visible"]]
        unseen = [m for m in images if not m["visible"]]
        mean = lambda values: round(float(np.mean(values)), 4) if values else None  # noqa: E731
        return {
            "scenes": len(chosen),
            "scene_hit": mean([r["hit"] for r in chosen]),
            "scene_hit_iou": mean([r["hit_iou"] for r in chosen]),
            "images_visible": len(seen),
            "iou": mean([m["iou"] for m in seen]),
            "hit": mean([m["hit"] for m in seen]),
            "wrong_object": mean([m["wrong_object"] for m in seen]),
            "miss": mean([m["miss"] for m in seen]),
            "false_alarm": mean([m["false_alarm"] for m in unseen]),
        }

    tags = sorted({t for r in rows for t in r["tags"]})
    return {"all": block(rows), "per_tag": {t: block([r for r in rows if t in r["tags"]]) for t in tags}}


def evaluate_head(
    checkpoint: Path,
    scenes: Sequence[EnvScene],
    frames: Sequence[Frames],
    out: Path | None = None,
    sensor: str = "exact",
) -> dict:
    """Metrics of the head at ``checkpoint`` (either design) on ``scenes`` (``frames``: theirs, their
    depth through ``sensor``); with ``out``: ``images.jsonl`` (one row per scene, every camera),
    ``summary.json`` and ``summary.md`` there."""
    from scenegen.perception.retrieval.perceive import RetrievalPerception

    predict = RetrievalPerception.load(checkpoint).predict
    rows = [scene_metrics(predict, s, f) for s, f in zip(scenes, frames, strict=True)]
    summary = {"checkpoint": str(checkpoint), **({"sensor": sensor} if sensor != "exact" else {})}
    summary |= summarise(rows)
    if out is not None:
        from scenegen.store.batch import atomic_write

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write(out / "images.jsonl", "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))
        atomic_write(out / "summary.json", json.dumps(summary, indent=1) + "\n")
        atomic_write(out / "summary.md", summary_table(summary))
    return summary


def _cell(value) -> str:
    return "-" if value is None else f"{value:.3f}" if isinstance(value, float) else str(value)


def summary_table(summary: dict) -> str:
    """The summary as a markdown table, a row per tag and one for all scenes."""
    keys = ("scenes", "scene_hit", "scene_hit_iou", "iou", "hit", "wrong_object", "miss", "false_alarm")
    lines = ["| tag | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for name, block in [("all", summary["all"]), *summary["per_tag"].items()]:
        cells = [_cell(block[k]) for k in keys]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
