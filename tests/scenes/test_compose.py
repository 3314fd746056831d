"""compose: drift removal, yaw, placement on the circle, names, rates, errors, CLI; any take:
resampling, one subject of many, leaving, naming conventions, up axis."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labeler_service.capture import Capture, read_capture, split_label
from labeler_service.cli.main import main
from labeler_service.errors import SceneError
from labeler_service.scenes.compose import (
    CENTRE_SMOOTH_S,
    YAW_JITTER_DEG,
    TakeSpec,
    body_centre,
    compose_scene,
    detect_up,
    heading,
    principal_heading,
    resample,
    side_pairs,
)

# a small "body": left/right pairs so the heading is defined, facing +x when yaw = 0
_NAMES = ("LSHO", "RSHO", "LASI", "RASI", "LKNE", "RKNE", "CLAV", "C7", "LFHD", "RFHD")
_LOCAL = np.array(
    [
        [0, 180, 1400],
        [0, -180, 1400],
        [60, 120, 950],
        [60, -120, 950],
        [40, 100, 500],
        [40, -100, 500],
        [80, 0, 1380],
        [-80, 0, 1450],
        [90, 60, 1650],
        [90, -60, 1650],
    ],
    dtype=np.float64,
)


def synthetic_take(
    rng: np.random.Generator,
    frames: int = 300,
    rate: float = 120.0,
    name: str = "take",
    facing_deg: float = 0.0,
    drift_mm_s: float = 400.0,
    prefix: bool = True,
) -> Capture:
    """A rigid, bobbing marker body that drifts and turns a little: enough for compose."""
    t = np.arange(frames) / rate
    yaw = math.radians(facing_deg) + 0.2 * np.sin(2 * np.pi * 0.3 * t)
    start = rng.uniform(-2000, 2000, size=2)
    direction = rng.normal(size=2)
    direction /= np.linalg.norm(direction)
    drift = start + drift_mm_s * t[:, None] * direction
    c, s = np.cos(yaw), np.sin(yaw)
    x = c[:, None] * _LOCAL[None, :, 0] - s[:, None] * _LOCAL[None, :, 1]
    y = s[:, None] * _LOCAL[None, :, 0] + c[:, None] * _LOCAL[None, :, 1]
    z = _LOCAL[None, :, 2] + 30 * np.sin(2 * np.pi * 1.5 * t)[:, None]
    pos = np.stack([x + drift[:, None, 0], y + drift[:, None, 1], z + 0 * x], axis=-1)
    labels = tuple(f"{name}:{n}" if prefix else n for n in _NAMES)
    return Capture(positions=pos.astype(np.float32), labels=labels, rate=rate, source=name)


def _centres(scene: Capture) -> dict[str, np.ndarray]:
    """Each performer's body centre, smoothed as compose smooths the drift it removes."""
    out = {}
    for subject in scene.subjects:
        cols = scene.subject_columns(subject)
        pos = scene.positions[:, cols].astype(np.float64)
        out[subject] = body_centre(pos, CENTRE_SMOOTH_S * scene.rate)
    return out


def test_drift_removed_and_placed_on_circle(rng):
    takes = [synthetic_take(rng, name=f"S{i}", facing_deg=rng.uniform(0, 360)) for i in range(3)]
    scene = compose_scene(takes, radius=400.0, frames=240, seed=7)
    centres = _centres(scene)
    assert list(centres) == ["S0", "S1", "S2"]
    angles = []
    for c in centres.values():
        # drift gone: the (smoothed) centre sits on one point the whole time
        assert np.abs(c - c[0]).max() < 10.0
        assert np.linalg.norm(c.mean(axis=0)) == pytest.approx(400.0, abs=5.0)
        angles.append(math.atan2(c[:, 1].mean(), c[:, 0].mean()))
    gaps = np.sort(np.diff(np.sort(np.unwrap(angles))) % (2 * np.pi))
    assert gaps == pytest.approx([2 * np.pi / 3] * 2, abs=0.02)


