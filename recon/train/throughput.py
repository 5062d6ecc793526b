"""How fast this run's device trains its method, measured in the first seconds of the run.

The working resolution (`recon.train.resolution.choose_resolution`) and the step plan
(`planned_steps`) need the device's training throughput. A method's `ResolutionPolicy` holds
what whole runs averaged on one machine, the reference (2 threads of the benchmark VM's x86-64
CPU): training pixels a second for the level rule, and a step's time, affine in its pixels P,
overhead + P / rate, for the plan. A run elsewhere (another CPU, more threads, a GPU) scales
those figures by its `Speed`: how many times faster than the reference a step's fixed cost
(`overhead`) and its per-pixel cost (`pixels`) are; on a GPU the two differ by orders of
magnitude, so one factor would not do.

The speed is measured by the probe: real training steps of a throw-away model built from the
run's config, on a few training views at one or two small pyramid levels, timed (`run_probe`).
A run's first steps are not its average ones (a 3DGS model grows as it densifies, an ngp
occupancy grid empties), so the probe's times are compared with what the same probe took on
the reference machine (`ResolutionPolicy.probe_overhead_s`, `probe_pixels_per_s`) and never
used as the run's figures themselves (`measured_speed`); a speed near the prior is the prior
(`settled_speed`). Where nothing is measured (a --steps run, a resume, a method with no
reference probe) the speed is the prior: threads / 2 for both costs (`prior_speed`).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass

import torch

from recon.models.base import Model, ResolutionPolicy, TrainData
from recon.train.trainer import Trainer

MEASURED_THREADS = 2  # the policies' figures were measured at 2 threads
MAX_SPEEDUP = 1e4  # a speed is clamped to [1 / this, this] (a degenerate fit: no cost at all)
# A measured speed within this factor of the prior at every probed size counts as the prior
# (`settled_speed`). Probes on the quiet reference machine vary by ~5 %, and a probe's first
# steps depend on the scene where a policy holds one figure for all (lego-200's 3dgs probe
# steps run 0.8x as fast as fox's, its plenoxel ones 1.6x; each reference sits between the two
# benchmark scenes), but some levels sit within 1-3 % of a budget's bound (fox, 2 minutes: 3dgs
# moves from 1/9 to 1/8 at a 3 % faster rate, ngp from 1/10 to 1/11 at a 1 % slower one):
# measured figures would flip them from run to run and scene to scene. A device off by more
# (another thread count, a GPU) is measured.
PRIOR_TOLERANCE = 1.5
# ... and slower than the prior by up to this factor: the probe errs towards the prior's longer
# plan, since a step plan too long is shortened by the replanner and one too short is not (its
# schedules end early). llff_flower's probe steps run 0.62-0.70x the prior's speed on the
# reference machine itself, where its whole runs step at the prior's rate (1.34 steps/s at
# full size, the prior 1.28): at 1 / 1.5 its 10-minute runs flipped between the prior's plan
# (2,337 steps made, 28.21 dB at the photos' size) and a measured one of 1,781 (2,335 made,
# its schedules over before the last quarter: 27.32 dB;
# bench/results/2026-11-29-vm-x86_64-2cpu-llff-flower-996860d.md).
PRIOR_TOLERANCE_SLOWER = 2.0
PROBE_VIEWS = 2  # training views the probe trains on (the first and last; read at full size)
PROBE_SIDES = (128, 256)  # longer sides of the probe levels of a whole-image-a-step method
PROBE_WARMUP = 2  # untimed steps at each level (first-step allocations, caches, compilation)
PROBE_STEPS = 8  # timed steps at each level, at most ...
PROBE_MAX_S = 1.5  # ... or this many seconds of them (at least 2 steps)
# A probe off the prior is run again and the faster steps kept (`fastest`): another process
# on the same cores can slow every step of one probe (the 2-core VM, a test suite beside it:
# 3dgs probe steps of 12 ms took 230 ms for seconds), and a level chosen on that would hold
# for the whole run
PROBE_TRIES = 2
# A device with no prior (a GPU): its run's average step over its probe's fastest. A GPU step is
# bound by kernel launches and Python, which do not grow with the model the way a CPU's
# rasterizer does (H200, 3dgs on lego at 100 px: probe steps of 5.7-7.2 ms, the run's 6,179
# steps 8.7 ms on average); a step plan too long is shortened by the replanner, one too short
# is not (its schedules would end early), so the margin errs long.
DEVICE_RUN_MARGIN = 1.5


@dataclass(frozen=True)
class Speed:
    """How many times faster than the reference machine this run's device takes a step's fixed
    cost and its per-pixel cost; where it comes from (measured | prior), and why."""

    overhead: float = 1.0
    pixels: float = 1.0
    source: str = "prior"
    reason: str = "the reference machine (2 threads)"

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ProbeSample:
    """One probed size: the `step_s` seconds of the fastest of `steps` timed steps (the fewest
    seconds a pixel) and the `pixels` it fitted (other processes only ever add time: on the
    shared 2-core VM a step of 15 ms took up to 600 ms while another job ran, and the median
    of eight followed such a stretch; the minimum, as `timeit` takes, did not)."""

    pixels: float
    step_s: float
    steps: int


REFERENCE = Speed()  # the reference machine itself: the policies' figures unscaled


def prior_speed(threads: int) -> Speed:
    """The speed assumed where none is measured: the reference's, scaled by threads / 2.
    Example: 4 threads -> 2x both costs."""
    s = max(threads, 1) / MEASURED_THREADS
    return Speed(s, s, "prior", f"the policy's figures x {s:g} ({threads} threads, measured at 2)")


# ---- the step model: the policy's figures at a speed ----------------------------------------
def step_seconds(policy: ResolutionPolicy, pixels: float, speed: Speed = REFERENCE) -> float:
    """A whole run's average step of `pixels` pixels at `speed`: step_overhead_s / overhead +
    P / (rate x pixels), rate = step_pixels_per_s (or pixels_per_s). Example: 3dgs's 50 ms +
    1 us a pixel at 269 x 478 (128,582 px) on a device 2x / 4x faster -> 25 + 32 = 57 ms."""
    rate = policy.step_pixels_per_s or policy.pixels_per_s
    return policy.step_overhead_s / speed.overhead + pixels / (rate * speed.pixels)


def pixels_per_s(policy: ResolutionPolicy, pixels: float, speed: Speed = REFERENCE) -> float:
    """The level rule's throughput at steps of `pixels` pixels: policy.pixels_per_s times how
    much faster such a step is at `speed` (`step_seconds` at speed 1 over at `speed`).
    Example: 3dgs (450k px/s) at 128,582 px a step, 2x / 4x faster: 178.6 / 57.1 ms -> 1.41M."""
    return policy.pixels_per_s * step_seconds(policy, pixels) / step_seconds(policy, pixels, speed)


# ---- the measurement: probe steps against the reference's -------------------------------------
def reference_probe_s(policy: ResolutionPolicy, pixels: float) -> float:
    """What a probe step of `pixels` pixels took on the reference machine: probe_overhead_s +
    P / probe_pixels_per_s."""
    return policy.probe_overhead_s + pixels / policy.probe_pixels_per_s


def fit_step_time(samples: list[ProbeSample]) -> tuple[float, float]:
    """(overhead s, s a pixel) of t = overhead + P x s_px, least squares over the samples, both
    kept >= 0. Example: 60 ms at 10k px, 90 ms at 40k px -> (50 ms, 1 us)."""
    ps = [s.pixels for s in samples]
    ts = [s.step_s for s in samples]
    p_mean, t_mean = statistics.fmean(ps), statistics.fmean(ts)
    var = sum((p - p_mean) ** 2 for p in ps)
    slope = sum((p - p_mean) * (t - t_mean) for p, t in zip(ps, ts)) / var if var else 0.0
    slope = max(slope, 0.0)
    overhead = t_mean - slope * p_mean
    if overhead < 0:  # all per-pixel: through the origin
        overhead, slope = 0.0, sum(p * t for p, t in zip(ps, ts)) / sum(p * p for p in ps)
    return overhead, slope


def _clamped(x: float) -> float:
    return min(max(x, 1 / MAX_SPEEDUP), MAX_SPEEDUP)


def measured_speed(policy: ResolutionPolicy, samples: list[ProbeSample]) -> Speed:
    """The speed the probe's samples show against the reference probe. Two sizes or more, and a
    reference with an overhead: each cost on its own, overhead_ref / overhead and rate / rate_ref
    of the fitted step times (`fit_step_time`); else one factor for both, the geometric mean of
    reference / measured step time. Example: a reference probe of 8 ms + P / 2M px/s, steps of
    10k and 40k px in 4.5 and 6 ms (4 ms + P / 20M px/s) -> 2x the fixed cost, 10x per pixel."""
    sizes = {s.pixels for s in samples}
    if len(sizes) >= 2 and policy.probe_overhead_s > 0:
        overhead, per_pixel = fit_step_time(samples)
        s_o = policy.probe_overhead_s / overhead if overhead > 0 else MAX_SPEEDUP
        s_p = 1 / (policy.probe_pixels_per_s * per_pixel) if per_pixel > 0 else MAX_SPEEDUP
        how = "fixed and per-pixel costs fitted"
    else:
        ratios = [reference_probe_s(policy, s.pixels) / s.step_s for s in samples]
        s_o = s_p = statistics.geometric_mean(ratios)
        how = "one factor"
    return Speed(_clamped(s_o), _clamped(s_p), "measured", how)


def device_speed(
    policy: ResolutionPolicy, samples: list[ProbeSample], margin: float = DEVICE_RUN_MARGIN
) -> Speed:
    """The speed of a device with no prior (a GPU): its probe's own step times, `margin` times
    longer, are the run's steps, expressed against the policy's run-level step model
    (`step_seconds`) rather than against the reference probe (a CPU run's steps are several
    times its probe's, a GPU's are not: `DEVICE_RUN_MARGIN`). Two sizes or more: the fitted
    fixed and per-pixel costs apart (`fit_step_time`); one: one factor.
    Example: 3dgs (50 ms + P / 1M px/s a step), probe steps of 7.2 ms at 10k px and 5.7 ms at
    40k px (H200, lego) -> 6.45 ms + 0 a pixel -> fixed cost 0.05 / (1.5 x 0.00645) = 5.17x,
    per-pixel MAX_SPEEDUP: a run's step 9.7 ms at any size."""
    sizes = {s.pixels for s in samples}
    rate = policy.step_pixels_per_s or policy.pixels_per_s
    if len(sizes) >= 2 and policy.step_overhead_s > 0:
        overhead, per_pixel = fit_step_time(samples)
        s_o = policy.step_overhead_s / (margin * overhead) if overhead > 0 else MAX_SPEEDUP
        s_p = 1 / (rate * margin * per_pixel) if per_pixel > 0 else MAX_SPEEDUP
        how = f"fixed and per-pixel costs fitted, x{margin:g} for a whole run"
    else:
        ratios = [step_seconds(policy, s.pixels) / (margin * s.step_s) for s in samples]
        s_o = s_p = statistics.geometric_mean(ratios)
        how = f"one factor, x{margin:g} for a whole run"
    return Speed(_clamped(s_o), _clamped(s_p), "measured", how)


