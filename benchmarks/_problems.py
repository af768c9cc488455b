"""The RCBF problems the benchmarks share (Unicycle with 8 obstacles, PVTOL with 9 + operator)."""

from __future__ import annotations

import numpy as np


def unicycle_params() -> dict:
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    return {'system': 'unicycle',
            'obstacles': {'x': (2.0 * np.cos(angles)).tolist(),
                          'y': (2.0 * np.sin(angles)).tolist(),
                          'radius': [0.5] * 8, 'margin': 0.1, 'lookahead': 0.03,
                          'heading_index': 2},
            'alpha': 2.0, 'input_limits': {'min': [-2.5, -2.5], 'max': [2.5, 2.5]}}


def pvtol_params() -> dict:
    return {'system': 'pvtol',
            'obstacles': {'x': [-3.0, -1.5, -1.5, 0.0, 0.0, 1.5, 1.5, 3.0, 3.5],
                          'y': [0.5, -1.5, 1.5, -0.5, 2.0, -2.0, 0.8, -0.8, 1.8],
                          'radius': [0.45, 0.4, 0.4, 0.45, 0.4, 0.4, 0.45, 0.4, 0.4],
                          'margin': 0.1, 'gammas': [2.0, 2.0]},
            'bands': {'operator': {'index': 0, 'center_index': 6, 'half_width': 0.6,
                                   'gammas': [2.0, 2.0]}},
            'alpha': 2.0, 'input_limits': {'min': [-2.5, -2.5], 'max': [2.5, 2.5]}}
