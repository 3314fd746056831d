"""Step 1: the marker surface (Hong et al. 2009, Sec. 3.1, Fig. 1b) and the rest pose.

The paper meshes its ~200 markers by hand (Park and Hodgins 2006). Here the faces either come
from a file (``--faces``: one triangle per line, three marker names or 0-based column indices,
separated by spaces or commas; ``#`` starts a comment) or are built automatically from the rest
pose:

1. 3-D Delaunay tetrahedralisation of the rest-pose markers (scipy / Qhull);
2. keep a tetrahedron face only if each of its three edges joins markers that are among each
   other's ``n_neighbors`` nearest neighbours (either direction) -- this keeps the skin-surface
   triangles of a dense, roughly even marker grid and drops the faces that cut through a limb or
   bridge two body parts;
3. drop slivers whose smallest angle is below ``min_angle_deg``: a thin triangle's rotation is
   ill-conditioned (Horn's method needs three well-separated points).

Near-rigid filter (:func:`rigid_faces`, our addition): a triangle whose shape does not survive
the motion (skin folding in the axilla or inside the elbow, a face bridging torso and arm) has
no meaningful rotation, and one such outlier can capture a whole k-means cluster. Triangles
whose edge-length ratio (95th / 5th percentile over the frames, worst edge) exceeds
``max_strain`` (default 2.0; soft-tissue noise alone gives about 1.5 on a 27 mm grid) are left
out of the clustering; their markers are still segmented (by the rigid fit of the clusters,
:mod:`skinning`). Likewise triangles that fold (1st-percentile area below 0.3 of the median:
a vertex crosses the opposite edge, the triangle comes back mirrored with nearly unchanged
edges and a rotation 180 deg off) and triangles with a vertex missing in more than 20 % of the
frames (interpolating their rotation across long gaps makes them outliers).

Rest pose: the frame where the most markers are visible (the first such frame); a marker missing
there takes its sample from the nearest frame in time where it is visible, carried to the rest
frame by the rigid motion (the labeler's Kabsch fit,
:func:`labeler_service.labeling.geometry.kabsch`) of its six nearest markers visible in both
frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from labeler_service.capture import split_label
from labeler_service.errors import CaptureFormatError, ModelError
from labeler_service.labeling.geometry import kabsch


def rest_pose(positions: np.ndarray) -> tuple[int, np.ndarray]:
    """``(frame index, rest (M, 3) float64)`` for ``positions`` (F, M, 3), NaN = missing."""
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[2] != 3 or pos.shape[0] == 0:
        raise ValueError(f"positions must be (frames, markers, 3), got {pos.shape}")
    vis = ~np.any(np.isnan(pos), axis=2)
    if not vis.any(axis=0).all():
        raise CaptureFormatError("some markers are never visible: drop them first")
    frame = int(np.argmax(vis.sum(axis=1)))
    rest = pos[frame].copy()
    for m in np.flatnonzero(~vis[frame]):
        idx = np.flatnonzero(vis[:, m])
        g = idx[np.argmin(np.abs(idx - frame))]
        # carry the marker from frame g to the rest frame with its nearest neighbours' motion
        both = np.flatnonzero(vis[g] & vis[frame])
        both = both[both != m]
        if both.size >= 3:
            near = both[np.argsort(np.linalg.norm(pos[g, both] - pos[g, m], axis=1))[:6]]
            R, t = kabsch(pos[g, near], pos[frame, near])
            rest[m] = R @ pos[g, m] + t
        else:
            rest[m] = pos[g, m]
    return frame, rest


def _min_angles(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Smallest interior angle (degrees) of each triangle."""
    p = points[faces]  # (T, 3, 3)
    out = np.full(len(faces), 180.0)
    for i in range(3):
        u = p[:, (i + 1) % 3] - p[:, i]
        v = p[:, (i + 2) % 3] - p[:, i]
        nu, nv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
        cos = np.einsum("ij,ij->i", u, v) / np.maximum(nu * nv, 1e-12)
        out = np.minimum(out, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return out


def auto_faces(rest: np.ndarray, n_neighbors: int = 6, min_angle_deg: float = 25.0) -> np.ndarray:
    """Triangles ``(T, 3)`` int of the marker surface built from the rest pose (module doc)."""
    pts = np.asarray(rest, dtype=np.float64)
    m = pts.shape[0]
    if pts.ndim != 2 or pts.shape[1] != 3 or m < 4:
        raise ModelError(f"need at least 4 markers to build a surface, got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise ModelError("rest pose contains NaN")
    k = min(n_neighbors, m - 1)
    _, nn = cKDTree(pts).query(pts, k + 1)
    near = np.zeros((m, m), dtype=bool)
    rows = np.repeat(np.arange(m), k)
    near[rows, nn[:, 1:].ravel()] = True
    near |= near.T
    try:
        tet = Delaunay(pts).simplices
    except QhullError as exc:
        raise ModelError(f"cannot triangulate the rest pose (flat or degenerate?): {exc}") from exc
    cand = np.concatenate(
        [tet[:, [0, 1, 2]], tet[:, [0, 1, 3]], tet[:, [0, 2, 3]], tet[:, [1, 2, 3]]]
    )
    cand = np.unique(np.sort(cand, axis=1), axis=0)
    keep = (
        near[cand[:, 0], cand[:, 1]] & near[cand[:, 1], cand[:, 2]] & near[cand[:, 0], cand[:, 2]]
    )
    faces = cand[keep]
    faces = faces[_min_angles(pts, faces) >= min_angle_deg]
    if len(faces) == 0:
        raise ModelError("automatic triangulation found no usable triangle")
    return faces.astype(np.intp)


def read_faces(path: str | Path, labels: Sequence[str]) -> np.ndarray:
    """Faces from a text file (module doc); names match with or without a subject prefix."""
    p = Path(path)
    if not p.exists():
        raise ModelError(f"{p}: no such faces file")
    if not p.is_file():
        raise ModelError(f"{p}: not a regular file (faces are a text file, module doc)")
    index = {}
    for i, label in enumerate(labels):
        index[label] = i
        index.setdefault(split_label(label)[1], i)
    faces = []
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ModelError(
            f"{p}: not a UTF-8 text file (faces are lines of 3 marker names, module doc): {exc}"
        ) from exc
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].replace(",", " ").split()
        if not line:
            continue
        if len(line) != 3:
            raise ModelError(f"{p}:{lineno}: a face needs 3 markers, got {len(line)}")
        tri = []
        for tok in line:
            if tok in index:
                tri.append(index[tok])
            elif tok.isdigit() and int(tok) < len(labels):
                tri.append(int(tok))
            else:
                raise ModelError(f"{p}:{lineno}: unknown marker {tok!r}")
        if len(set(tri)) != 3:
            raise ModelError(f"{p}:{lineno}: a face repeats a marker")
        faces.append(tri)
    if not faces:
        raise ModelError(f"{p}: no faces")
    return np.asarray(faces, dtype=np.intp)


def write_faces(path: str | Path, faces: np.ndarray, labels: Sequence[str]) -> Path:
    """Writes faces in the format :func:`read_faces` reads (marker names)."""
    p = Path(path)
    lines = ["# marker-surface triangles: three marker names per line"]
    lines += [" ".join(labels[i] for i in f) for f in np.asarray(faces)]
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


def edge_strain(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Worst edge-length ratio (95th / 5th percentile over visible frames) of each triangle."""
    pos = np.asarray(positions, dtype=np.float64)
    out = np.empty(len(faces))
    for a, b in ((0, 1), (1, 2), (0, 2)):
        d = np.linalg.norm(pos[:, faces[:, a]] - pos[:, faces[:, b]], axis=2)  # (F, T)
        lo, hi = np.nanpercentile(d, [5.0, 95.0], axis=0)
        ratio = hi / np.maximum(lo, 1e-9)
        out = ratio if a == 0 else np.maximum(out, ratio)
    return np.where(np.isfinite(out), out, np.inf)


def area_ratio(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """1st percentile over the visible frames of each triangle's area over its median area.

    A folding triangle (a vertex crossing the opposite edge) passes through zero area and comes
    back mirrored with nearly the same edge lengths; its Horn rotation then jumps by 180 deg.
    """
    p = np.asarray(positions, dtype=np.float64)[:, faces]  # (F, T, 3, 3)
    a = 0.5 * np.linalg.norm(np.cross(p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0]), axis=2)
    med = np.nanmedian(a, axis=0)
    lo = np.nanpercentile(a, 1.0, axis=0)
    return np.where(np.isfinite(lo) & (med > 0), lo / np.where(med > 0, med, 1.0), 0.0)


def rigid_faces(
    positions: np.ndarray,
    faces: np.ndarray,
    max_strain: float = 2.0,
    min_keep: int = 0,
    max_missing: float = 0.2,
    min_area_ratio: float = 0.3,
) -> np.ndarray:
    """Indices of the faces to cluster: near-rigid (:func:`edge_strain` <= ``max_strain``), not
    folding (:func:`area_ratio` >= ``min_area_ratio``) and complete in at least
    ``1 - max_missing`` of the frames (a long interpolated gap makes a triangle's features an
    outlier).

    If fewer than ``min_keep`` pass, the ``min_keep`` best (complete first, then least
    strained) are returned instead.
    """
    strain = edge_strain(positions, faces)
    missing = np.isnan(np.asarray(positions)[:, faces, 0]).any(axis=2).mean(axis=0)
    folds = area_ratio(positions, faces) < min_area_ratio
    score = np.where((missing <= max_missing) & ~folds, strain, np.inf)
    keep = np.flatnonzero(score <= max_strain)
    if keep.size < min_keep:
        rank = np.lexsort((strain, folds, missing > max_missing))
        keep = np.sort(rank[: min(min_keep, len(faces))])
    return keep


def marker_neighbors(faces: np.ndarray, n_markers: int) -> list[np.ndarray]:
    """Mesh neighbours of every marker (markers sharing a face edge)."""
    adj = np.zeros((n_markers, n_markers), dtype=bool)
    for a, b in ((0, 1), (1, 2), (0, 2)):
        adj[faces[:, a], faces[:, b]] = True
        adj[faces[:, b], faces[:, a]] = True
    return [np.flatnonzero(adj[i]) for i in range(n_markers)]
