"""``BootConfig``: the parameters of the boot (labeling/boot.py); one frozen pydantic model."""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field

#: How often the labeled start's booter learns again from the stream (s): the window labeler's
#: ``relearn_every_s`` (registry.make_window_labeler) and a service stream's default.
WINDOW_RELEARN_S = 2.0
#: The events of :attr:`BootingLabeler.events` that take labels from a booted subject:
#: ``withdraw`` (the re-verification withdrew some of its markers' labels), ``reject`` (it
#: dropped the subject), ``drop`` (the subject vanished), ``jump`` (the scene jumped past its
#: tracks, ``jump_fraction``) and ``blackout`` (points back after ``blackout_reboot_s`` with
#: none); a dropped subject is booted again.
LOSS_EVENTS = ("withdraw", "reject", "drop", "jump", "blackout")
#: The events of the re-verification a service counts and logs: the losses, and ``exchange``
#: (a segment and its mirror twin read on each other's points, exchanged back).
VERIFY_EVENTS = (*LOSS_EVENTS, "exchange")


class BootConfig(BaseModel):
    """Parameters of the boot (defaults measured on the simulated and composed scenes)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    window_s: float = Field(0.1, gt=0, description="window of tracked frames used by a boot")
    min_window_frames: int = Field(4, ge=2, description="at least this many frames per window")
    max_window_frames: int = Field(24, ge=2, description="at most this many frames per window")
    track_gate_mm: float = Field(6.0, gt=0, description="tracker gate around the prediction")
    track_accel_mm_s2: float = Field(
        100000.0,
        ge=0,
        description="acceleration the tracker gate allows (adds a dt^2 to it; a sprinter's "
        "feet at ground contact exceed 40 m/s^2 by far)",
    )
    track_speed_mm_s: float = Field(
        10000.0,
        ge=0,
        description="speed the gate allows for a point without velocity yet (a sprint is 9 m/s: "
        "at 3 m/s no marker of a sprinter ever got a second frame)",
    )
    track_neighbour_mm: float = Field(
        300.0,
        ge=0,
        description="a point without velocity yet is predicted at the mean velocity of the "
        "nearest tracked points within this distance (0: not moved); a sprinter's foot moves "
        "85 mm a frame at 250 Hz, and a broken track could never be continued",
    )
    track_relative_speed_mm_s: float = Field(
        5000.0,
        ge=0,
        description="speed relative to its neighbours the gate allows for a point predicted "
        "from them",
    )
    track_neighbour_gate_mm: float = Field(
        150.0,
        gt=0,
        description="the neighbours' prediction only while its gate (track_gate_mm + a dt^2 + "
        "the relative speed dt) is at most this: a gate wider than the spacing of a segment's "
        "markers tells no marker from the next (at 25 Hz and below it cost the matrix labels)",
    )
    track_hold_frames: int = Field(
        2,
        ge=0,
        description="empty frames in a row (a camera dropout: no point at all) that the tracks "
        "outlive; one empty frame in ten ended every track, so a stream never booted",
    )
    min_track_fraction: float = Field(
        0.75, gt=0, le=1, description="a point must be tracked over this fraction of the window"
    )
    tol_mm: float = Field(4.0, gt=0, description="absolute pair-distance tolerance")
    tol_sigma: float = Field(4.0, ge=0, description="pair-distance tolerance in units of A")
    tol_relative: float = Field(
        0.01,
        ge=0,
        description="relative pair-distance tolerance (raise to 0.05 for another person's model)",
    )
    pair_sigma: float = Field(
        4.0, ge=0, description="tolerance (units of A) for pairs across bodies in a hypothesis"
    )
    body_hidden: int = Field(
        2, ge=0, description="a body candidate may miss this many markers (keeping 3 or more)"
    )
    reach_relative: float = Field(
        0.5,
        ge=0,
        description="pairs across bodies may be this fraction of D longer (poses not trained)",
    )
    rigid_a_mm: float = Field(
        8.0,
        gt=0,
        description="pairs with A + rigid_weight D at most this are rigid (one segment)",
    )
    rigid_weight: float = Field(0.0, ge=0, description="preference for close rigid pairs")
    min_support: int = Field(
        2, ge=1, description="rigid links that must agree before a marker joins a hypothesis"
    )
    link_sigma: float = Field(
        3.0, ge=0, description="an articulated pair links two segments within D +- this A"
    )
    min_links: int = Field(
        6, ge=1, description="articulated pairs in range needed to join another segment"
    )
    link_fraction: float = Field(
        0.6, ge=0, le=1, description="share of a segment's articulated pairs that must be in range"
    )
    art_a_mm: float = Field(
        15.0,
        ge=0,
        description="a marker with no rigid evidence joins from partners with A at most this "
        "(same or next segment; 0 turns that off)",
    )
    art_anchors: int = Field(
        6, ge=1, description="steadiest placed partners such a marker is checked against"
    )
    art_min_anchors: int = Field(
        3, ge=2, description="... and at least this many of them (all within their range)"
    )
    fit_mm: float = Field(12.0, gt=0, description="predicted marker to point, Kabsch check")
    anchors_per_body: int = Field(4, ge=1, le=4, description="anchor triangles per body")
    max_candidates: int = Field(
        4000, ge=1, description="candidate triangles kept per anchor (closest distances first)"
    )
    constancy: float = Field(
        0.8, gt=0, le=1, description="fraction of window frames an in-body pair must hold in"
    )
    min_fraction: float = Field(
        0.5, gt=0, le=1, description="a subject boots with this fraction of its markers"
    )
    extend_every_s: float = Field(
        0.04,
        gt=0,
        description="BootingLabeler: free points joined to booted subjects this often (a limb "
        "back from a fast swing is read this late at most; 0.1 s cost the 50-60 Hz takes "
        "labels: docs/algorithm.md)",
    )
    fill_min_age_s: float = Field(
        0.2,
        ge=0,
        description="extension: a booted subject's leftover markers are assigned jointly to "
        "free tracks at least this old (a ghost lives a few frames; see boot_match._fill)",
    )
    fill_agreement: bool = Field(
        True,
        description="extension: when the joint fill's cheapest map is not unique, place the "
        "markers every rival map puts on one point (boot_match._fill_jointly); it trusts the "
        "trained distances to rank maps, so a model trained on a few frames (the labeled "
        "start's window model, registry.make_window_labeler) runs without it",
    )
    release_loose: bool = Field(
        True,
        description="extension: the weak completion also releases loose segments one at a "
        "time (boot_match._complete_weak, _loose_part: a partner's limb held by its own rigid "
        "pairs); the labeled start's window model (registry.make_window_labeler) runs without "
        "it: its window's labels placed every segment",
    )
    fill_past_partner: bool = Field(
        True,
        description="extension: when the joint fill places nothing, free points nearer another "
        "subject's labeled points join its candidates if one of this subject's leftover "
        "markers reaches them and no other active subject's does (boot_match._fill, _reach); "
        "the labeled start's window model (registry.make_window_labeler) runs without it: its "
        "reach comes from a window's few frames",
    )
    boot_every_s: float = Field(
        0.05, gt=0, description="BootingLabeler: a boot attempt at most this often"
    )
    boot_backoff_s: float = Field(
        0.2, gt=0, description="BootingLabeler: longest wait between fruitless boot attempts"
    )
    relearn_every_s: float = Field(
        0.0,
        ge=0,
        description="BootingLabeler of a labeled start (registry.make_window_labeler sets 2): "
        "the booter's templates learned again this often from the stream's own clean frames "
        "(every point, or every marker of the active subjects, labeled, and the 5 frames either "
        "side), the labeler kept (0 = off; "
        "BootingLabeler._relearn). Where the extension runs in the labeler (inline_extend: "
        "evaluate, label) in the frame that falls due; in the service on the next boot job",
    )
    relearn_min_frames: int = Field(
        100,
        ge=3,
        description="... from at least this many clean frames of the last "
        "booting.RELEARN_HISTORY_S seconds (from 50 frames of its own 25 Hz labels, a forearm "
        "was re-acquired on the wrong points)",
    )
    drop_after_s: float = Field(
        0.1,
        gt=0,
        description="BootingLabeler: a subject with no observed marker this long is dropped "
        "(its labels are given to nobody) and booted again when it comes back",
    )
    blackout_hold_s: float = Field(
        0.5,
        ge=0,
        description="BootingLabeler: frames with no point at all (a camera dropout) count toward "
        "no subject's drop_after_s for this long in a row; a performer who left meanwhile is "
        "dropped once points come back",
    )
    blackout_reboot_s: float = Field(
        0.25,
        ge=0,
        description="BootingLabeler: when points come back after this long with none (a camera "
        "dropout, frames lost), every active subject is dropped and booted again: the tracks "
        "cannot follow the performers over it (0 turns that off)",
    )
    vanish_fraction: float = Field(
        0.2,
        ge=0,
        le=1,
        description="BootingLabeler: a subject with fewer of its markers observed is vanishing "
        "(labels withheld)",
    )
    vanish_relative: float = Field(
        0.35,
        ge=0,
        le=1,
        description="BootingLabeler: a subject whose observed markers fall below this fraction "
        "of its recent count (a moving average over vanish_memory_s) is vanishing too: a "
        "performer who leaves while some of its labels sit on other performers' points",
    )
    vanish_memory_s: float = Field(
        0.5, gt=0, description="BootingLabeler: time constant of that recent count"
    )
    jump_fraction: float = Field(
        0.6,
        ge=0,
        le=1,
        description="BootingLabeler (and a service stream's plain labeler, JumpWatch): when this "
        "share of the previous frame's labeled points lose their anonymous tracks in one frame "
        "and this share of the frame's points are on new tracks (each at least "
        "jump_min_markers), the points are still there but moved beyond the tracker's gate: "
        "the scene jumped (a take looped, frames lost with seq and t continuous). The subjects "
        "that lost this share of their labeled tracks are dropped and booted again, not left to "
        "the wrong points their tracks take next (0 = off). Measured: 0.98-1.0 at the jumps "
        "tried, at most 0.415 in a frame of the real matrices (the tennis serve at 12.5 Hz)",
    )
    jump_min_markers: int = Field(
        8, ge=1, description="BootingLabeler: the fewest tracks ended (and begun) that are a jump"
    )
    rms_ratio: float = Field(
        1.25,
        gt=1,
        description="a template whose rigid-distance RMS on a performer is this much worse "
        "than another's yields that performer",
    )
    max_hypotheses: int = Field(3, ge=1, description="hypotheses kept per template")
    max_seeds: int = Field(12, ge=1, description="seed bodies tried per template")
    max_symmetries: int = Field(
        4, ge=1, description="readings of one seed body's points tried (body symmetries)"
    )
    verify: bool = Field(
        True,
        description="BootingLabeler: re-verify booted subjects over time (boot_verify.py): "
        "labels whose template pairs stop holding are withdrawn, a subject that mostly fails "
        "is dropped and booted again",
    )
    verify_every_s: float = Field(
        0.02, gt=0, description="re-verification: a sample of every edge this often"
    )
    verify_memory_s: float = Field(
        0.3, gt=0, description="re-verification: time constant of an edge's off rate"
    )
    verify_min_s: float = Field(
        0.25, ge=0, description="re-verification: samples an edge needs before it counts"
    )
    verify_bad: float = Field(
        0.5, gt=0, lt=1, description="re-verification: an edge off this often is bad"
    )
    verify_links: int = Field(
        3, ge=1, description="re-verification: steadiest cross pairs checked per joint"
    )
    verify_link_sigma: float = Field(
        4.0, ge=0, description="re-verification: a joint's pairs hold within D +- this A"
    )
    verify_drop: float = Field(
        0.5,
        gt=0,
        le=1,
        description="re-verification: a subject losing this fraction of its observed markers "
        "at once is dropped and booted again",
    )
    verify_block_s: float = Field(
        0.4,
        ge=0,
        description="re-verification: a withdrawn point's track is kept from that subject "
        "this long",
    )
    verify_recent_s: float = Field(
        1.0,
        gt=0,
        description="re-verification: markers withdrawn within about this long count together "
        "towards verify_drop (a subject wrong almost everywhere loses them one by one)",
    )
    verify_spread_mm: float = Field(
        5.0,
        ge=0,
        description="re-verification: a joint's pair off its range counts only while its "
        "distance spreads (over verify_memory_s) more than this plus verify_spread_sigma A",
    )
    verify_spread_sigma: float = Field(
        2.0, ge=0, description="re-verification: ... in units of the pair's trained A"
    )
    verify_marker_joints: bool = Field(
        True,
        description="re-verification: a marker's joint pairs count with its rigid ones when "
        "deciding that it alone is off",
    )
    verify_support: int = Field(
        2,
        ge=1,
        description="re-verification: a marker is withdrawn alone only while fewer than this "
        "many pairs of its trained bodies hold (partners that agree with it: a plate of its "
        "own; a model trained on a still segment calls pairs across a joint rigid, and they "
        "break when the subject bends)",
    )
    verify_cut: bool = Field(
        True,
        description="re-verification: a broken joint withdraws the segments beyond it",
    )
    verify_cut_tol: float = Field(
        3.0,
        ge=0,
        description="re-verification: a joint's pair counts towards a cut only when its mean "
        "distance is this many tolerances off (an untrained pose of the subject's own limb "
        "stays within one or two)",
    )
    verify_tol_scale: float = Field(
        2.0,
        gt=0,
        description="re-verification: the boot's rigid pair tolerances times this plus "
        "verify_tol_mm "
        "(a model trained on another or a still segment: skin slides)",
    )
    verify_tol_mm: float = Field(5.0, ge=0, description="re-verification: ... plus this")
    verify_exchange: bool = Field(
        True,
        description="re-verification: a booted subject whose left and right markers read each "
        "other's points (two feet exchanged) gets them back when the exchanged reading fits "
        "its template clearly better for verify_exchange_s (boot_verify.py)",
    )
    verify_exchange_s: float = Field(
        0.2, gt=0, description="re-verification: ... that long, tick after tick"
    )
    verify_contact_mm: float = Field(
        250.0,
        ge=0,
        description="re-verification: labels are withdrawn only from a marker group with a "
        "marker this close to another subject's, and the extension exchanges no two markers "
        "of a segment this close to another subject (0: everywhere)",
    )

    def boot_markers(self, n: int) -> int:
        """Markers a hypothesis of an ``n``-marker template must hold to boot its subject
        (``min_fraction`` of them, 3 at least)."""
        return max(3, math.ceil(self.min_fraction * n))
