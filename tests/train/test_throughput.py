"""The device's speed: the step model's worked examples, the fit of the probe's steps, the
prior's tolerance, and the probe timing a model's real steps."""

import pytest
import torch

from recon.models.base import Model, ResolutionPolicy
from recon.train.throughput import (
    PRIOR_TOLERANCE,
    PRIOR_TOLERANCE_SLOWER,
    PROBE_STEPS,
    PROBE_WARMUP,
    REFERENCE,
    ProbeSample,
    Speed,
    fastest,
    fit_step_time,
    measured_speed,
    pixels_per_s,
    prior_speed,
    run_probe,
    settled_speed,
    step_seconds,
)

SPLATS = ResolutionPolicy(
    pixels_per_s=450e3,
    step_overhead_s=0.05,
    step_pixels_per_s=1e6,
    probe_overhead_s=0.008,
    probe_pixels_per_s=2e6,
)
RAYS = ResolutionPolicy(pixels_per_s=10e3, pixels_per_step=2500, probe_pixels_per_s=25e3)


def test_step_model_worked_examples():
    faster = Speed(2.0, 4.0, "measured")
    assert step_seconds(SPLATS, 128582) == pytest.approx(0.178582)
    assert step_seconds(SPLATS, 128582, faster) == pytest.approx(0.025 + 0.0321455)
    assert pixels_per_s(SPLATS, 128582, faster) == pytest.approx(1.407e6, rel=1e-3)
    assert pixels_per_s(SPLATS, 128582) == SPLATS.pixels_per_s  # the reference machine
    # no overhead in the policy: the pixel speed alone
    assert pixels_per_s(RAYS, 2500, faster) == pytest.approx(4 * RAYS.pixels_per_s)


def test_prior_scales_with_threads():
    assert prior_speed(2) == Speed(1.0, 1.0, "prior", prior_speed(2).reason)
    four = prior_speed(4)
    assert (four.overhead, four.pixels, four.source) == (2.0, 2.0, "prior")
    assert prior_speed(1).pixels == 0.5


def test_fit_step_time_worked_example():
    o, s = fit_step_time([ProbeSample(10e3, 0.06, 8), ProbeSample(40e3, 0.09, 8)])
    assert (o, s) == (pytest.approx(0.05), pytest.approx(1e-6))
    # a per-pixel cost hidden in noise (slower at the smaller size) is none at all
    assert fit_step_time([ProbeSample(1e4, 0.006, 8), ProbeSample(4e4, 0.005, 8)]) == (
        pytest.approx(0.0055),
        0.0,
    )
    # a negative fixed cost: all per-pixel, through the origin
    o, s = fit_step_time([ProbeSample(1e4, 0.001, 8), ProbeSample(2e4, 0.004, 8)])
    assert o == 0.0 and s == pytest.approx((1e4 * 0.001 + 2e4 * 0.004) / (1e8 + 4e8))


def test_measured_speed_worked_examples():
    # the docstring's: reference 8 ms + P / 2M, measured 4 ms + P / 20M
    samples = [ProbeSample(10e3, 0.0045, 8), ProbeSample(40e3, 0.006, 8)]
    speed = measured_speed(SPLATS, samples)
    assert speed.source == "measured"
    assert (speed.overhead, speed.pixels) == (pytest.approx(2.0), pytest.approx(10.0))
    # one size (a ray batch): one factor, reference 100 ms / measured 25 ms
    one = measured_speed(RAYS, [ProbeSample(2500, 0.025, 8)])
    assert one.overhead == one.pixels == pytest.approx(4.0)
    # no per-pixel cost measured at all: clamped, finite
    flat = measured_speed(SPLATS, [ProbeSample(1e4, 0.004, 8), ProbeSample(4e4, 0.004, 8)])
    assert flat.pixels == 1e4 and flat.overhead == pytest.approx(2.0)