def settled_speed(
    policy: ResolutionPolicy,
    samples: list[ProbeSample],
    prior: Speed | None,
    tolerance: float = PRIOR_TOLERANCE,
    tolerance_slower: float = PRIOR_TOLERANCE_SLOWER,
) -> Speed:
    """The speed the run uses: the prior (one factor for both costs, `prior_speed`) while every
    probe step took what the prior predicts for it (the reference probe's time over the prior
    speed) up to `tolerance` times faster or `tolerance_slower` times slower, else the measured
    speed (`PRIOR_TOLERANCE` and `PRIOR_TOLERANCE_SLOWER` say why). No prior (a GPU, whose speed
    a CPU's threads do not tell): the probe's steps are the run's (`device_speed`). Example:
    prior 1x, probe steps 10 % slower than the reference's, or 1.8x slower -> the prior; 1.8x
    faster, or 2.5x slower -> measured."""
    note = "steps of " + ", ".join(
        f"{s.pixels / 1e3:.1f}k px in {s.step_s * 1e3:.1f} ms ({s.pixels / s.step_s / 1e3:.0f}k px/s)"
        for s in samples
    )
    if prior is not None:
        if not samples:
            return prior
        ratios = [
            reference_probe_s(policy, s.pixels) / (prior.overhead * s.step_s) for s in samples
        ]
        note += ": " + "/".join(f"{r:.2f}" for r in ratios) + "x the prior's speed"
        if all(1 / tolerance_slower <= r <= tolerance for r in ratios):
            return Speed(
                prior.overhead,
                prior.pixels,
                prior.source,
                f"{note}, within {tolerance_slower:g}x slower / {tolerance:g}x faster: the "
                f"prior stands, {prior.reason}",
            )
    speed = measured_speed(policy, samples) if prior is not None else device_speed(policy, samples)
    return Speed(
        speed.overhead,
        speed.pixels,
        "measured",
        f"{note}: measured, {speed.overhead:.3g}x the reference machine's fixed cost a step "
        f"and {speed.pixels:.3g}x its per-pixel cost ({speed.reason})",
    )


