"""Campaign specs: a TOML file saying which targets, how they are observed and what to produce.

::

    seed = 1                                  # campaign seed, int in [0, 2⁶⁴); without it a seed is
                                              # drawn and written into the dataset's spec.toml
    name = "snia-mock"                        # optional label
    [population]                              # see slicersim.campaign.population
    kind = "snia"
    n = 100
    redshift = {distribution = "uniform", min = 0.05, max = 1.5}
    [observation]
    snr = 20                                  # per resolution element (per_resolution = true)
    lbda_range = [4000, 6800]                 # Å, in ``frame``
    frame = "rest"                            # "rest" or "obs"
    config = "cbe"                            # "cbe", "eol", a TOML path or a list of them
    field_switch_redshift = 0.8               # narrow below, wide at and above; or field = "narrow"
    psf_profile = "airy"                      # of the cubes ("gaussian" or "airy")
    conventions = "physical"                  # or "slicersim-1.0"
    search = "exact"                          # or "reference"
    [products]
    spectrum = true                           # noiseless and noisy extracted spectrum
    cube = false                              # signal, variance, noisy cube
    detector_image = false                    # photo-electron rate on the H4RG
    ramps = false                             # raw MACC ramps (HDF5)
    cube_dtype = "float32"                    # or "float64"
    precision = "auto"                        # of the cube kernels: "auto", "double" or "single"
    compression = "none"                      # of the ramps kept: none, gzip[:level], lz4, zstd,
                                              # bitshuffle-lz4 (ramps reduced and deleted: none)
    effects = "none"                          # detector effects of the ramps: "lazuli", "all", names
    reference_files = false                   # JWST reference files beside each target's kept ramps
    reduce = false                            # stream: reduce each target's ramps as soon as they are
                                              # simulated, in the same task (true or "spectra": as
                                              # `slicersim reduce DATASET --spectra`, "cubes": as
                                              # `... --spectra --cubes`, "rates": as
                                              # `slicersim reduce DATASET`); needs ramps = true
    keep_ramps = "all"                        # with reduce: "all", "none" or N (the ramps of every
                                              # target whose target_id is a multiple of N)
    [survey]                                  # totals of the plan
    overhead = 0.0                            # s per target (slew, settle, acquisition)
    efficiency = 1.0                          # fraction of time on sky
    compression_ratio = 1.0                   # of the raw data volume

Unknown keys are errors naming the key; every value is checked before anything runs.
The canonical form (:meth:`CampaignSpec.canonical`, defaults filled in, configuration and
catalog files replaced by their content digests too) identifies a dataset.
"""
from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field as dc_field

from slicersim import validation
from slicersim.errors import ConfigError, SlicersimError
from slicersim.io.tables import file_digest, parse_toml, read_file_bytes
from slicersim.validation import choice, number, redshift as check_redshift

__all__ = ["CampaignSpec", "load_spec", "parse_spec", "with_products", "with_seed", "seed_was_drawn", "PRODUCTS"]

#: products a campaign can write per target
PRODUCTS = ("spectrum", "cube", "detector_image", "ramps")

_TOP = {"seed", "name", "population", "observation", "products", "survey"}
_OBSERVATION = {"snr": 20.0, "lbda_range": [4000.0, 6800.0], "frame": "rest", "config": "cbe",
                "field": None, "field_switch_redshift": None, "psf_profile": "airy",
                "conventions": "physical", "search": "exact", "per_resolution": True}
_PRODUCTS = {"spectrum": True, "cube": False, "detector_image": False, "ramps": False,
             "cube_dtype": "float32", "compression": "none", "precision": "auto", "reduce": False,
             "keep_ramps": "all", "effects": "none", "reference_files": False,
             "ramp_format": "hdf5"}
#: what ``products.reduce`` may be (True is "spectra")
REDUCE_MODES = (False, "spectra", "cubes", "rates")
_SURVEY = {"overhead": 0.0, "efficiency": 1.0, "compression_ratio": 1.0}
DEFAULT_Z_SWITCH = 0.8


