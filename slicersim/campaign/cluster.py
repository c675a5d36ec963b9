"""The Dask cluster of campaigns and dataset reductions: an embedded LocalCluster over TLS with temporary
credentials, or an existing scheduler by address (with TLS files); Dask's own configuration errors as one
line.  No physics, no datasets: :mod:`slicersim.campaign.runner` and :mod:`slicersim.reduction.campaign` use it.
"""
from __future__ import annotations

import contextlib
import os
import logging

from slicersim.errors import ConfigError, DatasetError

__all__ = ["tls_security", "dask_client", "DASHBOARD_ADDRESS", "dashboard_address"]


#: the embedded cluster's dashboard when asked for: this machine only (a busy port: distributed picks another)
DASHBOARD_ADDRESS = "127.0.0.1:8787"


def tls_security(ca_file=None, cert=None, key=None):
    """A :class:`distributed.Security` for a TLS scheduler from PEM files: ``ca_file`` (the CA that
    signed the scheduler's certificate), ``cert`` and ``key`` (this client's certificate and
    private key; ``key`` may be omitted when ``cert`` holds both).  None when no file is given
    (then Dask's configuration, ``distributed.comm.tls.*``, applies).  ParameterError naming the
    flag of a missing or unreadable file."""
    from distributed import Security

    from slicersim.validation import regular_file
    files = {"--tls-ca-file": ca_file, "--tls-cert": cert, "--tls-key": key}
    if all(v is None for v in files.values()):
        return None
    for flag, value in files.items():
        if value is not None:
            files[flag] = regular_file(f"{flag} (TLS {flag[6:]} file of the Dask scheduler)", value)
    if files["--tls-ca-file"] is None or files["--tls-cert"] is None:
        from slicersim.errors import ParameterError
        raise ParameterError("--tls-ca-file and --tls-cert are both needed for a TLS scheduler "
                             "(--tls-key too unless the certificate file holds the key)")
    _check_pem_files(files)
    return Security(tls_ca_file=files["--tls-ca-file"], tls_client_cert=files["--tls-cert"],
                    tls_client_key=files["--tls-key"], require_encryption=True)


def _check_pem_files(files):
    """Load the TLS files as the client will (Python's ssl): a file that is not PEM, a certificate without
    its key or a key that is not the certificate's is a ParameterError naming the flag and the file (OpenSSL
    said only "PEM lib")."""
    import ssl

    from slicersim.errors import ParameterError
    for flag, path in files.items():
        if path is None:
            continue
        with open(path, "rb") as fh:
            head = fh.read(1 << 20)
        if b"-----BEGIN " not in head:
            raise ParameterError(f"{flag} {path} is not a PEM file (no '-----BEGIN' line): give the "
                                 f"{'CA certificate' if flag == '--tls-ca-file' else flag[6:]} in PEM format")
    try:
        ssl.create_default_context().load_verify_locations(cafile=files["--tls-ca-file"])
    except (ssl.SSLError, ValueError) as exc:
        raise ParameterError(f"--tls-ca-file {files['--tls-ca-file']} holds no usable CA certificate "
                             f"({' '.join(str(exc).split())[:120]})") from None
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT).load_cert_chain(files["--tls-cert"], files["--tls-key"])
    except (ssl.SSLError, ValueError) as exc:
        which = (f"--tls-cert {files['--tls-cert']} and --tls-key {files['--tls-key']}" if files["--tls-key"]
                 else f"--tls-cert {files['--tls-cert']} (no --tls-key: the file must hold the key too)")
        raise ParameterError(f"{which} do not load as a client certificate with its private key: a certificate "
                             f"and the key it was made for are needed ({' '.join(str(exc).split())[:120]})") from None


def _connect(scheduler, security):
    """A Client of the existing scheduler at ``scheduler`` (``security``: a distributed.Security,
    or None for Dask's configuration)."""
    from distributed import Client
    if not isinstance(scheduler, str) or "://" not in scheduler:
        raise ConfigError(f"scheduler address must look like tls://host:port (or tcp://host:port), got {scheduler!r}")
    try:
        return Client(scheduler, timeout="10s", **({} if security is None else {"security": security}))
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        hint = ""
        if scheduler.startswith("tls://") and security is None:
            hint = (" (a tls:// scheduler needs the client's certificates: --tls-ca-file, --tls-cert, --tls-key, "
                    "security=tls_security(...) in Python, or Dask's distributed.comm.tls configuration)")
        raise DatasetError(f"cannot connect to the Dask scheduler {scheduler}: "
                           f"{' '.join(str(exc).split())[:200]}{hint}") from None


