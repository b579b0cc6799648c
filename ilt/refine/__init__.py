"""Where the next beams should land: ``ilt refine`` (docs/refine.md).

``indicator`` (how far each beam's column of T is from its neighbours' interpolation, and greedy
placement of new beams where it is largest), ``pointing`` (pixel targets to pan/tilt through
the plan-to-spot map, inverted locally; the unit's reach), ``stage`` (the refine
directory: ``refine.csv``, ``refine.json``, ``refine.png``).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "pointing": ["aim", "check_reach"],
        "indicator": ["Placement", "RefineError", "neighbour_edges", "place_beams", "prediction_residual"],
        "stage": ["refine"],
    },
)