def _unknown(section, allowed, where):
    for key in section:
        if key not in allowed:
            raise ConfigError(f"unknown key {where}{key!r} in the campaign spec; known: "
                              f"{', '.join(sorted(allowed))}")


@dataclass
class CampaignSpec:
    """A validated campaign spec (see the module docstring of ``slicersim.campaign.spec``).

    Built by ``load_spec`` / ``parse_spec`` from the TOML text, which checks every value.

    Parameters
    ----------
    seed : int
        Campaign seed, in [0, 2⁶⁴).
    population : object
        The ``[population]`` table: which targets.
    observation : dict
        The ``[observation]`` table: SNR, band [Å], frame, configuration, field, ...
    products : dict
        The ``[products]`` table: what is written per target.
    survey : dict
        The ``[survey]`` table: overhead [s per target], efficiency, compression ratio.
    name : str, optional
        Label.
    text : str, optional
        The TOML text the spec was read from.
    base_dir : str, optional
        Directory relative configuration paths are read from.
    config_digests : dict, optional
        SHA-256 content digests of the configuration files.
    """

    seed: int
    population: object
    observation: dict
    products: dict
    survey: dict
    name: str = ""
    text: str = ""
    base_dir: str = "."
    config_digests: dict = dc_field(default_factory=dict)

    @property
    def wanted(self):
        """Names of the products to write, in ``PRODUCTS`` order."""
        return [p for p in PRODUCTS if self.products[p]]

    @property
    def recorded(self):
        """Names of the products a done target may record: :attr:`wanted`, and ``reduced`` when the
        campaign streams (``products.reduce``)."""
        return self.wanted + (["reduced"] if self.products.get("reduce") else [])

    def keeps_ramps(self, target_id):
        """True when the ramps of ``target_id`` stay in the dataset (``products.keep_ramps``; always
        without ``products.reduce``)."""
        keep = self.products.get("keep_ramps", "all")
        if not self.products.get("reduce") or keep == "all":
            return True
        return keep != "none" and int(target_id) % int(keep) == 0

    def field_of(self, redshift):
        """Field observing a target at ``redshift``."""
        obs = self.observation
        if obs["field"] is not None:
            return obs["field"]
        return "narrow" if redshift < obs["field_switch_redshift"] else "wide"

    def canonical(self):
        """JSON-able canonical dict (defaults filled in): the identity of a dataset."""
        out = {"seed": self.seed, "name": self.name, "population": self.population.to_spec(),
               "observation": dict(self.observation), "products": dict(self.products),
               "survey": dict(self.survey)}
        # precision changes the cubes only: left out when it is the default "auto" (datasets made before
        # the key keep their identity) or when no cube is written
        if out["products"].get("precision") == "auto" or not out["products"].get("cube"):
            out["products"].pop("precision", None)
        # streaming: left out when off (datasets made before the keys keep their identity)
        if not out["products"].get("reduce"):
            out["products"].pop("reduce", None)
            out["products"].pop("keep_ramps", None)
        if out["products"].get("effects") == "none":     # no detector effects: the identity of earlier datasets
            out["products"].pop("effects", None)
        if not out["products"].get("reference_files"):
            out["products"].pop("reference_files", None)
        if out["products"].get("ramp_format") == "hdf5":  # the default: the identity of earlier datasets
            out["products"].pop("ramp_format", None)
        if self.config_digests:
            out["observation"]["config_sha256"] = dict(sorted(self.config_digests.items()))
        return out


