"""What the rig costs: the simulated pipeline against the same decomposition from noise-free frames.

Two decompositions of the same scene, beam plan and photos, both measured against the
renderer's true bounces (:mod:`ilt.sim.render`):

- **rig**: a workspace made by ``ilt run`` on the simulated rig: DNG brackets of the
  simulated camera (Poisson and read noise, clipping, quantisation, dark frames),
  ``ilt merge``, spots found on the merged frames, T, photos shot as brackets and merged;
- **ideal**: the renderer's noise-free frames of the same beams and photos, on the same
  half-resolution green grid the merge writes (the mean of each Bayer cell's two green
  sites), then the same centroids -> build-isf -> decompose.

The error of bounce n is ``||L_n - L_n*|| / ||L_n*||`` with ``L_n*`` the true n-bounce
frame integrated over the ISF's own cells (:func:`ilt.isf.build.sample_like`), so both
include the discretisation error of the cells; the rig's photos are in the merge's
units, so its truth is scaled by the one factor that matches the photo's sampled sum.
The ratio rig / ideal is what capture, RAW and merge add (issue 7: at most 1.2).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ilt.io.frames import PixelMapping

log = logging.getLogger(__name__)

#: the merged frames' grid: one pixel per 2x2 Bayer cell (ilt/io/raw.py)
GREEN_GRID = PixelMapping((0.5, 0.5), 2.0)


def green_grid(frames: np.ndarray, sensor) -> np.ndarray:
    """(..., H, W) rendered frames -> (..., h/2, w/2) float64 as the merge sees them: placed
    at the top left of the ``sensor`` (zeros elsewhere) and averaged over each cell's two
    green sites (green gain 1, ilt/sim/sensor.py)."""
    frames = np.asarray(frames, dtype=np.float64)
    padded = np.zeros(frames.shape[:-2] + (sensor.height, sensor.width))
    padded[..., :frames.shape[-2], :frames.shape[-1]] = frames
    green = sensor.colour_index() == 1
    top = green[0].nonzero()[0][0]          # column of the green site in the cell's first row
    return 0.5 * (padded[..., 0::2, top::2] + padded[..., 1::2, 1 - top::2])


def rendered_scene(cfg):
    """The :class:`~ilt.sim.render.RenderedScene` and sensor the simulated camera of a
    :class:`~ilt.capture.config.RigConfig` sees (ilt/capture/camera.py)."""
    from ilt.capture.camera import sim_sensor
    from ilt.capture.plan import make_plan
    from ilt.sim.render import render_scene

    c = cfg.camera
    scene = render_scene(c.scene, beams=make_plan(cfg.plan).m, px_per_beam=c.px_per_beam, rows=c.rows,
                         spot=c.spot)
    return scene, sim_sensor(scene)


def ideal_workspace(cfg, kinds, out: str | os.PathLike, n_bounces: int = 8, workers: int | None = 1) -> Path:
    """The noise-free counterpart of a rig workspace in ``out``: ``hdr/`` (the renderer's beam
    frames on the green grid), ``photos/<kind>.exr``, then ``spots/``, ``isf/``, ``decompose/``
    with the stages' default parameters."""
    from ilt.decompose.stage import decompose
    from ilt.io.exr import write_exr
    from ilt.io.manifest import write_manifest
    from ilt.isf.build import build_isf
    from ilt.isf.directory import load_isf
    from ilt.spots.stage import run_centroids

    out = Path(out)
    scene, sensor = rendered_scene(cfg)
    hdr, photos = out / "hdr", out / "photos"
    for d in (hdr, photos):
        d.mkdir(parents=True, exist_ok=True)
    attributes = GREEN_GRID.attributes()
    for j in range(scene.m):
        write_exr(hdr / f"beam-{j:05d}.exr", green_grid(scene.beam_frame(j), sensor).astype(np.float32),
                  attributes=attributes)
    write_manifest(hdr, "simulate", {"scene": scene.name}, extra={
        "m": scene.m, "layout": list(scene.layout), "pixel_mapping": GREEN_GRID.as_dict()})
    for kind in kinds:
        write_exr(photos / f"{kind}.exr", green_grid(scene.photo(kind, n_bounces=1)[0], sensor).astype(np.float32),
                  attributes=attributes)
    run_centroids(hdr, out / "spots", workers=workers, force=True)
    build_isf(hdr, out / "spots", out / "isf", workers=workers, force=True)
    decompose(load_isf(out / "isf"), [photos / f"{k}.exr" for k in kinds], out / "decompose",
              n_bounces=n_bounces, force=True)
    return out


def bounce_errors(workspace: str | os.PathLike, cfg, kinds, n_bounces: int = 4) -> dict[str, list[float]]:
    """Per photo kind, the relative error of bounces 1..``n_bounces`` of ``workspace/decompose``
    against the renderer's truth sampled like the workspace's ISF (module docstring)."""
    from ilt.evaluate.errors import relative_errors
    from ilt.isf.build import sample_like
    from ilt.isf.directory import load_isf

    workspace = Path(workspace)
    scene, sensor = rendered_scene(cfg)
    isf = load_isf(workspace / "isf")
    out = {}
    for kind in kinds:
        photo, bounces = scene.photo(kind, n_bounces=n_bounces)
        truth = sample_like(isf, green_grid(bounces, sensor))
        computed = np.load(workspace / "decompose" / kind / "bounces.npy")[:n_bounces]
        total = computed.sum(axis=0) + np.load(workspace / "decompose" / kind / "residual.npy")
        scale = total.sum() / sample_like(isf, green_grid(photo, sensor)).sum()
        out[kind] = relative_errors(computed, scale * truth).tolist()
    return out


def compare(workspace: str | os.PathLike, ideal: str | os.PathLike, cfg, kinds, n_bounces: int = 4) -> dict:
    """Both workspaces' errors per photo and bounce, and their ratio rig / ideal."""
    rig = bounce_errors(workspace, cfg, kinds, n_bounces)
    ref = bounce_errors(ideal, cfg, kinds, n_bounces)
    return {kind: {"rig": rig[kind], "ideal": ref[kind],
                   "ratio": [r / i for r, i in zip(rig[kind], ref[kind])]} for kind in kinds}
