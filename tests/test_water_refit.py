"""The water refits' own rules (seathru.nerf.water_refit): which refitted values are kept, when
open water counts, which rays look below the horizon. The refits on trained models are tested
in test_train.py (a held value) and test_water_fit.py (the fit itself)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from seathru.nerf.config import MediumConfig
from seathru.nerf.water_refit import (WATER_KEYS, below_horizon, refit_acceptance,
                                      refit_open_water_opacity)


def test_below_horizon_marks_rays_looking_down_by_more_than_the_margin():
    angles = torch.tensor([-30.0, -6.0, -4.0, 0.0, 20.0])
    radians = torch.deg2rad(angles)
    directions = torch.stack([torch.cos(radians), torch.zeros(5), torch.sin(radians)], -1)
    below = below_horizon(directions, [0.0, 0.0, 1.0], 5.0)
    assert below.tolist() == [True, True, False, False, False]
    assert below_horizon(directions, None, 5.0) is None        # models saved without it
    assert below_horizon(directions, [0.0, 0.0, 1.0], -1.0) is None



def _fit(**values):
    return SimpleNamespace(**{key: values.get(key, [0.5, 0.4, 0.3]) for key in WATER_KEYS})


def test_a_refit_keeps_only_the_values_the_views_determine():
    before = {key: [0.5, 0.4, 0.3] for key in WATER_KEYS}
    half = {key: [0.05, 0.05, 0.05] for key in WATER_KEYS}
    half["sigma_bs"] = [0.05, 0.3, 0.05]          # +-75% of 0.4: too loose for 0.5
    fit = _fit(sigma_attn=[0.5, 0.002, 0.3],      # green collapsed below 1% of 0.4
               c_med=[0.5, 0.4, 0.96])            # blue ran to the colour's edge (0.95 x 1.0)
    accepted = refit_acceptance(fit, SimpleNamespace(halfwidth=half), before, colour_max=1.0,
                                max_relative=0.5)
    assert accepted == {"sigma_attn": [True, False, True], "sigma_bs": [True, False, True],
                        "c_med": [True, True, False]}
    # the same fit with a looser rule keeps the loose value, never the ones at an edge
    loose = refit_acceptance(fit, SimpleNamespace(halfwidth=half), before, colour_max=1.0,
                             max_relative=1.0)
    assert loose["sigma_bs"] == [True, True, True] and loose["sigma_attn"][1] is False
    assert loose["c_med"][2] is False


@pytest.mark.parametrize("from_images, progress, expected", [
    (True, 0.15, 0.1),     # the photographs' open water needs no converged model
    (False, 0.15, 0.0),    # the model's empty rays: not before medium.open_water_from
    (False, 0.95, 0.1)])
def test_open_water_counts_from_the_photographs_at_once_and_from_the_model_late(
        from_images, progress, expected):
    medium = MediumConfig(open_water_opacity=0.1, open_water_from=0.9)
    assert refit_open_water_opacity(medium, from_images, progress) == expected


class _Clock(SimpleNamespace):
    def _progress(self) -> float:
        return self.progress


def test_refit_points_passed_while_a_refit_ran_are_skipped_not_made_up():
    from seathru.nerf.water_refit import WaterRefitting

    trainer = _Clock(config=SimpleNamespace(medium=MediumConfig(refit_at=[0.15, 0.4, 0.7, 0.9])),
                     water_refits=[{"step": 980, "accepted": {}}], step=981, progress=0.55)
    WaterRefitting._skip_refits_passed_meanwhile(trainer)    # the refit due at 0.15 ran to 0.55
    assert len(trainer.water_refits) == 2
    assert trainer.water_refits[1]["step"] == 981 and "skipped" in trainer.water_refits[1]
    trainer.progress = 0.6                                    # nothing new is due
    WaterRefitting._skip_refits_passed_meanwhile(trainer)
    assert len(trainer.water_refits) == 2
