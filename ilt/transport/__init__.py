"""The paper's equations and the solvers that apply them to a measured T.

``scan`` (T checked and measured in one pass: :class:`IsfMatrix`, handed to every
solver), ``operators`` (``C1 = T1 T^-1``, Eq. 13, and the bounce recursion
``Cn = C1 (I - C1)^(n-1)``), ``diagnostics`` (condition, spectral radius of ``A = I - C1``,
closure, negatives), ``solvers`` (dense, mixed precision, independent blocks, and the
auto choice), ``series`` (sparse Neumann series), ``compressed`` (hierarchical
low-rank, HODLR), ``regularise`` (denoising T before inversion).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "compressed": ["compressed_operator", "grid_points"],
        "diagnostics": ["decomposition_diagnostics", "operator_diagnostics", "spectral_radius"],
        "operators": ["CancellationOperator", "Decomposition", "bounce_images", "cancellation_operator"],
        "regularise": ["regularise_isf", "smooth_isf"],
        "scan": ["IsfMatrix", "TransportError", "scan_isf"],
        "series": ["series_operator"],
        "solvers": ["SOLVERS", "build_operator", "choose_solver", "estimate_noise", "independent_groups"],
    },
)
