"""The SeaThru-NeRF model: rays, object fields, samplers, the water medium, the medium-aware
closed-form renderer, losses, the training loop (``training``) with its model choices
(``selection``) and water refits (``water_refit``, on ``water_fit`` and ``water_uncertainty``),
and whole-frame inference.

PyTorch, no file I/O (steps pass callbacks). Never imports ``seathru.sim``.
"""
