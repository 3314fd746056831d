"""Checks against ground truth and the acceptance rules of the shoulder study.

Ground truth (``simulate-shoulder``'s ``truth.npz``, format in docs/shoulder.md): the true
segment of every marker and the true joint centres per frame of every motion.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labeler_service.errors import ModelError


@dataclass(frozen=True)
class Truth:
    labels: tuple[str, ...]
    segment: np.ndarray  # (M,) true segment per marker
    segment_names: tuple[str, ...]
    joint_names: tuple[str, ...]
    joint_segments: np.ndarray  # (J, 2) parent, child
    joints: dict[str, np.ndarray]  # motion -> (F, J, 3)

    def aligned(self, labels: Sequence[str]) -> Truth:
        """The truth re-ordered to a capture's marker order (every label must be known)."""
        index = {x: i for i, x in enumerate(self.labels)}
        missing = [x for x in labels if x not in index]
        if missing:
            raise ModelError(f"truth file lacks markers {', '.join(missing[:5])}")
        order = np.asarray([index[x] for x in labels], dtype=np.intp)
        return Truth(
            tuple(labels), self.segment[order], self.segment_names, self.joint_names,
            self.joint_segments, self.joints,
        )  # fmt: skip


def read_truth(path: str | Path) -> Truth:
    """Loads a ``truth.npz`` written by ``simulate-shoulder``."""
    p = Path(path)
    if not p.is_file():
        raise ModelError(f"{p}: no such truth file")
    try:
        with np.load(p, allow_pickle=False) as z:
            need = ("labels", "segment", "segment_names", "joint_names", "joint_segments")
            absent = [k for k in need if k not in z.files]
            if absent:  # (numpy's KeyError read "no 'segment is not a file in the archive'")
                raise ModelError(
                    f"{p}: not a shoulder truth file (the truth.npz simulate-shoulder writes): "
                    f"no {', '.join(repr(k) for k in absent)} array in it"
                )
            joints = {k.split(":", 1)[1]: z[k] for k in z.files if k.startswith("joints:")}
            return Truth(
                labels=tuple(str(x) for x in z["labels"]),
                segment=np.asarray(z["segment"], dtype=np.intp),
                segment_names=tuple(str(x) for x in z["segment_names"]),
                joint_names=tuple(str(x) for x in z["joint_names"]),
                joint_segments=np.asarray(z["joint_segments"], dtype=np.intp),
                joints=joints,
            )
    except (ValueError, OSError) as exc:
        # (numpy's own message suggested allow_pickle for a JSON file given here)
        raise ModelError(
            f"{p}: not a shoulder truth file (the truth.npz simulate-shoulder writes)"
        ) from exc


def adjusted_rand_index(a: np.ndarray, b: np.ndarray) -> float:
    """Adjusted Rand index of two labelings (1 = identical partitions, ~0 = chance)."""
    a = np.unique(np.asarray(a), return_inverse=True)[1]
    b = np.unique(np.asarray(b), return_inverse=True)[1]
    n = a.size
    table = np.zeros((a.max() + 1, b.max() + 1), dtype=np.int64)
    np.add.at(table, (a, b), 1)

    def comb2(x: np.ndarray) -> float:
        return float((x * (x - 1) / 2).sum())

    s_ij = comb2(table)
    s_a, s_b = comb2(table.sum(axis=1)), comb2(table.sum(axis=0))
    expected = s_a * s_b / (n * (n - 1) / 2) if n > 1 else 0.0
    top = 0.5 * (s_a + s_b)
    return 1.0 if top == expected else float((s_ij - expected) / (top - expected))


def majority(true_segment: np.ndarray, labels: np.ndarray, s: int) -> int:
    """The true segment most of our segment ``s``'s markers belong to."""
    return int(np.bincount(true_segment[labels == s]).argmax())


def joint_errors(
    truth: Truth,
    labels: np.ndarray,
    parent: np.ndarray,
    trajectories: dict[int, np.ndarray],
    motion: str,
) -> dict[str, dict]:
    """Error (mm) of each true joint centre against the matching estimated joint.

    An estimated joint between our segments ``(p, c)`` matches the true joint whose (parent,
    child) are the majority true segments of ``p`` and ``c`` (either order); if none matches,
    the estimated joint nearest on average is used and ``matched`` is False.
    """
    if motion not in truth.joints:
        return {}
    true = truth.joints[motion]
    out: dict[str, dict] = {}
    for j, name in enumerate(truth.joint_names):
        tp, tc = (int(x) for x in truth.joint_segments[j])
        cands = []
        for c, traj in trajectories.items():
            pair = {
                majority(truth.segment, labels, int(parent[c])),
                majority(truth.segment, labels, c),
            }
            d = np.linalg.norm(traj - true[:, j], axis=1)
            cands.append((pair == {tp, tc}, float(np.nanmean(d)), d))
        if not cands:
            continue
        matched = [x for x in cands if x[0]]
        ok, mean, d = min(matched or cands, key=lambda x: x[1])
        out[name] = {
            "mean_mm": mean,
            "p95_mm": float(np.nanpercentile(d, 95)),
            "matched": bool(ok),
        }
    return out


def acceptance(errors: dict, mg03: dict) -> dict:
    """The acceptance rules of the study (issue #5), evaluated on a results table.

    ``errors[motion][set][k]`` and ``mg03[motion][set]`` hold ``{"avg": ...}`` dicts.
    """
    rules: dict[str, dict] = {}
    for motion, sets in errors.items():
        for mset, by_k in sets.items():
            e = {int(k): v["avg"] for k, v in by_k.items()}
            key = f"{motion}/{mset}"
            if 3 in e and 4 in e:
                rules[f"{key}: e4 <= 0.85 e3"] = {
                    "value": e[4] / e[3], "limit": 0.85, "pass": e[4] <= 0.85 * e[3],
                }  # fmt: skip
            if 4 in e and 5 in e:
                rel = abs(e[5] - e[4]) / e[4]
                rules[f"{key}: abs(e5 - e4) <= 5% e4"] = {
                    "value": rel, "limit": 0.05, "pass": rel <= 0.05,
                }  # fmt: skip
            if 4 in e and motion in mg03 and mset in mg03[motion]:
                m = mg03[motion][mset]["avg"]
                rules[f"{key}: ours(4) < MG03"] = {
                    "value": e[4] / m,
                    "limit": 1.0,
                    "pass": e[4] < m,
                }
    return rules
