"""One beam's spot (:class:`Spot`) and the spots table, ``spots.csv`` (docs/formats.md):
centroid, flux, peak, area and the QA flags, one row per beam."""

from __future__ import annotations

import csv
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

SPOTS_FILE = "spots.csv"

SPOTS_HEADER = ["beam", "x", "y", "flux", "peak", "area", "flags"]


FLAGS = ("none", "multiple", "large", "elongated", "saturated", "outside")


class SpotsError(ValueError):
    """A spots table that cannot be read; the message names the file and line."""


@dataclass
class Spot:
    """One beam's spot: centroid (x, y) px, flux (background-subtracted sum), peak (above
    background), area (pixels over threshold) and flags {name: figure}."""

    x: float
    y: float
    flux: float
    peak: float
    area: int
    flags: dict = field(default_factory=dict)


def flag_large(spots: list[Spot], factor: float) -> None:
    """Flag spots whose area exceeds ``factor`` x the median area of the clean spots (in place)."""
    areas = [s.area for s in spots if not s.flags]
    if not areas:
        return
    median = float(np.median(areas))
    for s in spots:
        if "none" not in s.flags and s.area > factor * median and "large" not in s.flags:
            s.flags["large"] = round(s.area / median, 3)


def format_flags(flags: dict) -> str:
    return ";".join(f"{k}={v:g}" for k, v in flags.items())


def parse_flags(text: str) -> dict:
    out = {}
    for item in filter(None, text.split(";")):
        name, _, value = item.partition("=")
        out[name] = float(value) if value else 0.0
    return out


def write_spots(path: str | os.PathLike, beams: list[int], spots: list[Spot]) -> None:
    """Write ``spots.csv`` (header ``beam,x,y,flux,peak,area,flags``)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(SPOTS_HEADER)
        for b, s in zip(beams, spots):
            w.writerow([b, repr(s.x), repr(s.y), repr(s.flux), repr(s.peak), s.area, format_flags(s.flags)])


def read_spots(path: str | os.PathLike) -> tuple[list[int], list[Spot]]:
    """Read ``spots.csv``; returns plan beams (strictly increasing) and their spots."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            if reader.fieldnames != SPOTS_HEADER:
                raise SpotsError(f"{path}: header {reader.fieldnames} is not {','.join(SPOTS_HEADER)}")
            rows = list(reader)
    except OSError as exc:
        raise SpotsError(f"{path}: cannot read ({exc.strerror})") from None
    beams, spots = [], []
    for i, row in enumerate(rows):
        try:
            beam = int(row["beam"])
            spot = Spot(float(row["x"]), float(row["y"]), float(row["flux"]), float(row["peak"]),
                        int(row["area"]), parse_flags(row["flags"] or ""))
        except (TypeError, ValueError):
            raise SpotsError(f"{path}: line {i + 2} is not beam,x,y,flux,peak,area,flags: {row}") from None
        if beams and beam <= beams[-1]:
            raise SpotsError(f"{path}: line {i + 2}: beam {beam} after beam {beams[-1]} (beams must increase)")
        beams.append(beam)
        spots.append(spot)
    if not beams:
        raise SpotsError(f"{path}: no spots")
    return beams, spots


def spot_dict(spot: Spot) -> dict:
    return asdict(spot)
