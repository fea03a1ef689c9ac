"""Which torch device a training runs on (``--device auto|cpu|cuda`` of `scenegen train` and
`scenegen retrieval train`).

Randomness stays on the CPU whatever the device: weights are initialised, batches drawn and noise
sampled there and then moved, so a CPU run is byte-identical to one made before devices existed, and
a CUDA run draws the same batches (its arithmetic, not its data, differs). torch is imported only
when a device is resolved.
"""

from __future__ import annotations

DEVICES = ("auto", "cpu", "cuda")


def resolve_device(name: str):
    """The ``torch.device`` for ``name``: ``auto`` is CUDA when torch sees one, else the CPU;
    ``cuda`` without one is a one-line ValueError saying what to use instead."""
    import torch

    if name not in DEVICES:
        raise ValueError(f"--device {name!r}: choose one of {', '.join(DEVICES)}")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    elif name == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"--device cuda: this torch ({torch.__version__}) sees no CUDA device; use --device cpu or auto"
        )
    return torch.device(name)