def with_products(spec, **changes):
    """A copy of ``spec`` with ``products.<key> = value`` for each change, written into its TOML text
    as well (the dataset stores the text: ``DIR/spec.toml`` must resume the same dataset), e.g. the
    CLI's ``--precision``.  ConfigError when the text cannot be edited safely."""
    import re
    lines = spec.text.splitlines()
    header = next((i for i, line in enumerate(lines) if re.match(r"\s*\[products\]\s*(#.*)?$", line)), None)
    keys = "|".join(map(re.escape, changes))
    new_lines = [f"{key} = {_toml_value(value)}" for key, value in changes.items()]
    if header is None:
        lines += ["", "[products]"] + new_lines
    else:
        end = next((i for i in range(header + 1, len(lines)) if re.match(r"\s*\[", lines[i])), len(lines))
        body = [line for line in lines[header + 1:end] if not re.match(rf"\s*({keys})\s*=", line)]
        lines = lines[:header + 1] + new_lines + body + lines[end:]
    text = "\n".join(lines) + "\n"
    try:
        edited = parse_spec(tomllib.loads(text), text=text, base_dir=spec.base_dir)
    except (tomllib.TOMLDecodeError, ConfigError) as exc:
        raise ConfigError(f"could not write {', '.join(changes)} into the campaign spec ({exc}); set it in the "
                          "spec's [products] table instead") from None
    want = spec.canonical()
    want["products"] = {**dict(spec.products), **changes}
    edited_products = dict(edited.products)
    if edited_products != want["products"] or {k: v for k, v in edited.canonical().items() if k != "products"} \
            != {k: v for k, v in want.items() if k != "products"}:
        raise ConfigError(f"could not write {', '.join(changes)} into the campaign spec safely; set it in the "
                          "spec's [products] table instead")
    return edited


#: the line :func:`parse_spec` puts at the top of a spec's text when it drew the seed
DRAWN_SEED_COMMENT = "# drawn by slicersim: the spec gave no seed"


def _with_seed_line(text, seed):
    """``text`` with ``seed = <seed>`` as its first line (top-level keys precede the tables), so
    the dataset's stored spec.toml repeats the campaign."""
    return f"seed = {int(seed)}  {DRAWN_SEED_COMMENT}\n" + text


def seed_was_drawn(spec):
    """True when the spec's file gave no seed (:func:`parse_spec` drew one)."""
    first = spec.text.split("\n", 1)[0]
    return first.startswith("seed = ") and first.rstrip().endswith(DRAWN_SEED_COMMENT)


def with_seed(spec, seed):
    """A copy of a spec whose seed was drawn (no ``seed`` key in its file) with ``seed`` instead,
    e.g. the seed recorded in the dataset being resumed."""
    from dataclasses import replace
    lines = spec.text.splitlines(keepends=True)
    body = "".join(lines[1:]) if seed_was_drawn(spec) else spec.text
    return replace(spec, seed=validation.seed(seed, allow_none=False, error=ConfigError),
                   text=_with_seed_line(body, seed))


def _toml_value(value):
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)


def _check_config(config, base_dir):
    """Configuration names/paths (paths relative to the spec's directory) and their digests."""
    items = config if isinstance(config, list) else [config]
    if not items or not all(isinstance(c, str) and c for c in items):
        raise ConfigError(f"observation.config must be 'cbe', 'eol', a TOML path or a list of them, got {config!r}")
    resolved, digests = [], {}
    for item in items:
        if item in ("cbe", "eol") or not item.endswith(".toml"):
            resolved.append(item)
            continue
        path = item if os.path.isabs(item) else os.path.normpath(os.path.join(base_dir, item))
        if not os.path.lexists(path):
            raise ConfigError(f"observation.config: no such configuration file {path}")
        validation.regular_file("observation.config", path, error=ConfigError)     # a FIFO, device, directory
        resolved.append(path)
        digests[item] = file_digest(path)
    return (resolved if isinstance(config, list) else resolved[0]), digests


