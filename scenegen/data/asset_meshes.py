"""A user's mesh file as an asset's meshes: read (trimesh), merged, scaled to metres, turned +z up,
cleaned, made watertight where trimesh can, and centred on its centre of mass.

The result is two meshes in one frame: ``visual`` (what is rendered: the file's triangles, with its
texture coordinates when one texture image goes with them, decimated past ``VISUAL_MAX_FACES``) and
``solid`` (what physics is measured on: vertices merged, degenerate faces dropped, holes filled,
decimated past ``COLLISION_MAX_FACES``; the convex hull when it cannot be made watertight). Every
change is a one-line note; what cannot be imported is a :class:`MeshImportError` naming the file and
what to do.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

FORMATS = (".obj", ".stl", ".ply", ".glb", ".gltf")
UNITS = {"mm": 0.001, "cm": 0.01, "m": 1.0}
SIZE_RANGE = (0.005, 0.6)  # metres: the largest side of a graspable tabletop object
VISUAL_MAX_FACES = 20_000  # rendered triangles per asset (llvmpipe draws every one per frame)
COLLISION_MAX_FACES = 50_000  # coacd's input: keeps one decomposition within ~2 minutes on 2 cores
UP_ROTATIONS = {  # file's up axis -> rotation (3, 3) that turns it to +z
    "z": np.eye(3),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
}


class MeshImportError(ValueError):
    """A mesh file cannot become an asset; the one-line message names the file and what to do."""


@dataclass
class UserMesh:
    """A user's mesh in the asset frame (metres, +z up, origin at the solid's centre of mass)."""

    visual: trimesh.Trimesh
    solid: trimesh.Trimesh
    collision: str  # "convex_decomposition" (solid is watertight) or "convex_hull"
    rgba: tuple[float, float, float, float]
    uv: np.ndarray | None = None  # (V, 2) texture coordinates of visual's vertices, with ``texture``
    texture: np.ndarray | None = None  # (H, W, 3) uint8 RGB image
    notes: list[str] = field(default_factory=list)


def read_user_mesh(
    path: Path,
    scale: float | None = None,
    units: str | None = None,
    up: str = "z",
    texture: Path | None = None,
) -> UserMesh:
    """Read ``path`` into a :class:`UserMesh`. ``scale`` (explicit) or ``units`` (mm, cm, m; default m)
    gives metres; a largest side outside ``SIZE_RANGE`` needs an explicit ``scale``. ``texture`` (an
    image) replaces the file's own texture, mapped with the file's texture coordinates."""
    path = Path(path)
    if not path.is_file():
        raise MeshImportError(f"{path}: no such file; give the path of an OBJ, STL, PLY, GLB or glTF mesh")
    if path.suffix.lower() not in FORMATS:
        raise MeshImportError(
            f"{path}: {path.suffix or 'a name without a suffix'} is not a mesh format read here; "
            "export it as OBJ, STL, PLY, GLB or glTF"
        )
    notes: list[str] = []
    bodies = _bodies(path)
    if len(bodies) > 1:
        notes.append(f"{len(bodies)} bodies in the file, imported as one rigid object")
    visual, uv, image = _visual(path, bodies, texture, notes)
    rgba = _colour(bodies, image)
    factor = _scale(path, visual, scale, units, notes)
    transform = np.eye(4)
    transform[:3, :3] = UP_ROTATIONS[up] * factor
    visual.apply_transform(transform)
    solid, collision = _solid(path, visual, notes)
    shift = -solid.center_mass
    solid.apply_translation(shift)
    visual.apply_translation(shift)
    if len(visual.faces) > VISUAL_MAX_FACES:
        before = len(visual.faces)
        visual = _decimate(visual, VISUAL_MAX_FACES)
        dropped = (
            "; its texture dropped (decimation keeps no texture coordinates)" if image is not None else ""
        )
        notes.append(f"visual mesh decimated from {before} to {len(visual.faces)} triangles{dropped}")
        uv = image = None
    return UserMesh(visual, solid, collision, rgba, uv, image, notes)


def _bodies(path: Path) -> list[trimesh.Trimesh]:
    """The file's triangle meshes, each in the file's frame (scene transforms applied)."""
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as exc:  # noqa: BLE001 - any parser failure is the same user error
        reason = (str(exc).strip() or type(exc).__name__).splitlines()[0][:120]
        raise MeshImportError(
            f"{path}: cannot read it as a mesh ({reason}); check the file, "
            "or export it again as OBJ, STL, PLY or GLB"
        ) from None
    if isinstance(loaded, trimesh.Scene):
        bodies = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
    else:
        bodies = [loaded] if isinstance(loaded, trimesh.Trimesh) else []
    bodies = [b for b in bodies if len(b.faces) > 0]
    if not bodies:
        raise MeshImportError(
            f"{path}: holds no triangles (a point cloud, lines or an empty file); "
            "export the object's surface as OBJ, STL, PLY or GLB"
        )
    for body in bodies:
        if not np.isfinite(body.vertices).all():
            raise MeshImportError(f"{path}: has vertices that are not finite numbers; repair or re-export it")
    return bodies


def _visual(path: Path, bodies: list[trimesh.Trimesh], texture: Path | None, notes: list[str]):
    """The mesh to render, its texture coordinates and texture image (or None, None)."""
    textured = [b for b in bodies if _uv(b) is not None and _image(b) is not None]
    if texture is not None:
        if len(bodies) != 1 or _uv(bodies[0]) is None:
            raise MeshImportError(
                f"{path}: --texture needs one body with texture coordinates (vt) in the "
                "mesh; leave --texture out to keep its colour"
            )
        image = _read_image(texture)
        return _copy(bodies[0]), _uv(bodies[0]), image
    notes.extend(_missing_texture_files(path))
    if len(bodies) == 1 and textured:
        return _copy(bodies[0]), _uv(bodies[0]), _image(bodies[0])
    if textured:
        notes.append(f"textures of {len(textured)} bodies dropped (one texture per asset): kept their colour")
    merged = trimesh.util.concatenate([_copy(b) for b in bodies]) if len(bodies) > 1 else _copy(bodies[0])
    return merged, None, None


def _copy(body: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(body.vertices, float), np.asarray(body.faces), process=False)


def _uv(body: trimesh.Trimesh) -> np.ndarray | None:
    uv = getattr(body.visual, "uv", None)
    return None if uv is None or len(uv) != len(body.vertices) else np.asarray(uv, float)


def _image(body: trimesh.Trimesh) -> np.ndarray | None:
    image = getattr(getattr(body.visual, "material", None), "image", None)
    if image is None:
        image = getattr(getattr(body.visual, "material", None), "baseColorTexture", None)
    return None if image is None else np.asarray(image.convert("RGB"))


def _read_image(path: Path) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR) if Path(path).is_file() else None
    if image is None:
        raise MeshImportError(f"{path}: cannot read it as an image; give a PNG or JPEG texture")
    return image[:, :, ::-1].copy()


def _missing_texture_files(path: Path) -> list[str]:
    """Notes for an OBJ's texture maps (map_Kd in its .mtl) that are missing or outside its folder."""
    if path.suffix.lower() != ".obj":
        return []
    notes, folder = [], path.parent.resolve()
    libraries = re.findall(r"^mtllib\s+(.+?)\s*$", path.read_text(errors="replace"), re.MULTILINE)
    for library in libraries:
        mtl = (folder / library).resolve()
        if not mtl.is_relative_to(folder) or not mtl.is_file():
            notes.append(f"material file {library} missing or outside the mesh's folder: colour kept")
            continue
        for image in re.findall(
            r"^\s*map_Kd\s+(?:-\S+\s+\S+\s+)*(.+?)\s*$", mtl.read_text(errors="replace"), re.MULTILINE
        ):
            where = (mtl.parent / image).resolve()
            if not where.is_relative_to(folder):
                notes.append(
                    f"texture {image} lies outside the mesh's folder, not read: give it with --texture"
                )
            elif not where.is_file():
                notes.append(f"texture {image} missing: the material's colour kept")
    return notes


