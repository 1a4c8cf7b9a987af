"""The 95% interval ``water.json`` writes around a trained water value, shared by the training
step's assessment (``water_uncertainty.interval_determined``) and the file format
(``seathru.io.water``).

Plain floats, no PyTorch: the report and evaluate steps read ``water.json`` without loading it.
"""

from __future__ import annotations

# a value whose interval reaches further than this share of it either side is not determined
DETERMINED_MAX_RELATIVE = 0.25


def interval_halfwidth(trained: float, surface_fit: float, halfwidth: float) -> float:
    """Half-width of the interval around ``trained``: the surface fit's 95% ``halfwidth``
    widened by the trained value's distance to that fit (the value may have drifted from it
    since the last refit).

    Example::

        >>> interval_halfwidth(1.25, 1.0, 0.25)
        0.5
    """
    return halfwidth + abs(trained - surface_fit)
