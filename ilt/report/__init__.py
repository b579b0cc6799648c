"""The HTML report of a workspace: spots (Fig. 4), T and Cn T (Fig. 5), bounce
images (Fig. 6), diagnostics and capture statistics.

``page`` (the page and its figures).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "page": ["fig5_matrices", "write_report"],
    },
)