def _colour(bodies: list[trimesh.Trimesh], image: np.ndarray | None) -> tuple[float, float, float, float]:
    """One RGBA for the asset: the texture's mean, else the largest body's main colour."""
    if image is not None:
        rgb = image.reshape(-1, 3).mean(axis=0) / 255
        return (*(round(float(c), 3) for c in rgb), 1.0)
    body = max(bodies, key=lambda b: b.area)
    try:
        colour = np.asarray(body.visual.main_color, float) / 255
    except Exception:  # noqa: BLE001 - a visual without a colour
        colour = np.array([0.6, 0.6, 0.6, 1.0])
    return (*(round(float(c), 3) for c in colour[:3]), 1.0)


def _scale(
    path: Path, mesh: trimesh.Trimesh, scale: float | None, units: str | None, notes: list[str]
) -> float:
    """Metres per file unit; refuses a largest side outside SIZE_RANGE unless ``scale`` is explicit."""
    if scale is not None and units is not None:
        raise MeshImportError(f"{path}: give --scale or --units, not both")
    if scale is not None and not (np.isfinite(scale) and scale > 0):
        raise MeshImportError(f"{path}: --scale {scale} must be a positive number")
    factor = scale if scale is not None else UNITS[units or "m"]
    size = float(mesh.extents.max()) * factor
    lo, hi = SIZE_RANGE
    if not lo <= size <= hi:
        message = f"largest side {size:.4g} m is outside {lo * 1000:g} mm - {hi * 100:g} cm"
        if scale is None:
            guess = next((u for u, f in UNITS.items() if lo <= mesh.extents.max() * f <= hi), None)
            hint = f" (--units {guess} fits)" if guess else ""
            raise MeshImportError(
                f"{path}: {message} in units of {units or 'm'}; give --units mm|cm|m{hint} "
                "or an explicit --scale FACTOR"
            )
        notes.append(f"{message}: kept, as --scale {scale:g} asks")
    return factor


