"""The impulse scatter matrix T: how it is sampled, built, stored and refined.

``directory`` (the ISF directory: ``T.npy``, ``samples.csv``, ``cells.exr``, scales),
``cells`` (each sample's cell of pixels), ``layout`` (the plan's layout: a vector of m
samples as an image), ``build`` (``ilt build-isf``: T's columns from the frames, one
pass), ``fine`` (the fine operator for full-resolution bounces, fitted in that pass),
``slopes`` (the slopes of the cells it keeps flat, from their neighbours' means),
``fold_transfer`` (the light the cells beside each fold send across it, spread over the
cell, which decompose adds to T).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "build": ["build_isf", "centroids_and_isf"],
        "cells": ["integrate", "mosaic", "voronoi_cells"],
        "directory": ["ISF", "ISFError", "load_isf", "write_isf"],
        "fine": ["FineError", "FineOperator", "fit_operator", "load_fine"],
        "fold_transfer": ["apply_corrections", "fold_corrections"],
        "layout": ["sample_frame", "splat", "vector_to_image"],
        "slopes": ["NeighbourSlopes"],
    },
)
