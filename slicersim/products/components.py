"""Scene components and the ``switch_off`` rule shared by cubes, spectra and the variance budget.

Photon cube (reference §2.9) [ph/s/cell] = Σ of the scene components

* ``pointsource``  LSF[F f2p P]
* ``host``         LSF[f2p (F_host ⊛ P)]
* ``background``   LSF[B f2p s²]                   (uniform: zodiacal light)
* ``thermal``      LSF[N_telescope + N_optics]     (uniform: dispersed thermal emission)

``switch_off`` takes any of :data:`VARIANCE_SOURCES` (a name or a list; case-insensitive),
plus ``"effective_dark"`` = dark + thermal_dark.  A scene component switched off leaves the
photon cube, hence the signal and the variance; a detector term leaves the variance only:
``dark`` and ``roic_glow`` → 0 e-/s, ``ron`` → 0 electron, ``thermal_dark`` → optics emissivity 0
(the undispersed thermal dark *and* the dispersed optics emission, as slicersim 1.4.2 does).
"""
from __future__ import annotations

from slicersim.errors import ParameterError

__all__ = ["SCENE_COMPONENTS", "VARIANCE_SOURCES", "SWITCH_OFF_NAMES", "UNIFORM_TERMS", "check_switch_off",
           "as_switched_off", "uniform_terms_on"]

#: scene components of the photon cube, in the order of ``get_scene_cubes``
SCENE_COMPONENTS = ("pointsource", "background", "host", "thermal")
#: the eight variance sources of slicersim (the names ``switch_off`` accepts)
VARIANCE_SOURCES = ("dark", "roic_glow", "thermal_dark", "ron", "pointsource", "background", "host", "thermal")
#: shorthands expanded by ``switch_off``
SWITCH_OFF_ALIASES = {"effective_dark": ("dark", "thermal_dark")}
SWITCH_OFF_NAMES = VARIANCE_SOURCES + tuple(SWITCH_OFF_ALIASES)
#: uniform photon terms [ph/s/cell]: zodiacal light, dispersed telescope and optics emission
UNIFORM_TERMS = ("background", "thermal_telescope", "thermal_optics")
_UNIFORM_REMOVED_BY = {"background": ("background",), "thermal": ("thermal_telescope", "thermal_optics"),
                       "thermal_dark": ("thermal_optics",)}


def as_switched_off(switch_off):
    """Internal form of already valid names: a frozenset (None → empty; aliases expanded)."""
    if switch_off is None:
        return frozenset()
    names = (switch_off,) if isinstance(switch_off, str) else tuple(switch_off)
    out = set()
    for name in names:
        out.update(SWITCH_OFF_ALIASES.get(name, (name,)))
    return frozenset(out)


def check_switch_off(switch_off):
    """Validated ``switch_off`` (None, a name or a list/tuple/set of names) as a frozenset.

    ParameterError, listing the valid names, for unknown names or non-string entries."""
    if switch_off is None:
        return frozenset()
    if isinstance(switch_off, str):
        items = [switch_off]
    elif isinstance(switch_off, (list, tuple, set, frozenset)):
        items = list(switch_off)
    else:
        raise ParameterError(f"switch_off must be a name or a list of names, got {switch_off!r}; "
                             f"valid: {', '.join(SWITCH_OFF_NAMES)}")
    bad = [name for name in items if not isinstance(name, str) or name.lower() not in SWITCH_OFF_NAMES]
    if bad:
        raise ParameterError(f"unknown switch_off name(s) {bad}; valid: {', '.join(SWITCH_OFF_NAMES)}")
    return as_switched_off(name.lower() for name in items)


def uniform_terms_on(switch_off):
    """The :data:`UNIFORM_TERMS` left on by ``switch_off`` (internal frozenset)."""
    removed = set()
    for name in switch_off:
        removed.update(_UNIFORM_REMOVED_BY.get(name, ()))
    return tuple(term for term in UNIFORM_TERMS if term not in removed)