def _solid(path: Path, visual: trimesh.Trimesh, notes: list[str]) -> tuple[trimesh.Trimesh, str]:
    """The physics mesh: merged, cleaned, filled and decimated; its convex hull where not watertight."""
    solid = trimesh.Trimesh(visual.vertices.copy(), visual.faces.copy(), process=False)
    solid.merge_vertices(merge_tex=True, merge_norm=True)
    if not solid.is_watertight:  # a closed mesh keeps its slivers: removing one would open a hole
        faces = len(solid.faces)
        solid.update_faces(solid.nondegenerate_faces())
        solid.update_faces(solid.unique_faces())
        solid.remove_unreferenced_vertices()
        if len(solid.faces) < faces:
            notes.append(f"{faces - len(solid.faces)} degenerate or duplicate triangles removed")
    if len(solid.faces) < 4:
        raise MeshImportError(f"{path}: fewer than 4 proper triangles; the file holds no solid object")
    if not solid.is_watertight:
        trimesh.repair.fill_holes(solid)
        if solid.is_watertight:
            notes.append("holes filled: the mesh is watertight now")
    if solid.is_watertight and len(solid.faces) > COLLISION_MAX_FACES:
        before = len(solid.faces)
        solid = _decimate(solid, COLLISION_MAX_FACES)
        notes.append(f"collision input decimated from {before} to {len(solid.faces)} triangles")
    if solid.is_watertight:
        trimesh.repair.fix_normals(solid)
        if solid.volume > 0:
            pieces = len(solid.split(only_watertight=False))
            if pieces > 1:
                notes.append(f"{pieces} separate pieces, imported as one rigid object")
            return solid, "convex_decomposition"
    notes.append("not watertight after repair: its collision model is its convex hull (one part)")
    return solid.convex_hull, "convex_hull"


def _decimate(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    out = mesh.simplify_quadric_decimation(face_count=faces)
    return trimesh.Trimesh(out.vertices, out.faces, process=False)


def obj_text(mesh: trimesh.Trimesh, uv: np.ndarray | None = None) -> bytes:
    """OBJ text of ``mesh`` with 7 significant digits (stable across runs), with ``vt`` lines and
    ``f v/vt`` faces when texture coordinates are given."""
    lines = [f"v {x:.7g} {y:.7g} {z:.7g}" for x, y, z in mesh.vertices]
    if uv is None:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    else:
        lines += [f"vt {u:.7g} {v:.7g}" for u, v in uv]
        lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in mesh.faces]
    return ("\n".join(lines) + "\n").encode()
