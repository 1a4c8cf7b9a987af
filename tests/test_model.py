"""Unit tests of the model's parts: rays, contraction, sampler, losses, medium, model, inference."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from seathru.geometry.poses import pixel_of_points
from seathru.nerf.fields import contract, grid_vertices, trilinear_lookup, uncontract
from seathru.nerf.inference import render_frame
from seathru.nerf.losses import (distortion_loss, reconstruction_loss, sparse_depth_loss,
                                 total_variation_3d, transmittance_prior)
from seathru.nerf.medium import Medium
from seathru.nerf.config import TrainConfig
from seathru.settings import SettingsError
from seathru.nerf.model import AUTO_FAR_FACTOR, SeaThruModel, far_bound_choice
from seathru.nerf.rays import (RayDataset, covisible_box, frame_rays,
                               ray_box_intersect, view_counts)
from seathru.nerf.rendering import nerf_weights
from seathru.nerf.sampler import (candidate_edges, lookup_nearest, merge_edges,
                                  normalised_distance, occupancy_weights, sample_pdf,
                                  stratified_edges)
from seathru.sim.camera_paths import look_at
from seathru.io.cameras import Frame

torch.set_num_threads(1)
SMALL = dict(density_res=[16, 20, 24], plane_res=[16, 24, 32], plane_coarse_res=8,
             density_coarse_res=8, plane_channels=4, decoder_hidden=8, candidates_linear=16,
             candidates_disparity=4, samples_per_ray=8, medium="global", eval_rays=64)


def rotation(a: float, b: float, c: float) -> np.ndarray:
    ca, sa, cb, sb, cc, sc = math.cos(a), math.sin(a), math.cos(b), math.sin(b), math.cos(c), \
        math.sin(c)
    rz = np.array([[ca, -sa, 0], [sa, ca, 0], [0, 0, 1]])
    ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    rx = np.array([[1, 0, 0], [0, cc, -sc], [0, sc, cc]])
    return rz @ ry @ rx


def make_frame(rot=(0.3, -0.2, 0.1), centre=(0.5, -1.0, 2.0), width=12, height=8, fx=10.0,
               fy=11.0, cx=6.2, cy=3.9, near=0.5, far=6.0, split="train", name="f") -> Frame:
    c2w = np.eye(4)
    c2w[:3, :3] = rotation(*rot)
    c2w[:3, 3] = centre
    return Frame(name=name, image=f"{name}.tiff", width=width, height=height, fx=fx, fy=fy,
                 cx=cx, cy=cy, c2w=c2w.tolist(), near=near, far=far, split=split)


def look_at_frame(position, target=(0.0, 0.0, 0.0), name="f", **kw) -> Frame:
    frame = make_frame(name=name, **kw)
    frame.c2w = look_at(position, target).tolist()
    return frame


# ---------------------------------------------------------------------------------------- rays

@settings(max_examples=40, deadline=None)
@given(st.floats(-3, 3), st.floats(-1.4, 1.4), st.floats(-3, 3), st.integers(0, 11),
       st.integers(0, 7), st.floats(0.3, 7.0), st.sampled_from([1, 2]))
def test_pixel_ray_passes_through_the_point_that_projects_to_its_centre(a, b, c, u, v, t, down):
    frame = make_frame(rot=(a, b, c))
    origins, dirs = frame_rays(frame, downscale=down)
    w = frame.width // down
    if u >= w or v >= frame.height // down:
        return
    index = v * w + u
    point = origins[index].double().numpy() + t * dirs[index].double().numpy()
    # project with the float64 pinhole model: the point lands on the pixel's centre
    w2c = np.linalg.inv(frame.c2w_array)
    cam = w2c[:3, :3] @ point + w2c[:3, 3]
    assert cam[2] > 0
    assert cam[0] / cam[2] * frame.fx + frame.cx == pytest.approx((u + 0.5) * down, abs=1e-4)
    assert cam[1] / cam[2] * frame.fy + frame.cy == pytest.approx((v + 0.5) * down, abs=1e-4)
    assert float(torch.linalg.norm(dirs[index])) == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(origins[index].numpy(), frame.c2w_array[:3, 3], atol=1e-6)


def test_rays_are_row_major_and_follow_opencv_axes():
    frame = make_frame(rot=(0, 0, 0), centre=(0, 0, 0), width=4, height=3, fx=2, fy=2, cx=2,
                       cy=1.5)
    _, dirs = frame_rays(frame)
    grid = dirs.reshape(3, 4, 3)
    assert torch.all(grid[:, 1:, 0] > grid[:, :-1, 0])   # x grows to the right (columns)
    assert torch.all(grid[1:, :, 1] > grid[:-1, :, 1])   # y grows downwards (rows)
    assert torch.all(grid[..., 2] > 0)                   # looking along +z
    assert dirs.shape == (12, 3)


def test_ray_box_intersection_hits_the_faces():
    origins = torch.tensor([[0.0, 0.0, -5.0], [0.2, 0.1, 0.0], [5.0, 5.0, 5.0]])
    dirs = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.5, 0.2],
                                                       [1.0, 0.0, 0.0]]), dim=-1)
    lo, hi = torch.tensor([-1.0, -1.0, -1.0]), torch.tensor([1.0, 1.0, 1.0])
    t_in, t_out = ray_box_intersect(origins, dirs, lo, hi)
    assert t_in[0] == pytest.approx(4.0) and t_out[0] == pytest.approx(6.0)
    exit_point = origins[1] + dirs[1] * t_out[1]
    assert float(exit_point.abs().max()) == pytest.approx(1.0, abs=1e-6)
    assert t_in[1] < 0 < t_out[1]          # origin inside
    assert t_in[2] > t_out[2]              # miss


def test_covisible_box_contains_cameras_and_the_looked_at_centre():
    frames = [look_at_frame((3 * math.cos(k), 3 * math.sin(k), 2.0), name=f"c{k}", near=1.0,
                            far=8.0) for k in np.linspace(0, 2 * math.pi, 8, endpoint=False)]
    lo, hi = covisible_box(frames)
    centres = np.array([f.c2w_array[:3, 3] for f in frames])
    assert np.all(centres >= lo) and np.all(centres <= hi)
    assert np.all(lo < 0) and np.all(hi > 0)
    counts = view_counts(np.zeros((1, 3)), frames)
    assert counts[0] == len(frames)


def test_ray_dataset_drops_masked_and_nonfinite_pixels():
    frame = make_frame(width=4, height=3)
    image = np.full((3, 4, 3), 0.5, np.float32)
    image[0, 0] = np.nan
    mask = np.ones((3, 4), bool)
    mask[2, 3] = False
    data = RayDataset([frame], [image], [mask])
    assert len(data) == 10 and data.dropped_nonfinite == 1
    batch = data.sample(5, torch.Generator().manual_seed(0))
    assert batch.rgb.shape == (5, 3) and torch.all(batch.near == frame.near)
    before = data.pixel_ids.clone()
    held = data.hold_out(3, seed=0)
    assert len(held) == 3 and len(data) == 7
    remaining = {tuple(d.tolist()) for d in data.batch(torch.arange(len(data))).directions}
    assert not any(tuple(d.tolist()) in remaining for d in held.directions)
    # the rest stay in pixel order, each with its own colour and ray
    assert torch.all(data.pixel_ids[1:] > data.pixel_ids[:-1])
    assert len(set(before.tolist()) - set(data.pixel_ids.tolist())) == 3
    rest = RayDataset([frame], [image], [mask]).batch(torch.searchsorted(before, data.pixel_ids))
    torch.testing.assert_close(data.batch(torch.arange(len(data))).directions, rest.directions)


def test_ray_dataset_makes_each_pixels_ray_as_the_frame_does():
    """Rays made when drawn are those of ``frame_rays`` for the same pixels, across frames of
    different sizes, intrinsics and bounds, masked pixels skipped."""
    rng = np.random.default_rng(7)
    frames = [look_at_frame((x, 0.3 * i, -4.0), name=f"v{i}", width=w, height=h, cx=w / 2.3,
                            cy=h / 1.7, near=0.2 + 0.1 * i, far=5.0 + i)
              for i, (x, w, h) in enumerate(((-1.0, 16, 12), (0.5, 9, 13), (1.0, 20, 5)))]
    images = [rng.random((f.height, f.width, 3)).astype(np.float32) for f in frames]
    masks = [rng.random((f.height, f.width)) > 0.3 for f in frames]
    data = RayDataset(frames, images, masks)
    everything = data.batch(torch.arange(len(data)))
    expected = [frame_rays(f) for f in frames]
    origins = torch.cat([o[torch.from_numpy(m.reshape(-1))] for (o, _), m in zip(expected, masks)])
    directions = torch.cat([d[torch.from_numpy(m.reshape(-1))]
                            for (_, d), m in zip(expected, masks)])
    torch.testing.assert_close(everything.origins, origins, rtol=0, atol=1e-7)
    torch.testing.assert_close(everything.directions, directions, rtol=0, atol=1e-7)
    counts = [int(m.sum()) for m in masks]
    torch.testing.assert_close(everything.near, torch.cat(
        [torch.full((n,), float(f.near)) for f, n in zip(frames, counts)]))
    torch.testing.assert_close(everything.far, torch.cat(
        [torch.full((n,), float(f.far)) for f, n in zip(frames, counts)]))
    torch.testing.assert_close(everything.rgb, torch.cat(
        [torch.from_numpy(i[m]) for i, m in zip(images, masks)]))
    # a drawn batch is the same rays as the whole set at those indices
    index = torch.tensor([len(data) - 1, 0, counts[0], counts[0] - 1])
    part = data.batch(index)
    torch.testing.assert_close(part.directions, everything.directions[index])
    torch.testing.assert_close(part.far, everything.far[index])


@pytest.mark.parametrize("count", [7, 1000, 300_001])
def test_int32_permutations_are_the_int64_ones_and_leave_the_same_random_stream(count):
    """The training set draws its permutations in int32 to halve their memory; the draws, and
    what a generator gives after them, must be those of the default int64."""
    generators = [torch.Generator().manual_seed(5) for _ in range(2)]
    wide = torch.randperm(count, generator=generators[0])
    narrow = torch.randperm(count, generator=generators[1], dtype=torch.int32)
    assert torch.equal(wide, narrow.long())
    assert torch.equal(torch.rand(4, generator=generators[0]),
                       torch.rand(4, generator=generators[1]))


def test_rays_through_points_are_the_pixels_they_fall_in_where_the_dataset_has_them():
    frames = [look_at_frame((x, 0.3, -4.0), name=f"v{i}", width=16, height=12, cx=8.0, cy=6.0)
              for i, x in enumerate((-1.0, 0.0, 1.0))]
    rng = np.random.default_rng(2)
    images = [rng.random((12, 16, 3)).astype(np.float32) for _ in frames]
    masks = [np.ones((12, 16), bool) for _ in frames]
    points = rng.uniform(-0.5, 0.5, (40, 3))
    points[0] = [60.0, 0.0, 0.0]                      # in no frame
    row, column, _, _ = pixel_of_points(frames[1].c2w_array, frames[1].fx, frames[1].fy,
                                        frames[1].cx, frames[1].cy, 16, 12, points[1:2])
    masks[1][row[0], column[0]] = False               # masked: no ray there
    data = RayDataset(frames, images, masks)
    rays, owner = data.rays_through(points)
    assert 0 not in owner
    assert np.bincount(owner, minlength=40)[1] == 2
    for ray_index, point in zip(range(len(owner)), owner):
        # the ray's pixel is the one the point falls in, in the frame whose centre it leaves
        origin = rays.origins[ray_index].double().numpy()
        frame = next(f for f in frames if np.allclose(f.c2w_array[:3, 3], origin, atol=1e-5))
        r, c, local, inside = pixel_of_points(frame.c2w_array, frame.fx, frame.fy, frame.cx,
                                              frame.cy, 16, 12, points[point:point + 1])
        assert inside[0]
        pixel_direction = frame.c2w_array[:3, :3] @ np.array(
            [(c[0] + 0.5 - frame.cx) / frame.fx, (r[0] + 0.5 - frame.cy) / frame.fy, 1.0])
        np.testing.assert_allclose(rays.directions[ray_index].double().numpy(),
                                   pixel_direction / np.linalg.norm(pixel_direction), atol=1e-6)
        np.testing.assert_allclose(rays.rgb[ray_index].numpy(),
                                   images[frames.index(frame)][r[0], c[0]])
    # held-out rays are no longer the dataset's: the points give fewer rays, never those
    held = data.hold_out(100, seed=1)
    after, _ = data.rays_through(points)
    held_directions = {tuple(np.round(d.tolist(), 6)) for d in held.directions}
    assert len(after) < len(rays)
    assert not any(tuple(np.round(d.tolist(), 6)) in held_directions for d in after.directions)


def test_deblurred_colours_stay_with_their_rays_through_every_selection():
    """The water fit's colour of a ray comes from the same pixel of the deblurred image as its
    training colour, after a hold-out, in a fixed subset and through surface points."""
    frames = [look_at_frame((x, 0.3, -4.0), name=f"v{i}", width=16, height=12, cx=8.0, cy=6.0)
              for i, x in enumerate((-1.0, 0.0, 1.0))]
    rng = np.random.default_rng(3)
    images = [rng.random((12, 16, 3)).astype(np.float32) for _ in frames]
    images[0][0, 0] = np.nan                           # dropped: the two must stay aligned
    masks = [np.ones((12, 16), bool) for _ in frames]
    masks[2][5, :] = False
    sharp = [image * 10.0 + 1.0 for image in images]   # a different colour, the same pixel
    data = RayDataset(frames, images, masks, deblurred=sharp)
    data.hold_out(50, seed=4)
    plain, deblurred = data.fixed_subset(200, seed=5), data.fixed_subset(200, seed=5,
                                                                        deblurred=True)
    torch.testing.assert_close(plain.directions, deblurred.directions)
    torch.testing.assert_close(deblurred.rgb, plain.rgb * 10.0 + 1.0)
    points = rng.uniform(-0.5, 0.5, (30, 3))
    (through, _), (through_sharp, _) = data.rays_through(points), data.rays_through(points, True)
    assert len(through) > 0
    torch.testing.assert_close(through_sharp.rgb, through.rgb * 10.0 + 1.0)
    # made one at a time by an iterator, they are the same colours
    lazily = RayDataset(frames, images, masks, deblurred=iter(sharp))
    lazily.hold_out(50, seed=4)
    torch.testing.assert_close(lazily.fixed_subset(200, seed=5, deblurred=True).rgb,
                               deblurred.rgb)
    # without deblurred images the option gives the training colour
    bare = RayDataset(frames, images, masks)
    torch.testing.assert_close(bare.fixed_subset(50, 6, deblurred=True).rgb,
                               bare.fixed_subset(50, 6).rgb)


# ---------------------------------------------------------------------------------- contraction

@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-50, 50), min_size=3, max_size=3))
def test_contraction_is_bounded_and_invertible(values):
    u = torch.tensor([values], dtype=torch.float64)
    v = contract(u)
    assert float(v.abs().max()) < 2.0
    if float(u.abs().max()) <= 1.0:
        assert torch.allclose(v, u)
    assert torch.allclose(uncontract(v), u, rtol=1e-6, atol=1e-6)


def test_grid_vertices_map_back_to_grid_coordinates():
    model = SeaThruModel(TrainConfig.from_dict(SMALL), scene_dict())
    dims = [5, 4, 3]
    points = grid_vertices(model.box, dims).reshape(-1, 3)
    g = model.box.to_grid(points)
    expected = torch.stack(torch.meshgrid(torch.linspace(-1, 1, 3), torch.linspace(-1, 1, 4),
                                          torch.linspace(-1, 1, 5), indexing="ij")[::-1], -1)
    inner = expected.reshape(-1, 3).abs().amax(-1) < 0.99
    assert torch.allclose(g[inner], expected.reshape(-1, 3)[inner], atol=1e-5)


# -------------------------------------------------------------------------------------- sampler

@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 24), st.floats(0.0, 1.0))
def test_sample_pdf_gives_sorted_contiguous_intervals_inside_the_bounds(seed, samples, mix):
    gen = torch.Generator().manual_seed(seed)
    rays = 6
    near = torch.rand(rays, generator=gen) + 0.1
    far = near + torch.rand(rays, generator=gen) * 20 + 0.01
    split = near + (far - near) * torch.rand(rays, generator=gen)
    edges = candidate_edges(near, far, split, 12, 4)
    assert torch.all(edges[:, 1:] >= edges[:, :-1])
    assert torch.allclose(edges[:, 0], near) and torch.allclose(edges[:, -1], far)
    weights = torch.rand(rays, 16, generator=gen) ** 4
    weights[0] = 0.0  # a ray with no weight at all
    jitter = torch.rand(rays, samples - 1, generator=gen) if samples > 1 else None
    t = sample_pdf(edges, weights, samples, mix, jitter)
    assert t.shape == (rays, samples + 1)
    assert torch.all(t[:, 1:] >= t[:, :-1])
    assert torch.equal(t[:, 0], edges[:, 0]) and torch.equal(t[:, -1], edges[:, -1])
    s = normalised_distance(t, near, far, split, 0.75)
    assert float(s.min()) >= 0.0 and float(s.max()) <= 1.0


def test_sample_pdf_concentrates_samples_where_the_weight_is():
    edges = torch.linspace(1.0, 9.0, 33)[None]
    weights = torch.zeros(1, 32)
    weights[0, 20] = 1.0
    t = sample_pdf(edges, weights, 16, 0.1, None)
    mids = 0.5 * (t[0, 1:] + t[0, :-1])
    inside = ((mids >= edges[0, 20]) & (mids <= edges[0, 21])).sum()
    assert int(inside) >= 12


def test_stratified_and_merged_edges_stay_sorted():
    gen = torch.Generator().manual_seed(1)
    edges = candidate_edges(torch.ones(4), torch.full((4,), 10.0), torch.full((4,), 5.0), 8, 4)
    jittered = stratified_edges(edges, torch.rand(4, 11, generator=gen))
    assert torch.all(jittered[:, 1:] >= jittered[:, :-1])
    merged = merge_edges(jittered, sample_pdf(jittered, torch.rand(4, 12, generator=gen), 6,
                                              0.0, None))
    assert merged.shape == (4, 13 + 7 - 2) and torch.all(merged[:, 1:] >= merged[:, :-1])


def test_occupancy_weights_match_nerf_weights_in_float64():
    gen = torch.Generator().manual_seed(2)
    sigma = torch.rand(5, 9, generator=gen, dtype=torch.float64) * 3
    edges = torch.cumsum(torch.rand(5, 10, generator=gen, dtype=torch.float64), -1)
    reference, _ = nerf_weights(sigma, edges[:, 1:] - edges[:, :-1])
    assert torch.allclose(occupancy_weights(edges, sigma), reference, atol=1e-12)


def test_nearest_lookup_matches_grid_sample_nearest():
    gen = torch.Generator().manual_seed(3)
    volume = torch.rand(1, 1, 5, 6, 7, generator=gen)
    g = torch.rand(100, 3, generator=gen) * 2 - 1
    expected = torch.nn.functional.grid_sample(volume, g.reshape(1, -1, 1, 1, 3), mode="nearest",
                                               align_corners=True).reshape(-1)
    assert torch.allclose(lookup_nearest(volume, g), expected)



@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("points", [1, 4096, 9001])
def test_trilinear_lookup_matches_grid_sample_and_its_gradient_in_float64(threads, points):
    gen = torch.Generator().manual_seed(points + threads)
    volume = torch.rand(1, 2, 5, 6, 7, generator=gen, dtype=torch.float64, requires_grad=True)
    g = torch.rand(points, 3, generator=gen, dtype=torch.float64) * 2.6 - 1.3  # some outside
    weights = torch.rand(points, 2, generator=gen, dtype=torch.float64)
    expected = torch.nn.functional.grid_sample(
        volume, g.reshape(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border",
        align_corners=True).reshape(2, -1).t()
    expected_grad, = torch.autograd.grad((expected * weights).sum(), volume)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        values = trilinear_lookup(volume, g)
        grad, = torch.autograd.grad((values * weights).sum(), volume)
    finally:
        torch.set_num_threads(before)
    assert values.shape == (points, 2)
    torch.testing.assert_close(values, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(grad, expected_grad, rtol=0, atol=1e-12)

# --------------------------------------------------------------------------------------- losses

def test_transmittance_prior_is_minimal_at_zero_and_one():
    t = torch.linspace(0, 1, 101)
    values = torch.stack([transmittance_prior(x[None]) for x in t])
    assert float(values[0]) == pytest.approx(0.0, abs=1e-6)
    assert float(values[-1]) == pytest.approx(0.0, abs=1e-6)
    assert torch.all(values[1:-1] > 1e-3)
    assert int(values.argmax()) == 50
    assert torch.allclose(values, values.flip(0), atol=1e-5)


def test_reconstruction_loss_matches_a_float64_reference_and_its_gradient():
    gen = torch.Generator().manual_seed(4)
    pred = (torch.rand(7, 3, generator=gen, dtype=torch.float64) + 0.01).requires_grad_()
    target = torch.rand(7, 3, generator=gen, dtype=torch.float64)
    loss = reconstruction_loss(pred, target, 1e-3)
    p, tg = pred.detach().numpy(), target.numpy()
    assert float(loss.detach()) == pytest.approx(float(np.mean(((p - tg) / (p + 1e-3)) ** 2)), rel=1e-12)
    loss.backward()
    expected = 2 * (p - tg) / (p + 1e-3) ** 2 / p.size  # the denominator is stop-gradient
    assert np.allclose(pred.grad.numpy(), expected, rtol=1e-10)
    assert float(reconstruction_loss(target, target)) == 0.0
    mask = torch.tensor([1, 0, 1, 1, 0, 1, 1], dtype=torch.bool)
    masked = reconstruction_loss(pred.detach(), target, 1e-3, mask)
    assert float(masked) == pytest.approx(float(reconstruction_loss(pred.detach()[mask],
                                                                    target[mask], 1e-3)))


def test_sparse_depth_loss_is_the_mean_relative_l1_error_and_pulls_depth_to_the_target():
    gen = torch.Generator().manual_seed(3)
    target = torch.rand(50, generator=gen, dtype=torch.float64) * 4 + 0.5
    depth = (target * (1 + 0.3 * torch.randn(50, generator=gen, dtype=torch.float64))
             ).requires_grad_(True)
    loss = sparse_depth_loss(depth, target)
    reference = sum(abs(d - t) / t for d, t in zip(depth.tolist(), target.tolist())) / 50
    assert float(loss) == pytest.approx(reference, rel=1e-12)
    loss.backward()
    # descent moves every depth towards its target, the nearer points the more
    assert torch.all(torch.sign(depth.grad) == torch.sign(depth.detach() - target))
    torch.testing.assert_close(depth.grad.abs(), 1 / (50 * target))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 12))
def test_distortion_loss_matches_the_quadratic_definition(seed, samples):
    gen = torch.Generator().manual_seed(seed)
    w = torch.rand(3, samples, generator=gen, dtype=torch.float64)
    s = torch.cumsum(torch.rand(3, samples + 1, generator=gen, dtype=torch.float64), -1)
    mids = 0.5 * (s[:, 1:] + s[:, :-1])
    reference = (w[:, :, None] * w[:, None, :] * (mids[:, :, None] - mids[:, None, :]).abs()
                 ).sum((1, 2)) + (w ** 2 * (s[:, 1:] - s[:, :-1])).sum(-1) / 3
    assert float(distortion_loss(w, s)) == pytest.approx(float(reference.mean()), rel=1e-10)


def test_total_variation_is_zero_for_constant_and_positive_otherwise():
    assert float(total_variation_3d(torch.ones(1, 1, 4, 5, 6), None)) == 0.0
    gen = torch.Generator().manual_seed(0)
    vol = torch.rand(1, 1, 4, 5, 6, generator=gen)
    assert float(total_variation_3d(vol, None)) > 0
    assert float(total_variation_3d(vol, 50, gen)) > 0


# ------------------------------------------------------------------------------- medium, model

def test_medium_modes():
    medium = Medium("global", 0.3, (0.1, 0.2, 0.3))
    dirs = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    attn, bs, colour = medium(dirs)
    assert torch.allclose(attn, torch.full_like(attn, 0.3), atol=1e-5)
    assert torch.allclose(colour[0], torch.tensor([0.1, 0.2, 0.3]), atol=1e-4)
    medium.set_mode("view")
    attn_v, _, colour_v = medium(dirs)  # starts at the global values
    assert torch.allclose(attn_v, attn) and torch.allclose(colour_v, colour)
    medium.set_mode("off")
    assert all(float(x.abs().max()) == 0.0 for x in medium(dirs))
    with pytest.raises(ValueError):
        medium.set_mode("soup")


def scene_dict() -> dict:
    return {"box_min": [-1.0, -1.0, -0.5], "box_max": [1.0, 1.0, 1.0], "near": 0.5, "far": 6.0,
            "typical_range": 2.5, "normalisation": {"centre": [0.0, 0.0, 0.0], "scale": 1.0},
            "c_med_init": [0.1, 0.2, 0.3]}


def random_rays(count=32, seed=0):
    gen = torch.Generator().manual_seed(seed)
    origins = torch.tensor([0.0, -2.5, 0.8]) + 0.1 * torch.randn(count, 3, generator=gen)
    dirs = torch.nn.functional.normalize(torch.tensor([0.0, 1.0, -0.3])
                                         + 0.3 * torch.randn(count, 3, generator=gen), dim=-1)
    return origins, dirs, torch.full((count,), 0.5), torch.full((count,), 6.0)


def test_medium_off_renders_plain_nerf_exactly():
    model = SeaThruModel(TrainConfig.from_dict({**SMALL, "medium": "off"}), scene_dict())
    with torch.no_grad():
        model.field.density.coarse.fill_(0.5)
        out = model(*random_rays()).render
    assert torch.equal(out.rgb, out.restored)
    assert float(out.backscatter.abs().max()) == 0.0
    assert float(out.opacity.min()) > 0.1


def test_model_survives_a_weights_only_round_trip():
    model = SeaThruModel(TrainConfig.from_dict(SMALL), scene_dict())
    with torch.no_grad():
        for p in model.field.parameters():
            p.add_(0.05 * torch.randn_like(p))
    model.set_stage(2)  # grids of another shape than a fresh model has
    buffer = io.BytesIO()
    torch.save(model.export(), buffer)
    buffer.seek(0)
    loaded = SeaThruModel.from_checkpoint(torch.load(buffer, weights_only=True))
    model.eval()
    rays = random_rays()
    with torch.no_grad():
        a, b = model(*rays).render, loaded(*rays).render
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth_mean, b.depth_mean)
    assert loaded.water_parameters() == model.water_parameters()


def test_the_ray_interval_scales_the_camera_bounds():
    widened = SeaThruModel(TrainConfig.from_dict({**SMALL, "far_factor": 2.0}), scene_dict())
    plain = SeaThruModel(TrainConfig.from_dict(SMALL), scene_dict())
    with torch.no_grad():
        widened.field.density.raw.add_(torch.randn_like(widened.field.density.raw).mul_(0.5))
    plain.load_state_dict(widened.state_dict())
    widened.eval()
    plain.eval()
    origins, dirs, near, far = random_rays()
    with torch.no_grad():
        a = widened(origins, dirs, near, far).render
        b = plain(origins, dirs, near, 2.0 * far).render
        c = plain(origins, dirs, near, far).render
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth_median, b.depth_median)
    assert not torch.equal(a.rgb, c.rgb)
    near_w, far_w = widened.ray_interval(near, far)
    assert torch.equal(near_w, near) and torch.equal(far_w, 2.0 * far)


def test_far_factor_below_one_is_refused():
    with pytest.raises(SettingsError, match="far_factor"):
        TrainConfig.from_dict({"sampler": {"far_factor": 0.5}})


@pytest.mark.parametrize("medium, share, spread, expected", [
    ("auto", 0.2, 0.02, AUTO_FAR_FACTOR),   # open water of one colour: far seabed past the bound
    ("global", 0.2, 0.5, AUTO_FAR_FACTOR),  # global as asked, whatever the spread
    ("auto", 0.2, 0.3, 1.0),                # starts veiling: the field would fill the open water
    ("veiling", 0.2, 0.02, 1.0),
    ("off", 0.2, 0.02, 1.0),                # no water: no veiling light to go by
    ("auto", 0.01, 0.02, 1.0),              # hardly any open water: the sparse points bound it
])
def test_auto_far_factor_follows_the_open_water_and_the_starting_medium(medium, share, spread,
                                                                        expected):
    config = TrainConfig.from_dict({**SMALL, "medium": medium, "far_factor": 0.0})
    scene = {**scene_dict(), "open_water_image_share": share,
             "open_water_direction_spread": spread}
    choice = far_bound_choice(config, scene)
    assert choice["requested"] == "auto" and choice["chosen"] == expected and choice["reason"]
    model = SeaThruModel(config, scene)
    near, far = random_rays()[2:]
    assert torch.equal(model.ray_interval(near, far)[1], expected * far)
    # a model reloaded from its export samples as far as it was trained to
    assert SeaThruModel.from_checkpoint(model.export()).far_bound == model.far_bound


def test_a_widened_far_bound_leaves_the_near_candidates_as_they_were(monkeypatch):
    """The candidates are linear up to the box's exit or the camera's far bound, whichever is
    nearer, with any far factor: past the bound they go linear in 1/t."""
    import seathru.nerf.model as model_module

    seen = []
    original = model_module.candidate_edges

    def recording(near, far, t_split, *args):
        seen.append((far.clone(), t_split.clone()))
        return original(near, far, t_split, *args)

    monkeypatch.setattr(model_module, "candidate_edges", recording)
    origins, dirs, near, _ = random_rays()
    camera_far = torch.full_like(near, 2.0)   # the box's exit lies past it on these rays
    edges = {}
    for factor in (1.0, 3.0):
        model = SeaThruModel(TrainConfig.from_dict({**SMALL, "far_factor": factor}), scene_dict())
        model.eval()
        seen.clear()
        with torch.no_grad():
            model(origins, dirs, near, camera_far)
        far, t_split = seen[-1]
        assert torch.equal(far, factor * camera_far)
        edges[factor] = original(near, far, t_split, SMALL["candidates_linear"], 0)
    box_exit = model._split_distance(origins, dirs, near)
    assert (box_exit > camera_far).any()
    assert torch.equal(edges[1.0], edges[3.0])   # the linear candidates are the same


def test_an_explicit_far_factor_is_kept():
    config = TrainConfig.from_dict({**SMALL, "far_factor": 1.5, "medium": "veiling"})
    choice = far_bound_choice(config, {**scene_dict(), "open_water_image_share": 0.0})
    assert choice == {"requested": 1.5, "chosen": 1.5,
                      "reason": "sampler.far_factor 1.5 (0: auto)"}


def test_upsampling_the_grids_keeps_the_rendering():
    model = SeaThruModel(TrainConfig.from_dict(SMALL), scene_dict())
    with torch.no_grad():
        model.field.density.raw.add_(torch.randn_like(model.field.density.raw).mul_(0.3))
    model.eval()
    rays = random_rays(64)
    with torch.no_grad():
        before = model(*rays).render.rgb
        model.set_stage(1)
        after = model(*rays).render.rgb
    assert model.field.density.raw.shape[-1] > 16
    assert float((before - after).abs().max()) < 0.05


def test_water_parameters_view_mode_reports_range():
    model = SeaThruModel(TrainConfig.from_dict({**SMALL, "medium": "view"}), scene_dict())
    with torch.no_grad():
        model.medium.view_net[-1].weight.normal_(0, 0.5)
    water = model.water_parameters(torch.nn.functional.normalize(torch.randn(50, 3), dim=-1))
    assert water["mode"] == "view"
    for key in ("sigma_attn", "sigma_bs", "c_med"):
        assert all(lo <= m <= hi for lo, m, hi in zip(water["min"][key], water[key],
                                                      water["max"][key]))


def test_render_frame_shapes_and_chunk_invariance():
    model = SeaThruModel(TrainConfig.from_dict(SMALL), scene_dict())
    frame = look_at_frame((0.0, -2.5, 0.8), target=(0.0, 0.0, 0.2), width=10, height=6,
                          fx=8, fy=8, cx=5, cy=3, near=0.5, far=6.0)
    full = render_frame(model, frame, chunk=7)
    big = render_frame(model, frame, chunk=8192)
    assert full["rgb"].shape == (6, 10, 3) and full["depth"].shape == (6, 10)
    assert set(full) == {"rgb", "restored", "direct", "backscatter", "depth", "opacity",
                         "direct_share"}
    assert full["direct_share"].shape == (6, 10, 3)
    # a uniform object colour c reaches the camera as direct_share * c, at most its opacity
    assert np.all(full["direct_share"] <= full["opacity"][..., None] + 1e-6)
    for key in full:
        assert full[key].dtype == np.float32
        assert np.allclose(full[key], big[key], atol=1e-6)
    half = render_frame(model, frame, downscale=2)
    assert half["rgb"].shape == (3, 5, 3)
    assert np.allclose(full["rgb"], full["direct"] + full["backscatter"], atol=1e-6)


def test_config_round_trip_and_validation():
    config = TrainConfig.from_dict({"steps": 10, "medium": {"mode": "off"}})
    assert config.medium.mode == "off" and config.steps == 10
    assert TrainConfig.from_dict(config.to_dict()) == config
    identity = config.identity()
    assert "max_minutes" not in identity and identity["medium.mode"] == "off"
    with pytest.raises(SettingsError, match="sampler.kind=hierarchical"):
        TrainConfig.from_dict({"field": {"kind": "mlp"}, "sampler": {"kind": "occupancy"}})
    with pytest.raises(SettingsError, match="medium.mode: 'soup' is not one of"):
        TrainConfig.from_dict({"medium": {"mode": "soup"}})


def test_flat_configs_of_version_1_model_files_still_load():
    flat = {"field": "grid", "sampler": "occupancy", "medium": "view", "medium_sigma_init": 0.2,
            "density_res": [8, 12, 16], "lr": 0.01, "steps": 7, "recon_eps": 1e-2,
            "removed_long_ago": 3}
    config = TrainConfig.from_dict(flat)
    assert (config.field.kind, config.sampler.kind, config.medium.mode) == \
        ("grid", "occupancy", "view")
    assert config.medium.sigma_init == 0.2 and config.field.density_res == [8, 12, 16]
    assert config.optim.lr == 0.01 and config.steps == 7 and config.loss.recon_eps == 1e-2


def test_presets_sit_beneath_explicit_settings():
    fast = TrainConfig.from_dict({"preset": "fast"})
    balanced = TrainConfig.from_dict({})
    quality = TrainConfig.from_dict({"preset": "quality"})
    assert max(fast.field.density_res) < max(balanced.field.density_res) \
        < max(quality.field.density_res)
    assert fast.sampler.samples_per_ray < balanced.sampler.samples_per_ray \
        < quality.sampler.samples_per_ray
    mine = TrainConfig.from_dict({"preset": "fast", "sampler": {"samples_per_ray": 20}})
    assert mine.sampler.samples_per_ray == 20 and mine.field.density_res == fast.field.density_res
    paper = TrainConfig.from_dict({"preset": "paper"})
    assert (paper.field.kind, paper.sampler.kind, paper.medium.mode) == \
        ("mlp", "hierarchical", "view")
    assert TrainConfig.from_dict(paper.to_dict()) == paper


def test_veiling_water_varies_only_its_colour_with_direction():
    medium = Medium("veiling", 0.3, (0.1, 0.2, 0.3), colour_max=1.0)
    with torch.no_grad():
        for param in medium.view_net.parameters():
            param.normal_(0.0, 0.5)
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator()
                                                     .manual_seed(0)), dim=-1)
    attn, bs, colour = medium(dirs)
    assert torch.allclose(attn, attn[:1].expand_as(attn))
    assert torch.allclose(bs, bs[:1].expand_as(bs))
    assert float(colour.std(0).max()) > 1e-3
    medium.set_mode("view")          # switching between directional modes keeps the network
    assert float(medium(dirs)[0].std(0).max()) > 1e-3


def test_auto_starts_veiling_only_where_the_open_water_changes_with_direction():
    from seathru import settings as typed
    from seathru.nerf.model import initial_medium_mode

    config = typed.from_mapping(TrainConfig, {})
    spread = config.medium.auto_veiling_spread
    assert initial_medium_mode(config, {"open_water_direction_spread": 2 * spread}) == "veiling"
    assert initial_medium_mode(config, {"open_water_direction_spread": spread / 2}) == "global"
    assert initial_medium_mode(config, {}) == "global"
    fixed = typed.from_mapping(TrainConfig, {"medium": {"mode": "global"}})
    assert initial_medium_mode(fixed, {"open_water_direction_spread": 1.0}) == "global"


def test_view_dependent_colour_starts_from_the_view_independent_colours():
    from seathru.nerf.fields import ColourDecoder

    torch.manual_seed(0)
    features = torch.randn(64, 12)
    dirs = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    auto = ColourDecoder(12, 8, "auto", 1.5)
    assert not auto.uses_view      # auto trains without the direction until it is decided
    start = auto(features, dirs)
    auto.set_view_enabled(True)
    assert auto.uses_view
    assert torch.equal(auto(features, dirs), start)     # zero view weights: same colours
    with torch.no_grad():
        auto.view.weight.normal_()
    assert not torch.allclose(auto(features, dirs), start)
    auto.set_view_enabled(False)
    assert torch.equal(auto(features, dirs), start)     # switched off: the direction is ignored
    with pytest.raises(ValueError, match="auto"):
        ColourDecoder(12, 8, "on", 1.5).set_view_enabled(False)
    assert not ColourDecoder(12, 8, "off", 1.5).uses_view


@pytest.mark.parametrize("chosen", [True, False])
def test_the_view_decision_survives_a_weights_only_round_trip(chosen):
    model = SeaThruModel(TrainConfig.from_dict(SMALL), scene_dict())
    assert model.config.field.view_dependent_colour == "auto"
    with torch.no_grad():
        model.field.decoder.view.weight.normal_()
    model.field.decoder.set_view_enabled(chosen)
    buffer = io.BytesIO()
    torch.save(model.export(), buffer)
    buffer.seek(0)
    loaded = SeaThruModel.from_checkpoint(torch.load(buffer, weights_only=True))
    assert loaded.field.uses_view is chosen
    model.eval()
    rays = random_rays()
    with torch.no_grad():
        assert torch.equal(model(*rays).render.rgb, loaded(*rays).render.rgb)


def test_models_saved_with_the_view_weights_in_the_first_layer_still_load():
    model = SeaThruModel(TrainConfig.from_dict({**SMALL, "view_dependent_colour": True}),
                         scene_dict())
    with torch.no_grad():
        model.field.decoder.view.weight.normal_()
    exported = model.export()
    state = dict(exported["state_dict"])
    # the layout before the decoder's separate view layer: features then SH in one matrix
    state["field.decoder.net.0.weight"] = torch.cat(
        [state["field.decoder.net.0.weight"], state.pop("field.decoder.view.weight")], dim=1)
    loaded = SeaThruModel.from_checkpoint({**exported, "state_dict": state})
    model.eval()
    rays = random_rays()
    with torch.no_grad():
        assert torch.equal(model(*rays).render.rgb, loaded(*rays).render.rgb)
