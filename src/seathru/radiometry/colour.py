"""Colour transfer functions (IEC 61966-2-1 sRGB), vectorised for numpy arrays and torch tensors."""

from __future__ import annotations


def srgb_to_linear(encoded):
    """Inverse sRGB transfer: encoded values in [0, 1] to linear."""
    xp = _namespace(encoded)
    return xp.where(encoded <= 0.04045, encoded / 12.92,
                    ((xp.clip(encoded, 0.04045, None) + 0.055) / 1.055) ** 2.4)


# The standard's two segments do not quite meet: 0.04045 / 12.92 = 0.00313080495 decodes past
# its 0.0031308. Switching at the decoded breakpoint makes encode(decode(x)) == x there too.
LINEAR_BREAK = 0.04045 / 12.92


def linear_to_srgb(linear):
    """sRGB transfer: linear values (clipped to [0, 1]) to encoded."""
    xp = _namespace(linear)
    linear = xp.clip(linear, 0.0, 1.0)
    return xp.where(linear <= LINEAR_BREAK, linear * 12.92,
                    1.055 * xp.clip(linear, LINEAR_BREAK, None) ** (1.0 / 2.4) - 0.055)


def _namespace(array):
    if type(array).__module__.startswith("torch"):
        import torch

        class _Torch:
            where = staticmethod(torch.where)

            @staticmethod
            def clip(x, lo, hi):
                return torch.clamp(x, lo, hi)

        return _Torch
    import numpy as np

    return np