def test_two_takes_face_each_other_and_interleave(rng):
    takes = [synthetic_take(rng, name="A", facing_deg=30), synthetic_take(rng, name="B")]
    scene = compose_scene(takes, radius=300.0, frames=200, seed=3)
    centres = _centres(scene)
    a, b = centres["A"][0], centres["B"][0]
    assert np.linalg.norm(a - b) == pytest.approx(600.0, abs=2.0)
    for subject, c in centres.items():
        sub = scene.select(scene.subject_columns(subject))
        to_centre = math.degrees(math.atan2(-c[0, 1], -c[0, 0]))
        diff = (math.degrees(heading(sub)) - to_centre + 180) % 360 - 180
        assert abs(diff) <= YAW_JITTER_DEG + 0.5


def test_shape_and_vertical_motion_kept(rng):
    take = synthetic_take(rng, name="A")
    scene = compose_scene([take], radius=250.0, frames=100, seed=0)
    src = take.positions[:100].astype(np.float64)
    out = scene.positions.astype(np.float64)
    np.testing.assert_allclose(out[..., 2], src[..., 2], atol=1e-3)
    d_src = np.linalg.norm(src[:, :, None] - src[:, None], axis=-1)
    d_out = np.linalg.norm(out[:, :, None] - out[:, None], axis=-1)
    np.testing.assert_allclose(d_out, d_src, atol=0.05)


def test_labels_prefixed_and_unique(rng):
    a = synthetic_take(rng, name="Same")
    b = synthetic_take(rng, name="Same")
    c = synthetic_take(rng, name="stem_name", prefix=False)
    scene = compose_scene([a, b, c], radius=300.0, frames=50, seed=1)
    assert scene.subjects == ("Same", "Same_2", "stem_name")
    assert len(set(scene.labels)) == len(scene.labels)
    assert all(label.split(":", 1)[0] in scene.subjects for label in scene.labels)
    assert "Same_2:LSHO" in scene.labels


def test_seeded_reproducible(rng):
    takes = [synthetic_take(rng, name=f"S{i}") for i in range(2)]
    one = compose_scene(takes, radius=300.0, frames=80, seed=11)
    two = compose_scene(takes, radius=300.0, frames=80, seed=11)
    other = compose_scene(takes, radius=300.0, frames=80, seed=12)
    np.testing.assert_array_equal(one.positions, two.positions)
    assert one.labels == two.labels
    assert np.nanmax(np.abs(one.positions - other.positions)) > 10.0


def test_sparse_and_empty_markers_dropped_with_note(rng):
    take = synthetic_take(rng, name="A")
    pos = take.positions.copy()
    pos[:, 0] = np.nan  # never visible
    pos[:70, 1] = np.nan  # visible in 30 of the 100 window frames
    take = take.with_positions(pos)
    scene = compose_scene([take], radius=300.0, frames=100, seed=0)
    assert "A:LSHO" not in scene.labels and "A:RSHO" not in scene.labels
    assert scene.n_markers == len(_NAMES) - 2
    assert any("never-visible" in n and "LSHO" in n for n in scene.notes)
    assert any("< 50%" in n and "RSHO" in n for n in scene.notes)


def test_start_and_rate_decimation(rng):
    fast = synthetic_take(rng, frames=600, rate=240.0, name="Fast")
    slow = synthetic_take(rng, frames=300, rate=120.0, name="Slow")
    scene = compose_scene(
        [TakeSpec(capture=fast, start=10), slow], radius=300.0, frames=120, seed=2, rate=120.0
    )
    assert scene.rate == 120.0 and scene.n_frames == 120
    cols = scene.subject_columns("Fast")
    np.testing.assert_allclose(
        scene.positions[:, cols, 2], fast.positions[10 : 10 + 240 : 2, :, 2], atol=1e-3
    )


def test_y_up_take(rng):
    take = synthetic_take(rng, name="A")
    x, y, z = (take.positions[..., i] for i in range(3))
    y_up = take.with_positions(np.stack([x, z, -y], axis=-1))
    scene = compose_scene([TakeSpec(capture=y_up, up="y")], radius=0.0, frames=50, seed=0)
    np.testing.assert_allclose(scene.positions[..., 2], take.positions[:50, :, 2], atol=1e-3)