def test_settled_speed_prefers_the_prior_within_the_tolerance():
    ref = [ProbeSample(10e3, 0.013, 8), ProbeSample(40e3, 0.028, 8)]  # the reference's own
    within = (1.0, 1.2, 1 / 1.2, 0.99 * PRIOR_TOLERANCE_SLOWER, 1.01 / PRIOR_TOLERANCE)
    for slower in within:
        samples = [ProbeSample(s.pixels, s.step_s * slower, 8) for s in ref]
        speed = settled_speed(SPLATS, samples, prior_speed(2))
        assert speed.source == "prior" and speed.overhead == speed.pixels == 1.0, slower
        assert "the prior stands" in speed.reason
    # the bounds: up to 1.5x faster, 2x slower (a plan too long is shortened, one too short is not)
    for slower in (0.99 / PRIOR_TOLERANCE, 1.01 * PRIOR_TOLERANCE_SLOWER):
        samples = [ProbeSample(s.pixels, s.step_s * slower, 8) for s in ref]
        assert settled_speed(SPLATS, samples, prior_speed(2)).source == "measured", slower
    assert (PRIOR_TOLERANCE, PRIOR_TOLERANCE_SLOWER) == (1.5, 2.0)
    slow = settled_speed(SPLATS, [ProbeSample(s.pixels, s.step_s * 4, 8) for s in ref], REFERENCE)
    assert slow.source == "measured"
    assert (slow.overhead, slow.pixels) == (pytest.approx(0.25), pytest.approx(0.25))
    assert "measured" in slow.reason and "k px/s" in slow.reason
    # the prior of 4 threads predicts half the reference's probe time
    half = [ProbeSample(s.pixels, s.step_s / 2, 8) for s in ref]
    assert settled_speed(SPLATS, half, prior_speed(4)).source == "prior"
    assert settled_speed(SPLATS, half, prior_speed(1)).source == "measured"
    assert settled_speed(SPLATS, [], prior_speed(2)) == prior_speed(2)
    # no prior (a GPU): measured, even right at the reference's speed
    assert settled_speed(SPLATS, ref, None).source == "measured"


def test_fastest_of_two_probes():
    first = [ProbeSample(9e3, 0.012, 8), ProbeSample(3e4, 0.40, 4)]  # a busy second level
    second = [ProbeSample(9e3, 0.230, 3), ProbeSample(3e4, 0.021, 8)]
    assert fastest(first, second) == [ProbeSample(9e3, 0.012, 11), ProbeSample(3e4, 0.021, 12)]
    assert fastest([], second) == second
    # adaptive ray batches: the fewer seconds a ray
    rays = fastest([ProbeSample(800, 0.080, 8)], [ProbeSample(1100, 0.100, 8)])
    assert rays == [ProbeSample(1100, 0.100, 16)]


class Counting(Model):
    """A model whose steps take 2 ms plus 1 us a pixel and count themselves; with `batch`, it
    fits that many rays a step instead of an image."""

    def __init__(self, batch: int = 0):
        super().__init__()
        self.register_buffer("background", torch.zeros(3))
        self.steps, self.batch = [], batch

    def step_pixels(self, data):
        return self.batch or super().step_pixels(data)

    def optimizers(self):
        return {}

    def training_loss(self, data, step, background):
        import time

        self.steps.append((step, tuple(data.images.shape[1:3])))
        time.sleep(0.002 + self.step_pixels(data) * 1e-6)
        return torch.zeros(()), {"loss": 0.0}


def _views(size: int):
    from recon.cameras import Cameras
    from recon.models.base import TrainData

    cams = Cameras(
        torch.eye(3)[None].repeat(2, 1, 1),
        torch.eye(4)[None].repeat(2, 1, 1),
        torch.tensor([size, size]),
        torch.tensor([size, size]),
    )
    return TrainData(torch.rand(2, size, size, 3), cams)


def test_run_probe_times_each_level_after_a_warm_up():
    model = Counting()
    samples = run_probe(model, _views(64), [4, 1])
    per_level = PROBE_WARMUP + PROBE_STEPS
    assert [s for s, _ in model.steps] == list(range(2 * per_level))  # steps go on
    assert [shape for _, shape in model.steps] == [(16, 16)] * per_level + [(64, 64)] * per_level
    assert [s.pixels for s in samples] == [256.0, 4096.0]
    assert all(s.steps == PROBE_STEPS for s in samples)
    assert samples[0].step_s >= 0.002 and samples[1].step_s >= 0.006
    # a ray batch counts its rays; a slow method stops after max_s (but times two steps)
    (batch,) = run_probe(Counting(batch=2500), _views(64), [1], max_s=0.001)
    assert batch.pixels == 2500.0 and batch.steps == 2


def test_each_method_counts_a_step_in_its_policys_pixels(one_thread):
    """`Model.step_pixels` in the units of the method's policy: the fast configs' batches are
    the policy's pixels_per_step; the paper presets' larger sample targets count more rays (the
    probe then sees the bigger batch a GPU trains), a fixed batch its rays, 3dgs one image."""
    from recon.models.registry import import_methods
    from tests.conftest import sphere_scene

    data, info = sphere_scene(n_cams=2, size=16)
    expected = {
        "3dgs": (256, 256),
        "ngp": (2500, 10000),  # 4x the sample target
        "nerf": (1024, 4096),  # its fixed batch
        "plenoxel": (12000, 5000),  # the paper's fixed batch
        "sdf": (1024, 1024),
    }
    specs = import_methods()
    for name, sizes in expected.items():
        spec = specs[name]
        got = tuple(
            spec.build(spec.config_cls(**spec.presets[p]), info).step_pixels(data)
            for p in ("fast", "paper")
        )
        assert got == sizes, name
        assert spec.resolution.pixels_per_step in (0, sizes[0])
