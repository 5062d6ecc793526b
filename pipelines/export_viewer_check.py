"""How a splat viewer (no antialiasing compensation) shows an antialiased 3dgs run's export.

Held-out PSNR at pyramid level K of the run as trained (compensated opacities), and drawn
without compensation from raw opacities (what `recon export` wrote before) and from opacities
times their mean compensation over the training views (what it writes now):

    python pipelines/export_viewer_check.py WS RUN [K]
"""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np
import torch

from recon.metrics.image import psnr
from recon.render.views import render_view
from recon.train.resolution import trained_resolution
from recon.workspace import Workspace
from recon.workspace.runs import load_run
from recon.workspace.scene import load_images


def main(workspace: str, run: str, level: int = 4) -> None:
    torch.set_num_threads(2)
    ws = Workspace(workspace)
    model, scene, doc = load_run(ws, run)
    if not getattr(model.config, "antialiased", False):
        sys.exit(f"run '{run}' was not trained with antialiased=true")
    level = trained_resolution(doc, scene).downscale
    train_cams = scene.cameras(scene.split("train"), "cpu", level)
    idx = scene.split("test")
    gts = load_images(ws, scene, idx, level)
    cams = scene.cameras(idx, "cpu", level)
    logits = model.params["opacity_logits"].data.clone()
    # what `recon export` writes (`GaussianModel.splats` with the training cameras)
    baked = torch.from_numpy(model.splats(train_cams)["opacity_logits"]).reshape(logits.shape)
    trained_cfg = model.config
    for name, antialiased, lg in (
        ("as trained (compensated)", True, logits),
        ("viewer, raw opacities", False, logits),
        ("viewer, baked opacities", False, baked),
    ):
        model.config = replace(trained_cfg, antialiased=antialiased)
        model.params["opacity_logits"].data.copy_(lg)
        values = []
        for j in range(len(idx)):
            with torch.no_grad():
                rgb = render_view(model, cams[j], gts.shape[2], gts.shape[1])["rgb"]
            values.append(float(psnr(rgb.clamp(0, 1), gts[j])))
        print(f"{name}: {np.mean(values):.2f} dB at 1/{level} ({len(idx)} held-out views)")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 4)