@contextlib.contextmanager
def _dask_configuration_errors(scheduler):
    """Dask's own configuration problems as one ConfigError line: a malformed file under DASK_CONFIG (or
    ~/.config/dask), or encryption required by it while the scheduler address is plain tcp://."""
    try:
        yield
    except ValueError as exc:
        if "dask config" not in str(exc).lower():
            raise
        raise ConfigError(f"Dask configuration: {' '.join(str(exc).split())[:300]} (fix or remove the file; "
                          "DASK_CONFIG names the folder Dask reads)") from None
    except RuntimeError as exc:
        if "encryption required" not in str(exc):
            raise
        raise ConfigError(f"the Dask configuration requires encryption (distributed.comm.require-encryption) but the "
                          f"scheduler {scheduler} is plain tcp://: give a tls:// scheduler with --tls-ca-file, "
                          "--tls-cert and --tls-key, or drop the requirement from the Dask configuration") from None


def dask_client(workers, scheduler, threads, security=None, dashboard=False):
    """(client, cluster or None): an existing scheduler or an embedded LocalCluster (see :func:`_dask_client`);
    a broken Dask configuration is a :class:`~slicersim.errors.ConfigError`."""
    with _dask_configuration_errors(scheduler):
        return _dask_client(workers, scheduler, threads, security, dashboard)


def _dask_client(workers, scheduler, threads, security=None, dashboard=False):
    """(client, cluster or None): an existing scheduler or an embedded LocalCluster.

    The embedded cluster listens on 127.0.0.1 only, over TLS with temporary credentials
    (``distributed.Security.temporary()``: a key pair and self-signed certificate made for this
    run and held in memory, required by the scheduler and workers), so no other process, local
    user included, can submit work to it.  Its dashboard is off unless ``dashboard`` (then on
    :data:`DASHBOARD_ADDRESS`, this machine only; an address "127.0.0.1:PORT" picks the port).
    ``security`` (a :class:`distributed.Security`, e.g. :func:`tls_security`) is used to reach
    an existing ``scheduler``; None takes Dask's configuration (``distributed.comm.tls.*``)."""
    import dask
    from distributed import LocalCluster, Security
    if scheduler:
        return _connect(scheduler, security), None
    env = {"POCL_MAX_PTHREAD_COUNT": str(threads), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    try:
        credentials = Security.temporary()
    except ImportError as exc:                   # distributed needs the cryptography package for it
        raise ConfigError(f"the embedded Dask cluster needs the 'cryptography' package for its TLS credentials "
                          f"({exc}); install it (pip install cryptography)") from None
    address = dashboard_address(dashboard)
    # distributed starts an HTTP server even without a dashboard (health, metrics, JSON, proxy routes):
    # off, it serves none of them, on a free port of 127.0.0.1
    config = {} if address else {"distributed.scheduler.http.routes": [], "distributed.worker.http.routes": []}
    pre_spawn = dict(dask.config.get("distributed.nanny.pre-spawn-environ", None) or {})
    config["distributed.nanny.pre-spawn-environ"] = {**pre_spawn, **worker_allocator_env()}
    with dask.config.set(config):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                               protocol="tls", security=credentials, dashboard_address=address or "127.0.0.1:0",
                               scheduler_kwargs={"dashboard": bool(address)}, silence_logs=logging.CRITICAL, env=env)
    from distributed import Client
    return Client(cluster, security=credentials), cluster


def worker_allocator_env(environ=None):
    """Environment the embedded cluster's worker processes start with (Dask's
    ``distributed.nanny.pre-spawn-environ``, which Dask applies before spawning them) for large arrays, as
    the ``slicersim`` command sets its own allocator (:mod:`slicersim.app.allocator`).

    Dask's default there, ``MALLOC_TRIM_THRESHOLD_=65536``, returns every freed whole-detector temporary to
    the system, so the next one faults in fresh pages: one streamed target (simulate and reduce, 20 groups)
    took 37.7 s of system time instead of 10.6 s on the 2-core VM.  The workers get glibc keeping up to
    1 GiB of freed memory and serving large arrays from its heap (``MALLOC_TRIM_THRESHOLD_``,
    ``MALLOC_MMAP_MAX_=0``) and NumPy's transparent-huge-page requests off (``NUMPY_MADVISE_HUGEPAGE=0``,
    unless ``environ`` — default ``os.environ`` — sets it: the user's choice stands)."""
    environ = os.environ if environ is None else environ
    out = {"MALLOC_TRIM_THRESHOLD_": str(1 << 30), "MALLOC_MMAP_MAX_": "0"}
    if "NUMPY_MADVISE_HUGEPAGE" not in environ:
        out["NUMPY_MADVISE_HUGEPAGE"] = "0"
    return out


def dashboard_address(dashboard):
    """None (no dashboard), or the dashboard's address: on 127.0.0.1 only."""
    if dashboard is None or dashboard is False:
        return None
    if dashboard is True:
        return DASHBOARD_ADDRESS
    text = str(dashboard)
    host, _, port = text.rpartition(":")
    if host not in ("127.0.0.1", "localhost", "") or not port.isdigit() or int(port) > 65535:
        from slicersim.errors import ParameterError
        raise ParameterError(f"dashboard must be True or an address 127.0.0.1:PORT (this machine only), got {text!r}")
    return f"127.0.0.1:{int(port)}"
