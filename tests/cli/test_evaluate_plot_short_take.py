"""``evaluate --plot`` on a take long enough for the asked run but too short for the plot's
4x down-sampled run: the report and the plot of the factors that fit are written and a note
says which factor was left out (it failed with '38 frames is not more than the 50-frame init
window' and lost the report)."""

from __future__ import annotations

import json

from labeling.scene import articulated

from labeler_service.capture import Capture, write_capture
from labeler_service.cli.main import main


def test_plot_leaves_out_a_factor_the_take_is_too_short_for(rng, tmp_path, capsys):
    pos, names = articulated(rng, subjects=2, frames=150)
    src = tmp_path / "take.npz"
    write_capture(Capture(pos, names, 120.0, source="take"), src)
    png = tmp_path / "acc.png"
    args = ["evaluate", str(src), "--method", "online", "--plot", str(png), "--json"]
    assert main(args) == 0
    out = capsys.readouterr()
    report = json.loads(out.out.strip().splitlines()[-1])
    assert report["plot"] == str(png) and png.exists()
    assert any("--downsample 4 left out (38 frames" in n for n in report["notes"])
    assert "--downsample 4 left out" in out.err
    assert not any("--downsample 2" in n for n in report["notes"])  # 75 frames: scored
