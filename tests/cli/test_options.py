"""One source for every default: each command-line option that sets a config field has the
field's default and help, and every config field a command exposes is an option."""

import dataclasses

import pytest

from recon.cli import eval_cmd, mesh_cmd, render_cmd, sfm_cmd, train_cmd
from recon.eval.stage import EvalConfig
from recon.mesh.stage import MeshConfig
from recon.options import field_help
from recon.render.stage import RenderConfig
from recon.sfm.colmap_config import SfmConfig
from recon.sfm.scene_writer import SceneConfig
from recon.train.config import TrainConfig

COMMANDS = [
    (train_cmd.command, [TrainConfig], {"method"}),
    (render_cmd.command, [RenderConfig], set()),
    (mesh_cmd.command, [MeshConfig], set()),
    (eval_cmd.command, [EvalConfig], set()),
    (sfm_cmd.sfm, [SceneConfig, SfmConfig], {"verbose"}),  # verbose: the global -v
]


@pytest.mark.parametrize(
    "command, configs, not_options", COMMANDS, ids=[c[0].name for c in COMMANDS]
)
def test_options_take_default_and_help_from_the_config(command, configs, not_options):
    params = {p.name: p for p in command.params}
    for cls in configs:
        helps = field_help(cls)
        for f in dataclasses.fields(cls):
            if f.name in not_options:
                continue
            assert f.name in params, (
                f"{cls.__name__}.{f.name} has no option in `recon {command.name}`"
            )
            p = params[f.name]
            assert p.default == f.default, (f.name, p.default, f.default)
            assert p.help.lower().startswith(helps[f.name][:20].lower()), (f.name, p.help)
            assert helps[f.name], f"{cls.__name__}.{f.name} has no help"