@pytest.mark.parametrize(
    ("text", "expect"),
    [
        ("walk.c3d", (0, "auto", None)),
        ("walk.c3d:240", (240, "auto", None)),
        ("walk.c3d:12:y", (12, "y", None)),
        ("walk.c3d::Y", (0, "y", None)),
        ("walk.c3d:5:z:Viktor", (5, "z", "Viktor")),
        ("walk.c3d:::Viktor", (0, "auto", "Viktor")),
    ],
)
def test_take_syntax(text, expect):
    spec = TakeSpec.parse(text)
    assert (spec.start, spec.up, spec.subject) == expect
    assert str(spec.path) == "walk.c3d"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("walk.c3d:x", "not a frame number"),
        ("walk.c3d:-3", ">= 0"),
        ("walk.c3d:0:q", "unknown up axis"),
        ("walk.c3d:0:z:S:extra", "FILE[:start[:up[:subject]]]"),
        (":0", "FILE[:start[:up[:subject]]]"),
    ],
)
def test_take_syntax_errors(text, message):
    with pytest.raises(SceneError, match=message.replace("[", r"\[").replace("]", r"\]")):
        TakeSpec.parse(text)


def test_a_take_whose_markers_all_appear_late_says_where_to_start(rng):
    """Every marker dropped by the half-the-window rule: the error says so and where the
    markers appear (it said "no marker is visible" of a take whose markers were there)."""
    take = synthetic_take(rng, frames=300, name="A")
    pos = take.positions.copy()
    pos[:180] = np.nan  # the performer walks in at frame 180
    take = take.with_positions(pos)
    with pytest.raises(SceneError, match=r"fewer than 50% .* first appears at take frame ~180"):
        compose_scene([take], radius=300.0, frames=300, seed=0)
    scene = compose_scene([TakeSpec(capture=take, start=180)], radius=300.0, frames=100, seed=0)
    assert scene.n_markers == len(_NAMES)


def test_errors(rng):
    a = synthetic_take(rng, frames=200, rate=120.0, name="A")
    b = synthetic_take(rng, frames=200, rate=100.0, name="B")
    with pytest.raises(SceneError, match="--rate"):
        compose_scene([a, b], radius=300.0, frames=50, seed=0)
    with pytest.raises(SceneError, match="cannot resample 100 Hz up to 120 Hz"):
        compose_scene([a, b], radius=300.0, frames=50, seed=0, rate=120.0)
    with pytest.raises(SceneError, match="start frame 200 is past its last frame 199"):
        compose_scene([TakeSpec(capture=a, start=200)], radius=300.0, frames=60, seed=0)
    for radius in (-1.0, float("nan"), float("inf")):
        with pytest.raises(SceneError, match="radius"):
            compose_scene([a], radius=radius, frames=10, seed=0)
    for frames in (0, -5):
        with pytest.raises(SceneError, match="frames"):
            compose_scene([a], radius=300.0, frames=frames, seed=0)
    with pytest.raises(SceneError, match="at least one take"):
        compose_scene([], radius=300.0, frames=10, seed=0)
    # a scene readers would map to missing (coordinates past 10 km)
    with pytest.raises(SceneError, match="past 5e\\+06 mm"):
        compose_scene([a], radius=1e8, frames=10, seed=0)
    two = Capture.concat_markers([a, synthetic_take(rng, frames=200, name="C")])
    with pytest.raises(SceneError, match="single-person.*pick one"):
        compose_scene([two], radius=300.0, frames=10, seed=0)
    with pytest.raises(SceneError, match="no subject 'D'"):
        compose_scene([TakeSpec(capture=two, subject="D")], radius=300.0, frames=10, seed=0)


def test_cli_writes_scene_and_reports(rng, tmp_path, capsys):
    from labeler_service.capture import write_capture

    paths = []
    for name in ("A", "B"):
        p = tmp_path / f"{name}.npz"
        write_capture(synthetic_take(rng, name=name), p)
        paths.append(str(p))
    out = tmp_path / "scene.c3d"
    argv = ["compose", str(out), *paths, "--radius", "300", "--frames", "90", "--seed", "4"]
    assert main(argv) == 0
    line = capsys.readouterr().out.strip()
    assert "2 subjects" in line and "90 frames" in line and "120 Hz" in line
    scene = read_capture(out)
    assert scene.subjects == ("A", "B") and scene.n_frames == 90
    assert "up axis z (detected" in line
    assert main([*argv[:-2], "--seed", "4", "--rate", "240"]) == 2
    assert "cannot resample" in capsys.readouterr().err
    assert main([*argv[:-2], "--seed", "4", "--rate", "50"]) == 0
    assert "resampled 120 -> 50 Hz" in capsys.readouterr().out
    assert main(["compose", str(out), paths[0] + ":zz", *argv[3:]]) == 2
    assert "bad take" in capsys.readouterr().err


