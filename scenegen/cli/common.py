"""What every command handler shares: the usage-error exit code and the one-line error."""

from __future__ import annotations

import sys

USAGE_ERROR = 2


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name when it has none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


MAX_ERROR = 300  # characters of the whole error line


def fail(message: str) -> int:
    """Print ``scenegen: error: MESSAGE`` on stderr and return the usage-error code. One line of at
    most MAX_ERROR characters: further lines are dropped, and an overlong line keeps its first two
    thirds (the file, the field, what is wrong) and its last third (what to do) around a `` ... ``."""
    text = message.strip()
    line = "scenegen: error: " + (text.splitlines()[0] if text else "failed")
    if len(line) > MAX_ERROR:
        head = (MAX_ERROR - 5) * 2 // 3
        line = line[:head] + " ... " + line[len(line) - (MAX_ERROR - 5 - head) :]
    print(line, file=sys.stderr)
    return USAGE_ERROR


def add_backend_arguments(parser) -> None:
    """``--backend`` and ``--address``: where the per-scene work runs (scenegen/runner/executors.py)."""
    parser.add_argument(
        "--backend",
        choices=("local", "ray"),
        default="local",
        help="local: this process or a spawn pool of --workers processes (default); ray: --workers Ray "
        "actors, 1 CPU each (pip install 'scenegen[ray]'); this process still writes every file",
    )
    parser.add_argument(
        "--address",
        metavar="ADDR",
        help="with --backend ray: join this Ray cluster ('auto', HOST:6379 or ray://HOST:10001) "
        "instead of starting a local one (docs/scale.md)",
    )
    parser.add_argument(
        "--recycle-after",
        type=int,
        metavar="N",
        help="with the local pool: replace each worker by a fresh process after N items (its memory "
        "returned; results unchanged, a worker's start paid again); default: never",
    )


def backend_from(args):
    """The :class:`~scenegen.runner.executors.Backend` the arguments name; BackendError if they
    cannot run here (Ray not installed, --address without --backend ray)."""
    from scenegen.runner.executors import Backend, import_ray

    backend = Backend(args.backend, args.address, getattr(args, "recycle_after", None))
    if backend.kind == "ray":
        import_ray()  # fail before any work when Ray is missing
    return backend


def add_device_argument(parser) -> None:
    """``--device auto|cpu|cuda`` of a training command (scenegen/devices.py)."""
    from scenegen.devices import DEVICES

    parser.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where the weights and batches live (default auto: CUDA when torch sees one, else the CPU, "
        "what tests and CI use); random draws stay on the CPU, so a CPU run is byte-identical to one "
        "made before this flag existed",
    )


def device_error(args) -> str | None:
    """The one-line answer when ``--device`` names a device this machine lacks, else None (checked
    before any work, so a missing GPU costs nothing)."""
    from scenegen.devices import resolve_device

    try:
        resolve_device(args.device)
    except ValueError as exc:
        return str(exc)
    return None


def add_sensor_argument(parser, what: str, default: str | None = "exact") -> None:
    """``--sensor NAME``: the depth ``what`` holds, the renderer's (exact) or a depth sensor's
    (docs/sensor.md)."""
    from scenegen.render.sensor import SENSOR_NAMES  # numpy only: no MuJoCo, no GL

    parser.add_argument(
        "--sensor",
        choices=SENSOR_NAMES,
        default=default,
        help=f"{what}: exact, the renderer's depth; active_stereo, a simulated RealSense D415 (about 0.33 "
        "CPU-s a 640x480 frame); structured_light, the parametric noise (docs/sensor.md)",
    )


def physics_from(args) -> str:
    """The control-loop physics ``--physics`` names (default: the default physics); ValueError names
    the choices."""
    from scenegen.env.physics import DEFAULT_PHYSICS, physics_named

    name = args.physics or DEFAULT_PHYSICS
    physics_named(name)
    return name
