"""The simulate stage: a synthetic scene written as an ISF directory with ground truth.

Layout of the directory (docs/formats.md)::

    T.npy  samples.csv  manifest.json          the ISF, as build-isf writes it
    lambertian.json  lambertian.png            its reciprocity verdict (ilt.isf.lambertian)
    photos/<kind>.npy  photos/<kind>.exr       photos: sample vectors and camera frames
    truth/A.npy  truth/T1.npy                  true transport and diag(T1) for unit columns
    truth/isf-bounces.npy                      (N, m, m) true n-bounce ISFs (m <= 2048)
    truth/photos/<kind>-bounces.npy            (N, m) true bounces of each photo
"""

from __future__ import annotations

import os
from pathlib import Path

from ilt.io.exr import write_exr
from ilt.io.manifest import save_npy, write_manifest
from ilt.io.staged import staged_directory
from ilt.isf.directory import write_isf
from ilt.isf.lambertian import check_lambertian
from ilt.isf.layout import splat
from ilt.sim import ILLUMINATIONS, Scene
from ilt.sim.gloss import glossy_scene
from ilt.sim.lighting import DEFAULTS, PROJECTOR_PERIOD_DEG
from ilt.sim.memory import require

#: the largest m for which the (N, m, m) true n-bounce ISFs are written
TRUTH_ISF_MAX_M = 2048


def write_simulation(
    scene: Scene,
    out: str | os.PathLike,
    parameters: dict,
    n_bounces: int = 8,
    max_bounces: int | None = None,
    force: bool = False,
    gloss: float = 0.0,
    patterns: int = 0,
) -> Path:
    """Write ``scene`` as an ISF directory at ``out`` (atomically), with ``lambertian.json``.

    ``max_bounces`` renders T with the paper's forward tracer truncated at that many
    bounces (the paper used 7); None gives the exact T. ``gloss`` > 0 (flatland only):
    that share of every patch's reflection glossy (:mod:`ilt.sim.gloss`); the truth then
    holds the photos' true bounces only (no A, T1 or n-bounce ISFs: the transport is
    over pairs of patches). ``patterns`` = K > 0: also the projector's photos for Nayar et
    al.'s separation (``ilt separate``): ``photos/patterns/stripes-<k>.npy|.exr``, its
    stripes shifted by k / K of a cycle, and ``photos/projector-full.npy|.exr`` (every
    projector pixel on) with its true bounces.
    """
    out = Path(out)
    glossy = glossy_scene(scene, gloss) if gloss > 0 else None
    if glossy is not None and max_bounces is not None:
        raise ValueError("--tracer-bounces and --gloss cannot be combined: the glossy scene's T is the exact solve")
    if scene.m <= TRUTH_ISF_MAX_M and glossy is None:  # (N, m, m) float64
        require(8 * n_bounces * scene.m**2, f"the {n_bounces} true n-bounce ISFs of {scene.m} beams")
    T, scale = scene.isf(max_bounces=max_bounces) if glossy is None else glossy.isf()
    with staged_directory(out, force=force) as tmp:
        fields = write_isf(tmp, T, scene.samples, scene.layout, scene.frame_shape)
        fields["lambertian"] = check_lambertian(tmp, T, scene.samples, None, None, scene.layout)
        truth = tmp / "truth"
        (truth / "photos").mkdir(parents=True)
        (tmp / "photos").mkdir()
        if glossy is None:
            save_npy(truth / "A.npy", scene.A)
            save_npy(truth / "T1.npy", scene.direct / scale)
            if scene.m <= TRUTH_ISF_MAX_M:
                save_npy(truth / "isf-bounces.npy", scene.bounce_isfs(n_bounces))
        for kind in ILLUMINATIONS:
            photo, bounces = (scene if glossy is None else glossy).photo(kind, n_bounces=n_bounces)
            save_npy(tmp / "photos" / f"{kind}.npy", photo)
            write_exr(
                tmp / "photos" / f"{kind}.exr", splat(photo, scene.samples, scene.frame_shape),
                attributes={"ilt:scene": scene.name, "ilt:illumination": kind},
            )
            save_npy(truth / "photos" / f"{kind}-bounces.npy", bounces)
        if patterns:
            _write_patterns(tmp, scene if glossy is None else glossy, scene, patterns, n_bounces)
        write_manifest(
            tmp, "simulate",
            {**parameters, "truth_bounces": n_bounces, "tracer_bounces": max_bounces, "gloss": gloss,
             "patterns": patterns},
            extra=fields,
        )
    return out