@pytest.mark.realdata
def test_real_cmu_takes(real_path):
    a = real_path("cmu_01_01_playground.c3d")
    b = real_path("cmu_02_05_expressions.c3d")
    scene = compose_scene([str(a), f"{b}:200"], radius=300.0, frames=600, seed=5)
    assert scene.subjects == ("cmu_01_01_playground", "TakeoMonday")
    assert not any(label.endswith("RBAC-1") for label in scene.labels)
    assert any("RBAC-1" in n for n in scene.notes)
    centres = _centres(scene)
    for c in centres.values():
        # drift gone, sway kept: the smoothed centre stays within a few cm of its place
        assert np.linalg.norm(c - c.mean(axis=0), axis=1).max() < 60.0
    gap = np.linalg.norm(centres["cmu_01_01_playground"].mean(0) - centres["TakeoMonday"].mean(0))
    assert gap == pytest.approx(600.0, abs=30.0)
    # Removing the drift adds no whole-body jumps: frame-to-frame marker steps stay as in the take.
    take = read_capture(b).frames(200, 800)
    before = np.linalg.norm(np.diff(take.positions, axis=0), axis=2)
    tb = scene.positions[:, scene.subject_columns("TakeoMonday")]
    after = np.linalg.norm(np.diff(tb, axis=0), axis=2)
    assert np.nanpercentile(after, 99) < np.nanpercentile(before, 99) + 1.0
    assert np.nanmax(after) < np.nanmax(before) + 5.0
    # markers of the two people come close: arms interleave
    pa = scene.positions[:, scene.subject_columns("cmu_01_01_playground")]
    pb = scene.positions[:, scene.subject_columns("TakeoMonday")]
    closest = np.nanmin(np.linalg.norm(pa[:, :, None] - pb[:, None], axis=-1), axis=(1, 2))
    assert np.nanmedian(closest) < 200.0


@pytest.mark.realdata
def test_real_mixed_rates(real_path):
    a = real_path("cmu_01_01_playground.c3d")
    k = real_path("kneel_to_prone_62markers_240hz.c3d")
    with pytest.raises(SceneError, match="--rate"):
        compose_scene([str(a), str(k)], radius=300.0, frames=300, seed=0)
    scene = compose_scene([str(a), str(k)], radius=300.0, frames=300, seed=0, rate=120.0)
    assert scene.rate == 120.0 and len(scene.subjects) == 2
    # 1745 frames at 240 Hz cover 873 frames at 120 Hz: then the performer leaves
    long = compose_scene([str(k)], radius=300.0, frames=900, seed=0, rate=120.0)
    assert long.visible[:873].any(axis=1).all() and not long.visible[873:].any()
    assert any("leaves the volume" in n for n in long.notes)


# ----------------------------------------------------------------- any real take
def _renamed(take: Capture, rename) -> Capture:
    labels = []
    for label in take.labels:
        subject, name = split_label(label)
        labels.append(f"{subject}:{rename(name)}" if subject else rename(name))
    return Capture(take.positions, tuple(labels), take.rate, source=take.source)


def _y_up(take: Capture) -> Capture:
    x, y, z = (take.positions[..., i] for i in range(3))
    return take.with_positions(np.stack([x, z, -y], axis=-1))


