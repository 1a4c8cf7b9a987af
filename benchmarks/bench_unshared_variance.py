"""Which variance model should the refit's incidental term use? (synthetic, a few minutes)

``water_fit.unshared_variance`` estimates the variance of what each surface pixel does not
share with its group as a constant plus a variance per range bin times the squared
transmission. Texture whose spread scales with the surface's colour suggests a model that
scales with each group's fitted clean colour too. Side by side on synthetic groups (six pixels
each, 0.5-6 m, 500 open-water pixels; texture the water transmits like the signal), the errors
of ``fit_water`` (% of ``sigma_attn`` R G B and ``sigma_bs`` R G B):

- no term; the term with the per-bin variance (``plain``, the refit's); with a variance per
  bin times the group's squared clean colour (``colour``); with both (``both``);
- texture relative to the colour (30%: ``tests/test_water_fit._textured``, the data of the
  term's test) and additive (12% of the colour range), three seeds each.

    python benchmarks/bench_unshared_variance.py [--seeds 3]

Writes benchmarks/results/unshared_variance.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from machine import cpu_name

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
sys.path.insert(0, str(REPO))
RESULTS = REPO / "benchmarks" / "results" / "unshared_variance.md"


def additive(seed: int, groups: int = 1500, per_group: int = 6, texture: float = 0.12,
             open_water: int = 500):
    """Groups as in ``_textured`` but with texture added, not scaled with the colour."""
    from tests.test_water_fit import KEYS, TRUE

    rng = np.random.default_rng(seed)
    clean = rng.uniform(0.05, 0.9, size=(groups, 3))
    ids = np.repeat(np.arange(groups), per_group)
    ranges = rng.uniform(0.5, 6.0, ids.size)
    attn, bs, c_med = (np.array(TRUE[k]) for k in KEYS)
    spots = clean[ids] + texture * rng.standard_normal((ids.size, 3))
    observed = spots * np.exp(-attn * ranges[:, None]) \
        + c_med * (1 - np.exp(-bs * ranges[:, None]))
    ranges = np.r_[ranges, np.full(open_water, np.inf)]
    observed = np.r_[observed, np.tile(c_med, (open_water, 1))]
    ids = np.r_[ids, np.full(open_water, groups)]
    return (torch.from_numpy(ranges), torch.from_numpy(observed), torch.from_numpy(ids),
            groups + 1)


def by_colour(with_bins: bool):
    """An ``unshared_variance`` whose per-bin variance is scaled by each group's squared
    fitted clean colour (beside the plain per-bin one when ``with_bins``)."""
    from seathru.nerf import water_fit as wf

    def estimate(fit, ranges, observed, ids, groups, bins=12):
        parts = wf.residual_variance_design(fit, ranges, observed, ids, groups, bins)
        surface, f2, one_hot = parts.surface, parts.f2, parts.one_hot
        j2 = parts.clean.clamp_min(0.0)[ids] ** 2
        out = torch.zeros_like(parts.squared)
        for c in range(3):
            scaled = [f2[:, c:c + 1] * one_hot] if with_bins else []
            scaled.append(f2[:, c:c + 1] * j2[:, c:c + 1] * one_hot)
            design = torch.cat([torch.ones_like(f2[:, :1]), *scaled], 1)[surface]
            coef = torch.linalg.lstsq(design, parts.squared[surface, c:c + 1]
                                      ).solution[1:, 0].clamp_min(0.0)
            out[surface, c] = torch.cat(scaled, 1)[surface] @ coef
        return out
    return estimate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)
    from seathru.nerf import water_fit as wf
    from tests.test_water_fit import KEYS, START, TRUE, _textured

    plain = wf.unshared_variance
    models = {"plain": plain, "colour": by_colour(False), "both": by_colour(True)}
    started, rows = time.time(), []
    for kind, make in (("relative", _textured), ("additive", additive)):
        for seed in range(args.seeds):
            data = make(seed)
            cells = [kind, str(seed)]
            fits = [wf.fit_water(*data, START)]
            for estimate in models.values():
                wf.unshared_variance = estimate
                try:
                    fits.append(wf.fit_water(*data, START, noise_term=True))
                finally:
                    wf.unshared_variance = plain
            for fit in fits:
                error = [100 * (v / t - 1) for k in KEYS[:2]
                         for v, t in zip(getattr(fit, k), TRUE[k])]
                cells.append(" ".join(f"{e:+.0f}" for e in error))
            rows.append("| " + " | ".join(cells) + " |")
            print(rows[-1], flush=True)
    lines = ["# The incidental term's variance model (`benchmarks/bench_unshared_variance.py`)",
             "", "Errors of `fit_water` on synthetic groups (% of `sigma_attn` R G B, then "
             "`sigma_bs` R G B); texture relative to the colour (30%) or additive (12%).", "",
             "| texture | seed | no term | plain (per bin) | colour (per bin x J^2) | both |",
             "|---|---|---|---|---|---|", *rows, "",
             f"Machine: {cpu_name()}, 1 torch thread; {time.strftime('%Y-%m-%d')}; "
             f"{(time.time() - started) / 60:.1f} min in all.", ""]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
