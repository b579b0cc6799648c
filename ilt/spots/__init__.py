"""Laser spots: one subpixel centroid per beam, with quality flags (paper Sec. 4).

``find`` (the spot in one frame: background, peak component, aperture centroid,
shape flags), ``table`` (the spot record and ``spots.csv``), ``stage`` (``ilt
centroids``: every beam of a merged or raw capture, the sum image and the overlay).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "find": ["SpotParameters", "find_spot"],
        "stage": ["read_shortest_exposure", "run_centroids"],
        "table": ["SPOTS_FILE", "Spot", "SpotsError", "read_spots", "write_spots"],
    },
)
