"""Re-verification of booted subjects over time (:class:`BootVerifier`).

A boot reads distances in one 0.1 s window. In a crowd (a 10-person hug) a partner's forearm
or hand can fit where a subject's hidden upper arm or forearm should be, and a wrist bar or a
hand can be read mirrored: within the window the wrong reading keeps the template's pairs as
well as the right one would. Over a longer time it does not: a partner's arm moves with the
partner, so its distances to this subject's placed segments stop fitting the template.

The verifier keeps, while a booted subject is active, evidence per *edge* of its template:

- **rigid edges**: every pair of markers of one trained body (``strict`` in the boot's
  templates) with the boot's tolerance ``tol_mm + tol_sigma A + tol_relative D`` times
  ``verify_tol_scale`` plus ``verify_tol_mm`` (over a stream a model trained on another or a
  still segment is off by more than in one window: skin over a scapula slides);
- **joint edges**: the template's bodies are joined into a *chain*, a minimum spanning tree
  over the cost of joining two bodies (0 when they share a marker, else their cheapest cross
  pair's ``A + JOINT_D D``, only for pairs closer than ``JOINT_REACH`` times the larger body:
  a model trained with the hands held together has the two forearms steadier than either
  elbow); per joint of the chain its ``verify_links`` cheapest cross pairs with no marker twice
  (one wrong marker breaks one of them, a wrong segment all), with the looser tolerance
  ``tol_mm + verify_link_sigma A + tol_relative D``.

Each tick (every ``verify_every_s``) every edge whose two markers are observed in the frame
adds a sample: off (outside its tolerance) or not, into an exponential average of the off
rate with time constant ``verify_memory_s`` (the sliding window), and the same average of its
distance and squared distance (its spread). An edge with at least ``verify_min_s`` of samples
is *bad* when its off rate exceeds ``verify_bad`` and, for a joint edge, its distance also
spreads by ``verify_spread_mm + verify_spread_sigma A`` or more: an articulated pair held off
its trained range but steady is a pose the training did not see (an arm raised into a hug),
another performer's limb moves. A marker seen on another track than before starts its
evidence again (the labeler moved it).

Decisions (only on positive evidence: a hidden marker gives no sample, never a withdrawal;
and only for markers within ``verify_contact_mm`` of another subject's observed marker: a
performer apart from the others cannot hold their limbs):

- **a marker is off**: two or more of its edges bad and more bad than good (its partners
  agree among themselves, it does not); the worst first, its edges then no longer count, so a
  marker whose partners are wrong is not withdrawn with them;
- **a joint is broken** (``verify_cut``): two or more of its pairs bad, more than good, each
  from a near-side marker its own body confirms (two good rigid edges, no bad one): the body
  farther from the chain's centre (the trunk) is withdrawn with every body that hangs from it
  (its subtree in the breadth-first tree from the centre), except markers shared with a body
  that stays: a partner's forearm and hand read where this subject's are. Each such pair must
  also be off by ``verify_cut_tol`` tolerances on average (the subject's own limb in an
  untrained pose stays within one or two), and another subject must lack (have unobserved)
  markers of the segment's names, either side, for half of it (where the partner's segment came
  from);
- **a subject mostly fails** when the markers withdrawn from it within about
  ``verify_recent_s`` reach ``verify_drop`` of its observed markers: it is dropped (as a
  performer who left) and booted again.

:class:`~labeler_service.labeling.booting.BootingLabeler` applies the withdrawals (labels
removed from the frame and the window, the inner labeler's markers withdrawn with
``Labeler.withdraw_markers`` until they are placed again) and keeps the withdrawn points'
tracks away from that subject for ``verify_block_s``, so the extension or the acquisition
places the markers elsewhere. Cost: one vectorised pass over the edges per tick (~1,100 edges
for 10 performers: ~0.1 ms a tick, ~0.02 ms a frame at 360 Hz).
"""

from __future__ import annotations

import re
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse.csgraph import minimum_spanning_tree
from scipy.spatial import cKDTree

from labeler_service.capture.model import side_pairs
from labeler_service.labeling.boot import Booter
from labeler_service.labeling.boot_config import BootConfig


@dataclass
class Verdict:
    """One tick's decisions: per subject index the global markers to withdraw, the subjects to
    drop (booted again), and per subject the ``(K, 2)`` pairs of left and right markers to
    exchange (each takes the other's point: :meth:`BootVerifier._exchanges`)."""

    withdraw: dict[int, np.ndarray]
    drop: list[int]
    exchange: dict[int, np.ndarray] = field(default_factory=dict)


#: an exchange of left and right markers is made only when its reading's mean excess over the
#: template's tolerances is at most this share of the current reading's ...
EXCHANGE_GAIN = 0.25
#: ... and the current reading's mean excess is at least this (tolerances past, per edge)
EXCHANGE_MIN_EXCESS = 0.3
#: an edge's excess counts at most this many tolerances (one wild pair does not decide)
EXCHANGE_CAP = 10.0
#: an exchange moves at least this many left-right pairs (a segment and its twin)
EXCHANGE_MIN_PAIRS = 2
#: seconds of stream before the same pairs of a subject are exchanged again
EXCHANGE_HOLD_S = 2.0
#: left-right pairs tried together at most (every subset of them: 2^n readings)
EXCHANGE_MAX_PAIRS = 8


