"""A simulated Bayer sensor that writes real DNG files, so every HDR test has ground truth.

Signal model of one photosite (all per exposure; DESIGN.md sec. 5):

    electrons  ~ Poisson(radiance * colour_scale[c] * t / N^2) + Normal(0, read_noise)
    linear DN  =  electrons / gain                       (gain in e-/DN)
    DN         =  clip(black + round(linear DN), 0, white)          (linear sensor)
    DN         =  black + round((white - black) * response(x)),    (non-linear camera)
                  x = clip(linear DN / (white - black), 0, 1)

``radiance`` is in electrons per second at f/1 per photosite (green scale 1), ``t`` the
true exposure time in seconds, ``N`` the f-number. The response is the identity for a
linear RAW sensor; a monotonic curve with response(0) = 0, response(1) = 1 models a
non-linear camera (8-bit JPEG/TIFF pipelines).

The DNG is an uncompressed 16-bit CFA TIFF with the DNG tags LibRaw needs (DNGVersion,
CFARepeatPatternDim, CFAPattern, BlackLevel, WhiteLevel, ColorMatrix1, Make, Model,
UniqueCameraModel) and the EXIF ExposureTime and FNumber as exact rationals in IFD 0.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

#: CFA letters -> DNG CFAPattern colour codes (0 red, 1 green, 2 blue)
_CFA_CODES = {"R": 0, "G": 1, "B": 2}
_COLOURS = "RGB"


@dataclass(frozen=True)
class SensorModel:
    """A Bayer sensor and its noise.

    width, height: full-frame size in photosites (even numbers, >= 22 for LibRaw).
    cfa: the 2x2 pattern in scanline order, one of RGGB, BGGR, GRBG, GBRG.
    black_level, white_level: DN of black and of clipping (``white_level`` <= 2**bits - 1).
    gain: electrons per DN. read_noise: electrons (standard deviation).
    bits: ADC bits. colour_scale: (r, g, b) multipliers of the green-channel radiance.
    response: None (linear) or a callable on normalised exposure x in [0, 1] returning
        normalised DN in [0, 1], monotonic, response(0) = 0, response(1) = 1.
    make, model: written to the DNG (Make, Model, UniqueCameraModel = make + model).
    """

    width: int = 64
    height: int = 48
    cfa: str = "RGGB"
    black_level: int = 1024
    white_level: int = 15000
    gain: float = 1.0
    read_noise: float = 2.0
    bits: int = 14
    colour_scale: tuple[float, float, float] = (0.5, 1.0, 0.7)
    response: Callable[[np.ndarray], np.ndarray] | None = field(default=None, compare=False)
    make: str = "ilt"
    model: str = "SimSensor"

    def __post_init__(self):
        if self.cfa not in ("RGGB", "BGGR", "GRBG", "GBRG"):
            raise ValueError(f"cfa {self.cfa!r} is not a Bayer pattern (RGGB, BGGR, GRBG, GBRG)")
        if self.width % 2 or self.height % 2 or min(self.width, self.height) < 22:
            raise ValueError(f"sensor size {self.width} x {self.height} must be even and >= 22")
        if not 0 <= self.black_level < self.white_level <= 2**self.bits - 1:
            raise ValueError("need 0 <= black_level < white_level <= 2**bits - 1")

    @property
    def full_scale(self) -> int:
        """DN range above black: ``white_level - black_level``."""
        return self.white_level - self.black_level

    def colour_index(self) -> np.ndarray:
        """(height, width) int: colour (0 R, 1 G, 2 B) of each photosite."""
        cell = np.array([_CFA_CODES[c] for c in self.cfa]).reshape(2, 2)
        return np.tile(cell, (self.height // 2, self.width // 2))


def mosaic_radiance(radiance: np.ndarray, sensor: SensorModel) -> np.ndarray:
    """(height, width) float64 radiance per photosite: green radiance times the colour scale.

    ``radiance`` is (height, width) (one value per photosite) or (height/2, width/2)
    (one value per 2x2 cell, repeated over the cell's four photosites).
    """
    radiance = np.asarray(radiance, dtype=np.float64)
    if radiance.shape == (sensor.height // 2, sensor.width // 2):
        radiance = np.repeat(np.repeat(radiance, 2, axis=0), 2, axis=1)
    if radiance.shape != (sensor.height, sensor.width):
        raise ValueError(
            f"radiance shape {radiance.shape} fits neither the sensor ({sensor.height}, {sensor.width}) "
            f"nor its 2x2 cells ({sensor.height // 2}, {sensor.width // 2})"
        )
    if (radiance < 0).any() or not np.isfinite(radiance).all():
        raise ValueError("radiance must be finite and >= 0")
    return radiance * np.asarray(sensor.colour_scale)[sensor.colour_index()]


def expected_dn(radiance, exposure_time: float, f_number: float, sensor: SensorModel) -> np.ndarray:
    """(height, width) float64 ground truth: the DN each photosite would read without noise.

    ``min(black + mean electrons / gain, white)`` for a linear sensor,
    ``black + full_scale * response(clip(mean electrons / gain / full_scale, 0, 1))``
    for a non-linear one; not rounded. For a linear sensor below clipping, ``expected_dn - black`` is exactly
    ``radiance * colour_scale * t / N^2 / gain``.
    """
    electrons = mosaic_radiance(radiance, sensor) * (exposure_time / f_number**2)
    return _to_dn(electrons / sensor.gain, sensor, rounded=False)


def expose(radiance, exposure_time: float, f_number: float, sensor: SensorModel,
           rng: np.random.Generator) -> np.ndarray:
    """(height, width) uint16 raw mosaic of one exposure, through the full noise model."""
    mean = mosaic_radiance(radiance, sensor) * (exposure_time / f_number**2)
    electrons = rng.poisson(mean).astype(np.float64)
    if sensor.read_noise > 0:
        electrons += rng.normal(0.0, sensor.read_noise, size=mean.shape)
    return _to_dn(electrons / sensor.gain, sensor, rounded=True).astype(np.uint16)


def _to_dn(linear_dn: np.ndarray, sensor: SensorModel, rounded: bool) -> np.ndarray:
    if sensor.response is None:
        # a linear sensor keeps the noise below black (down to DN 0): the black offset is there for it
        dn = sensor.black_level + (np.rint(linear_dn) if rounded else linear_dn)
        return np.clip(dn, 0, sensor.white_level)
    x = np.clip(linear_dn / sensor.full_scale, 0.0, 1.0)
    x = np.clip(np.asarray(sensor.response(x), dtype=np.float64), 0.0, 1.0)
    dn = sensor.full_scale * x
    return sensor.black_level + (np.rint(dn) if rounded else dn)


def write_dng(
    path: str | os.PathLike,
    radiance,
    exposure_time: float,
    f_number: float,
    sensor: SensorModel,
    rng: np.random.Generator,
    nominal_time: str | Fraction | float | None = None,
    nominal_f_number: str | Fraction | float | None = None,
    mosaic: np.ndarray | None = None,
) -> Path:
    """Expose ``radiance`` for ``exposure_time`` s at ``f_number`` and write a DNG rawpy reads.

    ``nominal_time`` / ``nominal_f_number`` are what the EXIF says (default: the true
    values as the nearest rationals), as a camera writes 1/125 for a true 1/128 s.
    ``mosaic`` (height, width) uint16 overrides the exposure (for hand-made test data).
    The file is written to a temporary name and renamed.
    """
    import tifffile

    from ilt.io.atomic import atomic_path

    raw = expose(radiance, exposure_time, f_number, sensor, rng) if mosaic is None else mosaic
    raw = np.ascontiguousarray(raw, dtype=np.uint16)
    if raw.shape != (sensor.height, sensor.width):
        raise ValueError(f"mosaic shape {raw.shape} is not ({sensor.height}, {sensor.width})")
    t = _rational(exposure_time if nominal_time is None else nominal_time)
    n = _rational(f_number if nominal_f_number is None else nominal_f_number)
    identity = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)
    tags = [
        (271, "s", 0, sensor.make, True),
        (272, "s", 0, sensor.model, True),
        (33421, "H", 2, (2, 2), True),
        (33422, "B", 4, tuple(_CFA_CODES[c] for c in sensor.cfa), True),
        (33434, "2I", 1, (t.numerator, t.denominator), True),
        (33437, "2I", 1, (n.numerator, n.denominator), True),
        (50706, "B", 4, (1, 4, 0, 0), True),
        (50707, "B", 4, (1, 1, 0, 0), True),
        (50708, "s", 0, f"{sensor.make} {sensor.model}", True),
        (50713, "H", 2, (1, 1), True),
        (50714, "I", 1, sensor.black_level, True),
        (50717, "I", 1, sensor.white_level, True),
        (50721, "2i", 9, identity, True),
        (50778, "H", 1, 21, True),  # CalibrationIlluminant1 = D65
    ]
    path = Path(path)
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, raw, photometric=32803, extratags=tags, metadata=None, software=False)
    return path


def write_ldr(
    path: str | os.PathLike,
    radiance,
    exposure_time: float,
    f_number: float,
    sensor: SensorModel,
    rng: np.random.Generator,
) -> Path:
    """Write one grey 8- or 16-bit frame of a non-RAW camera (TIFF with EXIF rationals,
    or PNG/JPEG through OpenCV, whose times must then be given by hand).

    ``radiance`` is per pixel (height, width); the sensor's ``colour_scale`` is ignored
    (a grey camera), its response applies; ``black_level`` should be 0 for such files.
    """
    from ilt.io.atomic import atomic_path

    grey = SensorModel(**{**_fields(sensor), "colour_scale": (1.0, 1.0, 1.0)})
    frame = expose(radiance, exposure_time, f_number, grey, rng)
    dtype = np.uint8 if sensor.bits <= 8 else np.uint16
    frame = frame.astype(dtype)
    path = Path(path)
    with atomic_path(path) as tmp:
        if path.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            t, n = _rational(exposure_time), _rational(f_number)
            tags = [(33434, "2I", 1, (t.numerator, t.denominator), True),
                    (33437, "2I", 1, (n.numerator, n.denominator), True)]
            tifffile.imwrite(tmp, frame, photometric="minisblack", extratags=tags,
                             metadata=None, software=False)
        else:
            import cv2

            if not cv2.imwrite(str(tmp), frame, [cv2.IMWRITE_JPEG_QUALITY, 100]):
                raise OSError(f"{path}: OpenCV could not write the image")
    return path


def _fields(sensor: SensorModel) -> dict:
    return {f: getattr(sensor, f) for f in sensor.__dataclass_fields__}


def _rational(value) -> Fraction:
    # EXIF rationals are 32-bit numerator / denominator
    return Fraction(value).limit_denominator(1_000_000)


def spot_radiance(shape: tuple[int, int], centre: tuple[float, float], peak: float,
                  sigma: float, floor: float = 0.0, tail: float = 0.0) -> np.ndarray:
    """(h, w) float64 laser-spot scene: a Gaussian spot of ``peak`` radiance and width
    ``sigma`` pixels at ``centre`` (x, y), a ``tail`` * peak / (1 + (r / sigma)^2)^1.5
    halo (light scattered off nearby surfaces, many decades dimmer) and a constant
    ``floor``. Coordinates are pixels of the (h, w) grid, centre of the top-left at (0, 0).
    """
    y, x = np.indices(shape, dtype=np.float64)
    r2 = ((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / sigma**2
    return floor + peak * (np.exp(-0.5 * r2) + tail / (1.0 + r2) ** 1.5)


def write_bracket(
    beam_dir: str | os.PathLike,
    radiance,
    bracket: list[tuple[float, float, str | None]],
    sensor: SensorModel,
    rng: np.random.Generator,
    dark: bool = False,
) -> Path:
    """Write one beam's bracket as a capture beam directory (docs/hdr.md).

    ``bracket``: (true exposure time s, f-number, nominal time text or None) per frame.
    Frames are ``frame-00.dng`` ...; with ``dark`` a zero-radiance frame at the longest
    exposure is added as ``dark.dng``. The beam's ``manifest.json`` lists the nominal
    facts, as a camera reports them.
    """
    from ilt.io.beams import FrameRecord, write_beam_manifest

    beam_dir = Path(beam_dir)
    beam_dir.mkdir(parents=True, exist_ok=True)
    frames = []
    for k, (t, n, nominal) in enumerate(bracket):
        name = f"frame-{k:02d}.dng"
        write_dng(beam_dir / name, radiance, t, n, sensor, rng, nominal_time=nominal)
        frames.append(FrameRecord(name, str(_rational(nominal if nominal else t)), str(_rational(n))))
    dark_record = None
    if dark:
        t, n, nominal = max(bracket, key=lambda b: b[0] / b[1] ** 2)
        zeros = np.zeros((sensor.height, sensor.width))
        write_dng(beam_dir / "dark.dng", zeros, t, n, sensor, rng, nominal_time=nominal)
        dark_record = FrameRecord("dark.dng", str(_rational(nominal if nominal else t)), str(_rational(n)))
    write_beam_manifest(beam_dir, frames, dark_record)
    return beam_dir


#: The paper's bracket (Sec. 4): 1/15 s ... 1/8000 s at f/1.2 in full stops, plus f/16 at
#: 1/8000 s. Nominal EXIF times vs the true powers of two (1/125 s is really 1/128).
PAPER_BRACKET: list[tuple[float, float, str]] = [
    (2.0**-k, 1.2, nominal)
    for k, nominal in zip(range(4, 14), ["1/15", "1/30", "1/60", "1/125", "1/250", "1/500",
                                         "1/1000", "1/2000", "1/4000", "1/8000"])
] + [(2.0**-13, 16.0, "1/8000")]
