"""Numba kernels of the online labeler (seed 003).

Each module exposes private ``_kernels`` (no validation: the Labeler validates once per frame)
and each kernel has a plain-numpy twin in ``tests/reference.py``.

- :mod:`.kalman`: constant-velocity Kalman filter (Eq. 3-4), factorised per axis;
- :mod:`.gating`: Mahalanobis gate, at most K candidates per marker;
- :mod:`.fitting`: exhaustive (branch-and-bound) body search with score Eq. 5 and the greedy
  Algorithm 1;
- :mod:`.rigid`: Kabsch fit and missing-marker recovery (Sec. 3.3);
- :mod:`.window`: sliding-window update of D and A (Eq. 1-2);
- :mod:`.spatial`: the sweep index behind every "points near here" query;
- :mod:`.step`: the whole per-frame loop, one entry point;
- :mod:`.stacked`: labels over a window of stacked frames (a booting labeler's installs);
- :mod:`.state`: the state it works on, as named structures (``Tracks``, ``Bodies``,
  ``Recovery``, ``Scratch``) and their builders;
- :mod:`.params`: every setting as one named tuple ``Params``, built from ``LabelerConfig``.
"""
