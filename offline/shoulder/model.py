"""The data-driven shoulder skeleton as a scikit-learn style estimator (Hong et al. 2009, Sec. 3).

:func:`prepare_surface` does the work shared by every number of segments (rest pose, marker
surface, near-rigid triangles, log-map features); :class:`ShoulderSkeleton` then runs the five
steps for one ``n_segments``; :class:`MG03Baseline` is the comparison of Table 3.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from labeler_service.errors import ModelError
from offline.shoulder.joints import (
    boundary_centroid,
    choose_root,
    is_chain,
    joint_centre,
    skeleton_structure,
)
from offline.shoulder.markers import select_markers
from offline.shoulder.rigid import apply_point
from offline.shoulder.rotations import triangle_features
from offline.shoulder.segmentation import RestartKMeans, reduce_features
from offline.shoulder.skinning import (
    boundary_candidates,
    core_members,
    hard_labels,
    merge_small_segments,
    rigid_residuals,
    segment_fits,
    segment_members,
    skin_weights,
)
from offline.shoulder.synthesis import (
    ErrorStats,
    error_stats,
    fit_weights_nnls,
    mg03_bones,
    pose_chain,
    skin,
)
from offline.shoulder.triangles import auto_faces, marker_neighbors, rest_pose, rigid_faces

Pose = tuple[np.ndarray, np.ndarray]  # bone transforms R (F, S, 3, 3), t (F, S, 3)


@dataclass(frozen=True)
class Surface:
    """Marker surface of a training capture: rest pose, faces, clustered faces, features."""

    rest_frame: int
    rest: np.ndarray
    faces: np.ndarray  # (T_all, 3) every face
    kept: np.ndarray  # indices of the near-rigid faces that are clustered
    features: np.ndarray  # (len(kept), 3F)
    neighbors: list
    _reduced: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def clustered_faces(self) -> np.ndarray:
        return self.faces[self.kept]

    def reduced_features(self, keep_variance: float) -> np.ndarray:
        """``reduce_features(features, keep_variance)``, computed once per ``keep_variance``
        (every ``k`` clusters the same features)."""
        if keep_variance not in self._reduced:
            self._reduced[keep_variance] = reduce_features(self.features, keep_variance)
        return self._reduced[keep_variance]


def prepare_surface(
    positions: np.ndarray,
    faces: np.ndarray | None = None,
    n_neighbors: int = 6,
    min_angle_deg: float = 25.0,
    max_strain: float = 2.0,
    min_faces: int = 24,
) -> Surface:
    """Steps 1 and 2a for a training capture ``positions`` (F, M, 3) mm, NaN = missing."""
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[2] != 3:
        raise ModelError(f"positions must be (frames, markers, 3), got {pos.shape}")
    if pos.shape[0] < 10 or pos.shape[1] < 6:
        raise ModelError(f"need at least 10 frames and 6 markers, got {pos.shape[:2]}")
    frame, rest = rest_pose(pos)
    if faces is None:
        faces = auto_faces(rest, n_neighbors=n_neighbors, min_angle_deg=min_angle_deg)
    faces = np.asarray(faces, dtype=np.intp)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= pos.shape[1]:
        raise ModelError(f"faces must be (T, 3) marker indices < {pos.shape[1]}")
    kept = rigid_faces(pos, faces, max_strain=max_strain, min_keep=min(min_faces, len(faces)))
    X = triangle_features(pos, rest, faces[kept], frame)
    return Surface(frame, rest, faces, kept, X, marker_neighbors(faces, pos.shape[1]))


class ShoulderSkeleton:
    """Segmentation, single-chain skeleton, reduced markers and skin weights for one ``k``.

    Parameters: ``n_segments`` (k), ``n_restarts`` (k-means restarts, paper 1000), ``omega`` and
    ``n_reduced`` (Sec. 3.4), ``keep_variance`` (see :mod:`segmentation`), ``structure``
    (``"auto"``, ``"chain"`` or ``"tree"``, see :mod:`joints`), ``min_markers`` (a cluster
    owning fewer markers cannot carry a bone -- Sec. 3.4 needs four per segment -- and is merged
    into its neighbours, :func:`~offline.shoulder.skinning.merge_small_segments`),
    ``core_rounds`` (>= 1: fit, select the rigid core, refit, repeated), ``core_factor`` (a
    core marker's own rigid residual is at most this times its segment's median),
    ``random_state``.

    Fitted attributes: ``surface_`` (:class:`Surface`), ``triangle_labels_`` (clustered faces),
    ``labels_`` (M,) segment of every marker, ``n_segments_`` (segments realised, <= k),
    ``merged_`` (clusters merged away for owning too few markers),
    ``chain_`` (segments, parents first), ``parent_`` (S,) (-1 for the root), ``is_chain_``,
    ``joint_costs_`` (S, S) RMS residual of a ball joint between each pair (mm),
    ``structure_errors_`` (training full-set error of the chain and the tree when ``"auto"``),
    ``joints_`` (S, 3) rest-space centre of each bone's joint with its parent (NaN for the root),
    ``joint_rms_`` (S,) mm, ``weights_`` (M, S), ``sigma2_`` (mm^2), ``fit_markers_`` (list of
    marker indices per segment: its rigid core, used for its motion and the full-set pose),
    ``reduced_`` (list, up to ``n_reduced`` indices per segment), ``inertia_`` of the chosen
    clustering, ``segment_R_``, ``segment_t_`` (F, S, ...) the training motion of each core.
    """

    def __init__(
        self,
        n_segments: int = 4,
        n_restarts: int = 1000,
        omega: float = 0.5,
        n_reduced: int = 4,
        keep_variance: float = 0.999,
        structure: str = "auto",
        min_markers: int = 4,
        core_rounds: int = 2,
        core_factor: float = 2.5,
        random_state: int | np.random.Generator | None = None,
    ) -> None:
        self.n_segments = n_segments
        self.n_restarts = n_restarts
        self.omega = omega
        self.n_reduced = n_reduced
        self.keep_variance = keep_variance
        self.structure = structure
        self.min_markers = min_markers
        self.core_rounds = core_rounds
        self.core_factor = core_factor
        self.random_state = random_state

    # ------------------------------------------------------------------------- fitting
    def fit(
        self,
        positions: np.ndarray,
        surface: Surface | None = None,
        progress: Callable[[int], None] | None = None,
    ) -> ShoulderSkeleton:
        """Fits on a training capture (F, M, 3); ``surface`` reuses :func:`prepare_surface`."""
        pos = np.asarray(positions, dtype=np.float64)
        surf = prepare_surface(pos) if surface is None else surface
        k = int(self.n_segments)
        if k < 2 or k > len(surf.kept):
            raise ModelError(f"n_segments must be in 2..{len(surf.kept)} (faces), got {k}")
        # step 2: k-means on the log-map features
        km = RestartKMeans(
            n_clusters=k,
            n_restarts=self.n_restarts,
            keep_variance=self.keep_variance,
            random_state=self.random_state,
        ).fit(surf.features, progress, surf.reduced_features(self.keep_variance))
        tri = km.labels_
        S = int(tri.max()) + 1
        rest, faces = surf.rest, surf.clustered_faces
        labels = hard_labels(pos, rest, faces, tri, S)
        labels, merged = merge_small_segments(pos, rest, labels, S, self.min_markers)
        present = np.unique(labels)
        if present.size < S:  # renumber the surviving segments 0..S'-1
            remap = -np.ones(S, dtype=np.intp)
            remap[present] = np.arange(present.size)
            labels, tri = remap[labels], remap[tri]
            keep_tri = tri >= 0
            faces, tri, S = faces[keep_tri], tri[keep_tri], present.size
        members = segment_members(labels, S, faces, tri)
        R, t = segment_fits(pos, rest, members)
        for _ in range(self.core_rounds):  # refit on the rigid core; re-select against it
            core = core_members(rigid_residuals(pos, rest, R, t), members, self.core_factor)
            R, t = segment_fits(pos, rest, core)
        # step 5a (needed by 3 and 4): skin weights from rigid-prediction likelihoods
        resid = rigid_residuals(pos, rest, R, t)
        cand = boundary_candidates(labels, surf.neighbors)
        W, sigma2 = skin_weights(labels, resid, cand, S, core)
        # step 3: chain and joint centres
        cost = np.zeros((S, S))
        pair_joint = {}
        for p in range(S):
            for c in range(p + 1, S):
                x0 = boundary_centroid(rest, labels, surf.faces, p, c)
                j, r = joint_centre(R[:, p], t[:, p], R[:, c], t[:, c], x0)
                pair_joint[p, c] = pair_joint[c, p] = j
                cost[p, c] = cost[c, p] = r if np.isfinite(r) else 1e9
        root = choose_root(R)
        kinds = ("chain", "tree") if self.structure == "auto" else (self.structure,)
        candidates = {}
        for kind in kinds:
            order, parent = skeleton_structure(cost, root, kind)
            joints = np.full((S, 3), np.nan)
            rms = np.full(S, np.nan)
            for c in order[1:]:
                joints[c], rms[c] = pair_joint[int(parent[c]), c], cost[int(parent[c]), c]
            candidates[kind] = (order, parent, joints, rms)
        self.structure_errors_ = {}
        if len(candidates) > 1:
            for kind, (order, parent, joints, _) in candidates.items():
                js = {c: joints[c] for c in order[1:]}
                Rk, tk = pose_chain(pos, rest, order, parent, js, core)
                self.structure_errors_[kind] = error_stats(skin(rest, W, Rk, tk), pos).avg
            e = self.structure_errors_
            kind = "tree" if e["tree"] < 0.99 * e["chain"] else "chain"
        else:
            kind = kinds[0]
        order, parent, joints, rms = candidates[kind]
        # step 4: reduced marker set (Eq. 1-3) from each segment's dense-set motion
        e_r = resid * pos.shape[0]  # Eq. 1: mean over visible frames, scaled to all frames
        fit_markers, reduced = [], []
        for s in range(S):
            fit_markers.append(core[s])
            inside = np.intersect1d(core[s], np.flatnonzero(W[:, s] >= 0.999))
            cands = inside if inside.size >= self.n_reduced else core[s]
            reduced.append(
                select_markers(rest, cands, members[s], e_r[:, s], self.n_reduced, self.omega)
            )
        self.surface_ = surf
        self.triangle_labels_ = tri
        self.labels_ = labels
        self.n_segments_ = S
        self.merged_ = merged
        self.chain_ = [int(x) for x in order]
        self.parent_ = parent
        self.is_chain_ = is_chain(parent)
        self.joint_costs_ = cost
        self.joints_ = joints
        self.joint_rms_ = rms
        self.weights_ = W
        self.sigma2_ = sigma2
        self.fit_markers_ = fit_markers
        self.reduced_ = reduced
        self.inertia_ = km.inertia_
        self.segment_R_, self.segment_t_ = R, t
        return self

    # --------------------------------------------------------------------- using it
    def _markers(self, marker_set: str) -> list:
        if marker_set == "full":
            return self.fit_markers_
        if marker_set == "reduced":
            return self.reduced_
        raise ValueError(f"marker_set must be 'full' or 'reduced', got {marker_set!r}")

    def pose(
        self, positions: np.ndarray, marker_set: str = "full"
    ) -> tuple[np.ndarray, np.ndarray]:
        """Bone transforms ``(R, t)`` of a capture from the full or the reduced marker set."""
        joints = {c: self.joints_[c] for c in self.chain_[1:]}
        return pose_chain(
            np.asarray(positions, dtype=np.float64),
            self.surface_.rest,
            self.chain_,
            self.parent_,
            joints,
            self._markers(marker_set),
        )

    def synthesize(self, positions: np.ndarray, marker_set: str = "full") -> np.ndarray:
        """The whole marker surface ``(F, M, 3)`` skinned from the estimated joint angles."""
        R, t = self.pose(positions, marker_set)
        return skin(self.surface_.rest, self.weights_, R, t)

    def score(self, positions: np.ndarray, marker_set: str = "full") -> ErrorStats:
        """Synthesis error (Table 2) of a capture with the same markers as the training one."""
        return self.score_pose(positions, *self.pose(positions, marker_set))

    def score_pose(self, positions: np.ndarray, R: np.ndarray, t: np.ndarray) -> ErrorStats:
        """:meth:`score` for a pose ``(R, t)`` already estimated by :meth:`pose` from
        ``positions`` (callers that need the pose too estimate it once)."""
        return error_stats(skin(self.surface_.rest, self.weights_, R, t), positions)

    def joint_trajectories(self, R: np.ndarray, t: np.ndarray) -> dict[int, np.ndarray]:
        """World position ``(F, 3)`` of each joint (keyed by child segment) for a pose."""
        return {
            c: apply_point(R[:, self.parent_[c]], t[:, self.parent_[c]], self.joints_[c])
            for c in self.chain_[1:]
        }


class MG03Baseline:
    """Mohr and Gleicher's extra shoulder joint on a 3-segment skeleton (Hong et al. 2009, Table 3).

    ``skeleton`` is a fitted 3-segment :class:`ShoulderSkeleton`. Fitted attribute:
    ``weights_`` (M, 4) over (its 3 bones, the halfway bone), from :func:`fit_weights_nnls`.
    Each method takes an optional ``pose``: the skeleton's ``(R, t)`` for these positions and
    marker set when the caller already has it (``skeleton.pose(positions, marker_set)``).
    """

    def __init__(self, skeleton: ShoulderSkeleton, frame_step: int = 4) -> None:
        self.skeleton = skeleton
        self.frame_step = frame_step

    def _bones(
        self, positions: np.ndarray, marker_set: str, pose: Pose | None
    ) -> tuple[np.ndarray, np.ndarray]:
        sk = self.skeleton
        R, t = sk.pose(positions, marker_set) if pose is None else pose
        first = sk.chain_[1]
        return mg03_bones(R, t, sk.chain_, sk.joints_[first])

    def fit(self, positions: np.ndarray, pose: Pose | None = None) -> MG03Baseline:
        pos = np.asarray(positions, dtype=np.float64)
        R, t = self._bones(pos, "full", pose)
        self.weights_ = fit_weights_nnls(pos, self.skeleton.surface_.rest, R, t, self.frame_step)
        return self

    def synthesize(
        self, positions: np.ndarray, marker_set: str = "reduced", pose: Pose | None = None
    ) -> np.ndarray:
        R, t = self._bones(np.asarray(positions, dtype=np.float64), marker_set, pose)
        return skin(self.skeleton.surface_.rest, self.weights_, R, t)

    def score(
        self, positions: np.ndarray, marker_set: str = "reduced", pose: Pose | None = None
    ) -> ErrorStats:
        return error_stats(self.synthesize(positions, marker_set, pose), positions)
