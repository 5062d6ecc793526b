"""The run's configs: the preset "auto" resolves to one per device, one rule for all methods."""

import pytest

from recon.models.registry import METHOD_NAMES, import_methods
from recon.train.config import TrainConfig, build_config, resolve_preset


def test_auto_preset_is_gpu_or_paper_on_cuda_and_fast_elsewhere():
    assert resolve_preset("auto", {"fast": {}, "paper": {}, "gpu": {}}, "cuda")[0] == "gpu"
    presets = {"fast": {}, "paper": {"x": 1}}
    assert TrainConfig(method="3dgs").preset == "auto"
    assert resolve_preset("auto", presets, "cuda") == ("paper", "auto: paper on a cuda device")
    assert resolve_preset("auto", presets, "cpu") == ("fast", "auto: fast on a cpu device")
    assert resolve_preset("auto", {"fast": {}}, "cuda")[0] == "fast"  # no paper preset
    assert resolve_preset("lean", presets, "cuda") == ("lean", "--preset lean")  # as given


@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_every_method_builds_its_auto_preset(device):
    specs = import_methods()
    for name in METHOD_NAMES:  # not the toy methods other tests register
        spec = specs[name]
        preset, _ = resolve_preset("auto", spec.presets, device)
        on_cuda = "gpu" if name == "3dgs" else "paper"
        assert preset == (on_cuda if device == "cuda" else "fast"), name
        build_config(spec.config_cls, spec.presets, preset, [])
