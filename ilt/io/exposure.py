"""Exposure facts of a frame: exposure time and f-number, and where they came from.

Order of trust: the capture manifest, then times given by hand (``--times``), then the
file's EXIF (exact rationals through exifread), then rawpy's ``other.shutter_speed`` /
``aperture`` (LibRaw's reading of the same tags, or of maker notes exifread does not
read). An EXIF or LibRaw value that is 0, negative or absurd (:data:`TIME_RANGE`,
:data:`F_NUMBER_RANGE`) is not used: recorders such as Magic Lantern write 0, and LibRaw
turns an APEX ShutterSpeedValue of 0 into 1 s. These are nominal values: a camera's
1/125 s is really 1/128 s. Mitsunaga-Nayar calibration (ilt.hdr.mitsunaga_nayar)
measures the true ratios.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

log = logging.getLogger(__name__)

#: exposure times (s) outside this range, in EXIF or from LibRaw, are not believed
TIME_RANGE = (Fraction(1, 1_000_000), Fraction(3600))
#: f-numbers outside this range, in EXIF or from LibRaw, are not believed
F_NUMBER_RANGE = (Fraction(1, 2), Fraction(256))


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


_quiet_lock = threading.Lock()
_quiet_state: dict[str, list[int]] = {}  # logger name -> [readers inside, level to restore]


@contextlib.contextmanager
def quiet_logger(name: str):
    """The library logger ``name`` silenced meanwhile (exifread's "PNG file does not have
    exif data", "File format not recognized": a file without EXIF is an answer, not a
    warning). Safe across threads: the level is restored when the last one leaves."""
    logger = logging.getLogger(name)
    with _quiet_lock:
        state = _quiet_state.setdefault(name, [0, logging.NOTSET])
        if state[0] == 0:
            state[1] = logger.level
            logger.setLevel(logging.CRITICAL + 1)
        state[0] += 1
    try:
        yield
    finally:
        with _quiet_lock:
            state[0] -= 1
            if state[0] == 0:
                logger.setLevel(state[1])


def read_exif(source) -> dict:
    """exifread's tags of a file path or binary file object ({} where there are none).
    exifread's own log messages are silenced meanwhile; a file object is left at 0."""
    import exifread

    try:
        with quiet_logger("exifread"):
            if hasattr(source, "read"):
                source.seek(0)
                try:
                    return exifread.process_file(source, details=False)
                finally:
                    source.seek(0)
            with open(source, "rb") as f:
                return exifread.process_file(f, details=False)
    except OSError:
        raise
    except Exception:  # exifread raises many kinds on non-TIFF data; the caller falls back
        return {}


@dataclass(frozen=True)
class ExifValue:
    """One EXIF fact: ``value`` if usable, else None; ``present``: a tag holds it;
    ``problem``: why a present value is not used ("is 0 (the camera or recorder wrote none)")."""

    value: Fraction | None
    present: bool = False
    problem: str | None = None


_TIME_KEYS = ("EXIF ExposureTime", "Image ExposureTime")
_F_KEYS = ("EXIF FNumber", "Image FNumber")
#: the APEX tags LibRaw derives its shutter and aperture from when the above are 0 or absent
_APEX_TIME_KEYS = ("EXIF ShutterSpeedValue", "Image ShutterSpeedValue")
_APEX_F_KEYS = ("EXIF ApertureValue", "Image ApertureValue")


def exif_value(tags: dict, what: str) -> ExifValue:
    """``what`` = "time" or "f-number" from exifread tags, checked (:func:`check_range`)."""
    keys = _TIME_KEYS if what == "time" else _F_KEYS
    for key in keys:
        if key in tags:
            value, text = _ratio(tags[key])
            if value is None:
                return ExifValue(None, True, f"is {text!r} (not a number)")
            problem = check_range(value, what)
            return ExifValue(None if problem else value, True, problem)
    return ExifValue(None)


def check_range(value: Fraction | float, what: str) -> str | None:
    """None if ``value`` is a believable exposure time (s) or f-number, else why not."""
    unit = " s" if what == "time" else ""
    if value == 0:
        return "is 0 (the camera or recorder wrote none)"
    if value < 0:
        return f"is {_show(value)}{unit} (negative)"
    low, high = TIME_RANGE if what == "time" else F_NUMBER_RANGE
    if not low <= value <= high:
        span = "1e-06 s ... 1 hour" if what == "time" else f"f/{float(low):g} ... f/{float(high):g}"
        return f"is {_show(value)}{unit} (outside {span})"
    return None


