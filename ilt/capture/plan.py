"""Beam plans (DESIGN.md sec. 3): a 1D line, a 2D grid or an explicit list of directions.

A plan is a list of (pan, tilt) targets in scanline order plus its layout
``(rows, cols)``, kept so later stages can show a vector of m samples as an image.
Targets are in degrees or in the unit's steps; :func:`to_steps` turns them into
integer positions with the resolution the unit reports (``PR``/``TR``, arc-seconds
per position).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import ConfigError, PlanConfig


@dataclass(frozen=True)
class Plan:
    """``targets``: (m, 2) float64 (pan, tilt) in ``units``; ``layout``: (rows, cols)."""

    kind: str
    units: str
    targets: np.ndarray
    layout: tuple[int, int]
    #: a refined scan (:func:`extend_plan`): the beams at the end of each pass, the first
    #: being the configured plan's; empty for a plan as configured
    passes: tuple[int, ...] = ()
    #: the configured plan's layout, when ``passes`` appended beams to it
    base_layout: tuple[int, int] | None = None

    @property
    def m(self) -> int:
        return len(self.targets)

    @property
    def base_m(self) -> int:
        """The configured plan's beams (the first ``base_m`` targets)."""
        return self.passes[0] if self.passes else self.m

    def as_dict(self) -> dict:
        d = {"kind": self.kind, "units": self.units, "layout": list(self.layout), "targets": self.targets.tolist()}
        if self.passes:
            d["passes"] = list(self.passes)
            d["base_layout"] = list(self.base_layout)
        return d


def extend_plan(plan: Plan, added) -> Plan:
    """``plan`` with the beams of refine passes appended, in order: ``added`` is a list of
    (k, 2) (pan, tilt) arrays in the plan's units (rounded to whole steps when its units
    are steps). The result is a strip (layout 1 x m: the added beams are not on the
    plan's grid); ``passes`` and ``base_layout`` say what came from where."""
    added = [np.asarray(a, dtype=np.float64).reshape(-1, 2) for a in added]
    if not added:
        return plan
    if plan.units == "steps":
        added = [np.rint(a) for a in added]
    targets = np.concatenate([plan.targets, *added])
    if not np.all(np.isfinite(targets)):
        raise ConfigError("a refine pass has a non-finite angle")
    passes = tuple(int(n) for n in np.cumsum([plan.m, *(len(a) for a in added)]))
    return Plan(plan.kind, plan.units, targets, (1, len(targets)), passes, tuple(plan.layout))


def make_plan(cfg: PlanConfig) -> Plan:
    """The beams of a [plan] table. Raises ConfigError on a plan that makes no beams."""
    if cfg.kind == "line":
        if cfg.count < 1:
            raise ConfigError(f"[plan] count must be >= 1, got {cfg.count}")
        pan = _axis(cfg.pan, cfg.count, "pan")
        tilt = _axis(cfg.tilt, cfg.count, "tilt")
        targets = np.column_stack([pan, tilt])
        layout = (1, cfg.count)
    elif cfg.kind == "grid":
        if len(cfg.shape) != 2 or min(cfg.shape) < 1:
            raise ConfigError(f"[plan] shape must be [rows, cols] >= 1, got {list(cfg.shape)}")
        rows, cols = (int(v) for v in cfg.shape)
        pan = _axis(cfg.pan, cols, "pan")
        tilt = _axis(cfg.tilt, rows, "tilt")
        tt, pp = np.meshgrid(tilt, pan, indexing="ij")  # scanline order: rows of tilt, pan along a row
        targets = np.column_stack([pp.ravel(), tt.ravel()])
        layout = (rows, cols)
    else:
        if not cfg.points or any(len(p) != 2 for p in cfg.points):
            raise ConfigError("[plan] kind = 'list' needs points = [[pan, tilt], ...]")
        targets = np.asarray(cfg.points, dtype=np.float64)
        layout = (1, len(targets))
    if not np.all(np.isfinite(targets)):
        raise ConfigError("[plan] has a non-finite angle")
    return Plan(cfg.kind, cfg.units, targets.astype(np.float64), layout)


def _axis(values: tuple[float, ...], n: int, name: str) -> np.ndarray:
    """One value (constant), or [first, last] spaced evenly over n beams."""
    if len(values) == 1:
        return np.full(n, float(values[0]))
    if len(values) == 2:
        return np.linspace(float(values[0]), float(values[1]), n)
    raise ConfigError(f"[plan] {name} must be one value or [first, last], got {list(values)}")


def to_steps(plan: Plan, resolution: tuple[float, float]) -> np.ndarray:
    """(m, 2) int64 positions. ``resolution``: (pan, tilt) arc-seconds per position."""
    if plan.units == "steps":
        steps = np.rint(plan.targets)
        if not np.array_equal(steps, plan.targets):
            raise ConfigError("[plan] units = 'steps' needs whole numbers")
        return steps.astype(np.int64)
    return np.rint(plan.targets * 3600.0 / np.asarray(resolution, dtype=np.float64)).astype(np.int64)


def out_of_limits(steps: np.ndarray, limits: dict[str, int]) -> tuple[str, int, np.ndarray, int, int] | None:
    """The first axis on which some of (m, 2) ``steps`` fall outside ``limits``: (axis,
    column, indices of the targets out of range, lo, hi); None when all are inside."""
    for axis, col in (("pan", 0), ("tilt", 1)):
        lo, hi = limits[f"{axis}_min"], limits[f"{axis}_max"]
        bad = np.flatnonzero((steps[:, col] < lo) | (steps[:, col] > hi))
        if bad.size:
            return axis, col, bad, lo, hi
    return None


def check_limits(steps: np.ndarray, limits: dict[str, int]) -> None:
    """Every target inside the unit's limits, checked before anything moves."""
    outside = out_of_limits(steps, limits)
    if outside:
        axis, col, bad, lo, hi = outside
        j = int(bad[0])
        raise ConfigError(
            f"[plan] beam {j}: {axis} {int(steps[j, col])} steps is outside the unit's limits "
            f"[{lo}, {hi}] ({bad.size} beam(s) out of range); narrow the plan")


def planned_beams(plan) -> int:
    """The beams a [plan] table makes, counted without building it (a plan of 1e8 beams
    would take gigabytes of angles first)."""
    if plan.kind == "grid":  # a malformed shape counts none: make_plan refuses it
        return int(plan.shape[0]) * int(plan.shape[1]) if len(plan.shape) == 2 else 0
    if plan.kind == "list":
        return len(plan.points)
    return int(plan.count)
