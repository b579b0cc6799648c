"""How good and how fast: error measures, the solver benchmark, the rig end to end.

``errors`` (relative errors of bounce images and ISFs against ground truth),
``bench`` (``ilt bench``: run time against error per solver and noise level),
``end_to_end`` (the emulated rig's output against the renderer's truth).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "bench": ["run_bench"],
        "end_to_end": ["compare", "ideal_workspace"],
        "errors": ["bounce_isf_errors", "noise_amplification", "relative_errors"],
    },
)