def exif_facts(tags: dict) -> tuple[Fraction | None, Fraction | None]:
    """(exposure time, f-number) from exifread tags as exact rationals; None where absent
    or not usable (0, negative, absurd: :func:`check_range`)."""
    return exif_value(tags, "time").value, exif_value(tags, "f-number").value


def _ratio(tag) -> tuple[Fraction | None, str]:
    try:
        v = tag.values[0]
    except (IndexError, TypeError, AttributeError):
        return None, ""
    try:
        value = Fraction(int(v.numerator), int(v.denominator)) if hasattr(v, "numerator") else Fraction(v)
    except (ValueError, ZeroDivisionError, TypeError):
        return None, str(v)
    return value, str(v)


def _show(value) -> str:
    """EXIF rationals as written ("1/50"), other numbers as %g."""
    return str(value) if isinstance(value, Fraction) else f"{float(value):g}"


def _apex_zero(tags: dict, keys) -> bool:
    """An APEX tag written as 0: LibRaw makes 1 s or f/1 of it, which no one shot."""
    for key in keys:
        if key in tags:
            value, _ = _ratio(tags[key])
            return value is None or value == 0
    return False


def _rawpy_value(other, attribute: str, what: str) -> Fraction | None:
    """LibRaw's shutter or aperture if believable; rawpy reports 0 for none."""
    try:
        value = float(getattr(other, attribute, 0) or 0)
    except (TypeError, ValueError):
        return None
    if not math.isfinite(value) or check_range(value, what):
        return None
    return Fraction(value).limit_denominator(100000 if what == "time" else 1000)


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
    """The frame's facts: manifest text, else ``hand_time`` (``--times``), else EXIF, else
    rawpy's ``other``.

    ``tags``: the file's exifread tags if already read (else read from ``path``).
    EXIF and LibRaw values that are 0, negative or absurd are not used
    (:func:`check_range`); LibRaw's are not used either when the EXIF holds the fact but
    unusable, or as an APEX value of 0 (LibRaw reads the same tags: its 1 s comes from
    there). A hand-given time more than :data:`EXIF_TOLERANCE_STOPS` from a usable EXIF
    time wins, with one warning naming the file and both values.
    The f-number defaults to the EXIF one, then LibRaw's, then to 1 (a fixed aperture
    whose value cancels out of the exposure ratios).
    Raises ExposureError naming ``path`` when no exposure time can be found, or when
    the EXIF contradicts the manifest (:func:`check_exif`).
    """
    source = "manifest"
    time = parse_positive(time_text, "exposure time", path) if time_text is not None else None
    f_number = parse_positive(f_text, "f-number", path) if f_text is not None else None
    tags = read_exif(path) if tags is None else tags
    exif_t, exif_n = exif_value(tags, "time"), exif_value(tags, "f-number")
    check_exif(path, time, f_number, exif_t.value, exif_n.value)
    if time is None and hand_time is not None:
        time, source = Fraction(hand_time), "times"
        if exif_t.value is not None and abs(math.log2(time / exif_t.value)) > EXIF_TOLERANCE_STOPS:
            log.warning("%s: --times gives %s s, its EXIF %s s (%.2f stops apart): using --times",
                        path, time, exif_t.value, abs(math.log2(time / exif_t.value)))
    if time is None and exif_t.value is not None:
        time, source = exif_t.value, "exif"
    if f_number is None:
        f_number = exif_n.value
    if rawpy_other is not None:
        if time is None and not exif_t.present and not _apex_zero(tags, _APEX_TIME_KEYS):
            value = _rawpy_value(rawpy_other, "shutter_speed", "time")
            if value is not None:
                time, source = value, "rawpy"
        if f_number is None and not exif_n.present and not _apex_zero(tags, _APEX_F_KEYS):
            f_number = _rawpy_value(rawpy_other, "aperture", "f-number")
    if time is None:
        if exif_t.problem:
            raise ExposureError(f"{path}: EXIF exposure time {exif_t.problem}; give --times")
        raise ExposureError(f"{path}: no exposure time in the manifest or EXIF; give --times")
    if f_number is None:
        f_number = Fraction(1)
    return ExposureFacts(float(time), float(f_number), source, _text(time, False), _text(f_number, True))


def _text(value: Fraction, decimal: bool) -> str:
    """'1/125' for times; '1.2' for f-numbers (decimal when that is exact)."""
    if decimal and Fraction(repr(float(value))) == value:
        return repr(float(value)).removesuffix(".0")
    return str(value)
