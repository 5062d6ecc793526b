"""The 3dgs config's schedules: how a preset's step schedules fit a planned run."""

from recon.models.splatting_config import PRESETS, GaussiansConfig


def test_fit_schedules_worked_example():
    from recon.models.schedules import fit_schedules
    from recon.models.splatting_config import SCHEDULE_FRACTIONS

    def fit(config):
        return fit_schedules(config, SCHEDULE_FRACTIONS)

    fast = GaussiansConfig(**PRESETS["fast"])
    fitted = fit(GaussiansConfig(**{**PRESETS["fast"], "schedule_steps": 1600}))
    assert (
        fitted.lr_decay_steps,
        fitted.densify_stop,
        fitted.opacity_reset_interval,
        fitted.sh_degree_interval,
    ) == (1600, 1120, 560, 320)
    assert fit(fast) == fast  # schedule_steps 0: as configured
    long = GaussiansConfig(**{**PRESETS["fast"], "schedule_steps": 6000})  # lego-200, 10 min
    assert fit(long) == long  # a run longer than the schedules keeps them
