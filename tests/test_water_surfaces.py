"""Tests for seathru.nerf.water_surfaces: the surface pixels, groups, open water and dark-pixel
bound a water fit rests on."""

from __future__ import annotations

import numpy as np
import torch

from seathru.nerf.water_fit import fit_water, noise_allowance
from seathru.nerf.water_surfaces import (correspondence_rays, dark_pixels, surface_data,
                                         typical_open_water, voxel_groups)
from tests.test_water_fit import KEYS, START, TRUE, _observations


def test_voxel_groups_put_points_of_one_voxel_together():
    points = torch.tensor([[0.01, 0.01, 0.01], [0.09, 0.02, 0.05], [0.11, 0.0, 0.0],
                           [-0.01, 0.0, 0.0]])
    ids, groups = voxel_groups(points, 0.1)
    assert groups == 3
    assert ids[0] == ids[1] and len({int(ids[0]), int(ids[2]), int(ids[3])}) == 3


def _opaque_rays(rng: np.random.Generator, count: int = 4000):
    """``count`` parallel rays onto surfaces 1-6 units away, all opaque: origins, directions,
    depth, opacity."""
    origins = torch.zeros(count, 3, dtype=torch.float64)
    origins[:, 0] = torch.from_numpy(rng.uniform(0, 5, count))
    directions = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(count, 3)
    depth = torch.from_numpy(rng.uniform(1, 6, count))
    return origins, directions, depth, torch.ones(count, dtype=torch.float64)


def test_surface_data_keeps_surfaces_seen_over_a_range_and_adds_open_water():
    count = 4000
    origins, directions, depth, opacity = _opaque_rays(np.random.default_rng(4), count)
    opacity[:300] = 0.01                                     # open water
    rgb = torch.rand(count, 3, dtype=torch.float64)
    data = surface_data(origins, directions, rgb, depth, opacity, voxel=100.0,
                        min_pixels=10, open_water_opacity=0.1)
    assert not isinstance(data, str)
    assert int(torch.isinf(data.ranges).sum()) == 300
    assert data.groups == int(data.ids.max()) + 1
    # the photographs' open water wins over the model's opacity: a floater in the open water
    # is still open water, an empty ray elsewhere (a hole) is neither water nor surface
    photo = torch.zeros(count, dtype=torch.bool)
    photo[200:400] = True
    by_photo = surface_data(origins, directions, rgb, depth, opacity, voxel=100.0,
                            min_pixels=10, open_water_opacity=0.1, open_water=photo)
    assert int(torch.isinf(by_photo.ranges).sum()) == 200
    assert len(by_photo.ranges) == count - 300 + 200 - 100   # holes 0-199 out, 200-399 water
    unused = surface_data(origins, directions, rgb, depth, opacity, voxel=100.0,
                          min_pixels=10, open_water_opacity=0.0, open_water=photo)
    assert not bool(torch.isinf(unused.ranges).any())
    too_few = surface_data(origins, directions, rgb, depth, opacity * 0.5, voxel=1.0)
    assert isinstance(too_few, str) and "opaque" in too_few