def _write_patterns(tmp: Path, lit, scene: Scene, count: int, n_bounces: int) -> None:
    """The projector's shifted-stripe photos and its fully lit photo with truth (``lit``: Scene or GlossyScene)."""
    period = DEFAULTS[scene.geometry.dim]["projector"].get("period_deg", PROJECTOR_PERIOD_DEG)
    (tmp / "photos" / "patterns").mkdir()
    shots = [("projector-full", tmp / "photos", {"pattern": "full"})]
    shots += [(f"stripes-{k}", tmp / "photos" / "patterns", {"phase_deg": 2 * period * k / count})
              for k in range(count)]
    for name, directory, params in shots:
        photo, bounces = lit.photo("projector", n_bounces=n_bounces, **params)
        save_npy(directory / f"{name}.npy", photo)
        write_exr(directory / f"{name}.exr", splat(photo, scene.samples, scene.frame_shape),
                  attributes={"ilt:scene": scene.name, "ilt:illumination": f"projector {name}"})
        if name == "projector-full":
            save_npy(tmp / "truth" / "photos" / f"{name}-bounces.npy", bounces)


def write_frames(scene, out: str | os.PathLike, parameters: dict, n_bounces: int = 8,
                 force: bool = False, progress=None) -> Path:
    """Write a :class:`~ilt.sim.render.RenderedScene` as camera frames (atomically)::

        hdr/beam-00000.exr ... hdr/manifest.json    one float frame per unit-power beam,
                                                    as 'ilt merge' writes them, with the plan
        photos/<kind>.exr                           photo frames (flashlight, room, projector)
        truth/spots.csv                             true spot centres (beam,x,y), px
        truth/photos/<kind>-bounces.npy             (N, H, W) float32 true n-bounce frames
        manifest.json

    Frames are rendered and written one at a time.
    """
    from ilt.isf.directory import write_samples

    out = Path(out)
    # a photo's true bounces: (N, H, W) float32 frames
    require(4 * n_bounces * scene.frame_shape[0] * scene.frame_shape[1],
            f"the {n_bounces} true bounce frames of each photo")
    with staged_directory(out, force=force) as tmp:
        hdr, truth = tmp / "hdr", tmp / "truth"
        for d in (hdr, truth / "photos", tmp / "photos"):
            d.mkdir(parents=True)
        for j in range(scene.m):
            write_exr(hdr / f"beam-{j:05d}.exr", scene.beam_frame(j),
                      attributes={"ilt:scene": scene.name, "ilt:beam": j, "ilt:units": "radiosity per unit beam power"})
            if progress:
                progress(1)
        plan = {"m": scene.m, "layout": list(scene.layout), "frame_shape": list(scene.frame_shape)}
        write_manifest(hdr, "simulate", parameters, extra=plan)
        write_samples(truth / "spots.csv", scene.centres)
        for kind in ILLUMINATIONS:
            photo, bounces = scene.photo(kind, n_bounces=n_bounces)
            write_exr(tmp / "photos" / f"{kind}.exr", photo,
                      attributes={"ilt:scene": scene.name, "ilt:illumination": kind})
            save_npy(truth / "photos" / f"{kind}-bounces.npy", bounces)
        write_manifest(tmp, "simulate", {**parameters, "frames": True, "truth_bounces": n_bounces}, extra=plan)
    return out
