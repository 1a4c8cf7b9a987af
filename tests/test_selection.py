"""The races that choose the model during training (seathru.nerf.selection): the evidence of
water and the margins of the medium decision, on a 3-view dive of 48x64 pixels."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from seathru import settings
from seathru.nerf.config import TrainConfig
from seathru.nerf.training import Trainer

torch.set_num_threads(1)


def _evidence_trainer(track_change: dict | None = None, medium: str | None = None,
                      race_without_evidence: bool = False) -> Trainer:
    """A 3-view dive of 48x64 pixels for the medium decision; with ``medium`` the water is set
    dim (c_med 0.001) but attenuating, so no open water or backscatter shows water."""
    from tests.test_nerf_prepare import _dive_image, _frames
    from seathru.io.cameras import CameraSet
    from seathru.nerf.prepare import prepare_run

    rng = np.random.default_rng(6)
    frames = _frames(3)
    images = [_dive_image(rng, 0)[:48, :64] for _ in frames]
    options = {"batch_rays": 256, "max_minutes": 0, "steps": 40}
    options["medium"] = {"auto_race_without_evidence": race_without_evidence}
    if medium is not None:
        options["medium"]["mode"] = medium
    config = settings.from_mapping(TrainConfig, options)
    run = prepare_run(config, CameraSet(frames=frames, near=0.1, far=4.0), frames, images,
                      [None] * 3, track_change=track_change)
    if medium is not None:
        run.model.medium.set_global([0.5] * 3, [0.5] * 3, [0.001] * 3)
    return Trainer(run.model, run.data, device="cpu", frames=frames)


def test_colour_fading_along_tracks_is_evidence_of_water():
    change = {"tracks": 500, "t": [-12.0, 1.0, 0.5], "change_over_median_range": [-0.4, 0.02,
                                                                                   0.01]}
    evidence = [_evidence_trainer(track_change).select_medium()["statistics"]
                ["evidence_of_water"] for track_change in (change, None)]
    assert any("COLMAP tracks" in text and "-40%" in text for text in evidence[0])
    assert not any("COLMAP tracks" in text for text in evidence[1])


@pytest.mark.parametrize("gain_db, with_evidence, race_without_evidence, chosen", [
    (3.5, False, False, "off"),     # no evidence, no water: no race is run
    (1.7, False, True, "off"),      # what fern (in air) gained from a water model: not enough
    (3.5, False, True, "global"),
    (-0.3, True, False, "global"),  # with evidence, a tie keeps the water
    (-0.8, True, False, "off")])
def test_without_evidence_of_water_there_is_no_water_or_it_must_win_by_a_wide_margin(
        gain_db, with_evidence, race_without_evidence, chosen, monkeypatch):
    change = {"tracks": 500, "t": [-12.0, 1.0, 0.5],
              "change_over_median_range": [-0.4, 0.02, 0.01]} if with_evidence else None
    trainer = _evidence_trainer(change, medium="global",
                                race_without_evidence=race_without_evidence)
    monkeypatch.setattr(trainer, "_probe_psnr", lambda: 20.0 + (
        gain_db if trainer.model.medium.mode != "off" else 0.0))
    selection = trainer.select_medium()
    raced = with_evidence or race_without_evidence
    assert bool(selection["statistics"]["evidence_of_water"]) == with_evidence
    assert selection["chosen"] == chosen, selection["reason"]
    assert ("validation_psnr_water" in selection["statistics"]) == raced
    assert trainer.step == (trainer._trial_steps(trainer.config.medium.auto_trial_share)
                            if raced else 0)
    if not raced:
        assert selection["reason"].startswith("no evidence of water")
        assert trainer.model.medium.mode == "off"


@pytest.mark.parametrize("sigma_bs, evidence", [(0.001, False), (1.0, True)])
def test_backscatter_is_evidence_only_in_front_of_the_surfaces(sigma_bs, evidence, monkeypatch):
    # a half-trained scene's grey fog behind half-transparent surfaces makes up 61-70% of a
    # toy clear-water image as backscatter, 6-15% in front of its surfaces (decision_seeds.md)
    trainer = _evidence_trainer(medium="global")
    trainer.model.medium.set_global([0.0] * 3, [sigma_bs] * 3, [0.5] * 3)
    rays = len(trainer.probe)
    depth = torch.full((rays,), 2.0)
    monkeypatch.setattr(trainer, "render_batch", lambda batch: {
        "rgb": torch.full((rays, 3), 0.5), "backscatter": torch.full((rays, 3), 0.4),
        "opacity": torch.ones(rays), "depth": depth, "depth_median": depth})
    monkeypatch.setattr(trainer, "assess_water", lambda: {
        "surface_fit": {"sigma_attn": [0.0] * 3}, "fit_determined": {"sigma_attn": [False] * 3}})
    monkeypatch.setattr(trainer, "_probe_psnr", lambda: 20.0)
    stats = trainer.select_medium()["statistics"]
    assert stats["backscatter_share"] == pytest.approx(0.8)
    assert stats["backscatter_in_front_share"] == pytest.approx(-math.expm1(-2 * sigma_bs),
                                                                rel=1e-5)
    assert any("in front of the surfaces" in text
               for text in stats["evidence_of_water"]) == evidence, stats["evidence_of_water"]


@pytest.mark.parametrize("surface_attn, halfwidth, evidence", [
    (0.0, 0.1, False),        # fern's own surfaces fit no attenuation
    (2.0, 0.2, True),         # an oceanic I orbit's fade by 63-72%, at least 35-65%
    (2.0, 2.0, False),        # a half-formed clear scene's: up to 42%, at least 0-5%
    (2.0, math.inf, False)])
def test_surfaces_that_fade_with_range_are_evidence_even_when_not_determined(
        surface_attn, halfwidth, evidence, monkeypatch):
    trainer = _evidence_trainer(medium="global")
    monkeypatch.setattr(trainer, "assess_water", lambda: {
        "surface_fit": {"sigma_attn": [surface_attn] * 3},
        "halfwidth95": {"sigma_attn": [halfwidth] * 3},
        "fit_determined": {"sigma_attn": [False] * 3}})
    monkeypatch.setattr(trainer, "_probe_psnr", lambda: 20.0)
    stats = trainer.select_medium()["statistics"]
    found = stats["evidence_of_water"]
    assert any("surfaces seen over a range" in text for text in found) == evidence, found
    depth = stats["scene_depth_median"]
    assert stats["surface_attenuation_over_depth_lower"] == pytest.approx(
        -math.expm1(-max(surface_attn - halfwidth, 0.0) * depth))


def test_the_surface_fit_is_spared_when_other_evidence_shows_water(monkeypatch):
    # it costs seconds of the budget and could only add evidence to a decision already made
    tracks = {"tracks": 500, "t": [-12.0, 1.0, 0.5],
              "change_over_median_range": [-0.4, 0.02, 0.01]}
    calls = []
    for track_change in (tracks, None):
        trainer = _evidence_trainer(track_change, medium="global")
        monkeypatch.setattr(trainer, "assess_water", lambda: calls.append(1) or {
            "surface_fit": {"sigma_attn": [2.0] * 3}, "fit_determined": {"sigma_attn": [True] * 3}})
        monkeypatch.setattr(trainer, "_probe_psnr", lambda: 20.0)
        stats = trainer.select_medium()["statistics"]
        if track_change is not None:
            assert not calls and stats["surface_attenuation_over_depth"] is None
            assert any("COLMAP tracks" in text for text in stats["evidence_of_water"])
        else:
            assert calls == [1] and stats["attenuation_determined"] is True


@pytest.mark.parametrize("recovers, chosen", [(True, "off"), (False, "global")])
def test_without_evidence_no_water_gets_a_second_trial_to_adapt_to_the_switch(recovers, chosen,
                                                                             monkeypatch):
    # its object colours were learnt under the water; switched off they are all off by the
    # attenuation, which one trial does not undo (a clear-water survey: 3.5 dB behind)
    trainer = _evidence_trainer(medium="global", race_without_evidence=True)
    start = trainer.step
    trial = trainer._trial_steps(trainer.config.medium.auto_trial_share)

    def probe() -> float:
        if trainer.model.medium.mode != "off":
            return 23.5
        return 24.0 if recovers and trainer.step >= start + 2 * trial else 20.0

    monkeypatch.setattr(trainer, "_probe_psnr", probe)
    selection = trainer.select_medium()
    stats = selection["statistics"]
    assert not stats["evidence_of_water"]
    assert selection["chosen"] == chosen, selection["reason"]
    assert stats["validation_psnr_off"] == 20.0
    assert stats["validation_psnr_off_second_trial"] == (24.0 if recovers else 20.0)
    assert trainer.model.medium.mode == ("off" if recovers else "global")
    assert "more steps to adapt to the switch" in selection["reason"]
    # the run goes on from the chosen branch's end: no water from its second trial
    assert trainer.step == start + (2 if recovers else 1) * trial


@pytest.mark.parametrize("gain_db, with_evidence, chosen", [(1.0, False, "off"),
                                                         (3.5, True, "global")])
def test_with_evidence_or_a_close_race_there_is_no_second_trial(gain_db, with_evidence, chosen,
                                                                monkeypatch):
    change = {"tracks": 500, "t": [-12.0, 1.0, 0.5],
              "change_over_median_range": [-0.4, 0.02, 0.01]} if with_evidence else None
    trainer = _evidence_trainer(change, medium="global", race_without_evidence=True)
    trial = trainer._trial_steps(trainer.config.medium.auto_trial_share)
    monkeypatch.setattr(trainer, "_probe_psnr", lambda: 20.0 + (
        gain_db if trainer.model.medium.mode != "off" else 0.0))
    selection = trainer.select_medium()
    assert selection["chosen"] == chosen
    assert selection["statistics"]["validation_psnr_off_second_trial"] is None
    assert trainer.step == trial


def test_where_the_photographs_show_no_water_the_medium_is_chosen_earlier():
    # chosen at 0.8 of the run, no water kept too little of the budget to recover from the
    # switch (benchmarks/results/medium_decision_fern.md)
    fading = {"tracks": 500, "t": [-12.0, 1.0, 0.5],
              "change_over_median_range": [-0.4, 0.02, 0.01]}
    decided = {}
    for name, change in (("no evidence", None), ("tracks fading", fading)):
        trainer = _evidence_trainer(change)
        assert trainer.config.medium.mode == "auto"
        trainer.run()
        decided[name] = trainer.selection["decided_at_progress"]
    medium = TrainConfig().medium
    assert medium.auto_select_at_no_image_evidence < medium.auto_select_at
    assert medium.auto_select_at_no_image_evidence <= decided["no evidence"] < \
        medium.auto_select_at_no_image_evidence + 0.1
    assert medium.auto_select_at <= decided["tracks fading"] < medium.auto_select_at + 0.1
