"""RAW brackets to linear HDR (paper Sec. 4), above capture and below spots.

``bracket`` (a capture's beams and their frames, as ``ilt merge`` reads them),
``mitsunaga_nayar`` (radiometric self-calibration, Mitsunaga & Nayar 1999), ``merge``
(noise-optimal merging of a bracket into linear radiance) and ``stages`` (``ilt
calibrate`` and ``ilt merge`` on files). RAW decoding and EXIF exposure facts are
:mod:`ilt.io.raw` and :mod:`ilt.io.exposure`: capture reads them too.
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "bracket": ["list_beams", "read_beam"],
        "merge": ["MergeError", "NoiseModel", "cramer_rao_bound", "merge_bracket"],
        "mitsunaga_nayar": ["CalibrationError", "ResponseFit", "fit_response"],
        "stages": ["MergeOptions", "Response", "calibrate", "load_response", "merge_capture", "merge_files"],
    },
)
