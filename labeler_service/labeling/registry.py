"""The one place that builds a labeler: every command, the service and the scorer ask here.

======================  =========================================================================
kind                    labeler
======================  =========================================================================
``online``              :class:`~labeler_service.labeling.labeler.Labeler`, the online labeler of
                        Yu, Li and Deng (2007): Kalman gating + rigid-body fitting + recovery
``baseline``            :class:`~labeler_service.labeling.baseline.ClosestPointLabeler`, the
                        closest-point tracker the paper compares against
                        (alias ``closest-point``, the name ``evaluate`` reports it under)
======================  =========================================================================

A labeler starts either from ``marker_names`` (the labeled init frames the caller then feeds
train it) or from ``model``, a subject template written by ``train structure`` (a
:class:`~labeler_service.labeling.templates.LabelerModel` or the path of its JSON file).

Starting from a model, there are two ways (``boot``):

- ``boot=False`` (default): :meth:`Labeler.from_model`; the first frame(s) fed must carry labels
  (they give the initial assignment of points to markers).
- ``boot=True`` (or a :class:`~labeler_service.labeling.boot.BootConfig`): a
  :class:`~labeler_service.labeling.booting.BootingLabeler`, which needs no labeled frame at all:
  it boots the subjects from anonymous points, drops a subject that leaves and boots it again
  when it returns. Frames that do carry labels are used as ``from_model`` would use them, so
  this one labeler serves a stream whether or not its client sends labels. This is what
  ``--init-frames 0`` means in ``evaluate`` and ``label``. Only the ``online`` kind boots;
  ``boot`` without a model is an error.

A labeled start can also go through the model-based labeler (:func:`make_window_labeler`): a
model trained on the labeled init window itself, and a ``BootingLabeler`` fed the window's
labels. Its extension (free tracks joined to a subject from its template) re-finds markers the
plain labeler loses at low rates (``evaluate --labeled-start model``; docs/algorithm.md, "What
limits 12.5-25 Hz", item (5)); a service stream with ``labeled_start = "model"`` trains and runs
it in-stream.

The labeler modules are imported only when built, so importing this module stays cheap.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Protocol, overload

from labeler_service.errors import LabelerError
from labeler_service.labeling.boot_config import WINDOW_RELEARN_S

if TYPE_CHECKING:
    from labeler_service.labeling.boot import BootConfig
    from labeler_service.labeling.config import LabelerConfig
    from labeler_service.labeling.frame import FrameLabeler
    from labeler_service.labeling.labeler import Labeler
    from labeler_service.labeling.templates import LabelerModel

#: Every kind :func:`make_labeler` builds (aliases map onto these).
KINDS: tuple[str, ...] = ("online", "baseline")
ALIASES: dict[str, str] = {"closest-point": "baseline"}
#: How a labeled start runs: ``labeler`` (the labeler trained in place on the labeled frames),
#: ``model`` (:func:`make_window_labeler`), or ``auto`` (the default: ``model`` wherever it
#: applies, see :func:`resolve_labeled_start`); ``evaluate``/``label --labeled-start``, the
#: service's stream setting ``labeled_start``.
LABELED_STARTS: tuple[str, ...] = ("auto", "labeler", "model")


#: the lowest frame rate the benchmarks measure (the cross-take matrix's quarter rate)
LOWEST_MEASURED_HZ = 12.5


def low_rate_note(rate: float) -> str | None:
    """What a user labeling at ``rate`` Hz should know when it is below the rates measured
    (None otherwise)."""
    if rate >= LOWEST_MEASURED_HZ:
        return None
    return (
        f"{rate:g} Hz is below the lowest rate measured ({LOWEST_MEASURED_HZ:g} Hz): markers "
        "move far between frames and many go unlabeled (a two-person scene composed from the "
        "CMU takes: about 86-90 % at 10 Hz, half at 5 Hz); check the result"
    )


def resolve_labeled_start(
    requested: str,
    *,
    online: bool,
    init_frames: int,
    model_given: bool = False,
    labels: Sequence[str] = (),
    source: str = "the capture",
    advice: str = "use --labeled-start labeler",
) -> tuple[str, str | None]:
    """The start a labeled start runs: ``(start, why)``, ``start`` ``labeler`` or ``model``.

    ``labeler`` and ``model`` are returned as asked (the caller checks that ``model`` applies
    and says why not), except ``model`` with ``labels`` (the labeled frames' markers) that do
    not all name their subjects: the window model would rename them, so it is a
    :class:`LabelerError` naming ``source`` and the first such label, with ``advice``.
    ``auto`` is ``model`` when it applies: the online labeler (``online``), at least
    :data:`~labeler_service.labeling.structure.WINDOW_MIN_FRAMES` labeled frames to train the
    window model on, no model file (a model file is its own start) and ``subject:marker``
    labels. Else ``labeler``, with ``why`` saying what kept the model start out (``None`` when
    nothing did or nothing was asked)."""
    from labeler_service.capture import split_label
    from labeler_service.labeling.structure import WINDOW_MIN_FRAMES

    if requested not in LABELED_STARTS:
        raise LabelerError(
            f"unknown labeled start {requested!r} (choose from {', '.join(LABELED_STARTS)})"
        )
    bare = next((n for n in labels if not split_label(n)[0]), None)
    if requested == "model" and not model_given and bare is not None:
        raise LabelerError(
            f"{source}: the labeled start through a window model needs subject:marker labels "
            f"(the model names its subjects), got {bare!r}, a label without a subject prefix: "
            f"prefix the labels with the performer's name, or {advice}"
        )
    if requested != "auto" or model_given:
        return ("labeler" if requested == "auto" else requested), None
    why = None
    if not online:
        why = "the labeled start through a window model runs the online labeler only"
    elif init_frames < WINDOW_MIN_FRAMES:
        why = (
            f"the window model needs {WINDOW_MIN_FRAMES} or more labeled frames, got {init_frames}"
        )
    elif bare is not None:
        why = f"the window model names its subjects: the labels give bare marker names ({bare!r})"
    return ("labeler", why) if why else ("model", None)


def thin_subjects(labels: Sequence[str], min_markers: int | None = None) -> list[str]:
    """Notes on the subjects ``labels`` name with fewer markers than the presence check needs
    (``LabelerConfig.presence_min_markers``, ``min_markers``): a subject of fewer markers is
    absent in every frame, so none of its markers is ever labeled. Said once, where the labels
    come in (``evaluate``'s notes, ``label``, the service's log), not found in the scores."""
    from labeler_service.capture import subject_groups
    from labeler_service.labeling.config import LabelerConfig

    need = LabelerConfig().presence_min_markers if min_markers is None else min_markers
    groups = subject_groups(labels, skip_ghosts=True)
    return [
        f"subject {s or '(no subject)'} has {len(cols)} marker{'s' * (len(cols) != 1)}, fewer "
        f"than the {need} the labeler needs to see a subject present: its markers stay "
        "unlabeled"
        for s, cols in groups.items()
        if len(cols) < need
    ]


class LabelerFactory(Protocol):
    """The signature of :func:`make_labeler`; the service accepts any such callable (tests
    inject slow or failing labelers through it)."""

    def __call__(
        self,
        kind: str,
        *,
        marker_names: Sequence[str] = (),
        rate: float,
        config: LabelerConfig | None = None,
        model: LabelerModel | str | os.PathLike[str] | None = None,
        boot: bool | BootConfig = False,
    ) -> FrameLabeler: ...


@overload
def make_labeler(
    kind: Literal["online"],
    *,
    marker_names: Sequence[str] = (),
    rate: float,
    config: LabelerConfig | None = None,
    model: LabelerModel | str | os.PathLike[str] | None = None,
    boot: Literal[False] = False,
) -> Labeler: ...


@overload
def make_labeler(
    kind: str,
    *,
    marker_names: Sequence[str] = (),
    rate: float,
    config: LabelerConfig | None = None,
    model: LabelerModel | str | os.PathLike[str] | None = None,
    boot: bool | BootConfig = False,
) -> FrameLabeler: ...


def make_labeler(
    kind: str,
    *,
    marker_names: Sequence[str] = (),
    rate: float,
    config: LabelerConfig | None = None,
    model: LabelerModel | str | os.PathLike[str] | None = None,
    boot: bool | BootConfig = False,
) -> FrameLabeler:
    """A labeler of ``kind`` (table above) for ``marker_names`` at ``rate`` Hz.

    With ``model`` the marker set is the model's (``marker_names`` is then ignored) and the
    online labeler starts from its templates (``Labeler.from_model``); ``config`` tunes the
    online labeler only. ``boot`` (a model is then required) builds a
    :class:`~labeler_service.labeling.booting.BootingLabeler` that needs no labeled frame
    (``True`` for the default :class:`~labeler_service.labeling.boot.BootConfig`). Raises
    :class:`~labeler_service.errors.LabelerError` for an unknown kind, an empty marker set or
    ``boot`` without a model, :class:`~labeler_service.errors.ModelError` for a bad model file.
    """
    name = ALIASES.get(kind, kind)
    if name not in KINDS:
        choices = ", ".join((*KINDS, *ALIASES))
        raise LabelerError(f"unknown labeler kind {kind!r} (choose from {choices})")
    loaded = _load(model)
    if boot is not False:
        if loaded is None:
            raise LabelerError("booting needs a model (train structure output); none was given")
        if name != "online":
            raise LabelerError(f"only the online labeler can boot from a model, not {kind!r}")
        from labeler_service.labeling.boot import BootConfig
        from labeler_service.labeling.booting import BootingLabeler

        cfg = boot if isinstance(boot, BootConfig) else None
        return BootingLabeler(loaded, rate, config, cfg)
    if name == "baseline":
        from labeler_service.labeling.baseline import ClosestPointLabeler

        names = loaded.marker_names if loaded is not None else tuple(marker_names)
        if not names:
            raise LabelerError("a labeler needs at least one marker name")
        return ClosestPointLabeler(names, rate)
    from labeler_service.labeling.labeler import Labeler

    if loaded is not None:
        return Labeler.from_model(loaded, rate, config)
    return Labeler(marker_names, rate, config)


def _load(model: LabelerModel | str | os.PathLike[str] | None) -> LabelerModel | None:
    if model is None:
        return None
    if isinstance(model, str | os.PathLike):
        from labeler_service.labeling.templates import load_model

        return load_model(Path(model))
    return model


def make_window_labeler(
    model: LabelerModel,
    *,
    rate: float,
    window_frames: int,
    config: LabelerConfig | None = None,
    relearn_every_s: float = WINDOW_RELEARN_S,
) -> FrameLabeler:
    """The labeled start through the model-based labeler: a
    :class:`~labeler_service.labeling.booting.BootingLabeler` from ``model``, the subject
    templates trained on the labeled init window of ``window_frames`` frames (the caller trains
    them: :func:`labeler_service.labeling.structure.window_model`), to be fed those frames with
    their labels, then the stream.

    Six settings differ from a boot:

    - the inner labeler counts the model as the window's own samples
      (``restructure_prior_s = window_frames / rate``), not as ``restructure_prior_s`` seconds:
      a window too short for a trustworthy structure (fewer than
      ``restructure_max_train_frames``, e.g. 10 frames at 25 Hz) is re-formed from the stream
      as the labeler trained in place re-forms it. Counted as 5 s the structure froze:
      holdout04 ``quarter`` 86.49 -> 84.20 %;
    - no subject's labels are withheld while it vanishes (``vanish_fraction`` and
      ``vanish_relative`` 0; a subject with no observed marker is still dropped): a performer
      who walks out of the volume keeps the labels of his markers still seen, as the plain
      labeler does (withheld: the BTS walker's cells lost about a point each);
    - the joint fill places nothing when its cheapest map is not unique (``fill_agreement``
      off): the agreement of rival maps trusts the trained distances to rank the maps, and a
      window's distances come from a few frames (at 12.5 Hz, 5: with it on, tune18 and tune17
      ``quarter`` 90.9 -> 78.5 % and 92.7 -> 85.2 %);
    - the weak completion releases no loose segment (``release_loose`` off): the window's
      labels placed every segment, and at 12.5 Hz the release moved the worst cell's arm
      (tune04 ``quarter`` 76.61 -> 75.02 %; tune18 90.89 -> 93.57 %);
    - the joint fill takes no point nearer another subject's labeled points
      (``fill_past_partner`` off): with it, tune25 and tune26 ``quarter`` 91.82 -> 91.39 % and
      96.71 -> 96.48 %, tune07 ``half`` 99.20 -> 99.17 % (tune25 ``half`` 95.03 -> 95.07 %);
    - the inner labeler starts from the whole labeled window (``labeled_kept_s``), as the
      labeler trained in place does, not from its last ``booting.LABELED_KEPT_S`` (0.5 s):
      started from the last 15 of 50 frames at 30 Hz, it gave a ghost a hidden hand marker's
      label (acceptance scene c ``downsample4``, ghosts labeled 1.06 -> 0.71 %).
    """
    from labeler_service.labeling.boot import BootConfig
    from labeler_service.labeling.config import LabelerConfig

    if window_frames < 1:
        raise LabelerError(f"a labeled start needs at least one labeled frame, got {window_frames}")
    if not (rate > 0):
        raise LabelerError(f"invalid frame rate {rate}")
    base = config or LabelerConfig()
    cfg = LabelerConfig(**{**base.model_dump(), "restructure_prior_s": window_frames / rate})
    boot = BootConfig(
        vanish_fraction=0.0,
        vanish_relative=0.0,
        fill_agreement=False,
        release_loose=False,
        fill_past_partner=False,
        relearn_every_s=relearn_every_s,
    )
    from labeler_service.labeling.booting import BootingLabeler

    # the whole window starts the inner labeler (not its last ``LABELED_KEPT_S``)
    return BootingLabeler(
        model, rate, cfg, boot, labeled_kept_s=window_frames / rate, window_frames=window_frames
    )
