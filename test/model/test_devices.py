"""model.devices: the one parser of device names (node, replay, evaluation, training)."""

from __future__ import annotations

import pytest
import torch

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.model.devices import check_device


def test_cpu_and_auto():
    assert check_device("cpu") == torch.device("cpu")
    assert check_device(torch.device("cpu")) == torch.device("cpu")
    expected = torch.device("cuda", 0) if torch.cuda.is_available() else torch.device("cpu")
    assert check_device("auto") == expected


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("gpu9", "device 'gpu9' is not a torch device (auto, cpu, cuda, cuda:1)"),
        ("", "device '' is not a torch device (auto, cpu, cuda, cuda:1)"),
        ("meta", "device 'meta': only cpu and cuda devices are supported"),
        ("mps", "device 'mps': only cpu and cuda devices are supported"),
    ],
)
def test_bad_names(name, message):
    with pytest.raises(ConfigError) as caught:
        check_device(name)
    assert str(caught.value) == message


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the machine without CUDA")
@pytest.mark.parametrize("name", ["cuda", "cuda:1"])
def test_cuda_where_there_is_none(name):
    with pytest.raises(ConfigError) as caught:
        check_device(name)
    assert str(caught.value) == f"device '{name}': CUDA is not available here; use cpu"


def test_cuda_with_local_rank(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert check_device("cuda") == torch.device("cuda", 0)
    assert check_device("cuda", local_rank=1) == torch.device("cuda", 1)  # torchrun's process
    assert check_device("auto", local_rank=1) == torch.device("cuda", 1)
    assert check_device("cuda:1", local_rank=0) == torch.device("cuda", 1)  # explicit wins
    with pytest.raises(ConfigError, match=r"^device 'cuda:2': there is no cuda:2 here \(2 CUDA"):
        check_device("cuda:2")