def test_dark_pixels_follow_the_backscatter_where_some_surfaces_are_black():
    rng = np.random.default_rng(5)
    ranges, observed, ids, groups = _observations(rng, groups=2000, per_group=4)
    clean_black = rng.random(groups) < 0.1          # one surface in ten is black
    attn, bs, c_med = (np.array(TRUE[k]) for k in ("sigma_attn", "sigma_bs", "c_med"))
    z = ranges.numpy()
    backscatter = c_med * (1 - np.exp(-bs * z[:, None]))
    observed = torch.from_numpy(np.where(clean_black[ids.numpy(), None], backscatter,
                                         observed.numpy()))
    centres, values = dark_pixels(ranges, observed, bins=8)
    expected = c_med * (1 - np.exp(-bs * centres.numpy()[:, None]))
    assert np.all(values.numpy() >= expected - 1e-3)       # an upper bound on B(z) ...
    assert np.all(values.numpy() - expected < 0.05)        # ... and a tight one
    # a bound the fit must respect: with the bound the fitted backscatter stays below it
    narrow = _observations(np.random.default_rng(6), near=4.0, far=4.5, noise=1e-2)
    bound = (torch.tensor([4.25], dtype=torch.float64),
             torch.tensor([[0.01, 0.01, 0.01]], dtype=torch.float64))
    start = {"sigma_attn": 0.3, "sigma_bs": 0.3, "c_med": 0.5}
    fit = fit_water(*narrow, start, dark=bound)
    free = fit_water(*narrow, start)
    allowance = noise_allowance(free, *narrow).numpy()     # the bound, raised by the noise
    assert np.all((allowance > 0.015) & (allowance < 0.04)), allowance   # 2.33 x 0.01
    modelled = np.array(fit.c_med) * (1 - np.exp(-np.array(fit.sigma_bs) * 4.25))
    assert np.all(modelled < 0.01 + allowance + 0.005), modelled


