"""Detector systematics of an H4RG (pipeline stress tests): names and random streams.

Every effect is off unless asked for.  Each effect draws its random numbers from
its own Philox stream range (:data:`STREAMS`), keyed by (seed, position), so
switching one effect on or off leaves the draws of every other effect — and the
Poisson charge, read noise and kTC draws of the plain ramp — unchanged.

The plain ramp uses streams ``4·ramp + p`` (p < 4) and ``+ 0x80000000`` for PTRS;
effects use ``STREAMS[name] + sub`` with ``sub < 2**24`` (ramps enter the index,
never the stream), disjoint from those for any nramps < 2**26.
"""
from __future__ import annotations

import dataclasses
import importlib
import math

from slicersim import validation
from slicersim.errors import EffectsError

__all__ = ["EFFECT_NAMES", "STREAMS", "PRESETS", "DetectorEffects", "parameter_class", "check_number", "check_shape_rows",
           "check_fraction"]

#: effect names accepted by ``--effects`` and :class:`DetectorEffects` (``"all"`` = every one)
EFFECT_NAMES = ("cosmic_rays", "ipc", "nonlinearity", "correlated_noise", "reference_pixels",
                "bad_pixels", "persistence")

#: first Philox stream of each effect (each owns [base, base + 2**24))
STREAMS = {
    "cosmic_rays": 0x10000000,
    "nonlinearity": 0x11000000,
    "correlated_noise": 0x12000000,
    "reference_pixels": 0x13000000,
    "bad_pixels": 0x14000000,
    "persistence": 0x15000000,
}


# --------------------------------------------------------------------------- validation helpers
# thin wrappers around slicersim.validation with EffectsError (the effects modules import them)
def check_number(name, value, low=0.0, high=math.inf, *, low_open=False, high_open=False):
    """``value`` as a float in [low, high] (bounds open where asked), else EffectsError naming it."""
    return validation.number(name, value, low=low, high=high, low_open=low_open, high_open=high_open,
                             error=EffectsError)


def check_shape_rows(shape, rows=None, max_side=65536):
    """((ny, nx), (r0, r1)) of a detector ``shape`` and an optional row range ``rows`` = (r0, r1)."""
    ny, nx = validation.shape("shape", shape, max_side=max_side, error=EffectsError)
    if rows is None:
        return (ny, nx), (0, ny)
    if isinstance(rows, (str, bytes)) or not hasattr(rows, "__len__") or len(rows) != 2:
        raise EffectsError(f"rows must be a pair (r0, r1), got {validation.short_repr(rows)}")
    r0 = validation.integer("rows[0]", rows[0], low=0, high=ny - 1, error=EffectsError)
    r1 = validation.integer("rows[1]", rows[1], low=r0 + 1, high=ny, error=EffectsError)
    return (ny, nx), (r0, r1)


def check_fraction(name, value):
    """A fraction in [0, 1], else EffectsError naming it."""
    return validation.fraction(name, value, error=EffectsError)


# --------------------------------------------------------------------------- configuration
#: parameter dataclass of each effect: (module, class name); imported lazily (no import cycle)
PARAMETER_CLASSES = {
    "cosmic_rays": ("slicersim.physics.cosmic_rays", "CosmicRayParameters"),
    "ipc": ("slicersim.physics.ipc", "IPCParameters"),
    "nonlinearity": ("slicersim.physics.nonlinearity", "NonlinearityParameters"),
    "correlated_noise": ("slicersim.physics.correlated_noise", "CorrelatedNoiseParameters"),
    "reference_pixels": ("slicersim.physics.reference_pixels", "ReferencePixelParameters"),
    "bad_pixels": ("slicersim.physics.bad_pixels", "BadPixelParameters"),
    "persistence": ("slicersim.physics.persistence", "PersistenceParameters"),
}
#: presets: effect → parameter overrides of the defaults (every default is documented and cited
#: in its module); "lazuli": every effect with the default (Lazuli H4RG-10) values
PRESETS = {"lazuli": {name: {} for name in EFFECT_NAMES}}


@validation.checked_fields(error=EffectsError)
@dataclasses.dataclass(kw_only=True)
class _PlaceholderReferencePixelParameters:
    """Placeholder until slicersim.physics.reference_pixels exists: width of the reference border
    [pixels] (4 on an H4RG)."""

    width: int = 4

    def __post_init__(self):
        self.width = validation.integer("reference_pixels.width [pixels]", self.width, low=0, high=64,
                                        error=EffectsError)


def parameter_class(name):
    """The parameter dataclass of effect ``name``."""
    validation.choice("effect", name, EFFECT_NAMES, error=EffectsError)
    module, cls = PARAMETER_CLASSES[name]
    try:
        return getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError):
        if name == "reference_pixels":
            return _PlaceholderReferencePixelParameters
        raise


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


