"""Direct and global light from shifted high-frequency patterns: ``ilt separate`` (Nayar et al. 2006).

``nayar`` (the max/min estimator on a stack of pattern photos), ``stage`` (the separate
directory: ``direct.exr``, ``global.exr``, ``preview.png``). A peer of ilt's bounces
that needs no laser scan and holds for any reflectance: an independent cross-check of
bounce 1 and the indirect part on a scene that fails the Lambertian check.
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "nayar": ["direct_global"],
        "stage": ["SeparateError", "separate"],
    },
)
