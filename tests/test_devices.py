"""The training device (scenegen/devices.py): auto follows what torch sees, a missing CUDA device is a
one-line error naming what to use, and an unknown name is refused."""

from __future__ import annotations

import pytest
import torch

from scenegen.devices import resolve_device


def test_auto_is_cuda_exactly_when_torch_sees_it():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_a_device_says_what_to_use():
    with pytest.raises(ValueError, match="use --device cpu or auto"):
        resolve_device("cuda")


def test_an_unknown_device_is_refused():
    with pytest.raises(ValueError, match="choose one of auto, cpu, cuda"):
        resolve_device("tpu")