def test_resample_interpolates_any_lower_rate(rng):
    take = synthetic_take(rng, frames=400, rate=120.0, name="A", drift_mm_s=0.0)
    out = resample(take, 7, 50.0, 100)
    assert out.rate == 50.0 and out.n_frames == 100
    # heights bob as 30 sin(2 pi 1.5 t): compare with the motion at the new times
    t = (7 + np.arange(100) * 120.0 / 50.0) / 120.0
    expect = 30 * np.sin(2 * np.pi * 1.5 * t)
    got = out.positions[:, 0, 2] - 1400.0
    assert np.abs(got - expect).max() < 0.6  # linear interpolation of a 1.5 Hz sine at 120 Hz
    # a whole ratio is plain decimation
    np.testing.assert_array_equal(resample(take, 3, 40.0, 50).positions, take.positions[3::3][:50])
    with pytest.raises(SceneError, match="cannot resample 120 Hz up to 130 Hz"):
        resample(take, 0, 130.0, 10)


def test_resample_keeps_gaps_missing(rng):
    take = synthetic_take(rng, frames=100, rate=100.0, name="A")
    pos = take.positions.copy()
    pos[10, 0] = np.nan
    out = resample(take.with_positions(pos), 0, 30.0, 30)  # times 0, 3.33, 6.67, 10, 13.3 ...
    assert np.isnan(out.positions[3, 0]).all()  # exactly on the missing sample
    assert np.isfinite(out.positions[2, 0]).all() and np.isfinite(out.positions[4, 0]).all()
    pos[13, 1] = np.nan
    out = resample(take.with_positions(pos), 0, 30.0, 30)
    assert np.isnan(out.positions[4, 1]).all()  # 13.33 lies between 13 (missing) and 14


def test_scene_at_a_rate_that_is_no_whole_fraction(rng):
    a = synthetic_take(rng, frames=600, rate=250.0, name="A")
    b = synthetic_take(rng, frames=300, rate=100.0, name="B")
    scene = compose_scene([a, b], radius=300.0, frames=120, seed=0, rate=60.0)
    assert scene.rate == 60.0 and scene.n_frames == 120
    assert any("A: from" in n and "resampled 250 -> 60 Hz" in n for n in scene.notes)


def test_one_subject_of_a_multi_subject_file(rng):
    a = synthetic_take(rng, name="Derrick")
    b = synthetic_take(rng, name="Viktor")
    two = Capture.concat_markers([a, b], source="two.c3d")
    scene = compose_scene(
        [TakeSpec(capture=two, subject="Viktor"), a], radius=300.0, frames=60, seed=0
    )
    assert scene.subjects == ("Viktor", "Derrick")
    cols = scene.subject_columns("Viktor")
    assert len(cols) == len(_NAMES)
    np.testing.assert_allclose(scene.positions[:, cols, 2], b.positions[:60, :, 2], atol=1e-3)
    assert any("subject Viktor picked (left out: Derrick)" in n for n in scene.notes)


def test_short_take_leaves_the_volume(rng):
    short = synthetic_take(rng, frames=100, name="Short")
    pos = short.positions.copy()
    pos[:55, 0] = np.nan  # visible in 45 of its 100 frames: dropped
    pos[:40, 1] = np.nan  # visible in 60 of its 100 frames (but only 30 % of the scene): kept
    short = short.with_positions(pos)
    long = synthetic_take(rng, frames=300, name="Long")
    scene = compose_scene([short, long], radius=300.0, frames=200, seed=1)
    cols = scene.subject_columns("Short")
    assert "Short:LSHO" not in scene.labels and "Short:RSHO" in scene.labels
    vis = scene.visible[:, cols]
    assert vis[:100].any(axis=1).all() and not vis[100:].any()
    assert scene.visible[:, scene.subject_columns("Long")].all()
    assert any("ends at scene frame 100 of 200" in n for n in scene.notes)
    # the drift of the covered part is removed as usual: the body stays on its spot
    centre = np.nanmedian(scene.positions[:100, cols, :2], axis=1)
    assert np.ptp(centre, axis=0).max() < 60.0


