"""The simulated active stereo sensor against a real D415's figures, and its cost (issue 62).

    MUJOCO_GL=egl .venv/bin/python benchmarks/stereo_sensor.py [--scenes 40] [--out runs/stereo_sensor]

Measures, in one run (docs/sensor.md "Measured" holds a run's report):

1. the plane RMS of a bare table seen straight down from 0.8, 1.2 and 1.6 m (float depth, a plane
   fitted to the central 40 % of the frame) against ``z^2 s / (f B)`` with a D415's typical subpixel
   RMS ``s`` = 0.08 px and the simulated ``f``, ``B``; the bare table's fill rate inside the
   sensor's measurable field (and over the whole frame, where the imagers' narrower view counts);
2. the depth-less bands beside a 20 cm box edge at 0.8 and 1.0 m against the arrangement's prediction;
3. on the first ``--scenes`` training layouts of the reference set (no panel reads them: panels are
   drawn from the held-out split), both cameras at 640 x 480: per object category the share of its
   visible pixels with depth, and with depth within 1 cm of the truth;
4. CPU-seconds (``time.process_time``) per 640 x 480 frame: the renderer's exact frame (colour, depth,
   segmentation), and what each sensor adds to it (``structured_light``, ``active_stereo``);
5. a figure: colour, exact depth and the sensor's depth of three layouts (``<out>/depth.png``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from scenegen.render import stereo_quality as quality  # noqa: E402
from scenegen.render.stereo import ActiveStereo  # noqa: E402

SIZE = (640, 480)


def table_figures(renderer, sensor: ActiveStereo) -> dict:
    out = {"plane": [], "bands": []}
    for z in (0.8, 1.2, 1.6):
        frame = quality.bare_table(renderer, z, sensor)
        table = frame.seg == frame.ids["table"]
        rms, predicted = quality.plane_rms(frame), quality.predicted_rms(z, sensor)
        out["plane"].append({
            "range_m": z, "rms_mm": 1000 * rms, "predicted_mm": 1000 * predicted, "ratio": rms / predicted,
            "fill_measurable": quality.fill_rate(frame, sensor),
            "fill_frame": float((frame.sensed[table] > 0).mean()),
        })  # fmt: skip
    for height in (0.8, 1.0):
        frame = quality.box_edge(renderer, height, sensor)
        measured, predicted = quality.edge_bands(frame, sensor), quality.predicted_bands(frame, sensor)
        out["bands"].append({"camera_height_m": height, "measured_px": measured, "predicted_px": predicted})
    return out


def scene_model(scene):
    import mujoco

    from scenegen.assets.catalog import active_catalog
    from scenegen.sim import world

    model = world.build_world(
        active_catalog(), scene.objects, scene.furniture, scene.lighting, scene.cameras
    ).compile()
    data = mujoco.MjData(model)
    qpos, _ = world.initial_state(model, scene.robot_pose, scene.objects)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    return model, data


def layouts(n: int):
    from scenegen.core.files import load_rows
    from scenegen.env.scenes import reference_scene

    rows = load_rows(ROOT / "assets/reference/reference.parquet", "train")
    return [reference_scene(r) for r in rows[:n]]


def scene_figures(renderer, sensor: ActiveStereo, scenes, figure: Path) -> dict:
    from scenegen.render.sensor import SENSORS, Sight

    seen, filled, within = defaultdict(int), defaultdict(int), defaultdict(int)
    cpu = defaultdict(float)
    frames = 0
    shown = []
    for i, scene in enumerate(scenes):
        model, data = scene_model(scene)
        ids = scene.segmentation
        category = {ids[o.name]: o.category for o in scene.objects}
        for cam in scene.cameras:
            t = time.process_time()
            (frame,) = renderer.render(model, data, [cam.name], ids, [SIZE])
            cpu["render"] += time.process_time() - t
            sight = Sight(renderer, model, data, cam.name, SIZE, ids, frame.depth, frame.rgb)
            for name, s in SENSORS.items():
                t = time.process_time()
                depth = s.measure(sight, f"{scene.scene_id}|{cam.name}")
                cpu[name] += time.process_time() - t
                if name == "active_stereo":
                    sensed = depth
            frames += 1
            error = np.abs(sensed - frame.depth)
            for instance, cat in category.items():
                mask = frame.seg == instance
                seen[cat] += int(mask.sum())
                filled[cat] += int((mask & (sensed > 0)).sum())
                within[cat] += int((mask & (sensed > 0) & (error <= 0.01)).sum())
            if i < 3 and cam.name == scene.cameras[0].name:
                shown.append((frame.rgb, frame.depth, sensed))
    _figure(shown, figure)
    return {
        "frames": frames,
        "cpu_per_frame_s": {k: v / frames for k, v in cpu.items()},
        "categories": {
            c: {"pixels": seen[c], "with_depth": filled[c] / seen[c], "within_1cm": within[c] / seen[c]}
            for c in sorted(seen)
        },
    }


def _colourize(depth: np.ndarray) -> np.ndarray:
    import cv2

    scaled = np.clip((depth - 0.8) / 1.6, 0, 1)
    image = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    image[depth <= 0] = 0  # no return: black
    return image


def _figure(shown, path: Path) -> None:
    import cv2

    rows = [
        np.concatenate([rgb, _colourize(exact), _colourize(sensed)], axis=1) for rgb, exact, sensed in shown
    ]
    image = np.concatenate(rows, axis=0)
    image = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), image[..., ::-1])


def report(result: dict) -> str:
    lines = ["## Bare table: plane RMS about a fitted plane (central 40 %), fill rate", "",
             "| range | RMS | z^2 s/(fB), s = 0.08 px | ratio | fill (measurable) | fill (frame) |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for p in result["table"]["plane"]:
        lines.append(
            f"| {p['range_m']:.1f} m | {p['rms_mm']:.2f} mm | {p['predicted_mm']:.2f} mm | "
            f"{p['ratio']:.2f} | {p['fill_measurable']:.4f} | {p['fill_frame']:.3f} |"
        )
    lines += ["", "## Bands without depth beside a 20 cm box edge (colour px)", "",
              "| camera height | left measured | left predicted | right measured | right predicted |",
              "|---|---|---|---|---|"]  # fmt: skip
    for b in result["table"]["bands"]:
        (ml, mr), (pl, pr) = b["measured_px"], b["predicted_px"]
        lines.append(f"| {b['camera_height_m']:.1f} m | {ml:.0f} | {pl:.1f} | {mr:.0f} | {pr:.1f} |")
    s = result["scenes"]
    lines += ["", f"## Per category, {s['frames']} frames of reference layouts (640 x 480)", "",
              "| category | visible px | with depth | within 1 cm |", "|---|---|---|---|"]  # fmt: skip
    for c, v in s["categories"].items():
        lines.append(f"| {c} | {v['pixels']} | {v['with_depth']:.3f} | {v['within_1cm']:.3f} |")
    cpu = s["cpu_per_frame_s"]
    lines += ["", "## CPU-seconds per 640 x 480 frame", "", "| what | CPU-s |", "|---|---|",
              f"| exact frame (colour, depth, segmentation) | {cpu['render']:.3f} |"]  # fmt: skip
    for name in ("structured_light", "active_stereo"):
        lines.append(f"| + {name} | {cpu[name]:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scenes", type=int, default=40, help="reference training layouts measured (default 40)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "stereo_sensor", help="where results go")
    args = parser.parse_args(argv)
    from scenegen.render.offscreen import SceneRenderer

    sensor = ActiveStereo()
    renderer = SceneRenderer()
    try:
        result = {"sensor": sensor.key(), "table": table_figures(renderer, sensor)}
        result["scenes"] = scene_figures(renderer, sensor, layouts(args.scenes), args.out / "depth.png")
    finally:
        renderer.close()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "result.json").write_text(json.dumps(result, indent=1))
    text = report(result)
    (args.out / "report.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
