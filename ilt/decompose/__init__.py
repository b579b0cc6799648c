"""Photos to n-bounce images, at the m samples and at the photo's resolution.

``stage`` (``ilt decompose``: the operator built once per T and cached, photos solved
as one batch, outputs written whole), ``fullres`` (bounce images at every pixel from
the sample-level recursion and the fine operator).
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "fullres": ["full_resolution"],
        "stage": ["InputError", "decompose", "default_cache_dir", "load_operator", "read_photo"],
    },
)
