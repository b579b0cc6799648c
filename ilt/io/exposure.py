"""Exposure facts of a frame: exposure time and f-number, and where they came from.

Order of trust: the capture manifest, then the file's EXIF (exact rationals through
exifread; rawpy's ``other.shutter_speed``/``aperture`` as a fallback), then times
given by hand (``--times``). These are nominal values: a camera's 1/125 s is really
1/128 s. Mitsunaga-Nayar calibration (ilt.hdr.mitsunaga_nayar) measures the true ratios.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path


class ExposureError(ValueError):
    """An exposure fact that is missing or not a positive number."""


@dataclass(frozen=True)
class ExposureFacts:
    """exposure_time: seconds; f_number: dimensionless; source: "manifest", "exif",
    "rawpy" or "times"; text: the nominal values as written ("1/125", "1.2")."""

    exposure_time: float
    f_number: float
    source: str
    time_text: str
    f_number_text: str

    def relative_exposure(self) -> float:
        """t / N^2 in seconds at f/1: what the photosite collects per unit radiance."""
        return self.exposure_time / self.f_number**2

    def as_dict(self) -> dict:
        return {"exposure_time": self.exposure_time, "f_number": self.f_number,
                "exposure_time_text": self.time_text, "f_number_text": self.f_number_text,
                "source": self.source}


def parse_positive(text, what: str, where) -> Fraction:
    """'1/125', '0.008', 16, '16' -> a positive Fraction; ExposureError naming ``where``."""
    try:
        value = Fraction(str(text).strip())
    except (ValueError, ZeroDivisionError):
        raise ExposureError(f"{where}: {what} {text!r} is not a number or a ratio like 1/125") from None
    if value <= 0:
        raise ExposureError(f"{where}: {what} {text!r} must be positive")
    return value


def parse_times(text: str) -> list[Fraction]:
    """'1/15,1/30,1/60' -> Fractions (for ``--times``)."""
    return [parse_positive(t, "exposure time", "--times") for t in text.split(",") if t.strip()]


def read_exif(source) -> dict:
    """exifread's tags of a file path or binary file object ({} where there are none)."""
    import exifread

    try:
        if hasattr(source, "read"):
            source.seek(0)
            return exifread.process_file(source, details=False)
        with open(source, "rb") as f:
            return exifread.process_file(f, details=False)
    except OSError:
        raise
    except Exception:  # exifread raises many kinds on non-TIFF data; the caller falls back
        return {}


def exif_facts(tags: dict) -> tuple[Fraction | None, Fraction | None]:
    """(exposure time, f-number) from exifread tags as exact rationals; None where absent."""
    time = f_number = None
    for key in ("EXIF ExposureTime", "Image ExposureTime"):
        if key in tags and time is None:
            time = _ratio(tags[key])
    for key in ("EXIF FNumber", "Image FNumber"):
        if key in tags and f_number is None:
            f_number = _ratio(tags[key])
    return time, f_number


def _ratio(tag) -> Fraction | None:
    try:
        v = tag.values[0]
        value = Fraction(int(v.numerator), int(v.denominator)) if hasattr(v, "numerator") else Fraction(v)
    except (IndexError, ValueError, ZeroDivisionError, TypeError):
        return None
    return value if value > 0 else None


#: how far (in stops) a frame's EXIF may be from its manifest's nominal value: cameras
#: write 1/128 s for a nominal 1/125 s (0.03 stop), while the nearest other setting of a
#: bracket is at least 1/3 stop away
EXIF_TOLERANCE_STOPS = 1 / 6


def check_exif(path, time: Fraction | None, f_number: Fraction | None,
               exif_time: Fraction | None, exif_f_number: Fraction | None) -> None:
    """ExposureError naming ``path`` when the EXIF exposure time or f-number is not the
    manifest's (a frame of another exposure copied over this one); facts either side
    leaves out are not compared."""
    def stops(a, b, per):
        return a is not None and b is not None and abs(math.log2(a / b)) * per > EXIF_TOLERANCE_STOPS

    if stops(time, exif_time, 1) or stops(f_number, exif_f_number, 2):
        raise ExposureError(
            f"{path}: the manifest says {time if time is not None else '?'} s at f/"
            f"{_text(f_number, True) if f_number is not None else '?'}, its EXIF "
            f"{exif_time if exif_time is not None else '?'} s at f/"
            f"{_text(exif_f_number, True) if exif_f_number is not None else '?'}: not the frame "
            "that was shot (restore the captured file, or capture the beam again)")


def resolve_facts(path: Path, time_text: str | None, f_text: str | None, tags: dict | None = None,
                  rawpy_other=None, hand_time: Fraction | None = None) -> ExposureFacts:
    """The frame's facts: manifest text, else EXIF, else rawpy's ``other``, else ``hand_time``.

    ``tags``: the file's exifread tags if already read (else read from ``path``).
    The f-number defaults to the EXIF one, then to 1 with a hand-given time (a fixed
    aperture whose value cancels out of the exposure ratios).
    Raises ExposureError naming ``path`` when no exposure time can be found, or when
    the EXIF contradicts the manifest (:func:`check_exif`).
    """
    source = "manifest"
    time = parse_positive(time_text, "exposure time", path) if time_text is not None else None
    f_number = parse_positive(f_text, "f-number", path) if f_text is not None else None
    exif_t, exif_n = exif_facts(read_exif(path) if tags is None else tags)
    check_exif(path, time, f_number, exif_t, exif_n)
    if time is None or f_number is None:
        if time is None and exif_t is not None:
            time, source = exif_t, "exif"
        f_number = f_number if f_number is not None else exif_n
    if rawpy_other is not None:
        if time is None and getattr(rawpy_other, "shutter_speed", 0) > 0:
            time, source = Fraction(rawpy_other.shutter_speed).limit_denominator(100000), "rawpy"
        if f_number is None and getattr(rawpy_other, "aperture", 0) > 0:
            f_number = Fraction(rawpy_other.aperture).limit_denominator(1000)
    if time is None and hand_time is not None:
        time, source = hand_time, "times"
    if time is None:
        raise ExposureError(f"{path}: no exposure time in the manifest or EXIF; give --times")
    if f_number is None:
        f_number = Fraction(1)
    return ExposureFacts(float(time), float(f_number), source, _text(time, False), _text(f_number, True))


def _text(value: Fraction, decimal: bool) -> str:
    """'1/125' for times; '1.2' for f-numbers (decimal when that is exact)."""
    if decimal and Fraction(repr(float(value))) == value:
        return repr(float(value)).removesuffix(".0")
    return str(value)