@pytest.mark.parametrize(
    "rename",
    [
        lambda n: (n[1:] + "_" + n[0]) if n[0] in "LR" and n[1:] != "" else n,  # SHO_L
        lambda n: (n[0] + "_" + n[1:]) if n[0] in "LR" else n,  # L_SHO
        lambda n: (n[0] + "." + n[1:].title()) if n[0] in "LR" else n,  # L.Sho
        lambda n: (n[0].lower() + " " + n[1:].lower()) if n[0] in "LR" else n,  # l sho
        lambda n: (n[1:] + n[0].lower()) if n[0] in "LR" else n,  # SHOl
        lambda n: ({"L": "Left", "R": "Right"}[n[0]] + n[1:]) if n[0] in "LR" else n,
    ],
    ids=["suffix_L", "prefix_L_", "prefix_R.", "prefix_r_space", "suffix_l", "Left"],
)
def test_facing_from_other_naming_conventions(rng, rename):
    take = synthetic_take(rng, name="A", facing_deg=40.0)
    other = _renamed(take, rename)
    assert other.labels != take.labels
    names = [split_label(x)[1] for x in other.labels]
    assert len(side_pairs(names)) == 4
    assert heading(other) == pytest.approx(heading(take), abs=1e-9)


def test_side_pairs_need_matching_spelling():
    names = ["L_KNE", "R_KNE", "Lx", "rx", "KNEE_L", "KNEE.R", "C7", "LONE"]
    assert side_pairs(names) == [(0, 1)]
    classic = ["LSHO", "RSHO", "LKNE", "RKNE", "LASI", "RASI", "Elbow_L", "Elbow_R"]
    assert side_pairs(classic) == [(0, 1), (2, 3), (4, 5)]  # enough L*/R*: only those
    few = ["LSHO", "RSHO", "Elbow_L", "Elbow_R"]
    assert side_pairs(few) == [(0, 1), (2, 3)]  # too few: every convention


def test_principal_axes_fallback(rng):
    take = synthetic_take(rng, name="A", facing_deg=70.0, drift_mm_s=0.0)
    anonymous = _renamed(take, lambda n: f"m{_NAMES.index(n)}")
    assert heading(anonymous) is None
    face, how = principal_heading(anonymous)
    true = heading(take)
    diff = (face - true + math.pi / 2) % math.pi - math.pi / 2  # as a line: sign unknown
    assert abs(diff) < math.radians(5)
    assert "unknown" in how
    scene = compose_scene([anonymous], radius=300.0, frames=100, seed=0)
    assert any("principal axes" in n for n in scene.notes)


def test_principal_axes_sign_from_travel(rng):
    take = synthetic_take(rng, frames=300, name="A", facing_deg=0.0, drift_mm_s=0.0)
    walk = take.positions.copy()
    walk[..., 0] += 800.0 * np.arange(300)[:, None] / 120.0  # walking forward (+x)
    anonymous = _renamed(take.with_positions(walk), lambda n: f"m{_NAMES.index(n)}")
    face, how = principal_heading(anonymous)
    assert abs(math.remainder(face - 0.0, 2 * math.pi)) < math.radians(10)
    assert "travel" in how


def test_up_axis_detected_and_said(rng):
    take = synthetic_take(rng, name="A")
    assert detect_up(take)[0] == "z"
    assert detect_up(_y_up(take))[0] == "y"
    scene = compose_scene([TakeSpec(capture=_y_up(take))], radius=0.0, frames=50, seed=0)
    np.testing.assert_allclose(scene.positions[..., 2], take.positions[:50, :, 2], atol=1e-3)
    assert any("up axis y (detected" in n for n in scene.notes)
    given = compose_scene([TakeSpec(capture=take, up="z")], radius=0.0, frames=50, seed=0)
    assert any("up axis z (given)" in n for n in given.notes)


def test_ambiguous_up_axis_must_be_given(rng):
    take = synthetic_take(rng, name="A")
    pos = take.positions.copy()
    pos[..., 1] = pos[..., 2] * 0.9 + 200.0  # as tall along y as along z, both above 0
    flat = take.with_positions(pos)
    with pytest.raises(SceneError, match="append :z or :y"):
        compose_scene([flat], radius=0.0, frames=50, seed=0)
    scene = compose_scene([TakeSpec(capture=flat, up="z")], radius=0.0, frames=50, seed=0)
    assert scene.n_frames == 50


def test_below_the_floor_decides_a_lying_take(rng):
    # a take only a little taller along z than along y, but y goes far below the floor
    take = synthetic_take(rng, name="A")
    pos = take.positions.copy()
    pos[..., 1] = pos[..., 2] * 0.8 - 2000.0
    assert detect_up(take.with_positions(pos))[0] == "z"


