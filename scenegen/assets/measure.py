"""What every asset's catalog entry measures from its mesh, authored (authoring.py) or imported
(importer.py): convex parts (coacd), the hull-to-visual distance, resting poses, mass and inertia, and
the OBJ text the catalog stores.
"""

from __future__ import annotations

import hashlib

import manifold3d as m3
import numpy as np
import trimesh

MIN_POSE_PROBABILITY = 0.05  # resting poses less likely than this (quasi-static drop) are left out
MAX_POSES = 4
POSE_MAX_FACES = 2000


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def export_obj(mesh: trimesh.Trimesh) -> bytes:
    """OBJ text with 7 significant digits: stable across runs, small in git."""
    lines = [f"v {x:.7g} {y:.7g} {z:.7g}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    return ("\n".join(lines) + "\n").encode()


def coacd_version() -> str:
    from importlib.metadata import version

    return version("coacd")


def convex_parts(mesh: trimesh.Trimesh, params: dict) -> list[trimesh.Trimesh]:
    import coacd

    coacd.set_log_level("error")
    result = coacd.run_coacd(coacd.Mesh(mesh.vertices, mesh.faces), **params)
    return [trimesh.Trimesh(v, f).convex_hull for v, f in result]


def hull_to_visual_distance(mesh: trimesh.Trimesh, parts: list[trimesh.Trimesh], n: int = 20000) -> float:
    """Symmetric Hausdorff distance (metres) between the visual surface and the outer surface of the
    union of the parts.

    Points are sampled on both surfaces with a fixed seed; the union is computed with manifold3d so
    faces buried inside overlapping parts do not count.
    """
    union = m3.Manifold.batch_boolean(
        [m3.Manifold.hull_points(np.asarray(p.vertices)) for p in parts], m3.OpType.Add
    )
    raw = union.to_mesh()
    union_mesh = trimesh.Trimesh(np.asarray(raw.vert_properties)[:, :3], np.asarray(raw.tri_verts))
    # Voids enclosed by the parts are shells with inward normals (negative volume): no contact can
    # reach them, so only the outer surface is compared.
    shells = [c for c in union_mesh.split(only_watertight=False) if len(c.faces) >= 4 and c.volume > 0]
    union_mesh = trimesh.util.concatenate(shells)
    a, _ = trimesh.sample.sample_surface(mesh, n, seed=0)
    b, _ = trimesh.sample.sample_surface(union_mesh, n, seed=1)
    d_ab = trimesh.proximity.closest_point(union_mesh, a)[1].max()
    # Parts' surface inside the visual solid bounds a void between parts, which no contact reaches and
    # whose cost, missing coverage, the first direction already measures.
    b = b[~mesh.contains(b)]
    d_ba = trimesh.proximity.closest_point(mesh, b)[1].max() if len(b) else 0.0
    return float(max(d_ab, d_ba))


def resting_poses(mesh: trimesh.Trimesh, flat: bool = False) -> list[dict]:
    """Stable resting poses on a horizontal plane, most likely first.

    Each pose is the rotation (wxyz quaternion, yaw removed) that puts the object on the plane, the
    height of its centre of mass above the plane (metres), its quasi-static probability, and whether
    it is upright (the authored +z stays up; for ``flat`` assets, either face down is upright).
    A hull of more than POSE_MAX_FACES faces is decimated for the estimate (its cost grows with the
    hull's faces: 104 s for a 50,000-face sphere); heights are measured on ``mesh`` itself.
    """
    hull = mesh.convex_hull
    if len(hull.faces) > POSE_MAX_FACES:
        hull = hull.simplify_quadric_decimation(face_count=POSE_MAX_FACES).convex_hull
    transforms, probs = trimesh.poses.compute_stable_poses(
        hull, center_mass=mesh.center_mass, sigma=0.0, n_samples=1
    )
    candidates = []
    for tf, p in zip(transforms, probs, strict=True):
        rot = _remove_yaw(tf[:3, :3])
        upright = bool(rot[2, 2] > 0.99 or (flat and rot[2, 2] < -0.99))
        candidates.append((rot, float(p), upright))
    # The most likely poses, and the upright ones even when unlikely under a random drop (a bottle,
    # a cereal box on its end), since the upright/toppled distinction is defined against them.
    likely = [c for c in candidates if c[1] >= MIN_POSE_PROBABILITY][:MAX_POSES]
    if not likely and not any(c[2] for c in candidates):
        likely = candidates[:MAX_POSES]  # a round object (a lemon): many shallow poses, none likely
    upright = [c for c in candidates if c[2] and not any(c is k for k in likely)]
    kept = (upright + likely)[:MAX_POSES] if upright else likely
    kept.sort(key=lambda c: -c[1])
    poses = []
    for rot, p, is_upright in kept:
        height = float(-(mesh.vertices @ rot.T)[:, 2].min())
        poses.append(
            {
                "quat": [round(float(q), 7) for q in _quat_wxyz(rot)],
                "height": round(height, 6),
                "probability": round(p, 4),
                "upright": is_upright,
            }
        )
    return poses


def _remove_yaw(rot: np.ndarray) -> np.ndarray:
    """Left-multiply by a z rotation so that the body x axis projects onto world +x (or is vertical)."""
    x = rot[:, 0]
    if np.hypot(x[0], x[1]) < 1e-6:
        x = rot[:, 1]
    yaw = np.arctan2(x[1], x[0])
    c, s = np.cos(-yaw), np.sin(-yaw)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return rz @ rot


def _quat_wxyz(rot: np.ndarray) -> np.ndarray:
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rot).ravel())
    return q if q[0] >= 0 else -q


def inertial(mesh: trimesh.Trimesh, density: float) -> dict:
    """Mass (kg) and inertia tensor (kg m^2, about the centre of mass, body axes) of the solid."""
    mesh = mesh.copy()
    mesh.density = density
    return {
        "mass": round(float(mesh.mass), 6),
        "inertia": [[round(float(v), 10) for v in row] for row in mesh.moment_inertia],
    }
