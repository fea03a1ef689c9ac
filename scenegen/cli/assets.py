"""``scenegen assets add|list|show``: a user's own objects as verified assets (docs/assets.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from scenegen.cli.common import fail, first_line

ADD_HELP = """\
Import mesh files (OBJ, STL, PLY, GLB/glTF) as assets of a user catalog. Each import centres the mesh
on its centre of mass, turns --up to +z, scales it to metres, repairs what trimesh can (merged
vertices, degenerate triangles, holes), computes convex parts (coacd on a watertight mesh; the convex
hull otherwise, said in its notes), resting poses checked by a MuJoCo drop, mass and inertia, and keeps
the mesh's texture (one image with texture coordinates) or its colour. Each import is atomic: a failed
or interrupted one leaves the catalog as it was. The bundled catalog (assets/catalog.yaml) is never
written.

A folder imports every mesh file at its top, in name order, on --workers processes; what each file is
comes from --sidecar (YAML: `lemon.obj: {category: fruit, mass: 0.09, units: cm}`; or CSV with a
`file` column and columns category, name, units, scale, mass, density, friction, up, texture,
collision) over the flags given for all. It goes on past a file it refuses, skips a file whose asset
the catalog already holds from the same bytes (so rerunning a killed command finishes it), and ends
with one table: imported, refused with the reason, skipped as present (exit 1 if any was refused).

examples:
  scenegen assets add scans/lemon.obj --category fruit --mass 0.09
  scenegen assets add scans/ --sidecar scans/objects.yaml --workers 2
  scenegen assets add cad/bracket.stl --category bracket --units mm --density 2700
  scenegen assets add toy.glb --category toy --up y --catalog my_objects/catalog.yaml
"""


def add_commands(sub) -> None:
    parser = sub.add_parser("assets", help="import your own objects; list and show the asset catalogs")
    commands = parser.add_subparsers(dest="assets_command", metavar="SUBCOMMAND", required=True)
    add = commands.add_parser(
        "add",
        help="import mesh files into a user catalog",
        description=ADD_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add.add_argument(
        "meshes", nargs="+", type=Path, metavar="MESH", help="mesh files (one asset each) or folders of them"
    )
    add.add_argument(
        "--category", help="what the object is (e.g. fruit, can, mug); required unless a sidecar says"
    )
    add.add_argument(
        "--sidecar",
        type=Path,
        help="YAML or CSV: each file's category, units or scale, mass, ... (of one folder)",
    )
    add.add_argument("--workers", type=int, default=1, help="imports staged at once (default 1)")
    add.add_argument("--name", help="asset name (default: the file's name); only with one MESH")
    size = add.add_mutually_exclusive_group()
    size.add_argument("--units", choices=("mm", "cm", "m"), help="the file's length unit (default m)")
    size.add_argument(
        "--scale", type=float, help="metres per file unit; also allows sizes outside 5 mm-60 cm"
    )
    weight = add.add_mutually_exclusive_group()
    weight.add_argument("--mass", type=float, help="kg (default: from --density)")
    weight.add_argument("--density", type=float, help="kg/m^3 of the solid (default 500)")
    add.add_argument("--friction", type=float, default=0.7, help="sliding friction coefficient (default 0.7)")
    add.add_argument("--up", choices=("z", "y"), default="z", help="the file's up axis (default z)")
    add.add_argument("--texture", type=Path, help="an image mapped with the mesh's texture coordinates")
    add.add_argument(
        "--collision",
        choices=("auto", "hull"),
        default="auto",
        help="auto: convex parts by coacd when the mesh is watertight (up to ~2 min), else its convex "
        "hull; hull: one convex part, at once",
    )
    _catalog_argument(add, "the user catalog to write (default user_assets/catalog.yaml; created if missing)")
    add.set_defaults(run=_add)

    listing = commands.add_parser("list", help="the assets of the bundled and user catalogs")
    _catalogs_argument(listing)
    listing.set_defaults(run=_list)

    show = commands.add_parser(
        "show", help="a contact sheet: assets in their resting poses, convex parts beside"
    )
    show.add_argument("names", nargs="*", metavar="NAME", help="assets to show")
    show.add_argument("--all", action="store_true", help="every asset of the catalogs")
    show.add_argument(
        "--out", type=Path, default=Path("asset_sheet.png"), help="PNG to write (default asset_sheet.png)"
    )
    _catalogs_argument(show)
    show.set_defaults(run=_show)


def _catalog_argument(parser, text: str) -> None:
    from scenegen.paths import USER_CATALOG

    parser.add_argument("--catalog", type=Path, default=USER_CATALOG, help=text)


def _catalogs_argument(parser) -> None:
    parser.add_argument(
        "--catalog",
        type=Path,
        action="append",
        default=None,
        dest="catalogs",
        help="a user catalog (repeatable; default user_assets/catalog.yaml when it exists)",
    )


def _catalogs(args):
    from scenegen.assets.catalog import load_catalogs
    from scenegen.paths import USER_CATALOG

    if args.catalogs is None:
        args.catalogs = [USER_CATALOG] if USER_CATALOG.is_file() else []
    return load_catalogs(args.catalogs)


def _add(args) -> int:
    if args.name and (len(args.meshes) > 1 or args.meshes[0].is_dir()):
        return fail(f"--name {args.name}: give one MESH with --name (each asset needs its own name)")
    if args.workers < 1:
        return fail(f"--workers {args.workers}: must be at least 1")
    if len(args.meshes) == 1 and not args.meshes[0].is_dir() and args.sidecar is None:
        return _add_one(args)
    return _add_many(args)


def _options(args, category: str | None):
    from scenegen.data.asset_import import ImportOptions

    return ImportOptions(
        category=category,
        name=args.name,
        scale=args.scale,
        units=args.units,
        mass=args.mass,
        density=args.density,
        friction=args.friction,
        up=args.up,
        texture=args.texture,
        collision=args.collision,
    )


def _add_one(args) -> int:
    from scenegen.assets.catalog import CatalogError
    from scenegen.data.asset_import import add_asset
    from scenegen.data.asset_meshes import MeshImportError

    if not args.category:
        return fail(f"{args.meshes[0]}: give --category (what the object is, e.g. fruit)")
    try:
        result = add_asset(args.meshes[0], _options(args, args.category), args.catalog)
    except (MeshImportError, CatalogError, OSError) as exc:
        return fail(first_line(exc))
    asset = result.asset
    print(
        f"{asset.name}: {asset.category}, {len(asset.parts.files)} convex part(s) ({asset.collision}, "
        f"{asset.hull_to_visual_mm} mm off), {len(asset.resting_poses)} resting pose(s), "
        f"{asset.mass * 1000:.0f} g, {' x '.join(f'{e * 100:.1f}' for e in asset.extents)} cm "
        f"-> {result.catalog} ({result.seconds:.1f} s)"
    )
    for note in result.notes:
        print(f"  note: {note}")
    return 0


def _add_many(args) -> int:
    """Folders and several files: every file imported or refused, then one table."""
    from scenegen.assets.catalog import CatalogError
    from scenegen.data.asset_folder import SidecarError, folder_options, import_meshes, read_sidecar

    folders = [m for m in args.meshes if m.is_dir()]
    if args.sidecar is not None and (len(folders) != 1 or len(args.meshes) != 1):
        return fail(f"--sidecar {args.sidecar}: describes one folder; give that folder alone")
    flags = _options(args, args.category)
    jobs = []
    try:
        for path in args.meshes:
            if path.is_dir():
                sidecar = read_sidecar(args.sidecar, path) if args.sidecar else {}
                jobs += folder_options(path, flags, sidecar)
            elif not flags.category:
                jobs.append((path, "no category: give --category"))
            else:
                jobs.append((path, flags))
    except SidecarError as exc:
        return fail(first_line(exc))
    done = []

    def said(row) -> None:
        done.append(row)
        what = _shown(row)
        print(f"[{len(done)}/{len(jobs)}] {row.file}: {row.outcome} {what}", flush=True)

    try:
        rows = import_meshes(jobs, args.catalog, args.workers, on_row=said)
    except (CatalogError, OSError) as exc:  # the catalog itself cannot be read
        return fail(first_line(exc))
    print()
    for line in outcome_table(rows):
        print(line)
    return 1 if any(r.outcome == "refused" for r in rows) else 0


def _shown(row) -> str:
    """A row's asset, or the first line of why it was refused."""
    return (row.detail.strip().splitlines() or [""])[0] if row.outcome == "refused" else row.asset