def _observation(section):
    from slicersim.physics.conventions import CONVENTIONS
    from slicersim.products.psf_profiles import PSF_PROFILES
    _unknown(section, _OBSERVATION, "observation.")
    obs = {**_OBSERVATION, **section}
    obs["snr"] = number("observation.snr", obs["snr"], low=0, low_open=True, error=ConfigError)
    rng = obs["lbda_range"]
    if not isinstance(rng, list) or len(rng) != 2:
        raise ConfigError(f"observation.lbda_range must be [lo, hi] in Å with 0 < lo < hi, got {rng!r}")
    obs["lbda_range"] = [number(f"observation.lbda_range[{i}] [Å]", v, low=0, low_open=True, error=ConfigError)
                         for i, v in enumerate(rng)]
    if not obs["lbda_range"][0] < obs["lbda_range"][1]:
        raise ConfigError(f"observation.lbda_range must be [lo, hi] in Å with 0 < lo < hi, got {rng!r}")
    choice("observation.frame", obs["frame"], ("rest", "obs"), error=ConfigError)
    choice("observation.conventions", obs["conventions"], CONVENTIONS, error=ConfigError)
    choice("observation.search", obs["search"], ("exact", "reference"), error=ConfigError)
    choice("observation.psf_profile", obs["psf_profile"], tuple(PSF_PROFILES), error=ConfigError)
    if not isinstance(obs["per_resolution"], bool):
        raise ConfigError(f"observation.per_resolution must be true or false, got {obs['per_resolution']!r}")
    if obs["field"] is not None and obs["field_switch_redshift"] is not None:
        raise ConfigError("observation: give field or field_switch_redshift, not both")
    if obs["field"] is not None:
        choice("observation.field", obs["field"], ("narrow", "wide"), error=ConfigError)
    else:
        zs = DEFAULT_Z_SWITCH if obs["field_switch_redshift"] is None else obs["field_switch_redshift"]
        obs["field_switch_redshift"] = check_redshift("observation.field_switch_redshift", zs, allow_zero=True,
                                                      error=ConfigError)
    return obs


def _products(section):
    from slicersim.io.rampfile import compression_options
    _unknown(section, _PRODUCTS, "products.")
    prod = {**_PRODUCTS, **section}
    for name in PRODUCTS:
        if not isinstance(prod[name], bool):
            raise ConfigError(f"products.{name} must be true or false, got {prod[name]!r}")
    choice("products.cube_dtype", prod["cube_dtype"], ("float32", "float64"), error=ConfigError)
    choice("products.precision", prod["precision"], ("auto", "double", "single"), error=ConfigError)
    try:
        compression_options(None if prod["compression"] == "none" else prod["compression"])
    except (SlicersimError, ValueError) as exc:
        raise ConfigError(f"products.compression: {exc}") from None
    _streaming(prod)
    _effects(prod)
    _reference_files(prod)
    choice("products.ramp_format", prod["ramp_format"], ("hdf5", "jwst-uncal"), error=ConfigError)
    if prod["ramp_format"] == "jwst-uncal" and prod["compression"] != "none":
        raise ConfigError("products.ramp_format = \"jwst-uncal\" writes uncompressed level-1b FITS: set "
                          "products.compression = \"none\"")
    return prod


def _reference_files(prod):
    """``products.reference_files``: the JWST reference files of each target's kept ramps (stdatamodels)."""
    if not isinstance(prod["reference_files"], bool):
        raise ConfigError(f"products.reference_files must be true or false, got {prod['reference_files']!r}")
    if not prod["reference_files"]:
        return
    if not prod["ramps"]:
        raise ConfigError("products.reference_files = true describes the raw ramps: set products.ramps = true")
    from slicersim.products import reference
    if not reference.available():
        raise ConfigError("products.reference_files = true needs stdatamodels: pip install 'slicersim[jwst]'")


def _effects(prod):
    """``products.effects``: the detector effects of the ramps ("none", a preset such as "lazuli", "all" or
    comma-separated names: what ``slicersim ramp --effects`` accepts); only with ramps."""
    value = prod["effects"]
    if value is False or value is None or (isinstance(value, str) and value.strip().lower() in ("", "none")):
        prod["effects"] = "none"
        return
    from slicersim.errors import EffectsError
    from slicersim.physics.effects import DetectorEffects
    try:
        DetectorEffects.from_text(value)
    except EffectsError as exc:
        raise ConfigError(f"products.effects: {exc}") from None
    if not prod["ramps"]:
        raise ConfigError(f"products.effects = {value!r} applies to the raw ramps: set products.ramps = true")
    prod["effects"] = value.strip().lower()


