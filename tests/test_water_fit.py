"""Tests for seathru.nerf.water_fit: the water recovered from surfaces seen at several ranges."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from seathru.nerf.water_fit import fit_water, projected_loss, voxel_groups

TRUE = {"sigma_attn": [0.55, 0.25, 0.20], "sigma_bs": [0.45, 0.30, 0.25],
        "c_med": [0.08, 0.20, 0.30]}


def _observations(rng: np.random.Generator, groups: int = 400, per_group: int = 12,
                  near: float = 0.5, far: float = 12.0, noise: float = 0.0):
    clean = rng.uniform(0.05, 0.9, size=(groups, 3))
    ids = np.repeat(np.arange(groups), per_group)
    ranges = rng.uniform(near, far, size=ids.size)
    attn, bs, c_med = (np.array(TRUE[k]) for k in ("sigma_attn", "sigma_bs", "c_med"))
    observed = clean[ids] * np.exp(-attn * ranges[:, None]) \
        + c_med * (1 - np.exp(-bs * ranges[:, None]))
    observed += noise * rng.standard_normal(observed.shape)
    return (torch.from_numpy(ranges), torch.from_numpy(observed), torch.from_numpy(ids),
            groups)


def test_voxel_groups_put_points_of_one_voxel_together():
    points = torch.tensor([[0.01, 0.01, 0.01], [0.09, 0.02, 0.05], [0.11, 0.0, 0.0],
                           [-0.01, 0.0, 0.0]])
    ids, groups = voxel_groups(points, 0.1)
    assert groups == 3
    assert ids[0] == ids[1] and len({int(ids[0]), int(ids[2]), int(ids[3])}) == 3


def test_projected_loss_is_zero_at_the_true_water_and_positive_elsewhere():
    ranges, observed, ids, groups = _observations(np.random.default_rng(0))
    truth = [torch.tensor(TRUE[k], dtype=torch.float64) for k in ("sigma_attn", "sigma_bs",
                                                                  "c_med")]
    assert float(projected_loss(*truth, ranges, observed, ids, groups)) < 1e-20
    wrong = [truth[0] * 0.5, truth[1], truth[2]]
    assert float(projected_loss(*wrong, ranges, observed, ids, groups)) > 1e-6


@pytest.mark.parametrize("start", [0.05, 1.0])
def test_fit_recovers_the_water_from_surfaces_seen_over_a_range_of_distances(start):
    ranges, observed, ids, groups = _observations(np.random.default_rng(1), noise=1e-3)
    fit = fit_water(ranges, observed, ids, groups,
                    {"sigma_attn": start, "sigma_bs": start, "c_med": 0.5})
    for key in ("sigma_attn", "sigma_bs", "c_med"):
        assert np.allclose(getattr(fit, key), TRUE[key], rtol=0.05), (key, getattr(fit, key))
    assert fit.pixels == len(ranges) and fit.groups == groups
