"""``LabelerConfig``: every tunable of the online labeler, with documented defaults.

The service exposes it in its settings; ``docs/algorithm.md`` explains each choice.
"""

from __future__ import annotations

from typing import Literal, TypedDict

from pydantic import BaseModel, ConfigDict, Field


class BodyRule(TypedDict):
    """Keywords of the rigid-body rule (``training.select_bodies``, ``train_subject``)."""

    tolerance_mm: float
    distance_weight: float
    min_size: int
    max_size: int
    all_seeds: bool


class LabelerConfig(BaseModel):
    """Parameters of the seed-003 labeler (defaults measured on the acceptance scenes)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # motion model (Eq. 3-4) and gating
    gate_chi2: float = Field(
        16.27, gt=0, description="Mahalanobis gate, chi-square with 3 dof (16.27 = 99.9 %)"
    )
    K: int = Field(4, ge=1, le=16, description="at most K candidates per marker (best first)")
    min_gate_mm: float = Field(
        30.0,
        gt=0,
        description="the gate never shrinks below this radius: real captures have heavy-tailed "
        "prediction errors (p99.9 ~ 20 mm at 120 Hz on the CMU takes)",
    )
    common_mode_radius_mm: float = Field(
        120.0, gt=0, description="nearest-point radius of the per-subject common-mode shift"
    )
    common_mode_iters: int = Field(
        2, ge=0, le=5, description="iterations of the common-mode shift (0 = off)"
    )
    exchange: bool = Field(
        True,
        description="two markers tracked in the previous frame that hold each other's points "
        "exchange them when that brings their distances to their predictions below "
        "exchange_ratio of the current ones and their bodies' shape does not refute it (a "
        "symmetric body's pair)",
    )
    exchange_ratio: float = Field(
        0.25,
        gt=0,
        le=1,
        description="exchange: the exchanged points' summed distances to the two predictions "
        "must be below this fraction of the current ones",
    )
    reacquire_mm: float = Field(
        250.0,
        ge=0,
        description="bodies with no observed marker search free points this far (0 = off)",
    )
    reacquire_estimate_mm: float = Field(
        45.0,
        gt=0,
        description="the wide pass searches this close to a marker's rigid-neighbourhood "
        "estimate when 3+ neighbours give one (else reacquire_mm around its prediction)",
    )
    reacquire_loose_mm: float = Field(
        90.0,
        gt=0,
        description="the wide pass searches this far from a rigid-neighbourhood estimate whose "
        "kept neighbours still disagree by more than robust_fit_mm (a joint moved while the "
        "marker was hidden)",
    )
    reacquire_keep_observed: bool = Field(
        True,
        description="the wide pass keeps the markers of weakly seen bodies that were observed in "
        "the previous frame too (it always releases fresh acquisitions there, undoing a wrong "
        "partial re-acquisition)",
    )
    reacquire_sigma: float = Field(
        2.0,
        gt=0,
        description="missing_sigma of the wide re-acquisition pass (stricter: it sees more points)",
    )
    reacquire_all: bool = Field(
        True,
        description="the wide pass serves every missing marker (False: only bodies that saw "
        "nothing)",
    )
    verify_mm: float = Field(
        8.0,
        ge=0,
        description="an ambiguous marker farther than this from its rigid-neighbourhood (Kabsch) "
        "estimate moves to a free point twice as close (0 = no 3D check)",
    )
    verify_every: int = Field(
        8, ge=0, description="every marker gets the 3D check at least once in this many frames"
    )
    swap_check: bool = Field(
        True, description="the 3D check may exchange the points of two markers (swaps)"
    )
    contest: bool = Field(
        True,
        description="after Algorithm 1, a point held by a marker that jumped more than jump_mm "
        "for it goes back to the marker tracked onto it in the previous frame",
    )
    keep_tracks: bool = Field(
        True,
        description="after the contest and the exchange, a marker tracked in the previous frame "
        "whose track continues unambiguously onto a point (within jump_mm of its last point "
        "moved by its velocity, no other point within twice its predicted deviation) gets it "
        "back from a marker not tracked as long (a coasting one, a ghost's), or from nobody",
    )
    anonymous_tracks: bool = Field(
        True,
        description="a point followed unlabeled from frame to frame (unambiguously, within "
        "jump_mm) is refused to every marker observed while it was there on a track that began "
        "before it: it is another point (a ghost, a marker the model does not know)",
    )
    acquire_unseen: bool = Field(
        True,
        description="a marker never observed (a labeler started from a model: the labeled frames "
        "did not show it) takes the free point where the trained shapes of its bodies, fitted to "
        "3+ tracked members, place it (within reacquire_near_mm, unambiguous), or else the only "
        "free point keeping its trained distances to 2+ tracked members",
    )
    acquire_lost_frames: int = Field(
        5,
        ge=0,
        description="a marker lost this many frames in a row is placed like a never-observed one "
        "(acquire_unseen's shape rule, or the only free point keeping 3+ trained distances over "
        "its links that do not bend now; 0 = off)",
    )
    acquire_restart: bool = Field(
        True,
        description="a lost marker placed by acquire_lost_frames' rules starts a new track on its "
        "point, moving as the members that place it move (not with its coasted velocity)",
    )
    acquire_follow: bool = Field(
        True,
        description="a marker that loses its point follows the point it went on as (unambiguous, "
        "free) and takes it back when two or more anchors keep their trained distances over "
        "links that do not bend",
    )
    acquire_together: bool = Field(
        True,
        description="markers of one body lost together (3+, one for acquire_lost_frames) take "
        "together the free points their reference shape fits, when the trained distances to "
        "the members on points name one reading (with acquire_lost_frames > 0)",
    )
    reacquire_near_mm: float = Field(
        12.0, ge=0, description="a missing marker takes a free point this close to its estimate"
    )
    reject_mm: float = Field(
        25.0,
        gt=0,
        description="a marker re-acquired this frame is dropped if its point is this far from "
        "its rigid-neighbourhood estimate and no free point is closer (at any rate: the estimate "
        "comes from the same frame's neighbours)",
    )
    reject_limit: int = Field(
        6,
        ge=0,
        description="at most this many rejections in a row per marker (no lock-out); ghosts "
        "live a few frames, a marker that really moved is accepted after this many",
    )
    jump_mm: float = Field(
        8.0,
        gt=0,
        description="a point this far from the Kalman prediction triggers the 3D check",
    )
    suspect_mm: float = Field(
        60.0,
        ge=0,
        description="a free point this close to a labeled marker's prediction triggers its 3D "
        "check (0 = off)",
    )
    measurement_noise_mm: float = Field(
        1.0, gt=0, description="R = (this)^2 I per axis: reconstruction noise of a point"
    )
    recovered_noise_mm: float = Field(
        6.0, gt=0, description="R used when a recovered position updates the Kalman state"
    )
    max_position_sd_mm: float = Field(
        150.0, gt=0, description="cap on the predicted position deviation of a lost marker"
    )
    velocity_decay: float = Field(
        0.8, ge=0, le=1, description="velocity factor per frame while a marker is unrecoverable"
    )
    anchor_lost: bool = Field(
        True,
        description="a lost marker without a rigid estimate whose prediction broke the distance "
        "to its two most rigidly linked observed co-members (anchors) is searched for in the wide "
        "pass around its offset from them at its last observation, rotated with them, among "
        "points that keep those distances (docs/algorithm.md)",
    )
    anchor_loose: bool = Field(
        True,
        description="with anchor_lost: a lost marker whose rigid estimate is loose (its recovery "
        "neighbours disagree) and breaks an anchor link is searched for around the anchored "
        "estimate too, not around the loose estimate (docs/algorithm.md)",
    )
    anchor_state: bool = Field(
        False,
        description="with anchor_lost: also re-anchor the lost marker's Kalman state (off: only "
        "the wide re-acquisition pass searches around the anchored estimate)",
    )
    anchor_slack_mm: float = Field(
        15.0,
        gt=0,
        description="slack of an anchor link (mm), plus 3 times the link's window A + w D: a "
        "prediction off by more is broken, a point off by more is not the marker",
    )
    # structure model (Eq. 1-2) and fitting (Eq. 5, Algorithm 1)
    window_T: int = Field(240, ge=2, le=4096, description="sliding window of Eq. 1-2 (frames)")
    min_window_samples: int = Field(
        10, ge=1, description="pair samples needed before the window replaces the trained D, A"
    )
    a_floor_mm: float = Field(2.0, gt=0, description="A is floored at this value in Eq. 5")
    a_relative: float = Field(
        0.02, ge=0, description="A is also floored at this fraction of D (long links slide more)"
    )
    missing_sigma: float = Field(
        3.0,
        gt=0,
        description='"missing" scores each link as a distance off by this many A (Eq. 5)',
    )
    motion_weight: float = Field(
        0.25, ge=0, description="weight of the Kalman likelihood term per marker beside Eq. 5"
    )
    # rigid bodies (structure.py)
    body_tolerance_mm: float = Field(6.0, gt=0, description="largest cost A + w D inside a body")
    body_distance_weight: float = Field(0.02, ge=0, description="w: preference for close pairs")
    body_all_seeds: bool = Field(
        True, description="every marker seeds a body (more, overlapping bodies)"
    )
    body_min_size: int = Field(3, ge=1, le=8)
    body_max_size: int = Field(6, ge=1, le=8)
    # missing markers (Sec. 3.3)
    recovery_set_size: int = Field(
        4, ge=1, le=7, description="neighbours (lowest A + w D) a hidden marker is recovered from"
    )
    robust_fit_mm: float = Field(
        5.0,
        gt=0,
        description="Kabsch recovery drops neighbours whose residual exceeds this (while > 3)",
    )
    snapshot_age: int = Field(
        10,
        ge=1,
        description="a recovery snapshot is taken only of markers observed this many frames in "
        "a row",
    )
    recovered_min_neighbours: int = Field(
        3,
        ge=1,
        le=7,
        description="a hidden marker's estimate is published (state recovered) only when this "
        "many of its recovery neighbours are observed in the frame: with fewer it is a "
        "translation of theirs, no rotation (a serving arm's hand put 1 m off), which still "
        "steers the tracker weakly but is reported missing",
    )
    recovery: Literal["kabsch", "displacement"] = Field(
        "kabsch", description="rigid fit of the visible body markers, or the paper's averaging"
    )
    init_frames: int = Field(
        50, ge=3, description="labeled frames expected before training (informational)"
    )
    # rigid-body prediction (kernels/motion.py)
    body_prediction: bool = Field(
        True,
        description="predict a marker by its rigid body's motion (the last inter-frame rigid "
        "motion applied again) when that body has recently predicted it better than its Kalman "
        "filter did",
    )
    body_error_frames: float = Field(
        10.0,
        ge=1,
        description="memory (frames) of the running prediction errors that choose between the "
        "rigid-body and the Kalman prediction of each marker",
    )
    body_rigid_mm: float = Field(
        20.0,
        ge=0,
        description="a body predicts only while one rigid motion moves its members between two "
        "frames within this many mm (a body spanning a joint that bends does not; 0 = always)",
    )
    # 3D template check, swap repair, joint re-acquisition, guarded Eq. 1-2 (kernels/repair.py)
    repair: bool = Field(
        True,
        description="3D template check of suspect rigid bodies against their reference shape, "
        "swap repair and joint re-acquisition (False = off)",
    )
    repair_check_mm: float = Field(
        6.0,
        gt=0,
        description="a body's assignment fails the 3D template check when its shape RMS after "
        "the best proper rotation exceeds this; a permutation is accepted only within it",
    )
    repair_tol_mm: float = Field(
        10.0,
        gt=0,
        description="template fit: a pair of points may differ from its reference distance by "
        "this plus 3 trained deviations",
    )
    repair_age: int = Field(
        30,
        ge=0,
        description="a body with a member observed for fewer frames than this in a row is "
        "checked every frame",
    )
    repair_frames: int = Field(
        2,
        ge=1,
        description="a permutation that relabels held points must fit clearly better in this "
        "many consecutive checks",
    )
    repair_radius_mm: float = Field(
        60.0,
        ge=0,
        description="free points this far beyond twice the body's extent join its template fit",
    )
    repair_max_nodes: int = Field(
        5000, ge=1, description="node budget of one template fit (interpretation tree)"
    )
    repair_pairs: bool = Field(
        True,
        description="pair check: a freshly re-acquired marker's point goes to a body partner "
        "when the mean excess of its trained links to long-tracked anchors (beyond 3 trained "
        "deviations) exceeds repair_check_mm and the change cuts it to a third (False = off)",
    )
    repair_senior_frames: int = Field(
        3,
        ge=0,
        description="pair check: when the long-tracked anchors ask for nothing, anchors observed "
        "this many frames longer than the marker are asked (a limb re-acquired whole after a "
        "fast move), and their change is made when asked for in two frames in a row (0 = only "
        "anchors observed repair_age frames)",
    )
    contact_mm: float = Field(
        25.0,
        ge=0,
        description="a labeled point within this of another subject's labeled point registers "
        "a contact between the two markers, decided when the points part (0 = off)",
    )
    contact_part_mm: float = Field(
        10.0,
        gt=0,
        description="a contact is judged while its two points are this far apart (up to twice "
        "contact_mm): "
        "the labels are exchanged when the exchange fits the pre-contact neighbourhoods "
        "clearly better",
    )
    contact_ratio: float = Field(
        1.0 / 3.0,
        gt=0,
        le=1,
        description="a contact's exchange needs its summed distance to the two pre-contact "
        "estimates below this fraction of the kept assignment's",
    )
    contact_max_s: float = Field(
        2.0,
        gt=0,
        description="a contact that has not parted within this many seconds is dropped undecided",
    )
    window_guard: bool = Field(
        True,
        description="Eq. 1-2 learns only from bodies that pass the 3D template check",
    )
    window_drift_mm: float = Field(
        0.0,
        ge=0,
        description="the window's D stays within this of the trained D (0 = unbounded)",
    )
    distrust: bool = Field(
        True,
        description="the wide re-acquisition pass satisfies bodies in the order of their Eq. 5 "
        "score times their rigidity (body_tolerance_mm over the sliding-window A + w D of each "
        "link): a body the data shows bending pulls points after the bodies it shows rigid",
    )
    presence_min_markers: int = Field(
        3,
        ge=0,
        le=8,
        description="a subject with fewer markers than this observed in the previous frame "
        "(absent) keeps its labels only if one of its rigid bodies has this many labeled members "
        "whose distances agree with the body's D (a subject that left cannot hold isolated ghost "
        "points; 0 = off)",
    )
    presence_drop: float = Field(
        0.25,
        ge=0,
        le=1,
        description="a subject labeled in a frame with fewer than this share of the markers "
        "observed in the previous frame (a sudden vanish: a take that ends, a performer hidden "
        "at once) while the other subjects kept at least half of theirs (not a system dropout) "
        "is checked as absent: it keeps its labels only if one of its rigid bodies shows its "
        "shape (points taken near where it was are ghosts or other performers' markers; "
        "0 = off)",
    )
    presence_tol_mm: float = Field(
        15.0,
        gt=0,
        description="the presence check accepts a pair of members whose distance is within this "
        "plus 3 A of D",
    )
    absent_frames: int = Field(
        60,
        ge=0,
        description="a subject whose markers have all been missing this many frames has left: "
        "its markers are not re-acquired by the wide pass (0 = off)",
    )
    # structure re-formed from the stream's own motion (ours, issue 10; labeling/restructure.py)
    restructure_s: float = Field(
        0.5,
        ge=0,
        description="every this many seconds of stream a thin structure (restructure_max_train_"
        "frames) is re-formed from the pair-distance statistics of the labeler's confident "
        "output: the trained bodies stay, the bodies the evidence shows rigid are added "
        "(docs/algorithm.md; 0 = off)",
    )
    restructure_age: int = Field(
        10,
        ge=1,
        description="a marker's distances count as evidence only while it has been observed "
        "this many frames in a row and every body holding it passes the 3D check",
    )
    restructure_sample_hz: float = Field(
        60.0,
        gt=0,
        description="the evidence is sampled at most this often (a 360 Hz stream adds every "
        "sixth frame)",
    )
    restructure_prior_s: float = Field(
        5.0,
        ge=0,
        description="a labeler from a model counts the model's D and A as this many seconds of "
        "evidence (the trained model is the anchor the stream relaxes)",
    )
    restructure_max_train_frames: int = Field(
        12,
        ge=1,
        description="only a structure learned from fewer samples than this is re-formed: a "
        "labeled window of fewer frames (5 at 12.5 Hz) or a model counted as fewer "
        "(restructure_prior_s times the rate); re-forming a 20-frame structure lost accuracy",
    )
    restructure_break_mm: float = Field(
        0.0,
        ge=0,
        description="a trained body is dropped when the evidence shows a link of it costing more "
        "than this (A + w D); 0 = never (the default: bodies trained across a joint link a limb "
        "to the trunk, and a lost limb is re-acquired through them)",
    )
    restructure_tolerance_mm: float = Field(
        6.0,
        gt=0,
        description="the body rule's tolerance (largest A + w D) on the evidence",
    )
    restructure_recovery: bool = Field(
        False,
        description="re-form the recovery sets from the evidence too (the most rigid neighbours "
        "under motion); off: a limb lost whole then has no member outside it (docs/algorithm.md)",
    )
    restructure_margin_mm: float = Field(
        2.0,
        ge=0,
        description="with restructure_recovery, a recovery set is replaced only by one whose "
        "worst link costs this much less (each replacement waits for a new snapshot)",
    )
    restructure_add: bool = Field(
        True,
        description="add every body the evidence shows rigid (the body rule at "
        "restructure_tolerance_mm) that no kept body contains; off: only bodies for markers no "
        "kept body holds",
    )

    def body_rule(self, tolerance_mm: float | None = None) -> BodyRule:
        """The rigid-body rule's settings as keywords of ``training.select_bodies`` and
        ``training.train_subject`` (``tolerance_mm`` defaults to ``body_tolerance_mm``): one
        place, so the window's training and the restructure use the same rule."""
        return {
            "tolerance_mm": self.body_tolerance_mm if tolerance_mm is None else tolerance_mm,
            "distance_weight": self.body_distance_weight,
            "min_size": self.body_min_size,
            "max_size": self.body_max_size,
            "all_seeds": self.body_all_seeds,
        }