@pytest.mark.realdata
def test_real_takes_of_other_conventions(real_path):
    bts = real_path("gait_bts_yup_22markers_100hz.c3d")
    box = real_path("shoulder_upper_body_with_box_100hz.c3d")
    two = real_path("two_players_shifted_copy_50hz.c3d")
    dance = real_path("dance_qualisys_28markers_60hz.c3d")
    jump = real_path("broad_jump_arm_swing_31markers_240hz.c3d")
    # the BTS take is Y up and empty before frame 239: detected, said, turned to Z up
    scene = compose_scene([f"{bts}:300", f"{box}:0:z:Daphnee", f"{two}:0::Viktor"],
                          radius=300.0, frames=150, seed=3, rate=50.0)  # fmt: skip
    assert scene.subjects == ("gait_bts_yup_22markers_100hz", "Daphnee", "Viktor")
    notes = "\n".join(scene.notes)
    assert "gait_bts_yup_22markers_100hz: up axis y (detected" in notes
    assert "Daphnee: up axis z (given)" in notes
    assert "subject Viktor picked (left out: Derrick)" in notes
    feet = scene.positions[:, scene.subject_columns("gait_bts_yup_22markers_100hz"), 2]
    assert 0 < np.nanpercentile(feet, 5) < 200 and np.nanpercentile(feet, 95) > 1000
    # upper body only: as wide as tall, so the up axis must be given
    with pytest.raises(SceneError, match="append :z or :y"):
        compose_scene([f"{box}:0::Daphnee"], radius=0.0, frames=50, seed=0)
    # twin markers found under every naming convention of the real takes
    # (the box file's l/m suffixes are lateral/medial: only its three r/l twins count)
    for path, pairs in ((bts, 8), (box, 3), (dance, 13), (jump, 14)):
        cap = read_capture(path)
        assert len(side_pairs([split_label(x)[1] for x in cap.labels])) == pairs, path.name
    assert "facing from left/right marker pairs" in notes


def test_a_take_with_only_unlabeled_tracks_is_a_clear_error(rng, tmp_path):
    """A raw take (every column ``*N``, as raw_unlabeled_kneel_to_run) has no performer to
    place: compose says so instead of a numpy traceback from the up-axis test."""
    take = synthetic_take(rng, frames=60, name="Raw")
    raw = Capture(take.positions, tuple(f"*{i}" for i in range(take.n_markers)), take.rate)
    other = synthetic_take(rng, frames=60, name="B")
    with pytest.raises(SceneError, match="no labeled marker.*unlabeled tracks"):
        compose_scene([raw, other], radius=300.0, frames=50, seed=0)
    from labeler_service.capture import write_capture

    path = write_capture(raw, tmp_path / "raw.c3d")
    out = tmp_path / "scene.c3d"
    assert (
        main(
            ["compose", str(out), f"{path}:0:z", "--radius", "300", "--frames", "50", "--seed", "0"]
        )
        == 2
    )


def test_a_one_frame_take_composes_without_numpy_warnings(rng):
    one = synthetic_take(rng, frames=1, name="One")
    other = synthetic_take(rng, frames=60, name="B")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = compose_scene(
            [TakeSpec(capture=one, up="z"), other], radius=300.0, frames=50, seed=0
        )
    assert any("ends at scene frame 1 of 50" in n for n in scene.notes)


def test_the_notes_say_how_many_takes_and_that_radius_0_stacks_them(rng):
    a, b = synthetic_take(rng, name="A"), synthetic_take(rng, name="B")
    one = compose_scene([a], radius=0.0, frames=50, seed=0)
    assert "composed 1 take on a 0 mm circle, seed 0" in one.notes  # it said "1 takes"
    assert not any("same spot" in n for n in one.notes)
    two = compose_scene([a, b], radius=0.0, frames=50, seed=0)
    assert "radius 0 with 2 takes: every performer stands on the same spot" in two.notes
    apart = compose_scene([a, b], radius=300.0, frames=50, seed=0)
    assert not any("same spot" in n for n in apart.notes)