def _params_to_dict(params):
    """Init parameters of a dataclass as JSON/TOML-able values (None = default: left out)."""
    d = params.to_dict() if hasattr(params, "to_dict") else {
        f.name: getattr(params, f.name) for f in dataclasses.fields(params) if f.init}
    return {k: _jsonable(v) for k, v in d.items() if v is not None}


def _params_from_dict(name, section):
    cls = parameter_class(name)
    if section is None:
        section = {}
    if not isinstance(section, dict):
        raise EffectsError(f"effects.{name} must be a table of parameters, got {type(section).__name__}")
    known = [f.name for f in dataclasses.fields(cls) if f.init]
    unknown = sorted(set(section) - set(known))
    if unknown:
        raise EffectsError(f"unknown parameter(s) {', '.join(map(repr, unknown))} in effects.{name}; "
                           f"known: {', '.join(known)}")
    try:
        return cls(**section)
    except EffectsError:
        raise
    except (TypeError, ValueError) as exc:
        raise EffectsError(f"effects.{name}: {exc}") from None


def _parse_names(names, has_previous_charge):
    if names is None:
        return ()
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    try:
        names = [str(n).strip().lower() for n in names]          # "IPC" as "ipc", like the presets
    except TypeError:
        raise EffectsError(f"effect names must be a string or a list of strings, got {names!r}") from None
    out = []
    for n in names:
        if validation.choice("effect", n, EFFECT_NAMES + ("all",), error=EffectsError) == "all":
            out += [e for e in EFFECT_NAMES if e != "persistence" or has_previous_charge]
        else:
            out.append(n)
    return tuple(e for e in EFFECT_NAMES if e in out)


