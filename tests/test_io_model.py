"""seathru.io.model: model.pt written by save_model, read back by load_model."""

from __future__ import annotations

import pytest
import torch

from seathru.errors import PipelineError
from seathru.io.model import load_model, save_model
from seathru.nerf.config import TrainConfig
from seathru.nerf.model import SeaThruModel

SMALL = {"field": {"density_res": [8], "plane_res": [8], "plane_coarse_res": 4,
                   "density_coarse_res": 4, "plane_channels": 2, "decoder_hidden": 4,
                   "stage_starts": []},
         "sampler": {"candidates_linear": 8, "candidates_disparity": 2, "samples_per_ray": 4},
         "medium": {"mode": "global"}}
SCENE = {"box_min": [-1.0, -1.0, -0.5], "box_max": [1.0, 1.0, 1.0], "near": 0.5, "far": 6.0,
         "typical_range": 2.5, "normalisation": {"centre": [0.0, 0.0, 0.0], "scale": 1.0}}


@pytest.fixture(scope="module")
def model() -> SeaThruModel:
    torch.manual_seed(0)
    model = SeaThruModel(TrainConfig.from_dict(SMALL), SCENE)
    with torch.no_grad():  # not the initial values: the round trip must carry them
        for parameter in model.parameters():
            parameter.add_(0.01 * torch.randn_like(parameter))
    return model


def test_round_trip_keeps_weights_config_scene_and_records(model, tmp_path):
    export = {**model.export(), "training": {"steps": 3}}
    save_model(tmp_path / "model.pt", export)
    assert [p.name for p in tmp_path.iterdir()] == ["model.pt"]  # no temporary left
    loaded = load_model(tmp_path / "model.pt", torch.device("cpu"))
    assert not loaded.training
    assert loaded.config == model.config and loaded.scene == model.scene
    state, original = loaded.state_dict(), model.state_dict()
    assert state.keys() == original.keys()
    for key, value in original.items():
        torch.testing.assert_close(state[key], value, rtol=0, atol=0)
    saved = torch.load(tmp_path / "model.pt", weights_only=True)
    assert saved["training"] == {"steps": 3}


def test_missing_model_names_the_file(tmp_path):
    with pytest.raises(PipelineError, match=r"none\.pt: model file not found; run the 'train'"):
        load_model(tmp_path / "none.pt")


@pytest.mark.parametrize("content", ["garbage", "truncated", "not a model", "bad weights"])
def test_malformed_model_file_is_refused_naming_the_file(model, tmp_path, content):
    path = tmp_path / "model.pt"
    if content == "garbage":
        path.write_bytes(b"not a torch file")
    elif content == "truncated":
        save_model(path, model.export())
        path.write_bytes(path.read_bytes()[:200])
    elif content == "not a model":
        save_model(path, {"format": "something else", "weights": torch.zeros(3)})
    else:
        export = model.export()
        export["state_dict"] = {"field.no_such_parameter": torch.zeros(2)}
        save_model(path, export)
    with pytest.raises(PipelineError, match=r"model\.pt: "):
        load_model(path)
