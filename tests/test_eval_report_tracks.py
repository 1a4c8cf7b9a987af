"""The colour along COLMAP tracks in the report (seathru.eval.report_tracks): how much of the
input's slope the full render follows, and the rows of the page's section."""

from __future__ import annotations

import pytest

from seathru.eval.report import render_html, summary_table
from seathru.eval.report_records import DatasetRecord
from seathru.eval.report_tracks import (TRACK_SLOPE_FOLLOWED_MIN, followed_share,
                                        track_slope_rows)
from tests.test_eval_report import evaluation_summary, track_slope_record


def test_followed_share_pools_the_channels_whose_input_slope_stands_out():
    assert followed_share([(0.2, 0.01), (0.0, 0.01)], [(0.05, 0.01), (0.3, 0.01)]) == \
        pytest.approx(0.25)
    # a falling input followed by a falling render counts as followed; a rising one against it
    assert followed_share([(-0.2, 0.01), (0.1, 0.01)], [(-0.2, 0.01), (-0.1, 0.01)]) == \
        pytest.approx((0.2 - 0.1) / 0.3)
    assert followed_share([(0.01, 0.01)], [(0.01, 0.01)]) is None        # within its error
    assert followed_share([(0.2, 0.01)], [(None, None)]) is None          # not measured


def test_html_says_a_reduction_says_little_where_the_full_render_does_not_follow_the_input():
    reef = evaluation_summary("reef", 25.0)
    reef.track_colour_slope = track_slope_record(0.8, followed=0.2)
    demo = evaluation_summary("demo", 25.0)
    demo.track_colour_slope = track_slope_record(0.8, seed=2, followed=0.95)
    records = [DatasetRecord("reef", summary=reef), DatasetRecord("demo", summary=demo)]
    rows = {row["dataset"]: row["parts"][0] for row in track_slope_rows(records)}
    assert rows["reef"]["followed"] == pytest.approx(0.2, abs=0.02)
    assert rows["demo"]["followed"] == pytest.approx(0.95, abs=0.02)
    assert rows["reef"]["followed"] < TRACK_SLOPE_FOLLOWED_MIN < rows["demo"]["followed"]
    page = render_html(summary_table(records), records, {}, {}, "now")
    section = page.split("<h2>Colour along COLMAP tracks</h2>")[1].split("<h2>")[0]
    reef_part = section[section.index(">reef<"):section.index(">demo<")]
    demo_part = section[section.index(">demo<"):]
    note = "of the input's slope, so the share removed says little"
    assert reef_part.count(note) == 1 and "follows only 20%" in reef_part
    assert note not in demo_part