class DetectorEffects:
    """The enabled detector effects and the parameter dataclass of each (validated).

    ``"all"`` (names or config) means every effect except ``persistence``, which needs a previous
    exposure's charge image: it is included only with ``has_previous_charge=True`` or by naming
    it.  Config layout (TOML/JSON)::

        {"effects": {"enabled": ["cosmic_rays", "ipc"],       # or "all" / "cosmic_rays,ipc"
                     "cosmic_rays": {"rate": 5.0, ...}, "ipc": {"alpha": 0.016}, ...}}

    A section of an effect that is not enabled is validated and dropped; without ``enabled`` the
    effects that have a section are enabled; unknown sections or parameters raise EffectsError.
    """

    def __init__(self, params=None):
        params = dict(params or {})
        for name, p in params.items():
            cls = parameter_class(name)
            if not isinstance(p, cls):
                raise EffectsError(f"parameters of {name} must be a {cls.__name__}, got {type(p).__name__}")
        self._params = {n: params[n] for n in EFFECT_NAMES if n in params}

    # -- construction
    @classmethod
    def from_names(cls, names, has_previous_charge=False):
        """Default parameters for ``names``: "cosmic_rays,ipc", "all", a list, or None/"" (none)."""
        return cls({n: parameter_class(n)() for n in _parse_names(names, has_previous_charge)})

    @classmethod
    def preset(cls, name="lazuli", has_previous_charge=False):
        """A documented preset; "lazuli": every effect (persistence only with a previous charge
        image) at the default values of each module — CR 5 cm⁻² s⁻¹ through 6 µm of HgCdTe, IPC
        α = 1.6 %, α_d = 0.2 %, 5 % nonlinearity at the full well, NGHXRG-like correlated noise,
        4-pixel reference border, JWST-like bad-pixel fractions."""
        validation.choice("preset", name, PRESETS, error=EffectsError, what="effects preset")
        return cls({n: _params_from_dict(n, dict(over)) for n, over in PRESETS[name].items()
                    if n != "persistence" or has_previous_charge})

    @classmethod
    def from_text(cls, text, has_previous_charge=False):
        """The effects a user names in one string, as ``slicersim ramp --effects`` and a campaign's
        ``[products] effects`` read it.

        Parameters
        ----------
        text : str
            A preset (:data:`PRESETS`, e.g. ``"lazuli"``), ``"all"``, or comma-separated effect names
            (:data:`EFFECT_NAMES`).
        has_previous_charge : bool
            Whether a previous-exposure charge image is given (persistence needs one).

        Returns
        -------
        DetectorEffects
        """
        if not isinstance(text, str):
            raise EffectsError(f"effects must be a preset or comma-separated effect names, got {text!r}")
        name = text.strip().lower()
        return cls.preset(name, has_previous_charge) if name in PRESETS else cls.from_names(text, has_previous_charge)

    @classmethod
    def from_config(cls, config, has_previous_charge=False):
        """From a config dict: the whole config (with an "effects" table) or the table itself."""
        if not isinstance(config, dict):
            raise EffectsError(f"effects config must be a table, got {type(config).__name__}")
        section = config.get("effects", {}) if "effects" in config else config
        if section is not config:                 # [ipc] beside [effects] was silently ignored
            import difflib
            stray = sorted(k for k in config if k != "effects" and (k in EFFECT_NAMES or difflib.get_close_matches(
                str(k), EFFECT_NAMES, n=1, cutoff=0.8)))
            if stray:
                raise EffectsError(f"effect table(s) {', '.join(map(repr, stray))} outside [effects]: write them as "
                                   f"[effects.NAME] (TOML) or inside \"effects\" (JSON); known effects: "
                                   f"{', '.join(EFFECT_NAMES)}")
        if not isinstance(section, dict):
            raise EffectsError(f"effects config must be a table, got {type(section).__name__}")
        unknown = sorted(set(section) - {"enabled", *EFFECT_NAMES})
        if unknown:
            raise EffectsError(f"unknown key(s) {', '.join(map(repr, unknown))} in effects; known: enabled, "
                               f"{', '.join(EFFECT_NAMES)}")
        # without an "enabled" list, the effects that have a table are the enabled ones
        default = [n for n in EFFECT_NAMES if n in section]
        enabled = _parse_names(section.get("enabled", default), has_previous_charge)
        built = {n: _params_from_dict(n, section.get(n)) for n in EFFECT_NAMES if n in enabled or n in section}
        return cls({n: built[n] for n in enabled})

    @classmethod
    def from_file(cls, path, has_previous_charge=False, name="effects config"):
        """From a TOML (``.toml``) or JSON file holding an ``[effects]`` table (see :meth:`from_config`);
        errors about the file name it ``name`` (e.g. the CLI flag that gave it)."""
        import json
        import os

        from slicersim.io.tables import read_file_bytes
        path = os.fspath(path)
        raw = read_file_bytes(path, EffectsError, name)
        try:
            if path.lower().endswith(".json"):
                config = json.loads(raw.decode("utf-8"))
            else:
                import tomllib
                config = tomllib.loads(raw.decode("utf-8"))
        except (ValueError, UnicodeDecodeError) as exc:
            raise EffectsError(f"{path}: not a valid {'JSON' if path.lower().endswith('.json') else 'TOML'} "
                               f"file ({exc})") from exc
        except RecursionError:
            raise EffectsError(f"{path}: not a valid {'JSON' if path.lower().endswith('.json') else 'TOML'} file "
                               "for slicersim: arrays or tables nested too deeply") from None
        return cls.from_config(config, has_previous_charge)

    def restricted_to(self, names):
        """Exactly the effects ``names`` enabled, with this object's parameters where it has them
        (defaults otherwise)."""
        config = self.to_config()["effects"]
        config["enabled"] = list(names)
        for name in list(config):
            if name != "enabled" and name not in names:
                del config[name]
        return DetectorEffects.from_config(config, has_previous_charge="persistence" in names)

    def to_config(self):
        """JSON-able {"effects": {"enabled": [...], name: {parameters}, ...}} (from_config round trip)."""
        out = {"enabled": list(self.enabled)}
        out.update({n: _params_to_dict(p) for n, p in self._params.items()})
        return {"effects": out}

    def with_overrides(self, cr_rate=None):
        """A copy with CLI overrides: ``cr_rate`` [cm⁻² s⁻¹] (needs cosmic_rays enabled)."""
        config = self.to_config()["effects"]
        if cr_rate is not None:
            if "cosmic_rays" not in self._params:
                raise EffectsError("--cr-rate needs the cosmic_rays effect (add it to --effects)")
            config["cosmic_rays"]["rate"] = cr_rate
        return DetectorEffects.from_config(config, has_previous_charge="persistence" in self._params)

    # -- access
    @property
    def enabled(self):
        """Names of the enabled effects, in EFFECT_NAMES order."""
        return tuple(self._params)

    def params(self, name):
        """Parameter dataclass of an enabled effect."""
        if name not in self._params:
            validation.choice("effect", name, EFFECT_NAMES, error=EffectsError)
            raise EffectsError(f"effect {name!r} is not enabled (enabled: {', '.join(self.enabled) or 'none'})")
        return self._params[name]

    def __contains__(self, name):
        return name in self._params

    def __bool__(self):
        return bool(self._params)

    def __eq__(self, other):
        return isinstance(other, DetectorEffects) and self.to_config() == other.to_config()

    def __repr__(self):
        return f"DetectorEffects({', '.join(self.enabled) or 'none'})"
