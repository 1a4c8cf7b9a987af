"""Benchmark of seathru.nerf.rendering (a script, not a test).

    python benchmarks/bench_rendering.py [--threads 1] [--quick]

1. Throughput of render_seathru(method="exact") in rays/s for 1024/4096/16384 rays x 64 samples,
   forward only and forward+backward, on CPU (and CUDA when available), side by side with the
   paper discretisation and plain NeRF compositing on the same inputs.
2. Accuracy vs sample count, all in one run against a float64 reference of the continuous model:
   - "official": the SeaThru-NeRF approach as described in the brief: paper discretisation, extra
     stop-gradient medium-only fenceposts spread uniformly through [first, last] sample, no water
     before the first or after the last sample;
   - "paper": the paper discretisation on the samples only, same water handling;
   - "paper + closed-form water outside": the paper discretisation with water_before/after, which
     separates the discretisation error from the missing water outside the sampled range;
   - "exact": the closed form (water before/after included, no extra samples).
   Scene A: object fields piecewise constant on a 16-interval grid (sample counts are multiples
   of 16, so the samples resolve the field and only the rendering equation differs).
   Scene B: a continuous field (fog bump + a 0.3 m thick surface at a random depth) queried at
   the sample midpoints, as a NeRF does; this adds a field-sampling error shared by all methods.
   Both scenes mix rays that hit a surface with rays that see open water to infinity.

Writes the printed tables to benchmarks/results/rendering.md.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import torch

from seathru.nerf.rendering import nerf_weights, render_seathru
from seathru.io.atomic import write_text

from machine import cpu_name

RESULTS = Path(__file__).resolve().parent / "results" / "rendering.md"
ATTN = (0.40, 0.12, 0.07)    # per metre, red attenuates fastest
BACKSCATTER = (0.30, 0.18, 0.12)
WATER = (0.05, 0.25, 0.35)
NEAR, FAR = 0.2, 8.0


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_call(fn, device: torch.device, repeats: int) -> float:
    """Median wall time of fn() in seconds after one warm-up call."""
    fn()
    synchronize(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return sorted(times)[len(times) // 2]


def medium(rays: int, dtype, device, grad=False):
    make = lambda v: torch.tensor(v, dtype=dtype, device=device).expand(rays, 3).clone().requires_grad_(grad)
    return make(ATTN), make(BACKSCATTER), make(WATER)


def random_batch(rays: int, samples: int, device: torch.device, grad: bool, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    sigma = (torch.rand(rays, samples, generator=gen) * 4).to(device).requires_grad_(grad)
    rgb = torch.rand(rays, samples, 3, generator=gen).to(device).requires_grad_(grad)
    edges = (NEAR + torch.cumsum(torch.rand(rays, samples + 1, generator=gen) * 0.2, dim=1)).to(device)
    return (sigma, rgb, edges) + medium(rays, torch.float32, device, grad)


def plain_nerf(sigma, rgb, edges, *_):
    weights, _ = nerf_weights(sigma, edges[:, 1:] - edges[:, :-1])
    return (weights[..., None] * rgb).sum(dim=1)


RENDERERS = {
    "exact": lambda *a: render_seathru(*a).rgb,
    "paper": lambda *a: render_seathru(*a, method="paper").rgb,
    "plain NeRF": plain_nerf,
}


def throughput_table(devices, ray_counts, samples, repeats) -> list[str]:
    lines = [f"### Throughput, {samples} samples per ray (rays/s, median of {repeats})", "",
             "| device | rays | pass | exact | paper | plain NeRF | exact / paper time |",
             "|---|---:|---|---:|---:|---:|---:|"]
    print("\n".join(lines), flush=True)
    for device in devices:
        for rays in ray_counts:
            for backward in (False, True):
                inputs = random_batch(rays, samples, device, grad=backward)
                rates = {}
                for name, render in RENDERERS.items():
                    if backward:
                        def step(render=render):
                            render(*inputs).sum().backward()
                    else:
                        def step(render=render):
                            with torch.no_grad():
                                render(*inputs)
                    rates[name] = rays / time_call(step, device, repeats)
                lines.append(f"| {device.type} | {rays} | {'fwd+bwd' if backward else 'fwd'} | "
                             f"{rates['exact']:,.0f} | {rates['paper']:,.0f} | {rates['plain NeRF']:,.0f} | "
                             f"{rates['paper'] / rates['exact']:.2f} |")
                print(lines[-1], flush=True)
    return lines


# --------------------------------------------------------------------------------------------
# accuracy
# --------------------------------------------------------------------------------------------

def official_render(sigma, rgb, edges, attn, bs, cmed, extra: int):
    """Paper discretisation plus `extra` medium-only fenceposts spread uniformly over the sampled
    range (stop-gradient; the object field stays as queried), no water outside the samples."""
    rays, samples = sigma.shape
    frac = torch.linspace(0, 1, extra + 2, dtype=edges.dtype, device=edges.device)[1:-1]
    first, last = edges[:, :1], edges[:, -1:]
    extra_edges = (first + (last - first) * frac).detach()
    merged, _ = torch.sort(torch.cat([edges, extra_edges], dim=1), dim=1)
    mids = 0.5 * (merged[:, 1:] + merged[:, :-1])
    index = (torch.searchsorted(edges.contiguous(), mids.contiguous(), right=True) - 1).clamp(0, samples - 1)
    sigma_m = torch.gather(sigma, 1, index)
    rgb_m = torch.gather(rgb, 1, index[..., None].expand(-1, -1, 3))
    return render_seathru(sigma_m, rgb_m, merged, attn, bs, cmed, method="paper",
                          water_before=False, water_after=False).rgb


def methods(extra: int):
    return {
        f"official (+{extra} medium samples)": lambda *a: official_render(*a, extra=extra),
        "paper (samples only)": lambda *a: render_seathru(*a, method="paper", water_before=False,
                                                          water_after=False).rgb,
        "paper + closed-form water outside": lambda *a: render_seathru(*a, method="paper").rgb,
        "exact (closed form)": lambda *a: render_seathru(*a).rgb,
    }


def uniform_edges(rays: int, intervals: int, dtype) -> torch.Tensor:
    return torch.linspace(NEAR, FAR, intervals + 1, dtype=dtype).expand(rays, -1).contiguous()


def scene_a(rays: int, seed: int = 1):
    """Piecewise-constant fields on a 16-interval grid; half the rays hit an opaque surface."""
    gen = torch.Generator().manual_seed(seed)
    sigma = torch.rand(rays, 16, generator=gen, dtype=torch.float64) * 0.3
    sigma[torch.rand(rays, 16, generator=gen, dtype=torch.float64) < 0.5] = 0.0
    hit = torch.arange(rays) % 2 == 0
    surface = torch.randint(4, 16, (rays,), generator=gen)
    sigma[hit, surface[hit]] = 30.0
    rgb = torch.rand(rays, 16, 3, generator=gen, dtype=torch.float64)

    def at(samples: int):
        factor = samples // 16
        return sigma.repeat_interleave(factor, 1), rgb.repeat_interleave(factor, 1), uniform_edges(rays, samples, torch.float64)

    return at


def continuous_field(t: torch.Tensor, depth: torch.Tensor):
    """Density and colour at distances t (R, K); depth (R, 1) of a 0.3 m thick surface (inf: none)."""
    surface = ((t >= depth) & (t < depth + 0.3)).to(t.dtype) * 40.0
    fog = 0.8 * torch.exp(-(((t - 1.5) / 0.25) ** 2))
    sigma = surface + fog
    surface_rgb = torch.stack([0.8 + 0.1 * torch.sin(3 * t), 0.5 + 0.1 * torch.cos(2 * t), 0.3 + 0 * t], -1)
    fog_rgb = torch.tensor([0.9, 0.85, 0.8], dtype=t.dtype).expand_as(surface_rgb)
    share = surface / torch.where(sigma > 0, sigma, torch.ones_like(sigma))
    rgb = share[..., None] * surface_rgb + (1 - share[..., None]) * fog_rgb
    return sigma, rgb


def scene_b(rays: int, seed: int = 2):
    gen = torch.Generator().manual_seed(seed)
    depth = 2.0 + 5.0 * torch.rand(rays, 1, generator=gen, dtype=torch.float64)
    depth[1::2] = float("inf")

    def at(samples: int):
        edges = uniform_edges(rays, samples, torch.float64)
        sigma, rgb = continuous_field(0.5 * (edges[:, 1:] + edges[:, :-1]), depth)
        return sigma, rgb, edges

    def reference(intervals: int):
        """Exact float64 rendering on a fine grid with the surface boundaries as edges."""
        fine = torch.cat([uniform_edges(rays, intervals, torch.float64),
                          depth.clamp(max=FAR), (depth + 0.3).clamp(max=FAR)], dim=1)
        fine, _ = torch.sort(fine, dim=1)
        out = []
        for chunk in range(0, rays, 16):
            e = fine[chunk:chunk + 16]
            sigma, rgb = continuous_field(0.5 * (e[:, 1:] + e[:, :-1]), depth[chunk:chunk + 16])
            out.append(render_seathru(sigma, rgb, e, *medium(e.shape[0], torch.float64, "cpu")).rgb)
        return torch.cat(out)

    return at, reference


def accuracy_table(title: str, at, reference: torch.Tensor, sample_counts, extra, timing_rays, repeats):
    rays = reference.shape[0]
    hit = torch.arange(rays) % 2 == 0
    lines = [f"### {title}", "",
             "| samples | method | max abs err, surface rays | max abs err, open-water rays | "
             f"mean abs err | fwd+bwd ms / {timing_rays} rays |",
             "|---:|---|---:|---:|---:|---:|"]
    print("\n".join(lines), flush=True)
    for samples in sample_counts:
        sigma, rgb, edges = at(samples)
        for name, render in methods(extra).items():
            inputs = (sigma.float(), rgb.float(), edges.float()) + medium(rays, torch.float32, "cpu")
            error = (render(*inputs).double() - reference).abs()
            repeat = lambda x: x[torch.arange(timing_rays) % rays].detach().clone()
            timed = [repeat(x).requires_grad_(k in (0, 1, 3, 4, 5)) for k, x in enumerate(inputs)]

            def step(render=render):
                render(*timed).sum().backward()

            ms = 1e3 * time_call(step, torch.device("cpu"), repeats)
            lines.append(f"| {samples} | {name} | {error[hit].max():.2e} | {error[~hit].max():.2e} | "
                         f"{error.mean():.2e} | {ms:.1f} |")
            print(lines[-1], flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (at most 2)")
    parser.add_argument("--quick", action="store_true", help="fewer sizes and repeats (smoke run)")
    parser.add_argument("--no-write", action="store_true", help=f"do not write {RESULTS.name}")
    parser.add_argument("--out", type=Path, default=RESULTS, help="where the tables are written")
    parser.add_argument("--throughput-only", action="store_true",
                        help="skip the accuracy tables (CPU, device-independent)")
    args = parser.parse_args()
    threads = max(1, min(args.threads, 2))
    torch.set_num_threads(threads)

    devices = [torch.device("cpu")] + ([torch.device("cuda")] if torch.cuda.is_available() else [])
    header = [
        "## Rendering benchmark (`benchmarks/bench_rendering.py`)", "",
        f"- CPU: {cpu_name()}, torch threads: {threads}",
        f"- torch {torch.__version__}, Python {platform.python_version()}",
        f"- CUDA: {torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'not available'}",
        "- float32 renderers; references in float64", "",
    ]
    print("\n".join(header), flush=True)
    ray_counts = [1024, 4096] if args.quick else [1024, 4096, 16384]
    repeats = 2 if args.quick else 5
    lines = header + throughput_table(devices, ray_counts, 64, repeats) + [""]
    if args.throughput_only:
        if not args.no_write:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            write_text(args.out, "\n".join(lines))
            print(f"wrote {args.out}")
        return

    counts = [16, 32, 64] if args.quick else [16, 32, 64, 128]
    extra, rays, timing_rays = 128, 256, 4096
    at_a = scene_a(rays)
    sigma, rgb, edges = at_a(16)
    reference_a = render_seathru(sigma, rgb, edges, *medium(rays, torch.float64, "cpu")).rgb
    lines += accuracy_table("Accuracy, scene A: field piecewise constant on the samples (rendering error only)",
                            at_a, reference_a, counts, extra, timing_rays, repeats) + [""]

    at_b, reference_b = scene_b(rays)
    fine, finer = reference_b(8192), reference_b(16384)
    note = (f"Scene B reference: float64 closed form on 16384 intervals + surface edges; change from "
            f"8192 intervals {float((fine - finer).abs().max()):.1e} (max abs).")
    print(note, flush=True)
    lines += accuracy_table("Accuracy, scene B: continuous field queried at sample midpoints",
                            at_b, finer, counts, extra, timing_rays, repeats) + ["", note, ""]
    lines += [
        "Reading: 'official' and 'paper' miss the water outside the sampled range: in front of the near "
        "plane (c_med (1 - exp(-sigma_bs near)), ~8e-3 here, on every ray) and beyond the far plane "
        "(c_med T exp(-sigma_bs far), ~0.1 on open-water rays), whatever the sample count; "
        "'paper + closed-form water outside' shows the discretisation error alone (first order in the "
        "interval length). The closed form has no discretisation error in the rendering equation "
        "(scene A: float32 rounding only); in scene B its remaining error is the field sampling at "
        "the sample midpoints, shared by all methods. Times are medians on a shared 2-core machine "
        "(noisy to ~±30%).", ""]
    if not args.no_write:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_text(args.out, "\n".join(lines))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