def test_surfaces_placed_too_far_do_not_tighten_the_dark_pixel_bound():
    # Surfaces seen from several ranges, one in ten black; plus 5% of dark pixels that the
    # model placed 40% too far (each at its own spot, as no other view agrees with it): their
    # backscatter is that of the shorter, true range, below the backscatter at their given one.
    rng = np.random.default_rng(11)
    attn, bs, c_med = (np.array(TRUE[k]) for k in KEYS)
    surfaces, views = 1500, 6
    spots = rng.uniform(-20, 20, size=(surfaces, 3))
    clean = rng.uniform(0.05, 0.9, size=(surfaces, 3)) * (rng.random((surfaces, 1)) > 0.1)
    directions = rng.standard_normal((surfaces * views, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    ranges = rng.uniform(0.5, 8.0, surfaces * views)
    index = np.repeat(np.arange(surfaces), views)
    origins = spots[index] - directions * ranges[:, None]
    observed = clean[index] * np.exp(-attn * ranges[:, None]) \
        + c_med * (1 - np.exp(-bs * ranges[:, None]))
    misplaced = len(ranges) // 20
    true_range = rng.uniform(0.5, 8.0, misplaced)
    given = 1.4 * true_range
    away = rng.standard_normal((misplaced, 3))
    away /= np.linalg.norm(away, axis=1, keepdims=True)
    far_origins = rng.uniform(200, 400, size=(misplaced, 3))        # spots of their own
    origins = np.concatenate([origins, far_origins])
    directions = np.concatenate([directions, away])
    depth = np.concatenate([ranges, given])
    observed = np.concatenate([observed, c_med * (1 - np.exp(-bs * true_range[:, None]))])
    opacity = np.ones(len(depth))
    water = 500                                   # open water in view: it pins c_med
    origins = np.concatenate([origins, np.zeros((water, 3))])
    directions = np.concatenate([directions, np.tile([[0.0, 0.0, 1.0]], (water, 1))])
    depth = np.concatenate([depth, np.full(water, 50.0)])
    observed = np.concatenate([observed, np.tile(c_med, (water, 1))])
    opacity = np.concatenate([opacity, np.full(water, 0.01)])
    observed += 0.002 * rng.standard_normal(observed.shape)
    rays = [torch.from_numpy(a) for a in (origins, directions, observed, depth, opacity)]
    data = surface_data(*rays, voxel=0.05, open_water_opacity=0.1)
    assert not isinstance(data, str)
    fit = fit_water(data.ranges, data.observed, data.ids, data.groups, START, dark=data.dark)
    error = np.array(fit.sigma_bs) / bs - 1
    assert np.all(np.abs(error) < 0.1), error        # bound from every pixel: -16, -19, -24%
    # without open water the bound is all that holds the backscatter: the tighter one, from
    # every surface pixel, is kept
    dry = surface_data(*(r[:-water] for r in rays), voxel=0.05)
    assert torch.all(dry.dark[1] <= data.dark[1] + 1e-12)
    assert torch.any(dry.dark[1] < data.dark[1] - 0.005)


def test_surfaces_inside_the_open_water_mask_do_not_pull_the_veiling_light():
    rng = np.random.default_rng(6)
    c_med = torch.tensor(TRUE["c_med"], dtype=torch.float64)
    water = c_med * (1 + 0.003 * torch.from_numpy(rng.standard_normal((800, 3))))
    # smooth sand and the hazy far seabed join the mask: darker than the water by 5-40%
    surfaces = c_med * torch.from_numpy(rng.uniform(0.6, 0.95, (160, 1)))
    rgb = torch.cat([water, surfaces, torch.rand(40, 3, dtype=torch.float64)])
    flagged = torch.ones(len(rgb), dtype=torch.bool)
    flagged[-40:] = False                                   # not in the mask at all
    typical = typical_open_water(rgb, flagged)
    assert bool(typical[:800].all()) and not bool(typical[800:].any())
    assert torch.allclose(rgb[typical].mean(0), c_med, rtol=2e-3)
    assert not torch.allclose(rgb[flagged].mean(0), c_med, rtol=2e-2)   # the bias it removes
    # a veiling light that changes with direction is kept whole
    varying = c_med * torch.from_numpy(rng.uniform(0.7, 1.3, (500, 1)))
    assert bool(typical_open_water(varying, torch.ones(500, dtype=torch.bool)).all())


def test_open_water_below_the_horizon_is_used_only_where_none_looks_above():
    count = 4000
    origins, directions, depth, opacity = _opaque_rays(np.random.default_rng(11), count)
    rgb = torch.full((count, 3), 0.3, dtype=torch.float64) + 0.001 * torch.rand(count, 3)
    rgb[:600] = torch.tensor([0.05, 0.2, 0.3], dtype=torch.float64)
    photo = torch.zeros(count, dtype=torch.bool)
    photo[:600] = True
    below = torch.zeros(count, dtype=torch.bool)
    below[400:600] = True                                  # a third of the open water
    common = dict(voxel=100.0, min_pixels=10, open_water_opacity=0.1, open_water=photo)
    mixed = surface_data(origins, directions, rgb, depth, opacity, below_horizon=below, **common)
    assert int(torch.isinf(mixed.ranges).sum()) == 400 and not mixed.open_water_below_horizon
    assert len(mixed.ranges) == count - 200          # far seabed: neither water nor surface
    below[:600] = True
    orbit = surface_data(origins, directions, rgb, depth, opacity, below_horizon=below, **common)
    assert int(torch.isinf(orbit.ranges).sum()) == 600 and orbit.open_water_below_horizon
    unknown = surface_data(origins, directions, rgb, depth, opacity, **common)
    assert int(torch.isinf(unknown.ranges).sum()) == 600 and not unknown.open_water_below_horizon


def test_open_water_the_model_renders_as_a_near_surface_is_that_surface():
    """Turbid water's far seabed joins the photographs' open water; a converged model places
    it. Opaque rays short of the given range become surfaces at their depth; empty ones and
    the density a model piles at its far bound stay open water."""
    count = 4000
    origins, directions, depth, opacity = _opaque_rays(np.random.default_rng(12), count)
    rgb = torch.rand(count, 3, dtype=torch.float64)
    photo = torch.zeros(count, dtype=torch.bool)
    photo[:900] = True
    opacity[:300] = 0.02                          # real open water, rendered empty
    depth[300:600] = 7.9                          # a density wall at the far bound (8)
    # 600-899: seabed 1-6 units away, rendered opaque where it is
    within = torch.full((count,), 0.9 * 8.0, dtype=torch.float64)
    common = dict(voxel=100.0, min_pixels=10, open_water_opacity=0.1, open_water=photo)
    before = surface_data(origins, directions, rgb, depth, opacity, **common)
    after = surface_data(origins, directions, rgb, depth, opacity, **common,
                         open_water_surface_within=within)
    assert int(torch.isinf(before.ranges).sum()) == 900
    assert int(torch.isinf(after.ranges).sum()) == 600
    assert len(after.ranges) == len(before.ranges)
    seabed = set(depth[600:900].tolist())
    assert seabed <= set(after.ranges[torch.isfinite(after.ranges)].tolist())
    assert not seabed & set(before.ranges[torch.isfinite(before.ranges)].tolist())


def test_pixels_of_one_surface_point_fit_the_water_closer_than_voxel_groups():
    # The simulated survey's exact images and ranges through a perfect "model" (its depth is the
    # true range, opaque on surfaces): the same number of surface pixels, grouped by the point
    # they see across views, against random pixels grouped by voxel.
    from seathru.geometry.poses import pixel_of_points
    from seathru.io.textures import load_sample_textures
    from seathru.io.truth import truth_frame
    from seathru.nerf.rays import RayDataset
    from seathru.sim import dive as dive_mod
    from seathru.sim.water import water_params

    spec = dive_mod.DiveSpec(views=10, width=160, height=120, path="survey",
                             water=water_params("default"), seed=0, fov_deg=65.0,
                             supersample=2, seabed_amplitude=0.08)
    plan = dive_mod.plan_dive(spec, load_sample_textures())
    views = list(dive_mod.render_views(spec, plan))
    frames = [truth_frame(f"v{i}", plan.camera, v.c2w, v.range_m, "train")
              for i, v in enumerate(views)]
    water_flags = [~np.isfinite(v.range_m) for v in views]
    data = RayDataset(frames, [v.water for v in views], open_water=water_flags)
    centres = torch.tensor(np.array([f.c2w_array[:3, 3] for f in frames]), dtype=torch.float32)

    def perfect_render(rays):
        view = torch.cdist(rays.origins, centres).argmin(dim=1).numpy()
        depth = np.empty(len(rays))
        for v in np.unique(view):
            here = view == v
            frame = frames[v]
            points = (rays.origins[here] + rays.directions[here]).double().numpy()
            row, col, _, _ = pixel_of_points(frame.c2w_array, frame.fx, frame.fy, frame.cx,
                                             frame.cy, frame.width, frame.height, points)
            depth[here] = views[v].range_m[row, col]
        depth = torch.from_numpy(depth)
        surface = torch.isfinite(depth)
        return {"depth_median": torch.where(surface, depth, torch.nan).float(),
                "opacity": surface.float()}

    found = correspondence_rays(data, perfect_render, anchors=4000, budget=30000, seed=3)
    surface = found.point_ids >= 0
    assert 0 < int(surface.sum()) <= 30000
    # every ray of a point meets the surface at that point's distance (within the tolerance)
    ends = found.rays.origins[surface] + found.rays.directions[surface] \
        * found.depth[surface, None]
    for point in torch.unique(found.point_ids[surface])[:50]:
        members = ends[found.point_ids[surface] == point].double()
        spread = torch.linalg.norm(members - members.mean(0), dim=1).max()
        assert spread < 0.03 * float(found.depth[surface][found.point_ids[surface] == point].max())
    grouped = surface_data(found.rays.origins, found.rays.directions, found.rays.rgb,
                           found.depth, found.opacity, 0.05, open_water_opacity=0.5,
                           open_water=found.rays.open_water, point_ids=found.point_ids)
    # at least as many rays rendered as the anchors and the budget
    drawn = data.fixed_subset(4000 + 30000, seed=3)
    depth = perfect_render(drawn)
    by_voxel = surface_data(drawn.origins, drawn.directions, drawn.rgb, depth["depth_median"],
                            depth["opacity"], 0.05, open_water_opacity=0.5,
                            open_water=drawn.open_water)
    truth = np.array(spec.water.sigma_attn)
    errors = {}
    for name, d in (("points", grouped), ("voxels", by_voxel)):
        fit = fit_water(d.ranges, d.observed, d.ids, d.groups, START, dark=d.dark)
        errors[name] = np.abs(np.array(fit.sigma_attn) / truth - 1)
    assert errors["points"].max() < 0.05, errors
    assert errors["points"].mean() < errors["voxels"].mean(), errors
