"""Data-driven shoulder skeleton (Hong, Park and Hodgins 2009).

Pipeline (``mocap-labeler train shoulder``), one module per step of the paper:
:mod:`triangles` (marker surface), :mod:`rotations` (Horn's absolute orientation, log map,
Sec. 3.2), :mod:`segmentation` (k-means with restarts), :mod:`joints` (single-chain skeleton,
Sec. 3.3), :mod:`markers` (reduced marker set, Eq. 1-3), :mod:`skinning` (skin weights, Sec. 3.5),
:mod:`synthesis` (pose fit and linear-blend skinning, Sec. 4, MG03 baseline), :mod:`report`.
:mod:`simulate` makes a synthetic dense shoulder with ground truth.
"""
