"""The per-dataset evaluation summary (seathru.eval.summary): the views' means, the LPIPS
status, the training figures from the log."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from seathru.eval import summary as dataset_summary
from seathru.eval.summary import TrainingSummary


def test_view_means_and_lpips_status():
    table = pd.DataFrame({"dataset": ["d", "d"], "view": ["a", "b"], "psnr_linear": [30.0, 32.0],
                          "lpips": ["unavailable", "unavailable"]})
    assert dataset_summary.view_means(table) == {"psnr_linear": 31.0, "lpips": "unavailable"}
    table["lpips"] = [0.1, 0.3]
    assert dataset_summary.view_means(table)["lpips"] == pytest.approx(0.2)
    assert dataset_summary.lpips_network(None, None) == (None, "unavailable: no --lpips-weights "
                                                               "given")
    assert dataset_summary.lpips_network(None, "w.pth") == (None, "unavailable: w.pth not found")
    with pytest.raises(ValueError, match="lin0..lin4"):
        dataset_summary.lpips_network({}, "w.pth")


def test_training_summary_from_the_log():
    log = pd.DataFrame({"step": [0, 50, 100], "wall_time_s": [0.5, 20.0, 41.5],
                        "loss": [0.1, 0.01, 0.005], "test_psnr": [9.0, np.nan, np.nan]})
    training = dataset_summary.training_summary(log)
    assert training == TrainingSummary(time_s=41.5, steps=100, final_loss=0.005,
                                       final_test_psnr=9.0)
    assert dataset_summary.training_summary(None) is None
    assert dataset_summary.training_summary(pd.DataFrame({"step": [1]})) is None