#: mm of ``A`` per mm of ``D`` when choosing a joint's pairs and the chain: the pairs beside a
#: joint (an elbow marker to a forearm marker), not a long pair that happened to be steady in
#: training (C7 to an ankle while walking, ``A`` 10 mm over 1.3 m)
JOINT_D = 0.05
#: two bodies can be neighbours in the chain only when their closest cross pair is within this
#: many times the larger body's size (``D`` of its longest pair): a model trained with the
#: hands held together has the two forearms' pairs steadier than either elbow's
JOINT_REACH = 1.5


def _subsets(units: list, among: list) -> np.ndarray:
    """``(2^n, len(units))`` every subset of ``among`` (``n`` of the ``units``) as rows of
    flags over ``units``."""
    n = len(among)
    cols = np.array([units.index(u) for u in among], dtype=np.int64)
    out = np.zeros((1 << n, len(units)), dtype=bool)
    out[:, cols] = ((np.arange(1 << n)[:, None] >> np.arange(n)) & 1).astype(bool)
    return out


def _sideless(name: str) -> str:
    """A marker name without its body side (``LFRM``, ``RFRM`` -> ``FRM``; ``Ulna_L`` ->
    ``Ulna``; ``l bar 2`` -> ``bar 2``)."""
    return re.sub(r"^[LR](?=[A-Z])|[_ ][LRlr]$|^[lr] ", "", name)


def _chain(tpl, members: list[set[int]]) -> np.ndarray:
    """``(nb, nb)`` the chain of a template's bodies: a minimum spanning tree over the cost
    of joining two bodies (0 when they share a marker, else their cheapest cross pair's
    ``A + JOINT_D D``): neighbours along the skeleton, each body joined once."""
    nb = len(members)
    cost = np.zeros((nb, nb))
    idx = [np.array(sorted(s), dtype=np.int64) for s in members]
    size = [float(np.nanmax(tpl.D[np.ix_(i, i)])) if i.size > 1 else 0.0 for i in idx]
    for b1 in range(nb):
        for b2 in range(b1 + 1, nb):
            if members[b1] & members[b2]:
                w = 1e-6  # (a zero weight is no edge to scipy)
            else:
                d = tpl.D[np.ix_(idx[b1], idx[b2])]
                val = tpl.A[np.ix_(idx[b1], idx[b2])] + JOINT_D * d
                ok = np.isfinite(val)
                if not ok.any() or float(np.min(d[ok])) > JOINT_REACH * max(size[b1], size[b2]):
                    continue
                w = max(float(np.min(val[ok])), 1e-6)
            cost[b1, b2] = cost[b2, b1] = w
    tree = minimum_spanning_tree(cost).toarray() > 0
    return tree | tree.T