def fastest(a: list[ProbeSample], b: list[ProbeSample]) -> list[ProbeSample]:
    """Two probes of the same levels as one: at each, the faster step (the fewer seconds a
    pixel), counting the steps of both. Example: [(9k px, 12 ms, 8)] and [(9k px, 230 ms, 3)]
    -> [(9k px, 12 ms, 11)]."""
    if not a:
        return b
    out = []
    for x, y in zip(a, b):
        best = x if x.step_s / x.pixels <= y.step_s / y.pixels else y
        out.append(ProbeSample(best.pixels, best.step_s, x.steps + y.steps))
    return out


# ---- running the probe ------------------------------------------------------------------------
def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run_probe(
    model: Model, views: TrainData, levels: list[int], max_s: float = PROBE_MAX_S
) -> list[ProbeSample]:
    """Train `model` (a throw-away) on `views` downscaled by each of `levels` in turn:
    PROBE_WARMUP untimed steps, then up to PROBE_STEPS timed ones within `max_s` (at least 2).
    A step fits `Model.step_pixels` pixels (an image, or an adaptive ray batch); each level's
    sample is its step of the fewest seconds a pixel."""
    device = views.images.device
    samples, step = [], 0
    model.train()
    trainer = Trainer(model)
    for k in levels:
        data = views.downsampled(k)
        for _ in range(PROBE_WARMUP):
            trainer.step(data, step)
            step += 1
        timed: list[tuple[int, float]] = []
        spent = 0.0
        while len(timed) < PROBE_STEPS and (len(timed) < 2 or spent < max_s):
            pixels = model.step_pixels(data)
            _sync(device)
            t0 = time.perf_counter()
            trainer.step(data, step)
            _sync(device)
            timed.append((pixels, time.perf_counter() - t0))
            spent += timed[-1][1]
            step += 1
        pixels, seconds = min(timed, key=lambda ps: ps[1] / ps[0])
        samples.append(ProbeSample(float(pixels), seconds, len(timed)))
    return samples
