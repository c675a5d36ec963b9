"""SALT2 / SALT3 templates offline: sncosmo sources built from template files installed with a package.

sncosmo registers ``salt2``, ``salt3`` and ``salt3-nir`` but downloads their template files on
first use.  The PyPI package ``jax-bandflux`` (MIT) ships the very files of sncosmo's data
server, in sncosmo's own layout, as package data of its module ``jax_supernovae``:

=================  ========  ======================================  ======================
sncosmo name       version   folder (sncosmo's relative path)        reference
=================  ========  ======================================  ======================
``salt2``          T23       ``models/salt2/salt2-k21-frag``         Taylor et al. 2023
``salt3``          2.0       ``models/salt3/salt3-f22``              Kenworthy et al. 2021
``salt3-nir``      1.0       ``models/salt3-nir/salt3nir-p22``       Pierel et al. 2022
=================  ========  ======================================  ======================

Those are the versions sncosmo loads for the bare names, so ``source="salt3"`` gives the same
model with or without network.  Only the data files are read: the package's own code (and its
JAX dependency) is never imported, so ``pip install --no-deps jax-bandflux`` is enough (``make``
does it).  Where the package is absent, sncosmo's download path is used as before.
"""
from __future__ import annotations

import functools
import importlib.util
import os

__all__ = ["SALT_PACKAGE", "offline_model_dir", "offline_salt_source", "offline_salt_names"]

#: the PyPI package whose data files hold the SALT templates, and its import name
SALT_PACKAGE, _MODULE = "jax-bandflux", "jax_supernovae"
_SUBDIR = "sncosmo-modelfiles"
#: (name, version) → (relative folder, sncosmo Source class name)
_MODELS = {("salt2", "T23"): ("models/salt2/salt2-k21-frag", "SALT2Source"),
           ("salt3", "2.0"): ("models/salt3/salt3-f22", "SALT3Source"),
           ("salt3-nir", "1.0"): ("models/salt3-nir/salt3nir-p22", "SALT3Source")}
#: the version sncosmo loads for a bare name (its latest)
_DEFAULT_VERSION = {name: version for name, version in _MODELS}


def _package_root():
    """The folder of the installed ``jax_supernovae`` package, found without importing it (or None)."""
    try:
        spec = importlib.util.find_spec(_MODULE)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return list(spec.submodule_search_locations)[0]


def offline_model_dir(name, version=None):
    """Folder of the installed template files of a SALT model.

    Parameters
    ----------
    name : str
        sncosmo source name (``"salt2"``, ``"salt3"`` or ``"salt3-nir"``; case-insensitive).
    version : str, optional
        sncosmo version (None: the one sncosmo loads for the bare name).

    Returns
    -------
    str or None
        The folder, when the files are installed; None otherwise (or for another model).
    """
    if not isinstance(name, str):
        return None
    name = name.strip().lower()
    version = _DEFAULT_VERSION.get(name) if version is None else version
    entry = _MODELS.get((name, version))
    root = _package_root()
    if entry is None or root is None:
        return None
    folder = os.path.join(root, _SUBDIR, entry[0])
    return folder if os.path.isdir(folder) else None


def offline_salt_source(name, version=None):
    """An sncosmo SALT source built from the installed template files, without any download.

    The files are read once per process (``sncosmo.Model`` copies its source, so the cached
    source is never changed by a model).

    Parameters
    ----------
    name, version
        As :func:`offline_model_dir`.

    Returns
    -------
    sncosmo.Source or None
        A ``SALT2Source`` / ``SALT3Source`` named like sncosmo's own (same name and version),
        or None when the files are not installed.
    """
    folder = offline_model_dir(name, version)
    if folder is None:
        return None
    name = name.strip().lower()
    return _load(folder, name, _DEFAULT_VERSION[name] if version is None else version)


@functools.lru_cache(maxsize=8)
def _load(folder, name, version):
    import sncosmo
    cls = getattr(sncosmo, _MODELS[(name, version)][1])
    return cls(modeldir=folder, name=name, version=version)


def offline_salt_names():
    """Names of the SALT models whose files are installed here.

    Returns
    -------
    tuple of str
        E.g. ``("salt2", "salt3", "salt3-nir")`` with ``jax-bandflux`` installed, () without.
    """
    return tuple(name for name in _DEFAULT_VERSION if offline_model_dir(name) is not None)
