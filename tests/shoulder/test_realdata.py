"""The real upper-body capture with dense shoulder markers (pyomeca, 580 frames, gaps)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labeler_service.cli.main import main

FILE = "shoulder_upper_body_with_box_100hz.c3d"


@pytest.mark.realdata
def test_real_shoulder_segments_k3_to_6(real_path, tmp_path, capsys):
    path = real_path(FILE)
    out = tmp_path / "real"
    code = main(["train", "shoulder", str(path), "--subject", "Daphnee", "--restarts", "100",
                 "--no-plots", "--out", str(out)])  # fmt: skip
    assert code == 0
    capsys.readouterr()
    r = json.loads((out / "results.json").read_text())
    assert r["markers"] == 43  # the box (boite:) is excluded
    assert any("excluded subjects: boite" in n for n in r["notes"])
    assert r["missing_fraction"] > 0  # real gaps, handled
    errs = r["errors"][path.stem]["full"]
    avg = {int(k): v["avg"] for k, v in errs.items()}
    assert sorted(avg) == [3, 4, 5, 6]
    assert all(np.isfinite(v) and 0 < v < 50 for v in avg.values())
    assert avg[6] <= avg[3] * 1.05  # more segments do not make it worse (beyond noise)
    for k, seg in r["segmentation"].items():
        assert 2 <= seg["n_segments"] <= int(k)
        assert all(len(s) > 0 for s in seg["segments"])
        names = sorted(x for s in seg["segments"] for x in s)
        assert len(names) == 43 and all(x.startswith("Daphnee:") for x in names)
    # the hand/forearm markers never share a segment with the pelvis
    for seg in r["segmentation"].values():
        for s in seg["segments"]:
            assert not ({"Daphnee:ASISr", "Daphnee:WRIST"} <= set(s))