def _root_tree(adj: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth and parent of each body in the breadth-first tree from the chain's centre (least
    eccentricity, then most markers) over the body adjacency ``adj (nb, nb)``; bodies not
    reached get depth 0 and parent -1 (their own roots)."""
    nb = adj.shape[0]
    ecc = np.zeros(nb, dtype=np.int64)
    for b in range(nb):
        ecc[b] = int(_bfs(adj, b)[0].max()) if nb else 0
    order = np.lexsort((-sizes, ecc)) if nb else np.zeros(0, dtype=np.int64)
    depth = np.full(nb, -1, dtype=np.int64)
    parent = np.full(nb, -1, dtype=np.int64)
    for r in order:
        if depth[r] >= 0:
            continue
        d, p = _bfs(adj, int(r), depth >= 0)
        reached = d >= 0
        depth[reached] = d[reached]
        parent[reached] = p[reached]
    return depth, parent


def _bfs(
    adj: np.ndarray, root: int, skip: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    nb = adj.shape[0]
    depth = np.full(nb, -1, dtype=np.int64)
    parent = np.full(nb, -1, dtype=np.int64)
    depth[root] = 0
    queue = deque([root])
    while queue:
        b = queue.popleft()
        for c in np.flatnonzero(adj[b]):
            if depth[c] < 0 and (skip is None or not skip[c]):
                depth[c] = depth[b] + 1
                parent[c] = b
                queue.append(int(c))
    return depth, parent


class BootVerifier:
    """Evidence over time that each booted subject's labels keep its template (module doc)."""

    def __init__(self, booter: Booter, rate: float, config: BootConfig) -> None:
        c = config
        self.config = c
        templates = booter._templates
        self.n_markers = sum(t.n for t in templates)
        self._every = max(1, round(c.verify_every_s * rate))
        tick_hz = rate / self._every
        self._alpha = min(1.0, 1.0 / max(1.0, c.verify_memory_s * tick_hz))
        self._min_n = max(1, round(c.verify_min_s * tick_hz))
        ea: list[np.ndarray] = []
        eb: list[np.ndarray] = []
        ed: list[np.ndarray] = []
        ea_a: list[np.ndarray] = []  # trained A of each edge
        et: list[np.ndarray] = []
        eg: list[np.ndarray] = []  # joint index, -1 for rigid edges
        #: per joint: (subject, parent-side body, child-side body) as global body ids
        joints: list[tuple[int, int, int]] = []
        #: per global body: its markers (global) and the bodies of its subtree
        self._body_markers: list[np.ndarray] = []
        self._subtree: list[np.ndarray] = []
        self._marker_bodies: list[list[int]] = [[] for _ in range(self.n_markers)]
        for tpl in templates:
            off = tpl.offset
            i, j = np.nonzero(np.triu(tpl.strict, 1))
            ea.append(off + i)
            eb.append(off + j)
            ed.append(tpl.D[i, j])
            ea_a.append(tpl.A[i, j])
            et.append(tpl.tol[i, j])
            eg.append(np.full(i.size, -1, dtype=np.int64))
            nb = len(tpl.bodies)
            base = len(self._body_markers)
            members = [set(bd.markers.tolist()) for bd in tpl.bodies]
            adj = _chain(tpl, members)
            sizes = np.array([len(s) for s in members], dtype=np.int64)
            depth, parent = _root_tree(adj, sizes)
            children: list[list[int]] = [[] for _ in range(nb)]
            for b in range(nb):
                if parent[b] >= 0:
                    children[parent[b]].append(b)
            for b in range(nb):
                sub, stack = [], [b]
                while stack:
                    x = stack.pop()
                    sub.append(x)
                    stack += children[x]
                self._body_markers.append(off + tpl.bodies[b].markers)
                self._subtree.append(base + np.array(sorted(sub), dtype=np.int64))
                for mk in tpl.bodies[b].markers:
                    self._marker_bodies[off + int(mk)].append(base + b)
            for b1 in range(nb):
                for b2 in range(b1 + 1, nb):
                    if not adj[b1, b2] or depth[b1] == depth[b2]:
                        continue
                    near_b, far_b = (b1, b2) if depth[b1] < depth[b2] else (b2, b1)
                    pa = np.array(sorted(members[near_b] - members[far_b]), dtype=np.int64)
                    pb = np.array(sorted(members[far_b] - members[near_b]), dtype=np.int64)
                    if pa.size == 0 or pb.size == 0:
                        continue
                    gi, gj = np.meshgrid(pa, pb, indexing="ij")
                    ii, jj = gi.ravel(), gj.ravel()
                    a = tpl.A[ii, jj]
                    d = tpl.D[ii, jj]
                    ok = np.isfinite(a) & np.isfinite(d) & ~tpl.strict[ii, jj]
                    if not ok.any():
                        continue
                    ii, jj, a, d = ii[ok], jj[ok], a[ok], d[ok]
                    # the cheapest pairs with no marker twice (either side): one wrong marker
                    # breaks one of them, a wrong segment every one
                    keep_l: list[int] = []
                    used_a: set[int] = set()
                    used_b: set[int] = set()
                    for k in np.argsort(a + JOINT_D * d, kind="stable"):
                        if int(ii[k]) in used_a or int(jj[k]) in used_b:
                            continue
                        keep_l.append(int(k))
                        used_a.add(int(ii[k]))
                        used_b.add(int(jj[k]))
                        if len(keep_l) == c.verify_links:
                            break
                    keep = np.array(keep_l, dtype=np.int64)
                    g = len(joints)
                    joints.append((tpl.index, base + near_b, base + far_b))
                    ea.append(off + ii[keep])
                    eb.append(off + jj[keep])
                    ed.append(d[keep])
                    ea_a.append(a[keep])
                    et.append(c.tol_mm + c.verify_link_sigma * a[keep] + c.tol_relative * d[keep])
                    eg.append(np.full(keep.size, g, dtype=np.int64))

        def cat(parts: list[np.ndarray], dtype: type) -> np.ndarray:
            return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype=dtype)

        self.ea, self.eb = cat(ea, np.int64), cat(eb, np.int64)
        self.D, self.tol = cat(ed, np.float64), cat(et, np.float64)
        self.joint = cat(eg, np.int64)
        # (the boot's rigid tolerances hold one window; over a stream a model trained on
        # another segment, or a still one, is off by more: skin over a scapula slides)
        rig = self.joint < 0
        self.tol[rig] = c.verify_tol_scale * self.tol[rig] + c.verify_tol_mm
        ok = np.isfinite(self.D) & np.isfinite(self.tol)
        self.ea, self.eb, self.D, self.tol, self.joint = (
            self.ea[ok], self.eb[ok], self.D[ok], self.tol[ok], self.joint[ok]
        )  # fmt: skip
        self.joints = np.array(joints, dtype=np.int64).reshape(-1, 3)
        n_of = [t.n for t in templates]
        self._subject_of = np.repeat(np.arange(len(n_of)), n_of)
        #: per marker the markers of the same name, either side, in other subjects (a partner's
        #: limb can be read as this subject's only where the partner has one: its own side or,
        #: read mirrored, the other)
        names = [_sideless(n.split(":", 1)[-1]) for n in booter.model.marker_names]
        by_name: dict[str, list[int]] = {}
        for k, nm in enumerate(names):
            by_name.setdefault(nm, []).append(k)
        self._twins = [
            np.array([j for j in by_name[nm] if self._subject_of[j] != self._subject_of[k]])
            for k, nm in enumerate(names)
        ]
        self.ema = np.zeros(self.ea.size)
        #: running mean and mean square of each edge's distance (its spread over the memory)
        self.m1 = np.zeros(self.ea.size)
        self.m2 = np.zeros(self.ea.size)
        #: a joint edge is bad only while its distance also moves: more than this spread
        a_edge = np.concatenate(ea_a) if ea_a else np.zeros(0)
        self.spread = np.where(
            self.joint >= 0, c.verify_spread_mm + c.verify_spread_sigma * a_edge[ok], 0.0
        )
        self.n = np.zeros(self.ea.size, dtype=np.int64)
        self._on = np.zeros(len(n_of), dtype=bool)  # subjects verified
        self._edge_on = np.zeros(self.ea.size, dtype=bool)
        #: per marker the track of the point it had last (a new track restarts its evidence)
        self._track = np.full(self.n_markers, -1, dtype=np.int64)
        #: per subject the markers withdrawn lately (decaying with ``verify_recent_s``)
        self._recent = np.zeros(len(n_of))
        self._decay = float(np.exp(-1.0 / max(1.0, c.verify_recent_s * tick_hz)))
        self._frame = 0
        self.withdrawn = 0  # markers withdrawn so far (diagnostics)
        self.dropped = 0  # subjects dropped so far
        self.exchanged = 0  # left-right pairs exchanged so far
        #: per marker its twin of the other side in the same subject (-1: none)
        self._mirror = np.full(self.n_markers, -1, dtype=np.int64)
        for tpl in templates:
            local = [
                n.split(":", 1)[-1]
                for n in booter.model.marker_names[tpl.offset : tpl.offset + tpl.n]
            ]
            for left, right in side_pairs(local):
                self._mirror[tpl.offset + left] = tpl.offset + right
                self._mirror[tpl.offset + right] = tpl.offset + left
        #: per subject its first marker and its count (its markers are contiguous)
        self._subject_span = [(t.offset, t.n) for t in templates]
        #: per subject its edges (indices into ea, eb)
        self._subject_edges = [
            np.flatnonzero(self._subject_of[self.ea] == s) for s in range(len(n_of))
        ]
        self._exchange_n = max(1, round(c.verify_exchange_s * tick_hz))
        #: per marker: it shares a trained body holding two or more left-right pairs with its
        #: twin (a symmetric plate: a head, a pelvis), whose own distances cannot tell a
        #: reading across it; such pairs are not exchanged (the boot's symmetries' business)
        self._in_plate = np.zeros(self.n_markers, dtype=bool)
        for mk in self._body_markers:
            inside = set(mk.tolist())
            twins = [k for k in mk.tolist() if self._mirror[k] in inside]
            if len(twins) >= 4:  # (two pairs: four markers)
                self._in_plate[twins] = True
        #: per trained body the left-right pairs of it and of every body that hangs from it
        #: (its subtree in the chain from the trunk: a whole limb, tried exchanged at once)
        self._limb_pairs = [
            tuple(
                self._side_units(
                    {k for h in self._subtree[g].tolist() for k in self._body_markers[h].tolist()}
                )
            )
            for g in range(len(self._body_markers))
        ]
        self._has_limb = np.array(
            [len(u) >= EXCHANGE_MIN_PAIRS for u in self._limb_pairs], dtype=bool
        )
        self._body_subject = np.array(
            [int(self._subject_of[bm[0]]) for bm in self._body_markers], dtype=np.int64
        )
        #: per (subject, pairs) exchanged: the frame before which they are not exchanged again
        self._exchange_done: dict[tuple[int, tuple[tuple[int, int], ...]], int] = {}
        self._exchange_hold = max(1, round(EXCHANGE_HOLD_S * rate))
        #: per subject the exchange the last ticks preferred and for how many ticks in a row
        self._exchange_seen: dict[int, tuple[tuple[tuple[int, int], ...], int]] = {}

    # ------------------------------------------------------------------ subjects
    def start(self, subject: int) -> None:
        """Verifies ``subject`` from now on, with no evidence yet (booted now)."""
        self._on[subject] = True
        self._refresh()
        self.reset_subject(subject)

    def stop(self, subject: int) -> None:
        """No longer verifies ``subject`` (dropped, or labeled by the stream's labels)."""
        self._on[subject] = False
        self._refresh()
        self.reset_subject(subject)

    def verifies(self, subject: int) -> bool:
        return bool(self._on[subject])

    def idle(self) -> bool:
        """True when no subject is verified: :meth:`update` would only count the frame, which
        this then does (the caller skips building its arguments)."""
        if self._on.any():
            return False
        self._frame += 1
        return True

    def reset_subject(self, subject: int) -> None:
        self._recent[subject] = 0.0
        self._forget(self._subject_of[self.ea] == subject)

    def reset_markers(self, markers: np.ndarray) -> None:
        """Forgets the evidence of every edge touching ``markers`` (withdrawn or placed anew)."""
        hit = np.zeros(self.n_markers, dtype=bool)
        hit[markers] = True
        self._forget(hit[self.ea] | hit[self.eb])

    def _forget(self, e: np.ndarray) -> None:
        self.ema[e] = 0.0
        self.n[e] = 0
        self.m1[e] = self.m2[e] = 0.0

    def _refresh(self) -> None:
        self._edge_on = self._on[self._subject_of[self.ea]]

    # ------------------------------------------------------------------ per frame
    def update(
        self, positions: np.ndarray, observed: np.ndarray, tracks: np.ndarray
    ) -> Verdict | None:
        """One frame: ``positions (M, 3)`` of the model's markers, ``observed (M,)`` those seen
        in this frame, ``tracks (M,)`` the track of each one's point (-1 where not observed).
        Every ``verify_every_s`` the edges take a sample and the decisions are made; returns
        them (None between ticks or when nothing is to be done). A marker seen on another
        track than before starts its evidence again: what its edges said was about the point
        it had (the labeler moved it, e.g. off a wrong point)."""
        self._frame += 1
        if self._frame % self._every or not self._edge_on.any():
            return None
        moved = observed & (tracks != self._track)
        if moved.any():
            self._track[moved] = tracks[moved]
            self.reset_markers(np.flatnonzero(moved & (self._track >= 0)))
        self._recent *= self._decay
        e = np.flatnonzero(self._edge_on & observed[self.ea] & observed[self.eb])
        if e.size == 0:
            return None
        p = positions.astype(np.float64, copy=False)
        d = np.sqrt(((p[self.ea[e]] - p[self.eb[e]]) ** 2).sum(axis=1))
        off = np.abs(d - self.D[e]) > self.tol[e]
        self.ema[e] += self._alpha * (off - self.ema[e])
        first = self.n[e] == 0
        self.m1[e] = np.where(first, d, self.m1[e] + self._alpha * (d - self.m1[e]))
        self.m2[e] = np.where(first, d * d, self.m2[e] + self._alpha * (d * d - self.m2[e]))
        self.n[e] += 1
        exchange = self._exchanges(e, observed, p) if self.config.verify_exchange else {}
        if exchange:  # (the other decisions wait for the evidence of the new reading)
            return Verdict({}, [], exchange)
        return self._decide(e, observed, p)

    def _exchanges(
        self, e: np.ndarray, observed: np.ndarray, p: np.ndarray
    ) -> dict[int, np.ndarray]:
        """Left and right markers of a verified subject read on each other's points (a boot
        from a still window read a returning performer's two feet exchanged: every within-foot
        distance holds, the pairs across the feet and to the shins do not, and nothing took
        the reading back: his feet stayed exchanged for good, the stream ``online``).

        Per verified subject, the markers of its trained bodies with a bad pair (off more often
        than ``verify_bad``) and of the far side of a joint whose pair is far off, grown by the
        bodies sharing two markers with them, give left-right pairs
        (:func:`~labeler_service.capture.model.side_pairs`; none inside a symmetric plate).
        Every subset of 2 to :data:`EXCHANGE_MAX_PAIRS` of them is tried exchanged
        (:meth:`_best_exchange`, scored on the edges it touches), and so is each of their
        bodies with every segment that hangs from it, whole (a leg read as the other from the
        hip down; tune18 ``gaps2`` in the boot matrix, a mirrored boot after gaps); the best
        is taken when it wins on every tick for ``verify_exchange_s`` and the same pairs were
        not exchanged in the last :data:`EXCHANGE_HOLD_S`: a pose the template has not seen
        costs every reading alike, a mirrored one only the current."""
        c = self.config
        ready = e[self.n[e] >= self._min_n]
        bad = ready[self.ema[ready] > c.verify_bad]
        if bad.size == 0:  # (most ticks)
            self._exchange_seen.clear()
            return {}
        rigid = self.joint[bad] < 0
        far = np.abs(self.m1[bad] - self.D[bad]) >= c.verify_cut_tol * self.tol[bad]
        out: dict[int, np.ndarray] = {}
        # the markers of the trained bodies with a bad pair, and of the far side of a joint
        # whose pair is far off (a foot read as the other: its pairs to the shin)
        hit: set[int] = set()
        for a, b in zip(self.ea[bad[rigid]].tolist(), self.eb[bad[rigid]].tolist(), strict=True):
            for g in set(self._marker_bodies[a]) & set(self._marker_bodies[b]):
                hit.update(self._body_markers[g].tolist())
        for j in np.unique(self.joint[bad[~rigid & far]]).tolist():
            hit.update(self._body_markers[int(self.joints[j][2])].tolist())
        # and the bodies that share two markers with them (one segment: a foot's triangles)
        for _ in range(3):
            more = {
                g for k in hit for g in self._marker_bodies[k]
                if len(hit.intersection(self._body_markers[g].tolist())) >= 2
            }  # fmt: skip
            grown = hit.union(*(self._body_markers[g].tolist() for g in more))
            if grown == hit:
                break
            hit = grown
        by_subject: dict[int, set[int]] = {}
        for k in hit:
            by_subject.setdefault(int(self._subject_of[k]), set()).add(k)
        # the trained bodies among them (two of their markers hit), for their whole limbs
        n_hit = np.bincount(
            [g for k in hit for g in self._marker_bodies[k]], minlength=len(self._body_markers)
        )
        limbs_of: dict[int, set[tuple[tuple[int, int], ...]]] = {}
        for g in np.flatnonzero((n_hit >= 2) & self._has_limb).tolist():
            limbs_of.setdefault(int(self._body_subject[g]), set()).add(self._limb_pairs[g])
        for s in range(len(self._subject_edges)):
            mine = by_subject.get(s) if self._on[s] else None
            if not mine:
                self._exchange_seen.pop(s, None)
                continue
            units = self._side_units(mine)
            # each such body with every segment that hangs from it, as one more reading: a leg
            # read as the other from the hip down (its knee, shin and foot read across with
            # it) is off only at the hip, and no subset of the thigh's pairs reads it better
            limbs = limbs_of.get(s, set())
            every = sorted(set(units).union(*limbs))
            rows = [] if len(units) > EXCHANGE_MAX_PAIRS else [_subsets(every, units)]
            n_sub = sum(r.shape[0] for r in rows)  # (the rows after these: whole limbs)
            rows += [
                np.isin(np.arange(len(every)), [every.index(u) for u in lm])[None]
                for lm in sorted(limbs)
            ]
            best = None
            if every and rows:
                bits = np.concatenate(rows)
                whole = np.arange(bits.shape[0]) >= n_sub
                best = self._best_exchange(s, every, observed, p, bits, whole)
            if best is None:
                self._exchange_seen.pop(s, None)
                continue
            was, n = self._exchange_seen.get(s, ((), 0))
            n = n + 1 if was == best else 1
            self._exchange_seen[s] = (best, n)
            if n >= self._exchange_n and self._frame >= self._exchange_done.get((s, best), -1):
                del self._exchange_seen[s]
                # (the same pairs are not exchanged back soon: a dancer's forearms, read right
                # by one exchange, were read back 0.46 s later, from fresh evidence)
                self._exchange_done[(s, best)] = self._frame + self._exchange_hold
                out[s] = np.array(best, dtype=np.int64).reshape(-1, 2)
                self.exchanged += len(best)
                self.reset_markers(out[s].ravel())
        return out

    def _side_units(self, markers: set[int]) -> list[tuple[int, int]]:
        """The left-right pairs among ``markers`` (of one subject), none inside a symmetric
        plate: ``(lower, higher)`` global marker indices, sorted."""
        mk = np.array(sorted(markers), dtype=np.int64)
        mk = mk[~self._in_plate[mk]]
        tw = self._mirror[mk]
        return sorted(
            {(int(min(a, b)), int(max(a, b))) for a, b in zip(mk, tw, strict=True) if b >= 0}
        )

    def _best_exchange(
        self,
        s: int,
        units: list[tuple[int, int]],
        observed: np.ndarray,
        p: np.ndarray,
        bits: np.ndarray | None = None,
        limbs: np.ndarray | None = None,
    ) -> tuple[tuple[int, int], ...] | None:
        """The subset of ``units`` whose exchange reads subject ``s`` best, when it clearly
        beats the current reading; None otherwise. ``bits (R, len(units))``: the subsets
        tried (default every one); ``limbs (R,)``: those that are a whole limb (a body with
        every segment that hangs from it). Each subset is scored on the edges that touch its
        markers (the other edges read alike in both, and a pose the template never saw adds
        its own excess to every reading), a whole limb on those of them where the two readings
        differ: the mean excess over the template's tolerances (each capped at
        :data:`EXCHANGE_CAP`) of the exchanged reading must be at most :data:`EXCHANGE_GAIN` of
        the current one's, which is at least :data:`EXCHANGE_MIN_EXCESS`."""
        edges = self._subject_edges[s]
        if bits is None:
            bits = _subsets(units, units)
        n_sub = bits.shape[0]
        # (the subject's markers are contiguous: its own columns only, not every subject's)
        lo, n_s = self._subject_span[s]
        sigma = np.tile(np.arange(lo, lo + n_s), (n_sub, 1))
        inside = np.zeros((n_sub, n_s), dtype=bool)
        for u, (a, b) in enumerate(units):
            on = bits[:, u]
            sigma[on, a - lo], sigma[on, b - lo] = b, a
            inside[on, a - lo] = inside[on, b - lo] = True
        ea, eb = self.ea[edges], self.eb[edges]
        touch = inside[:, ea - lo] | inside[:, eb - lo]

        tol, dd = self.tol[edges], self.D[edges]

        def excess(ia: np.ndarray, ib: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """Per edge (and subset) its excess over its tolerance, and whether it is seen."""
            seen = observed[ia] & observed[ib]
            d = np.sqrt(((p[ia] - p[ib]) ** 2).sum(axis=-1))
            x = np.clip((np.abs(d - dd) - tol) / tol, 0.0, EXCHANGE_CAP)
            return np.where(seen, np.nan_to_num(x), 0.0), seen

        x0, seen0 = excess(ea, eb)  # the current reading: one row, masked per subset below
        x1, seen1 = excess(sigma[:, ea - lo], sigma[:, eb - lo])
        # a whole limb's reading counts the edges on which the two readings differ: its own
        # pairs read alike either way (a leg's twin holds them too) and would thin the hip's
        # excess below the threshold; a subset's counts every edge it touches
        count = touch.copy()
        if limbs is not None and limbs.any():
            count[limbs] &= seen0 & seen1[limbs] & (x0 != x1[limbs])
        now = (count * x0).sum(axis=1) / np.maximum((count & seen0).sum(axis=1), 1)
        new = (count * x1).sum(axis=1) / np.maximum((count & seen1).sum(axis=1), 1)
        ok = (now >= EXCHANGE_MIN_EXCESS) & (new <= EXCHANGE_GAIN * now)
        # a segment and its twin: two pairs or more (two markers on each other's points are
        # the labeler's own exchange's; alone, a head plate's front pair read across was
        # "exchanged" for 13 frames by a ghost in one cell of the boot matrix)
        ok &= bits.sum(axis=1) >= EXCHANGE_MIN_PAIRS
        if not ok.any():
            return None
        k = int(np.argmax(np.where(ok, now - new, -np.inf)))
        return tuple(units[u] for u in range(len(units)) if bits[k, u])

    def _partner_lacks(self, markers: np.ndarray, observed: np.ndarray) -> bool:
        """Some other subject lacks (has, unobserved) a marker of the same name, either side,
        for at least half of ``markers``: where a partner's segment read as this subject's
        would have come from."""
        lacks: dict[int, set[int]] = {}
        for k in markers:
            for j in self._twins[k]:
                if not observed[j]:
                    lacks.setdefault(int(self._subject_of[j]), set()).add(int(k))
        need = max(1, (len(markers) + 1) // 2)
        return any(len(v) >= need for v in lacks.values())

    def _contact(self, observed: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``(M,)`` observed markers within ``verify_contact_mm`` of an observed marker of
        another subject: only there can a label be another performer's."""
        if self.config.verify_contact_mm <= 0:
            return observed.copy()  # (0: everywhere, as the setting says)
        out = np.zeros(self.n_markers, dtype=bool)
        idx = np.flatnonzero(observed)
        if idx.size < 2:
            return out
        pairs = cKDTree(p[idx]).query_pairs(self.config.verify_contact_mm, output_type="ndarray")
        if pairs.size == 0:
            return out
        a, b = idx[pairs[:, 0]], idx[pairs[:, 1]]
        other = self._subject_of[a] != self._subject_of[b]
        out[a[other]] = True
        out[b[other]] = True
        return out

    def _decide(self, e: np.ndarray, observed: np.ndarray, p: np.ndarray) -> Verdict | None:
        c = self.config
        ready = e[self.n[e] >= self._min_n]
        if ready.size == 0:
            return None
        bad = self.ema[ready] > c.verify_bad
        # a joint's pair off its trained range but steady is the pose (one the training did
        # not see: an arm raised into a hug), not another performer's limb, which moves
        spread = np.sqrt(np.maximum(self.m2[ready] - self.m1[ready] ** 2, 0.0))
        bad &= spread >= self.spread[ready]
        if not bad.any():
            return None
        # joints: most of the edges with evidence bad, each from a near-side marker its own
        # body confirms (two good rigid edges, no bad one): a wrong marker on the near side
        # breaks its edges, not the far segment
        withdraw: dict[int, set[int]] = {}
        jr = self.joint[ready]
        on_joint = jr >= 0
        if on_joint.any() and c.verify_cut:
            m = self.n_markers
            rig = ~on_joint
            ends = np.concatenate([self.ea[ready[rig]], self.eb[ready[rig]]])
            rb = np.concatenate([bad[rig], bad[rig]])
            r_bad = np.bincount(ends, weights=rb, minlength=m)
            r_all = np.bincount(ends, minlength=m)
            confirmed = (r_bad == 0) & (r_all >= 2)
            # (ea is the near side of every joint edge)
            on_joint = on_joint & confirmed[self.ea[ready]]
            nj = self.joints.shape[0]
            # (a segment is cut only on pairs far off on average: an untrained pose keeps the
            # own limb's pairs within a tolerance or two)
            far = np.abs(self.m1[ready] - self.D[ready]) >= c.verify_cut_tol * self.tol[ready]
            cut = bad & far
            n_bad = np.bincount(jr[on_joint], weights=cut[on_joint], minlength=nj)
            n_all = np.bincount(jr[on_joint], minlength=nj)
            broken = np.flatnonzero((n_bad >= 2) & (2 * n_bad > n_all))
            for g in broken:
                s, near_b, far_b = (int(x) for x in self.joints[g])
                if not self._partner_lacks(self._body_markers[far_b], observed):
                    continue
                sub = self._subtree[far_b]
                beyond = set(np.concatenate([self._body_markers[b] for b in sub]).tolist())
                keep = set()
                for mk in beyond:
                    if any(b not in sub for b in self._marker_bodies[mk]):
                        keep.add(mk)
                withdraw.setdefault(s, set()).update(beyond - keep)
        # markers off their own body: two or more bad rigid edges, more than good ones; the
        # worst first, its edges then no longer count (a marker whose partners are wrong is not)
        rig = (self.joint[ready] < 0) | self.config.verify_marker_joints
        if (bad & rig).any():
            m = self.n_markers
            ea, eb, eb_bad = self.ea[ready[rig]], self.eb[ready[rig]], bad[rig]
            # edges of one trained body (the others are a joint's pairs)
            eb_body = self.joint[ready[rig]] < 0
            live = np.ones(ea.size, dtype=bool)
            while True:
                ends = np.concatenate([ea[live], eb[live]])
                b2 = np.concatenate([eb_bad[live], eb_bad[live]])
                n_bad = np.bincount(ends, weights=b2, minlength=m)
                n_all = np.bincount(ends, minlength=m)
                g2 = np.concatenate([~eb_bad[live] & eb_body[live]] * 2)
                n_good = np.bincount(ends, weights=g2, minlength=m)
                s2 = np.concatenate([eb_bad[live] & eb_body[live]] * 2)
                split = np.bincount(ends, weights=s2, minlength=m) > 0
                # (a pair of the marker's own trained body bad while verify_support of its
                # body pairs hold: a body trained still across a joint has split; whether the
                # bad partners agree among themselves is not checked)
                off = (n_bad >= 2) & (2 * n_bad > n_all) & ~(split & (n_good >= c.verify_support))
                if not off.any():
                    break
                mk = int(np.argmax(np.where(off, n_bad - 0.5 * (n_all - n_bad), -np.inf)))
                withdraw.setdefault(int(self._subject_of[mk]), set()).add(mk)
                live &= (ea != mk) & (eb != mk)
        if not withdraw:
            return None
        # (a performer alone, or apart from the others, keeps its labels: skin sliding over a
        # model trained on another segment is not another performer's limb)
        contact = self._contact(observed, p)
        withdraw = {s: mks for s, mks in withdraw.items() if contact[np.array(sorted(mks))].any()}
        out: dict[int, np.ndarray] = {}
        drop: list[int] = []
        for s, mks in withdraw.items():
            arr = np.array(sorted(mks), dtype=np.int64)
            arr = arr[observed[arr]]  # (only labeled markers have anything to withdraw)
            if arr.size == 0:
                continue
            n_obs = int(np.count_nonzero(observed[self._subject_of == s]))
            self._recent[s] += arr.size
            if self._recent[s] >= c.verify_drop * max(1, n_obs + self._recent[s] - arr.size):
                drop.append(s)
                self.dropped += 1
            else:
                out[s] = arr
                self.withdrawn += int(arr.size)
                self.reset_markers(arr)
        return Verdict(out, drop) if out or drop else None


def extend_blocked(
    booter: Booter,
    points: np.ndarray,
    history: np.ndarray,
    labels: np.ndarray,
    subjects: list[int],
    blocked: dict[int, np.ndarray] | None,
    age: np.ndarray | None = None,
    checked: list[int] | tuple[int, ...] = (),
) -> np.ndarray:
    """:meth:`Booter.extend` where each subject of ``blocked`` (subject -> ``(N,)`` bool) may not
    take the points marked for it (their tracks are hidden from that subject's call);
    ``checked``: the subjects whose readings it re-checks (:meth:`Booter.extend`)."""
    blocked = {s: b for s, b in (blocked or {}).items() if s in subjects and b.any()}
    plain = [s for s in subjects if s not in blocked]
    out = np.asarray(labels, dtype=np.int64)
    if plain:
        out = booter.extend(points, history, out, plain, age, checked)
    for s, mask in blocked.items():
        hist = np.array(history, dtype=np.float64, copy=True)
        hist[mask] = np.nan
        # (no joint fill: the verifier has just withdrawn labels of this subject; filling its
        # leftover markers would place them again on other points)
        out = booter.extend(points, hist, out, [s], checked=checked)
    return out