def _streaming(prod):
    """Check ``products.reduce`` and ``products.keep_ramps`` (``reduce = true`` is "spectra")."""
    reduce, keep = prod["reduce"], prod["keep_ramps"]
    if reduce is True:
        prod["reduce"] = reduce = "spectra"
    if not ((reduce is False) or (isinstance(reduce, str) and reduce in REDUCE_MODES)):
        raise ConfigError(f"products.reduce must be false, true, \"spectra\", \"cubes\" or \"rates\", got {reduce!r}")
    if isinstance(keep, bool) or not (keep in ("all", "none") if isinstance(keep, str) else
                                      isinstance(keep, int) and keep >= 1):
        raise ConfigError(f"products.keep_ramps must be \"all\", \"none\" or a whole number N ≥ 1 (the ramps of "
                          f"every target whose target_id is a multiple of N), got {keep!r}")
    if reduce and not prod["ramps"]:
        raise ConfigError("products.reduce reduces each target's ramps as they are simulated: set products.ramps "
                          "= true (and products.keep_ramps to keep none or a sample of them)")
    if not reduce and keep != "all":
        raise ConfigError("products.keep_ramps applies only with products.reduce (without it every ramp is kept)")


def _survey(section):
    _unknown(section, _SURVEY, "survey.")
    sv = {**_SURVEY, **section}
    sv["overhead"] = number("survey.overhead", sv["overhead"], low=0, unit="s", error=ConfigError)
    sv["efficiency"] = number("survey.efficiency", sv["efficiency"], low=0, low_open=True, high=1, error=ConfigError)
    sv["compression_ratio"] = number("survey.compression_ratio", sv["compression_ratio"], low=1, error=ConfigError)
    return sv


def parse_spec(doc, text="", base_dir="."):
    """:class:`CampaignSpec` from a parsed TOML document (dict)."""
    from slicersim.campaign.population import population_from_spec
    if not isinstance(doc, dict):
        raise ConfigError("a campaign spec is a TOML document with [population], [observation], [products]")
    _unknown(doc, _TOP, "")
    for name in ("population", "observation", "products", "survey"):
        if name in doc and not isinstance(doc[name], dict):
            raise ConfigError(f"{name} must be a TOML table [{name}], got {doc[name]!r}")
    if "population" not in doc:
        raise ConfigError("the campaign spec has no [population] table")
    seed = validation.seed(doc.get("seed"), error=ConfigError)
    if seed is None:                                  # drawn, and written into the stored spec's text
        seed = validation.new_seed()
        text = _with_seed_line(text, seed)
    name = doc.get("name", "")
    if not isinstance(name, str):
        raise ConfigError(f"name must be a string, got {name!r}")
    obs = _observation(doc.get("observation", {}))
    obs["config"], digests = _check_config(obs["config"], base_dir)
    products = _products(doc.get("products", {}))
    if not any(products[p] for p in PRODUCTS):
        raise ConfigError(f"[products] asks for nothing: set one of {', '.join(PRODUCTS)} to true")
    survey = _survey(doc.get("survey", {}))
    try:
        population = population_from_spec(doc["population"], base_dir=base_dir)
    except (TypeError, AttributeError) as exc:       # a value of the wrong kind the checks did not name
        raise ConfigError(f"[population]: a value has the wrong type ({exc})") from None
    return CampaignSpec(seed=seed, population=population, observation=obs, products=products,
                        survey=survey, name=name, text=text, base_dir=base_dir, config_digests=digests)


def load_spec(path):
    """Read and validate a campaign spec file (one :class:`~slicersim.errors.ConfigError` per problem)."""
    try:
        path = os.fspath(path)
    except TypeError:
        raise ConfigError(f"campaign spec must be a CampaignSpec or the path of its TOML file, got "
                          f"{validation.short_repr(path)}") from None
    if os.path.isdir(path):
        raise ConfigError(f"campaign spec {path} is a directory, not a TOML file")
    raw = read_file_bytes(path, ConfigError, "campaign spec")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"campaign spec {path} is not valid TOML: {exc}") from None
    doc = parse_toml(text, f"campaign spec {path}")
    return parse_spec(doc, text=text, base_dir=os.path.dirname(os.path.abspath(path)))
