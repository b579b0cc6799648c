"""``ilt run``: the whole pipeline in a workspace, skipping what is up to date.

capture -> merge -> centroids -> build-isf -> photos -> decompose, each stage a
directory of the workspace (:mod:`ilt.workspace`), each skipped when its run record
matches its parameters and inputs (:mod:`ilt.io.stage`). The config is the rig TOML of
``ilt capture`` (docs/capture.md) plus optional sections for the later stages, whose
keys are the long options of the stage commands (:mod:`ilt.workspace.options`, docs/workspace.md)::

    [merge]      margin = 0.05        # ilt merge --margin
    [centroids]  threshold = 0.2      # ilt centroids --threshold
    [build-isf]  sampling = "cell"    # ilt build-isf --sampling
    [photos]     sim = ["flashlight"] # simulated rig: photos under these illuminations
                 files = ["a.exr"]    # and/or EXR photos (paths relative to the config)
    [decompose]  bounces = 8          # ilt decompose --bounces
    [refine]     passes = 2           # after the scan: refine -> capture the new beams -> ...
                 beams = 16           # new beams a pass (or hours = H over all passes)
    [cluster]    scheduler = "tls://head:8786"  # ilt run --scheduler (docs/cluster.md)
                 ca = "~/.dask/ca.pem"          # TLS: the cluster's CA, this client's
                 cert = "~/.dask/cert.pem"      # certificate and key (or Dask's
                 key = "~/.dask/key.pem"        # distributed.comm.tls configuration)

With ``[refine] passes`` the scan grows in passes (:mod:`ilt.workspace.passes`,
docs/refine.md): capture to build-isf, ``ilt refine`` into ``passes/pass-P/``, the new
beams appended to ``capture/``, merge to build-isf again; photos and decompose once, on
the last pass.

Photos on the simulated rig are *captured*: the simulated camera shoots each photo's
bracket of DNG files under the illumination (same bracket, sensor and noise as the
beams) and it is merged with the beams' merge options into ``photos/<kind>.exr``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import tomllib
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ilt.capture.config import ConfigError, RigConfig, parse_config
from ilt.capture.loop import capture
from ilt.capture.plan import planned_beams
from ilt.io.atomic import atomic_path
from ilt.io.manifest import LOG_NAME, MANIFEST, StageError, fingerprint_file, write_manifest
from ilt.io.stage import (
    DONE,
    MISSING,
    STALE,
    StageState,
    changed_outputs,
    fingerprint_input,
    input_evidence,
    plain,
    read_record,
    run_stage,
    stage_state,
    write_record,
)
from ilt.io.staged import staged_directory
from ilt.io.workspace_dirs import PASSES, STAGE_DIRS, Workspace
from ilt.parallel.cluster import ClusterConfig
from ilt.workspace.options import BUILD_ISF, CENTROIDS, DECOMPOSE, MERGE, StageOption
from ilt.workspace.passes import (
    Pass,
    RefineConfig,
    completed_passes,
    finished,
    kept_coverage,
    parse_refine,
    passes_parameter,
    run_refine_pass,
    set_aside,
    write_landing,
)

log = logging.getLogger(__name__)

#: options of a stage command that change nothing in its output (not fingerprinted);
#: the [cluster] scheduler is one too, kept out of the stage sections altogether
RUNTIME_KEYS = ("workers", "scheduler")


@dataclass
class RunConfig:
    """A rig config with the options of every later stage (their keyword names, :mod:`ilt.workspace.options`)."""

    path: Path
    text: str
    rig: RigConfig
    merge: dict = field(default_factory=dict)
    centroids: dict = field(default_factory=dict)
    build_isf: dict = field(default_factory=dict)
    decompose: dict = field(default_factory=dict)
    photo_kinds: tuple[str, ...] = ()
    photo_files: tuple[Path, ...] = ()
    #: [cluster]: where the per-beam stages run and how to reach it (ilt.parallel.cluster)
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    #: [refine]: passes of ilt refine -> capture after the first scan (ilt.workspace.passes)
    refine: RefineConfig = field(default_factory=RefineConfig)


def stage_options(options: dict[str, StageOption], section: dict, where: str) -> dict:
    """A config section as keyword options of a stage: keys are the stage's long options
    (``read-noise`` or ``read_noise``), their values checked as the command line checks
    them (ConfigError naming the file, section and key); unspecified ones take their
    default."""
    if not isinstance(section, dict):
        raise ConfigError(f"{where}: must be a table")
    by_key = {o.key: o.name for o in options.values()}
    out = {o.name: o.default_value() for o in options.values()}
    for key, value in section.items():
        name = by_key.get(key.replace("-", "_"))
        if name is None:
            raise ConfigError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(by_key))})")
        try:
            options[name].check(value, where)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        out[name] = value
    return out


def load_run_config(path: str | os.PathLike) -> RunConfig:
    """Read a rig TOML with its stage sections. ConfigError names the file and key."""
    from ilt.sim import ILLUMINATIONS

    path = Path(path)
    text = path.read_text()
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    rig = parse_config(raw, str(path))
    photos = raw.get("photos", {})
    kinds = tuple(photos.get("sim", ILLUMINATIONS if rig.camera.backend == "sim" else ()))
    unknown = set(photos) - {"sim", "files"}
    if unknown:
        raise ConfigError(f"{path}: [photos] unknown key {min(unknown)!r} (known: files, sim)")
    for k in kinds:
        if k not in ILLUMINATIONS:
            raise ConfigError(f"{path}: [photos] sim: {k!r} unknown (known: {', '.join(ILLUMINATIONS)})")
    if kinds and rig.camera.backend != "sim":
        raise ConfigError(f"{path}: [photos] sim needs the simulated camera (backend = 'sim'); use files")
    return RunConfig(
        path, text, rig,
        merge=stage_options(MERGE, raw.get("merge", {}), f"{path}: [merge]"),
        centroids=stage_options(CENTROIDS, raw.get("centroids", {}), f"{path}: [centroids]"),
        build_isf=stage_options(BUILD_ISF, raw.get("build-isf", {}), f"{path}: [build-isf]"),
        decompose=stage_options(DECOMPOSE, raw.get("decompose", {}), f"{path}: [decompose]"),
        photo_kinds=kinds,
        photo_files=tuple(path.parent / f for f in photos.get("files", ())),
        cluster=_cluster(raw.get("cluster", {}), path),
        refine=parse_refine(raw.get("refine", {}), f"{path}: [refine]"),
    )


#: the [cluster] keys naming files, relative to the config (``~`` expanded)
CLUSTER_FILES = ("scheduler-file", "ca", "cert", "key")


def _cluster(section, path: Path) -> ClusterConfig:
    """The [cluster] table (runtime settings: no stage's parameters depend on them):
    ``scheduler = "local" | "tls://host:port" | "tcp://host:port"`` or ``scheduler-file``;
    ``ca``, ``cert``, ``key`` (TLS); ``insecure = true`` (plain TCP to another machine).
    Whether the files are there and the key private is checked when they are used
    (:func:`ilt.parallel.cluster.executor_for`)."""
    where = f"{path}: [cluster]"
    if not isinstance(section, dict):
        raise ConfigError(f"{where}: must be a table")
    known = ("scheduler", *CLUSTER_FILES, "insecure")
    if unknown := set(section) - set(known):
        raise ConfigError(f"{where}: unknown key {min(unknown)!r} (known: {', '.join(sorted(known))})")
    for key in ("scheduler", *CLUSTER_FILES):
        if key in section and (not isinstance(section[key], str) or not section[key].strip()):
            raise ConfigError(f"{where}: {key} must be " + ('"local" or an address such as "tls://host:8786"'
                                                            if key == "scheduler" else "a file's path"))
    if "scheduler" in section and "scheduler-file" in section:
        raise ConfigError(f"{where}: scheduler and scheduler-file both given; keep one")
    if not isinstance(section.get("insecure", False), bool):
        raise ConfigError(f"{where}: insecure must be true or false")
    files = {key.replace("-", "_"): path.parent / Path(section[key].strip()).expanduser()
             for key in CLUSTER_FILES if key in section}
    scheduler = section.get("scheduler")
    return ClusterConfig(scheduler=scheduler.strip() if scheduler else None, insecure=section.get("insecure", False),
                         origin=where, **files)


def fingerprinted(options: dict) -> dict:
    return {k: v for k, v in options.items() if k not in RUNTIME_KEYS}


# ---------------------------------------------------------------------- the stages


def capture_parameters(rig: RigConfig, passes: list[Pass] = ()) -> dict:
    """What a capture depends on: the beams, the bracket, the dark frame, the camera, and
    the refine passes whose beams it holds (:func:`ilt.workspace.passes.passes_parameter`)."""
    d = rig.as_dict()
    out = {k: d[k] for k in ("plan", "bracket", "dark", "camera")}
    if passes:
        out["passes"] = passes_parameter(list(passes))
    return out


def extends(directory: Path, parameters: dict) -> bool:
    """Whether the capture's run record is of an earlier pass of the same scan: the same
    parameters but fewer refine passes, each the same (its beams are a prefix of the
    ones asked for: the capture resumes and shoots the rest)."""
    record = read_record(directory)
    if record is None:
        return False
    old, new = dict(record.get("parameters", {})), dict(plain(parameters))
    before, after = old.pop("passes", []), new.pop("passes", [])
    return old == new and len(before) < len(after) and after[:len(before)] == before


def merge_options(options: dict):
    from ilt.hdr.merge import NoiseModel
    from ilt.hdr.stages import MergeOptions

    return MergeOptions(NoiseModel(options["gain"], options["read_noise"]), None, options["margin"],
                        options["color"], options["compression"])


@dataclass
class Stage:
    """One stage of a run: its directory, parameters, input directories/files and maker.

    ``by_hand``: for a directory the stage's own command filled without the stage's
    manifest (``ilt decompose`` run by hand writes ``decompose/<photo>/`` only): None
    when it holds what the stage would write, else why not.
    """

    name: str
    directory: Path
    parameters: dict
    inputs: dict[str, Path]
    make: object = None
    by_hand: Callable[[], str | None] | None = None

    def made_by_hand(self) -> bool:
        return self.by_hand is not None and self.directory.is_dir() and not (self.directory / MANIFEST).exists()


def no_progress(length: int, label: str):
    """The default ``progress`` of a run: ``update(n)`` that shows nothing."""
    return contextlib.nullcontext(lambda n=1: None)


def plan_stages(ws: Workspace, cfg: RunConfig, progress=no_progress, executor=None,
                passes: list[Pass] | None = None) -> list[Stage]:
    """The stages of a run in order (photos and decompose only when there are photos).

    ``progress(length, label)``: a context manager yielding ``update(n)``, called with the
    beams done as each per-beam stage goes (``ilt run`` draws a bar on a terminal, a
    line every tenth in a log). ``executor``: where merge, centroids and build-isf
    run their beams and the compressed solver its blocks (a cluster's,
    :func:`ilt.parallel.cluster.executor_for`), else each stage's process pool of its
    ``workers`` (the solver: threads of this process). ``passes``: the refine passes
    whose beams the capture holds (default: those done in the workspace).
    """
    from ilt.decompose.stage import decompose, default_cache_dir, not_decomposed
    from ilt.hdr.stages import merge_capture
    from ilt.isf.build import build_isf
    from ilt.isf.directory import load_isf
    from ilt.spots.find import SpotParameters
    from ilt.spots.stage import run_centroids

    d = {name: ws.stage_dir(name) for name in STAGE_DIRS}
    m, c, b, dec = cfg.merge, cfg.centroids, cfg.build_isf, cfg.decompose
    spot_params = {k: v for k, v in c.items() if k != "workers"}
    if spot_params.get("roi") is not None:
        spot_params["roi"] = tuple(float(v) for v in spot_params["roi"])
    isf_params = {k: v for k, v in b.items() if k not in ("workers", "no_fine")}
    if b.get("no_fine"):
        isf_params["fine_degree"] = None

    # centroids keeps every decoded frame for build-isf (ilt.io.frames.FrameScratch), so a
    # run decodes each EXR once. Only frames kept by this run are ever read back:
    # run_pipeline removes the directory before the first stage and after the last, and
    # a failed centroids stage ends the run before build-isf
    scratch = ws.root / SCRATCH_DIR
    passes = completed_passes(ws) if passes is None else passes
    beams = scan_beams(cfg, passes)

    def make_merge():
        with progress(beams, "merge") as update:
            merge_capture(d["capture"], d["merge"], merge_options(m), executor=executor, workers=m["workers"],
                          force=True, parameters=fingerprinted(m), progress=update)

    def make_centroids():
        _remove_scratch(ws)
        scratch.mkdir(parents=True)
        with progress(beams, "centroids") as update:
            run_centroids(d["merge"], d["centroids"], SpotParameters(**spot_params), executor=executor,
                          workers=c["workers"], force=True, frame_cache=scratch, progress=update)

    # a scan grown by refine passes keeps what its earlier builds covered
    covered = kept_coverage(passes) if isf_params.get("sampling", "cell") == "cell" else None
    isf_inputs = {"hdr": d["merge"], "spots": d["centroids"], **({"covered": covered} if covered else {})}

    def make_build_isf():
        try:
            with progress(beams, "build-isf") as update:
                build_isf(d["merge"], d["centroids"], d["build-isf"], executor=executor, workers=b["workers"],
                          force=True, frame_cache=scratch if scratch.is_dir() else None, progress=update,
                          keep_covered=covered, **isf_params)
        finally:
            _remove_scratch(ws)

    decompose_options = {"n_bounces": dec["n_bounces"], "tol": dec["tol"], "samples_only": dec["samples_only"],
                         "accept_non_lambertian": dec["accept_non_lambertian"]}

    def make_decompose():
        with staged_directory(d["decompose"], force=True) as tmp:
            decompose(load_isf(d["build-isf"], mmap=True), photo_paths(ws, cfg), tmp, cache_dir=default_cache_dir(),
                      force=True, executor=executor, shown_as=d["decompose"], **decompose_options)
            write_manifest(tmp, "decompose", fingerprinted(dec))

    def decomposed_by_hand():
        return not_decomposed(d["decompose"], load_isf(d["build-isf"], mmap=True), photo_paths(ws, cfg),
                              **decompose_options)

    stages = [
        Stage("capture", d["capture"], capture_parameters(cfg.rig, passes), {}),
        Stage("merge", d["merge"], fingerprinted(m), {"capture": d["capture"]}, make_merge),
        Stage("centroids", d["centroids"], fingerprinted(c), {"hdr": d["merge"]}, make_centroids),
        Stage("build-isf", d["build-isf"], fingerprinted(b), isf_inputs, make_build_isf),
    ]
    if cfg.photo_kinds:
        stages.append(Stage("photos", d["photos"], {"sim": list(cfg.photo_kinds), **capture_parameters(cfg.rig),
                                                     "merge": fingerprinted(m)}, {},
                            lambda: capture_photos(cfg.rig, cfg.photo_kinds, d["photos"], merge_options(m))))
    if cfg.photo_kinds or cfg.photo_files:
        inputs = {"isf": d["build-isf"]}
        if cfg.photo_kinds:
            inputs["photos"] = d["photos"]
        inputs.update({f"file {p.name}": p for p in cfg.photo_files})
        stages.append(Stage("decompose", d["decompose"], fingerprinted(dec), inputs, make_decompose,
                            decomposed_by_hand))
    return stages


#: where a run keeps decoded frames between centroids and build-isf (removed after)
SCRATCH_DIR = ".frames-scratch"


def _remove_scratch(ws: Workspace) -> None:
    import shutil

    shutil.rmtree(ws.root / SCRATCH_DIR, ignore_errors=True)


def photo_paths(ws: Workspace, cfg: RunConfig) -> list[Path]:
    return [ws.stage_dir("photos") / f"{k}.exr" for k in cfg.photo_kinds] + list(cfg.photo_files)


def capture_photos(rig: RigConfig, kinds, out: Path, options) -> Path:
    """Shoot each photo's DNG bracket with the simulated camera and merge it (atomically).

    ``out/raw/<kind>/`` holds the bracket (frames, dark, manifest.json as a beam's);
    ``out/<kind>.exr`` the merged photo, in the HDR frames' pixel grid.
    """
    from ilt.capture.camera import SimCamera, sim_sensor
    from ilt.capture.plan import make_plan
    from ilt.hdr.stages import merge_beam
    from ilt.io.beams import FrameRecord, write_beam_manifest
    from ilt.sim.render import render_scene
    from ilt.sim.sensor import write_dng

    c = rig.camera
    scene = render_scene(c.scene, beams=make_plan(rig.plan).m, px_per_beam=c.px_per_beam, rows=c.rows, spot=c.spot)
    sensor = sim_sensor(scene)
    with staged_directory(out, force=True) as tmp:
        for kind in kinds:
            radiance = np.zeros((sensor.height, sensor.width))
            h, w = scene.frame_shape
            radiance[:h, :w] = scene.photo(kind)[0] * c.radiance_scale
            lit = {"on": True}
            camera = SimCamera(lambda radiance=radiance, lit=lit: radiance if lit["on"] else np.zeros_like(radiance),
                               lambda p, r, t, f, rng: write_dng(p, r, t, f, sensor, rng), sensor.model,
                               c.seed + zlib.crc32(kind.encode()))
            bracket = tmp / "raw" / kind
            bracket.mkdir(parents=True)
            frames = []
            for k, e in enumerate(rig.bracket.exposures):
                camera.shoot(bracket / f"frame-{k:02d}.dng", e, f"photo/{kind}/{k}")
                frames.append(FrameRecord(f"frame-{k:02d}.dng", str(e.shutter), f"{e.aperture:g}"))
            dark = None
            if rig.dark.frames == "longest":
                lit["on"] = False
                e = max(rig.bracket.exposures, key=lambda x: x.relative)
                camera.shoot(bracket / "dark.dng", e, f"photo/{kind}/dark")
                dark = FrameRecord("dark.dng", str(e.shutter), f"{e.aperture:g}")
            write_beam_manifest(bracket, frames, dark, extra={"photo": kind})
            merge_beam(bracket, tmp, options)
        write_manifest(tmp, "photos", {"sim": list(kinds)})
    return out


# ---------------------------------------------------------------------- run / status


def input_fingerprints(stage: Stage) -> dict[str, str]:
    return {name: fingerprint_input(path) for name, path in stage.inputs.items()}


def input_evidences(stage: Stage) -> dict[str, str] | None:
    """What a stage made by hand must name in its manifest's inputs (:func:`ilt.io.stage.stage_state`);
    None once the stage has a run record (nothing is hashed then)."""
    if read_record(stage.directory) is not None:
        return None
    return {name: input_evidence(path) for name, path in stage.inputs.items()}


#: the state of a stage whose files differ from its manifest's fingerprints
CHANGED = "changed"


def _changed_state(stage: Stage, files: list[str]) -> StageState:
    shown = ", ".join(files[:3]) + (f" and {len(files) - 3} more" if len(files) > 3 else "")
    if stage.name == "capture":
        fix = f"restore them from a backup, or move {stage.directory} aside and scan again"
    else:
        fix = f"remove {stage.directory} and 'ilt run' writes it again"
    return StageState(stage.name, str(stage.directory), CHANGED,
                      f"{shown} changed since {stage.name} wrote {'them' if len(files) > 1 else 'it'} ({fix})")


@dataclass(frozen=True)
class Assessment:
    """A stage's state, with the input fingerprints it was judged on (None: not
    fingerprinted, as after a stage that is not done)."""

    state: StageState
    inputs: dict[str, str] | None


def assess_stages(stages: list[Stage], verify: str | None = None) -> list[Assessment]:
    """Each stage's state; a stage after one that is not done cannot be done.

    ``verify``: "quick" checks that a done stage's files are the ones its manifest
    fingerprints, re-hashing only those whose size or modification time changed since
    its run record; "full" re-hashes every file. A stage whose files differ is
    ``changed`` (the stages after it are judged as usual: they were made from the
    files as they were).
    """
    out: list[Assessment] = []
    by_dir = {}
    for stage in stages:
        blocked = [n for n, p in stage.inputs.items() if p in by_dir and by_dir[p].state not in (DONE, CHANGED)]
        inputs = None
        if blocked:
            complete = (stage.directory / "manifest.json").exists()
            s = StageState(stage.name, str(stage.directory), STALE if complete else MISSING,
                           f"after {', '.join(by_dir[stage.inputs[n]].stage for n in blocked)}" if complete else "")
        elif stage.made_by_hand():
            s = _by_hand_state(stage)
        else:
            try:
                inputs = input_fingerprints(stage)
                s = stage_state(stage.directory, stage.name, stage.parameters, inputs, input_evidences(stage))
            except (StageError, OSError) as exc:
                inputs, s = None, StageState(stage.name, str(stage.directory), MISSING, str(exc))
        if s.done and verify:
            files = _changed_files(stage, full=verify == "full")
            if files:
                s = _changed_state(stage, files)
        out.append(Assessment(s, inputs))
        by_dir[stage.directory] = s
    return out


def _changed_files(stage: Stage, full: bool) -> list[str]:
    """The files of a done stage that differ from its manifest (:func:`changed_outputs`);
    for one made by hand, from the manifests of its sub-directories (they have no run
    record: every file is hashed)."""
    if not stage.made_by_hand():
        return changed_outputs(stage.directory, full=full)
    return [f"{sub.name}/{name}" for sub in sorted(stage.directory.iterdir()) if (sub / MANIFEST).is_file()
            for name in changed_outputs(sub, full=full)]


def _by_hand_state(stage: Stage) -> StageState:
    """The state of a stage directory its command filled by hand (:attr:`Stage.by_hand`)."""
    try:
        why = stage.by_hand()
    except (OSError, ValueError) as exc:
        why = str(exc)
    if why is None:
        return StageState(stage.name, str(stage.directory), DONE)
    return StageState(stage.name, str(stage.directory), STALE, f"made by hand: {why}")


def workspace_status(ws: Workspace, cfg: RunConfig, verify: str | None = None) -> list[StageState]:
    """Each stage's state against ``cfg`` (:func:`assess_stages`); with [refine] passes,
    a "refine" line after build-isf: the passes done and the beams each added."""
    passes = completed_passes(ws)
    stages = plan_stages(ws, cfg, passes=passes)
    states = [a.state for a in assess_stages(stages, verify)]
    if states[0].state == STALE and extends(stages[0].directory, stages[0].parameters):
        states[0] = StageState("capture", states[0].directory, MISSING,
                               f"refine pass {len(passes)}: its beams to shoot ('ilt run' adds them)")
    if cfg.refine.passes or passes:
        states.insert(4, refine_state(ws, cfg, passes))
    return states


def refine_state(ws: Workspace, cfg: RunConfig, passes: list[Pass]) -> StageState:
    """The refine passes as a stage's state: done when no pass is left to run."""
    from ilt.workspace.passes import read_landing

    beams = " + ".join(str(n) for n in [planned_beams(cfg.rig.plan), *(p.beams for p in passes)])
    said = f"pass {len(passes)} of {cfg.refine.passes} ({beams} beams)"
    landing = (read_landing(ws) or {}).get("passes", [])
    found = [x for x in landing if x.get("median_px") is not None]
    if found:
        said += "; landing " + ", ".join(f"{x['median_px']:.2f}" for x in found) + " px (median a pass)"
    if len(passes) > cfg.refine.passes:
        return StageState("refine", str(ws.passes), STALE, said + ": more passes than the config asks")
    return StageState("refine", str(ws.passes), DONE if finished(cfg.refine, passes) else MISSING, said)


def check_unchanged(assessed: list[Assessment]) -> None:
    """StageError naming the first file of a done stage that no longer matches its
    manifest (``assessed`` with ``verify="quick"``: a stat per file, only files whose
    size or modification time moved are hashed): a run must not build on it, nor call
    it up to date."""
    for a in assessed:
        if a.state.state == CHANGED:
            raise StageError(f"{a.state.directory}: {a.state.reason}")


#: beside WORKSPACE/rig.toml: the fingerprint of the config `ilt run` last copied there
INSTALLED = ".rig.toml.installed"


def config_differences(old: str, new: str) -> str:
    """Which sections and keys of two rig TOML texts differ, e.g. "[merge] margin, [plan] count"."""
    try:
        a, b = tomllib.loads(old), tomllib.loads(new)
    except tomllib.TOMLDecodeError:
        return "it is not valid TOML"
    out = []
    for section in sorted(set(a) | set(b)):
        x, y = a.get(section), b.get(section)
        if x == y:
            continue
        if isinstance(x, (dict, type(None))) and isinstance(y, (dict, type(None))):
            x, y = x or {}, y or {}
            keys = sorted(k for k in set(x) | set(y) if x.get(k) != y.get(k))
            out.append(f"[{section}] {', '.join(keys)}")
        else:
            out.append(section)
    return ", ".join(out) or "comments or layout only"


def install_config(ws: Workspace, cfg: RunConfig) -> None:
    """Keep the run's config as WORKSPACE/rig.toml (what `ilt status` compares against).

    A rig.toml that is not the copy the last `ilt run` made (edited by hand, or written
    by someone else) is never overwritten: it is moved aside to rig.toml.previous-N,
    with a warning naming what differs and where it went.
    """
    ws.root.mkdir(parents=True, exist_ok=True)
    marker = ws.root / INSTALLED
    if ws.config.exists():
        if ws.config.resolve() == cfg.path.resolve():
            return
        old = ws.config.read_text()
        if old == cfg.text:
            return
        ours = marker.exists() and marker.read_text().strip() == fingerprint_file(ws.config)
        if not ours:
            k = 1
            while (aside := ws.config.with_name(f"{ws.config.name}.previous-{k}")).exists():
                k += 1
            os.replace(ws.config, aside)
            log.warning("%s: edited since 'ilt run' copied it (differs from %s in %s); kept as %s",
                        ws.config, cfg.path, config_differences(old, cfg.text), aside)
    with atomic_path(ws.config) as tmp:
        tmp.write_text(cfg.text)
    with atomic_path(marker) as tmp:
        tmp.write_text(fingerprint_file(ws.config) + "\n")


def check_capture(stage: Stage, force: bool, state: StageState | None = None) -> StageState:
    """The capture's state (``state`` when the caller found it); StageError when the scan
    differs from the config and not ``force``."""
    state = state or stage_state(stage.directory, "capture", stage.parameters)
    if state.state == STALE and not force and not extends(stage.directory, stage.parameters):
        held = len((read_record(stage.directory) or {}).get("parameters", {}).get("passes", []))
        asked = len(stage.parameters.get("passes", []))
        if held > asked:
            raise StageError(f"{stage.directory}: holds the beams of {held} refine pass(es), the workspace's "
                             f"{PASSES}/ and config give {asked} (raise [refine] passes, restore the "
                             "pass directories, or use --force to move the scan aside and scan again)")
        raise StageError(f"{stage.directory}: {state.reason}; the scan differs from the config "
                         "(use --force to move it aside and scan again)")
    return state


def run_capture(stage: Stage, state: StageState, cfg: RunConfig, force: bool, progress=no_progress,
                passes: list[Pass] = ()) -> bool:
    """The capture stage, in ``state`` (:func:`check_capture`): resumed when interrupted,
    extended by the beams of ``passes`` it does not hold yet; a scan that differs from
    the config is moved aside (never deleted) only with ``force``."""
    from ilt.capture.camera import check_sim_camera

    if state.done and not force:
        log.info("capture: up to date (%s)", stage.directory)
        if read_record(stage.directory) is None:  # shot by `ilt capture`: recorded as if run here
            write_record(stage.directory, "capture", stage.parameters, {})
        return False
    check_sim_camera(cfg.rig)   # an unknown scene or one too large: refused before anything moves
    extending = state.state == STALE and not force and extends(stage.directory, stage.parameters)
    if (state.state == STALE and not extending) or (state.done and force):
        k = 1
        while (aside := stage.directory.with_name(f"{stage.directory.name}.previous-{k}")).exists():
            k += 1
        os.replace(stage.directory, aside)
        log.info("capture: the previous scan is kept in %s", aside)
    resume = (stage.directory / LOG_NAME).exists()
    log.info("capture: %s (%s)", f"refine pass {len(passes)}: adding its beams" if extending else
             "resuming" if resume else "scanning", state.reason or state.state)

    with progress(scan_beams(cfg, passes), "capture") as update:
        def on_beam(result, done, total):
            log.debug("capture: beam %d (%d/%d) %.1f s", result.beam, done, total, result.seconds)
            update(1)

        capture(cfg.rig, stage.directory, resume=resume, on_beam=on_beam, added=[p.angles for p in passes])
    write_record(stage.directory, "capture", stage.parameters, {})
    return True


def run_pipeline(ws: Workspace, cfg: RunConfig, force: bool = False, progress=no_progress,
                 executor=None) -> list[dict]:
    """Run every stage that is not up to date, in order, and the refine passes the config
    asks for (:mod:`ilt.workspace.passes`). Returns one summary per stage run or skipped.
    ``progress``, ``executor``: as :func:`plan_stages` takes them."""
    passes = [] if force else completed_passes(ws)
    if len(passes) > cfg.refine.passes:
        raise StageError(f"{ws.passes}: holds {len(passes)} refine pass(es), the config asks for "
                         f"{cfg.refine.passes} (raise [refine] passes, or use --force to scan again)")
    summaries = _run_pass(ws, cfg, passes, force, progress, executor)
    while not finished(cfg.refine, passes):
        passes.append(run_refine_pass(ws, cfg.refine, cfg.rig, passes))
        summaries.append({"stage": "refine", "directory": str(passes[-1].directory), "ran": True,
                          "pass": len(passes), "beams": passes[-1].beams})
        summaries += _run_pass(ws, cfg, passes, False, progress, executor)
    return summaries


def _run_pass(ws: Workspace, cfg: RunConfig, passes: list[Pass], force: bool, progress, executor) -> list[dict]:
    """One pass of the run: the stages up to build-isf, and the rest when no refine pass
    follows (the landing of the passes' beams written after)."""
    stages = plan_stages(ws, cfg, progress, executor, passes=passes)
    if not finished(cfg.refine, passes):
        stages = stages[:4]
    # before the config is installed: a refused run changes nothing
    # --force writes every stage again (the scan moved aside): nothing is built on, no state kept
    assessed = None if force else assess_stages(stages, verify="quick")
    capture_state = check_capture(stages[0], force, assessed[0].state if assessed else None)
    if assessed:
        check_unchanged(assessed)
    if force and not passes:
        aside = set_aside(ws)
        if aside:
            log.info("refine: the previous passes are kept in %s", aside)
    install_config(ws, cfg)
    _remove_scratch(ws)  # frames a killed run kept
    try:
        summaries = _run_stages(stages, capture_state, assessed, cfg, force, progress, passes)
    finally:
        _remove_scratch(ws)
    if passes and any(s["ran"] for s in summaries) and stages[3].directory.joinpath(MANIFEST).is_file():
        write_landing(ws, passes, planned_beams(cfg.rig.plan))
    for s in summaries:
        s["pass"] = len(passes)
    return summaries


def scan_beams(cfg: RunConfig, passes: list[Pass]) -> int:
    """The beams of the config's plan and of the refine passes."""
    return planned_beams(cfg.rig.plan) + sum(p.beams for p in passes)


def _run_stages(stages: list[Stage], capture_state: StageState, assessed: list[Assessment] | None,
                cfg: RunConfig, force: bool, progress=no_progress, passes: list[Pass] = ()) -> list[dict]:
    """Run the stages in order. Each stage's state is found once: the assessment made
    before the run holds until a stage runs (its outputs are the next stages' inputs);
    from then on each stage is judged as its turn comes."""
    summaries = []
    known = assessed is not None
    for k, stage in enumerate(stages):
        t0 = time.monotonic()
        if stage.name == "capture":
            ran = run_capture(stage, capture_state, cfg, force, progress, passes)
        else:
            state, inputs = (assessed[k].state, assessed[k].inputs) if known else (None, None)
            if stage.made_by_hand():
                state = state or _by_hand_state(stage)
                if state.done:  # what the stage would write: given the stage's manifest, then recorded
                    write_manifest(stage.directory, stage.name, stage.parameters)
            inputs = input_fingerprints(stage) if inputs is None else inputs
            ran, _ = run_stage(stage.directory, stage.name, stage.parameters, inputs, stage.make, force=force,
                               evidence=None if state else input_evidences(stage), state=state)
        known = known and not ran
        summaries.append({"stage": stage.name, "directory": str(stage.directory),
                          "ran": ran, "seconds": round(time.monotonic() - t0, 3)})
    return summaries


def workspace_config(ws: Workspace, config: str | os.PathLike | None) -> RunConfig:
    """The config given, else the workspace's rig.toml."""
    path = Path(config) if config else ws.config
    if not path.exists():
        raise StageError(f"{path}: no config (give a rig TOML, e.g. configs/sim.toml)"
                         if config else f"{ws.root}: no {ws.config.name}; give a rig TOML to 'ilt run'")
    return load_run_config(path)
