"""Photos to n-bounce images, at the m samples and at the photo's resolution.

``stage`` (``ilt decompose``: the operator built once per T and cached, photos solved
as one batch, outputs written whole), ``fullres`` (bounce images at every pixel from
the sample-level recursion and the fine operator).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "fullres": ["full_resolution"],
        "stage": ["InputError", "decompose", "default_cache_dir", "load_operator", "read_photo"],
    },
)
