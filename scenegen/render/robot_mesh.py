"""The robot's visual meshes, decimated for drawing: a render-only copy of a compiled model.

robosuite's Panda is ~168k visual triangles of the ~190k a demo scene draws, and each camera draws
them twice (shadow map, then colour) plus once for segmentation and depth: most of a frame's cost on
llvmpipe. :func:`decimated_copy` returns a shallow copy of the model whose robot visual meshes are
quadric-decimated (fast_simplification, after welding the OBJ's split vertices) to a share
``detail`` of their triangles, written in place into the copy's mesh arrays (a decimated mesh never
has more vertices or faces than the original). Only a renderer's MjrContext is built from it; the
model that is simulated, tagged and exported is never touched, so physics is unchanged. The robot's
materials carry no texture, so its texture coordinates are dropped in the copy.
"""

from __future__ import annotations

import copy
import hashlib
import os
import tempfile
from pathlib import Path

import mujoco
import numpy as np

from scenegen.sim import world

MIN_FACES = 200  # meshes smaller than this are drawn as they are


def robot_visual_meshes(model: mujoco.MjModel, prefixes: tuple[str, ...]) -> list[int]:
    """Mesh ids of the visual (group world.VISUAL_GROUP) mesh geoms on bodies named with ``prefixes``."""
    meshes = set()
    for g in range(model.ngeom):
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH or model.geom_group[g] != world.VISUAL_GROUP:
            continue
        if model.body(model.geom_bodyid[g]).name.startswith(prefixes):
            meshes.add(int(model.geom_dataid[g]))
    return sorted(meshes)


def decimate(vertices: np.ndarray, faces: np.ndarray, detail: float) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) with about ``detail`` of the triangles, split vertices welded first."""
    import fast_simplification
    import trimesh

    mesh = trimesh.Trimesh(vertices.astype(np.float64), faces, process=True)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    return fast_simplification.simplify(
        mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32), 1.0 - detail
    )


def decimated_copy(model: mujoco.MjModel, prefixes: tuple[str, ...], detail: float) -> mujoco.MjModel:
    """A copy of ``model`` for drawing, its robot visual meshes at ``detail`` (0 < detail <= 1).

    The decimated meshes (~0.7 s to compute for the Panda) are cached on disk
    (:func:`scenegen.paths.cache_dir`), keyed by the meshes' own arrays, ``detail``, the versions of
    the decimation libraries and this module's source."""
    if not 0.0 < detail <= 1.0:
        raise ValueError(f"robot mesh detail {detail}: must be in (0, 1]")
    out = copy.copy(model)
    if detail == 1.0:
        return out
    meshes = [i for i in robot_visual_meshes(model, prefixes) if model.mesh_facenum[i] >= MIN_FACES]
    cache = _cache_path(model, meshes, detail)
    decimated = _load(cache, meshes)
    if decimated is None:
        decimated = {i: _decimate_mesh(model, i, detail) for i in meshes}
        _save(cache, decimated)
    for i, (verts, faces, normals) in decimated.items():
        vadr, fadr, nadr = out.mesh_vertadr[i], out.mesh_faceadr[i], out.mesh_normaladr[i]
        if len(verts) > min(out.mesh_vertnum[i], out.mesh_normalnum[i]) or len(faces) > out.mesh_facenum[i]:
            continue  # cannot happen for a decimation; keep the mesh rather than overrun its slots
        out.mesh_vert[vadr : vadr + len(verts)] = verts
        out.mesh_vertnum[i] = len(verts)
        out.mesh_face[fadr : fadr + len(faces)] = faces
        out.mesh_facenum[i] = len(faces)
        out.mesh_normal[nadr : nadr + len(verts)] = normals
        out.mesh_normalnum[i] = len(verts)
        out.mesh_facenormal[fadr : fadr + len(faces)] = faces  # one normal per vertex
        out.mesh_texcoordnum[i], out.mesh_texcoordadr[i] = 0, -1  # untextured materials
    return out


def _decimate_mesh(model: mujoco.MjModel, i: int, detail: float):
    import trimesh

    vadr, nv = model.mesh_vertadr[i], model.mesh_vertnum[i]
    fadr, nf = model.mesh_faceadr[i], model.mesh_facenum[i]
    verts, faces = decimate(model.mesh_vert[vadr : vadr + nv], model.mesh_face[fadr : fadr + nf], detail)
    normals = trimesh.Trimesh(verts, faces, process=False).vertex_normals
    return verts.astype(np.float32), faces.astype(np.int32), normals.astype(np.float32)


def _cache_path(model: mujoco.MjModel, meshes: list[int], detail: float) -> Path:
    from importlib.metadata import version

    from scenegen.paths import cache_dir

    key = hashlib.sha256(Path(__file__).read_bytes())
    key.update(f"{detail!r} {version('fast-simplification')} {version('trimesh')}".encode())
    for i in meshes:
        vadr, nv = model.mesh_vertadr[i], model.mesh_vertnum[i]
        fadr, nf = model.mesh_faceadr[i], model.mesh_facenum[i]
        key.update(model.mesh_vert[vadr : vadr + nv].tobytes() + model.mesh_face[fadr : fadr + nf].tobytes())
    return cache_dir() / "robot_meshes" / f"{key.hexdigest()[:24]}.npz"


def _load(path: Path, meshes: list[int]) -> dict | None:
    try:
        with np.load(path, allow_pickle=False) as data:
            return {i: (data[f"v{i}"], data[f"f{i}"], data[f"n{i}"]) for i in meshes}
    except (OSError, KeyError, ValueError):
        return None  # absent or unreadable: decimated again


def _save(path: Path, decimated: dict) -> None:
    """Write the cache atomically; one that cannot be written only makes the next start slower."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            arrays = {f"{k}{i}": a for i, mesh in decimated.items() for k, a in zip("vfn", mesh, strict=True)}
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except OSError:
        pass
