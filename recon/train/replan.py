"""Re-planning a budgeted run's step schedules from the step rate it actually gets.

`recon.train.resolution.planned_steps` lays a method's step schedules (learning-rate decay,
densification, SH degrees) out over the steps a time budget is expected to buy, at the
method's step time measured once on one machine. A slower machine, another load, or a
scene whose model grows more than expected makes fewer steps: a fox 3dgs run planned at
3,359 steps made 2,016, so it ended still densifying with its means learning rate
undecayed. So the loop measures the training step rate over windows of `REPLAN_EVERY_S`
seconds and has the model lay its schedules out over the run that estimate gives, never
longer than planned (`Model.replan`; a schedule that has ended stays ended). A 3DGS step
slows as Gaussians are added, so each window's estimate is still a little long; the next
windows shorten it further while densifying. A one-off slow window (lego's pruning when
densification ends) made a run planned at 6,666 steps re-plan to 4,077 and then make 6,746,
so later estimates lengthen the schedules back up to the plan.
"""

from __future__ import annotations

from dataclasses import dataclass

REPLAN_EVERY_S = 30.0  # length of a step-rate window, in seconds of the run
REPLAN_WARMUP_WINDOWS = 1  # windows measured before the first re-plan (initialisation, caches)


def projected_steps(
    step: int,
    steps_per_s: float,
    train_share: float,
    budget_s: float,
    elapsed_s: float,
    reserve_s: float,
) -> int:
    """The steps a budgeted run will have made when it stops: the steps so far plus the time
    left (budget - elapsed - the final evaluation's reserve) times the share of the run's time
    spent in training steps, at `steps_per_s` training steps per second. Example: step 1,000,
    3 steps/s, 95 % of the time training, 600 s budget, 300 s elapsed, 10 s reserve ->
    1,000 + 3 x 0.95 x 290 = 1,826."""
    left = max(budget_s - elapsed_s - reserve_s, 0.0) * train_share
    return step + int(steps_per_s * left)


@dataclass
class Replanner:
    """Step-rate windows over a budgeted run (one per `run_loop` call). `after_step` returns
    the projected length of the run when a window closes after the warm-up, else None."""

    budget_s: float
    start_step: int
    start_wall: float  # LoopState.wall_s / elapsed_s when the loop began
    start_elapsed: float
    every_s: float = REPLAN_EVERY_S
    warmup_windows: int = REPLAN_WARMUP_WINDOWS

    def __post_init__(self) -> None:
        self.windows = 0
        self.window = (self.start_step, self.start_wall, self.start_elapsed)

    @classmethod
    def starting_at(cls, budget_s: float, step: int, wall_s: float, elapsed_s: float):
        return cls(budget_s, step, wall_s, elapsed_s, REPLAN_EVERY_S, REPLAN_WARMUP_WINDOWS)

    def after_step(
        self, step: int, wall_s: float, elapsed_s: float, reserve_s: float
    ) -> int | None:
        """After a step, with the loop's clocks (`LoopState`: steps, training time, run time,
        the final evaluation's reserve)."""
        step0, wall0, elapsed0 = self.window
        if elapsed_s - elapsed0 < self.every_s or wall_s <= wall0:
            return None
        self.window = (step, wall_s, elapsed_s)
        self.windows += 1
        if self.windows <= self.warmup_windows:
            return None
        rate = (step - step0) / (wall_s - wall0)
        share = (wall_s - self.start_wall) / max(elapsed_s - self.start_elapsed, 1e-9)
        return projected_steps(step, rate, min(share, 1.0), self.budget_s, elapsed_s, reserve_s)
