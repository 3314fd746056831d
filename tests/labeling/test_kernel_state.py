"""The kernel state structures and ``Params``: names, builders, one compiled type per process."""

from __future__ import annotations

import inspect
import math
from typing import Literal

import numba
import numpy as np
import pytest

from labeler_service.labeling import frame
from labeler_service.labeling.config import LabelerConfig
from labeler_service.labeling.frame import MarkerState
from labeler_service.labeling.kernels import params as kp
from labeler_service.labeling.kernels.state import MAX_BODY, grow_scratch, new_bodies, new_scratch
from labeler_service.labeling.kernels.step import _process_frame, _process_frame_fields


def test_params_hold_every_config_field_then_the_derived_ones():
    p = kp.kernel_params(LabelerConfig())
    assert p._fields == (*LabelerConfig.model_fields, *kp.DERIVED)
    c = LabelerConfig()
    for name in LabelerConfig.model_fields:
        if name not in kp.CODES:
            assert getattr(p, name) == getattr(c, name), name
    assert p.recovery == kp.KABSCH
    assert kp.kernel_params(LabelerConfig(recovery="displacement")).recovery == kp.DISPLACEMENT


def test_derived_params_follow_their_formulas():
    c = LabelerConfig(measurement_noise_mm=2.0, min_gate_mm=40.0, gate_chi2=16.0, missing_sigma=2.0)
    p = kp.kernel_params(c)
    assert p.r == 4.0
    assert p.r_rec == c.recovered_noise_mm**2
    assert p.s_min * p.gate_chi2 == pytest.approx(40.0**2)  # the gate radius floor, squared
    assert p.miss_term == pytest.approx(math.exp(-2.0))
    assert p.v0 == kp.V0


def test_params_type_does_not_depend_on_how_a_value_is_spelled():
    # an int where a float is declared would otherwise compile the kernels a second time
    # (model_construct: as a config built without validation would hold it)
    spelled = LabelerConfig.model_construct(reacquire_mm=250, jump_mm=8, contest=1)
    a = kp.kernel_params(spelled)
    assert isinstance(a.reacquire_mm, float) and isinstance(a.K, int)
    assert isinstance(a.contest, bool)
    assert numba.typeof(a) == numba.typeof(kp.kernel_params(LabelerConfig()))


def test_a_setting_of_unknown_kind_fails_at_import_with_its_name():
    with pytest.raises(TypeError, match="LabelerConfig.odd"):
        kp._converter("odd", list[int])
    with pytest.raises(TypeError, match="no integer code"):
        kp._converter("recovery", Literal["kabsch", "icp"])
    assert kp._converter("recovery", Literal["kabsch"])("kabsch") == kp.KABSCH


def test_marker_state_constants_are_the_enum_values():
    for s in MarkerState:
        assert getattr(frame, s.name) == int(s) and type(getattr(frame, s.name)) is int


def test_new_bodies_indexes_markers_to_their_bodies():
    bodies = [[0, 2, 3], [3, 4], [1, 3, 0]]
    D0 = [np.full((len(b), len(b)), 10.0 + k) for k, b in enumerate(bodies)]
    A0 = [np.ones((len(b), len(b))) for b in bodies]
    st = new_bodies(6, bodies, D0, A0, T=5)
    assert st.members.shape == (3, MAX_BODY) and st.size.tolist() == [3, 2, 3]
    for i in range(6):
        got = st.mb_idx[st.mb_ptr[i] : st.mb_ptr[i + 1]].tolist()
        assert got == [b for b, body in enumerate(bodies) if i in body]
    np.testing.assert_array_equal(st.D, st.D0)
    assert st.D is not st.D0  # the window writes D, never the template
    assert np.isnan(st.D[1, 2:, :]).all() and st.ring.shape == (3, MAX_BODY, MAX_BODY, 5)


def test_grow_scratch_replaces_only_the_point_buffer():
    sc = new_scratch(5, 2, 1, 4, 8)
    big = grow_scratch(sc, 100)
    assert big.owner.shape == (100,) and big.cand is sc.cand and big.fit is sc.fit


@pytest.mark.parametrize("entry", [_process_frame, _process_frame_fields])
def test_the_per_frame_entry_takes_few_named_arguments(entry):
    names = list(inspect.signature(entry.py_func).parameters)
    assert len(names) <= 12
    assert names[-5:] == ["tracks", "bodies", "recovery", "scratch", "params"]
