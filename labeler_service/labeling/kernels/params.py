"""``Params``: every kernel setting in one named tuple, built from :class:`LabelerConfig`.

The kernels read ``params.gate_chi2`` or ``params.reject_limit`` instead of the 13th positional
float: numba passes a named tuple of scalars as one argument and compiles ``params.name`` to a
field access (no lookup at run time).

**Adding a setting touches one place.** Declare it in
:class:`~labeler_service.labeling.config.LabelerConfig` (type, default, range, description):
:func:`kernel_params` copies *every* field of the config into ``Params`` under the same name,
so a kernel reads it as ``params.<name>``. The copy converts by the field's annotation
(``float``, ``int``, ``bool``; a ``Literal`` becomes its integer code from :data:`CODES`), so the
compiled argument type never depends on how a value was spelled (``250`` or ``250.0`` in a
settings file): one compilation per process. A config field of any other type fails at import.

Quantities the kernels need in another form than the user gives them (a variance from a
deviation, a score from a number of deviations) are derived in :data:`DERIVED`, each next to
its formula; they follow the config fields in ``Params``. Later settings (per-body template
checks, swap repair, pose prediction with linear/angular velocity) go into ``LabelerConfig``
in the same way; only a setting the kernels need in a derived form adds a line to ``DERIVED``.
"""

from __future__ import annotations

import typing
from collections import namedtuple
from collections.abc import Callable
from typing import Any

import numpy as np

from labeler_service.labeling.config import LabelerConfig

# recovery methods (``LabelerConfig.recovery``), read by :func:`.rigid._recover`
DISPLACEMENT = 0  # the paper's displacement averaging (Sec. 3.3)
KABSCH = 1  # Kabsch fit of 3+ observed neighbours, else displacement averaging

#: integer code of each value of every ``Literal`` field of the config
CODES: dict[str, dict[str, int]] = {
    "recovery": {"displacement": DISPLACEMENT, "kabsch": KABSCH},
}

V0 = 1.0e6  # initial velocity variance of a new track, (mm/s)^2 (1 m/s deviation)

#: name -> (meaning, formula) of the settings the kernels read in a derived form
DERIVED: dict[str, tuple[str, Callable[[LabelerConfig], float]]] = {
    "r": (
        "R = r I: variance of a measured point per axis, mm^2 (Eq. 4)",
        lambda c: c.measurement_noise_mm**2,
    ),
    "r_rec": (
        "R of a recovered position when it updates the Kalman state, mm^2",
        lambda c: c.recovered_noise_mm**2,
    ),
    "s_min": (
        "floor of the innovation variance S: the gate radius never drops below min_gate_mm",
        lambda c: c.min_gate_mm**2 / c.gate_chi2,
    ),
    "p_cap": (
        "cap on the predicted position variance of a lost marker, mm^2",
        lambda c: c.max_position_sd_mm**2,
    ),
    "miss_term": (
        "Eq. 5 score of each link of a missing marker, exp(-missing_sigma^2 / 2)",
        lambda c: float(np.exp(-0.5 * c.missing_sigma**2)),
    ),
    "miss_reacq": (
        "the same in the wide re-acquisition pass, exp(-reacquire_sigma^2 / 2)",
        lambda c: float(np.exp(-0.5 * c.reacquire_sigma**2)),
    ),
    "v0": ("initial velocity variance P_vv of a new track, (mm/s)^2", lambda c: V0),
}


def _converter(name: str, annotation: Any) -> Callable[[Any], Any]:
    """How config field ``name`` becomes a numba scalar."""
    if annotation is bool:
        return bool
    if annotation is int:
        return int
    if annotation is float:
        return float
    if typing.get_origin(annotation) is typing.Literal:
        codes = CODES.get(name)
        missing = [v for v in typing.get_args(annotation) if codes is None or v not in codes]
        if missing:
            raise TypeError(f"LabelerConfig.{name}: no integer code in CODES for {missing}")
        assert codes is not None
        return codes.__getitem__
    raise TypeError(
        f"LabelerConfig.{name}: a kernel setting must be float, int, bool or a Literal "
        f"(got {annotation!r})"
    )


_CONVERT = {
    name: _converter(name, field.annotation) for name, field in LabelerConfig.model_fields.items()
}
_clash = set(_CONVERT) & set(DERIVED)
if _clash:
    raise TypeError(f"derived kernel settings shadow config fields: {sorted(_clash)}")


def _doc() -> str:
    lines = [
        "Every kernel setting (built by :func:`kernel_params`; fields in this order).",
        "",
        "From ``LabelerConfig`` (same names and meaning):",
        "",
    ]
    for name, field in LabelerConfig.model_fields.items():
        code = " (integer code, see ``CODES``)" if name in CODES else ""
        lines.append(f"- ``{name}``: {field.description or 'see LabelerConfig'}{code}")
    lines += ["", "Derived:", ""]
    lines += [f"- ``{name}``: {meaning}" for name, (meaning, _) in DERIVED.items()]
    return "\n".join(lines)


def _params_type() -> Any:
    # one module-level class, pickled by reference (numba's on-disk cache stores argument
    # types); the fields are computed, so type checkers see a plain factory call
    factory: Callable[..., Any] = namedtuple
    cls = factory("Params", [*_CONVERT, *DERIVED], module=__name__)
    cls.__doc__ = _doc()
    return cls


Params = _params_type()


def kernel_params(config: LabelerConfig) -> Any:
    """The ``Params`` of ``config``: every config field converted, then every derived value."""
    values = [conv(getattr(config, name)) for name, conv in _CONVERT.items()]
    values += [float(formula(config)) for _, formula in DERIVED.values()]
    return Params(*values)