def outcome_table(rows) -> list[str]:
    """One line per file (its asset, or why it was refused), then the counts."""
    width = max(len(r.file) for r in rows)
    lines = []
    for r in rows:
        what = _shown(r)
        lines.append(f"{r.file:<{width}}  {r.outcome:<8}  {what}")
    counts = {k: sum(r.outcome == k for r in rows) for k in ("imported", "refused", "skipped")}
    lines.append(
        f"{counts['imported']} imported, {counts['refused']} refused, {counts['skipped']} skipped as present"
    )
    return lines


def _list(args) -> int:
    from scenegen.assets.catalog import CatalogError

    try:
        catalog = _catalogs(args)
    except CatalogError as exc:
        return fail(first_line(exc))
    print(
        f"{'name':16s} {'category':12s} {'parts':>5s} {'poses':>5s} {'mass g':>7s}  {'collision':21s} catalog"
    )
    for a in catalog.assets:
        where = "bundled" if a.source is None else str(a.root)
        parts, poses, grams = len(a.parts.files), len(a.resting_poses), a.mass * 1000
        print(f"{a.name:16s} {a.category:12s} {parts:5d} {poses:5d} {grams:7.0f}  {a.collision:21s} {where}")
    return 0


def _show(args) -> int:
    from scenegen.analysis.asset_sheet import asset_sheet
    from scenegen.assets.catalog import CatalogError

    try:
        catalog = _catalogs(args)
        if args.all == bool(args.names):
            return fail("name the assets to show, or give --all (not both)")
        names = [a.name for a in catalog.assets] if args.all else args.names
        for name in names:
            catalog.get(name)
        out = asset_sheet(catalog, names, args.out)
    except (CatalogError, OSError) as exc:
        return fail(first_line(exc))
    print(f"wrote {out} ({len(names)} asset(s): resting poses, then convex parts)")
    return 0
