"""Ramps with detector effects: charge sampler with deposits and nonlinearity, and the readout
(IPC, read noise, correlated noise, bias map, digitisation) — OpenCL kernels
(``kernels/ramp.cl`` built with ``-DRAMP_EFFECTS=1``, ``kernels/ramp_readout.cl``) and their
bit-exact NumPy twins.

The charge stage keeps every draw of the plain sampler (:mod:`slicersim.backends.ramp`): same
Philox counters, same sparse/dense choice, so switching an effect on or off never changes the
Poisson charge, the read noise or the kTC noise of a pixel.  Deposits (cosmic rays, persistence)
are a CSR list per block pixel of (frame from the reset, electrons), sorted by frame.  The read
value of accumulated charge Q [e-] is R(Q) = Q + Q²(a2 + a3 Q) when nonlinearity is on.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slicersim import rng
from slicersim.backends import opencl
from slicersim.backends.ramp import (P_KTC, P_READ, _event_position, _event_words, block_arguments,
                                     charge_groups, device_block, launch_samplers)
from slicersim.io.rampfile import DQ

__all__ = ["ChargeEffects", "charge_block_numpy", "charge_block_opencl", "readout_numpy", "readout_opencl", "ReadoutOptions",
           "deposits_csr"]


def deposits_csr(npix, pixel, frame, electrons):
    """CSR arrays (start (npix+1) uint32, frame int32, electrons float64) of deposits given per row
    (block-local pixel index, frame, e-), sorted by (pixel, frame) with ties in input order."""
    pixel = np.asarray(pixel, np.int64)
    order = np.lexsort((np.asarray(frame), pixel))
    start = np.zeros(npix + 1, np.uint32)
    np.cumsum(np.bincount(pixel, minlength=npix), out=start[1:])
    return start, np.asarray(frame, np.int32)[order], np.asarray(electrons, np.float64)[order]


def nl_read(q, a2, a3):
    """Read value R(Q) = Q + Q²(a2 + a3 Q) [e-] (same operations as ``nl_read`` in ramp_effects.cl)."""
    return q + q * q * (a2 + a3 * q)


class ChargeEffects:
    """Charge-domain effects of a block of pixels for the NumPy twin (deposits, nonlinearity).

    start, frame, electrons : deposits CSR (:func:`deposits_csr`);  a2, a3 : (npix,) [e-⁻¹, e-⁻²] or None.
    """

    def __init__(self, start, frame, electrons, a2=None, a3=None):
        self.start, self.frame, self.electrons = start, frame, electrons
        counts = np.diff(start.astype(np.int64))
        self.owner = np.repeat(np.arange(counts.size), counts)          # local pixel of each deposit
        self.use_nl = a2 is not None
        self.a2, self.a3 = a2, a3
        self.f0 = 0

    def subset(self, pixels):
        """Effects of the pixels ``pixels`` (ascending indices into this block), in that order."""
        pixels = np.asarray(pixels, np.int64)
        npix = self.start.size - 1
        local = np.full(npix, -1, np.int64)
        local[pixels] = np.arange(pixels.size)
        rows = np.nonzero(local[self.owner] >= 0)[0]
        start = np.zeros(pixels.size + 1, np.uint32)
        np.cumsum(np.diff(self.start.astype(np.int64))[pixels], out=start[1:])
        a2 = None if not self.use_nl else self.a2[pixels]
        a3 = None if not self.use_nl else self.a3[pixels]
        return ChargeEffects(start, self.frame[rows], self.electrons[rows], a2, a3)

    # dense path ----------------------------------------------------------------------------
    def frame_deposits(self, charge, frame):
        """charge + the deposits of ``frame`` (per pixel summed in list order from 0.0)."""
        sel = np.nonzero(self.frame == frame)[0]
        if not sel.size:
            return charge
        add = np.zeros(charge.size)
        np.add.at(add, self.owner[sel], self.electrons[sel])
        return charge + add

    def read_value(self, charge):
        return nl_read(charge, self.a2, self.a3) if self.use_nl else charge

    # sparse path ---------------------------------------------------------------------------
    def start_window(self, f0):
        self.f0 = f0

    def window_deposits(self, w):
        """Per pixel: sum of the deposits at frames [f0, f0 + w) (list order from 0.0)."""
        npix = self.start.size - 1
        self.win = np.nonzero((self.frame >= self.f0) & (self.frame < self.f0 + w))[0]
        self.has_dep = np.zeros(npix, bool)
        self.has_dep[self.owner[self.win]] = True
        dsum = np.zeros(npix)
        np.add.at(dsum, self.owner[self.win], self.electrons[self.win])
        return dsum

    def window_read_sum(self, read_sum, before, K, pos0, g, w, m, full_well, pix, seed, stream):
        """Σ_j R(min(full_well, (before + c_j) + d_j)) where a deposit or R(Q) needs it."""
        sel = np.arange(before.size) if self.use_nl else np.nonzero(self.has_dep)[0]
        if not sel.size:
            return read_sum
        kmax = int(K[sel].max()) if sel.size else 0
        pos = [pos0[sel]] + [_event_position(_event_words(seed, g, k, pix[sel], stream), k, w)
                             for k in range(1, kmax)]
        local = np.full(before.size, -1)
        local[sel] = np.arange(sel.size)
        win = self.win[local[self.owner[self.win]] >= 0]
        out = read_sum.copy()
        total = np.zeros(sel.size)
        for j in range(m):
            cj = np.zeros(sel.size)
            for k in range(kmax):
                cj = np.where((k < K[sel]) & (pos[k] <= j), cj + 1.0, cj)
            charge = before[sel] + cj
            dj_rows = win[self.frame[win] - self.f0 <= j]
            if dj_rows.size:
                dj = np.zeros(sel.size)
                np.add.at(dj, local[self.owner[dj_rows]], self.electrons[dj_rows])
                charge = charge + dj
            charge = np.where(charge >= full_well, full_well, charge)
            total = total + (nl_read(charge, self.a2[sel], self.a3[sel]) if self.use_nl else charge)
        out[sel] = total
        return out


def charge_block_numpy(mu_frame, dead, pixel0, ramp, seed, p, fx):
    """(group means of the read values (n, npix) float64 [e-], charge-saturation flags (n, npix) uint8)."""
    n, m, _ = p.nmd
    gmean = np.empty((n, mu_frame.size))
    qsat = np.empty((n, mu_frame.size), np.uint8)
    for g, total, saturated in charge_groups(mu_frame, dead, pixel0, ramp, seed, p, fx):
        gmean[g] = total / float(m)
        qsat[g] = np.where(saturated, DQ["SATURATED"], 0)
    return gmean, qsat


def _charge_kernel(name, vector_width, precision="double"):
    return opencl.get_kernel("ramp.cl", name, (f"-DRNG_VW={int(vector_width)}", "-DRAMP_EFFECTS=1")
                             + opencl.precision_options(precision))


def charge_block_opencl(mu_frame, dead, pixel0, ramp, seed, p, fx, work_group=None, vector_width=None, *,
                        workspace=None, to_host=True, precision="double"):
    """OpenCL twin of :func:`charge_block_numpy` (same lists and launch geometry as the plain ramp).

    to_host=False returns the device buffers (gmean, flags) instead, for :func:`readout_opencl`;
    precision="single": the float build (group means as float32, see ``simulate_block_opencl``)."""
    n = p.nmd[0]
    npix = mu_frame.size
    real = np.float32 if precision == "single" else np.float64
    size = np.dtype(real).itemsize
    vw, work_group, lists, d_mu = device_block(mu_frame, dead, p, vector_width, work_group, workspace, real)
    key = rng.seed_to_key(seed)
    d_gdq = opencl.workspace_buffer(workspace, "gdq", n * npix)
    d_gmean = opencl.workspace_buffer(workspace, "gmean", size * n * npix)
    d_sci = opencl.workspace_buffer(workspace, "sci_unused", 8)
    ndep = max(1, fx.frame.size)
    d_start = opencl.to_device(np.ascontiguousarray(fx.start, np.uint32), opencl.workspace_buffer(workspace, "dep_start", 4 * (npix + 1)))
    d_frame = opencl.to_device(np.resize(np.ascontiguousarray(fx.frame, np.int32), ndep),
                               opencl.workspace_buffer(workspace, "dep_frame", 4 * ndep))
    d_e = opencl.to_device(np.resize(np.ascontiguousarray(fx.electrons, real), ndep),
                           opencl.workspace_buffer(workspace, "dep_e", size * ndep))
    if fx.use_nl:
        d_a2 = opencl.to_device(np.ascontiguousarray(fx.a2, real), opencl.workspace_buffer(workspace, "nl_a2", size * npix))
        d_a3 = opencl.to_device(np.ascontiguousarray(fx.a3, real), opencl.workspace_buffer(workspace, "nl_a3", size * npix))
    else:
        d_a2 = d_a3 = opencl.workspace_buffer(workspace, "nl_unused", 8)
    effect_args = (d_start, d_frame, d_e, d_a2, d_a3, np.int32(bool(fx.use_nl)), d_gmean)
    launch_samplers(lambda name, width: _charge_kernel(name, width, precision), lists, vw, work_group, workspace,
                    (d_mu,), (d_sci, d_gdq), block_arguments(npix, pixel0, ramp, key, p, True, real),
                    p.gauss_min_mean, effect_args, real=real)
    if not to_host:
        return d_gmean, d_gdq
    gmean = np.empty((n, npix), real)
    qsat = np.empty((n, npix), np.uint8)
    opencl.from_device(gmean, d_gmean)
    opencl.from_device(qsat, d_gdq)
    return gmean, qsat


# --------------------------------------------------------------------------- readout
def _check_readout_inputs(gmean, rows, halo_top):
    n, rows_in, nx = gmean.shape
    if not 0 <= halo_top <= rows_in - rows:
        raise ValueError(f"halo_top {halo_top} and rows {rows} do not fit the {rows_in} input rows")  # internal: block geometry from products.ramps
    return n, rows_in, nx


def readout_numpy(gmean, qsat, rows, halo_top, y0, ny, ramp, seed, p, ipc=None, extra=None, bias_map=None):
    """SCI (n, rows, nx) uint16 and GROUPDQ uint8 from group means (n, rows_in, nx) [e-] whose row
    ``halo_top`` is detector row ``y0`` (see kernels/ramp_readout.cl for the operations)."""
    n, rows_in, nx = _check_readout_inputs(gmean, rows, halo_top)
    m = p.nmd[1]
    ys = y0 + np.arange(rows)
    pix = (ys[:, None].astype(np.uint64) * np.uint64(nx) + np.arange(nx, dtype=np.uint64)[None, :]).ravel()
    sbase = 4 * ramp
    reset = np.zeros(pix.size)
    if p.ktc_noise > 0:
        reset = p.ktc_noise * rng.normal(seed, pix, sbase + P_KTC, 0)[..., 0]
    b0 = p.bias if bias_map is None else np.asarray(bias_map, np.float32).astype(np.float64).ravel()
    read_sigma = p.ron / math.sqrt(m)
    sci = np.empty((n, rows, nx), np.uint16)
    gdq = np.empty((n, rows, nx), np.uint8)
    sat = np.zeros(pix.size, bool)
    core = slice(halo_top, halo_top + rows)
    if ipc is not None:
        rows_idx = np.arange(rows_in) - halo_top + y0
        valid_row = (rows_idx >= 0) & (rows_idx < ny)
    for g in range(n):
        if ipc is not None:
            padded = np.zeros((rows_in + 2, nx + 2))
            padded[1:-1, 1:-1] = np.where(valid_row[:, None], gmean[g], 0.0)
            v = np.zeros((rows, nx))
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    s = padded[1 + halo_top + dy:1 + halo_top + dy + rows, 1 + dx:1 + dx + nx]
                    v = v + ipc[dy + 1, dx + 1] * s
            v = v.ravel()
        else:
            v = gmean[g, core].ravel()
        if g % 2 == 0:
            z_pair = rng.normal(seed, (np.uint64(g >> 1) << np.uint64(32)) | pix, sbase + P_READ, 0)
        mean = v + read_sigma * z_pair[:, g & 1]
        if extra is not None:
            mean = mean + np.asarray(extra[g], np.float32).astype(np.float64).ravel()
        adu = np.clip(np.rint(b0 + p.gain * (reset + mean)), 0.0, 65535.0)
        sat |= (qsat[g, core].ravel() != 0) | (adu >= p.saturation)
        sci[g] = adu.astype(np.uint16).reshape(rows, nx)
        gdq[g] = np.where(sat, DQ["SATURATED"], 0).astype(np.uint8).reshape(rows, nx)
    return sci, gdq


@dataclass(frozen=True, kw_only=True)
class ReadoutOptions:
    """Keywords of :func:`readout_opencl` after the block: the readout maps ``ipc`` (3×3 gather weights),
    ``extra`` (n, rows, nx) read-domain noise [e-], ``bias_map`` (rows, nx) [ADU] (as :func:`readout_numpy`),
    and the device's ``workspace`` (dict of reused buffers), ``vector_width``, ``shape_in`` = (n, rows_in,
    nx) when ``gmean``/``qsat`` are device buffers, ``precision`` ("double" or "single")."""

    ipc: object = None
    extra: object = None
    bias_map: object = None
    workspace: dict | None = None
    vector_width: int | None = None
    shape_in: tuple | None = None
    precision: str = "double"


def readout_opencl(gmean, qsat, rows, halo_top, y0, ny, ramp, seed, p, **options):
    """OpenCL twin of :func:`readout_numpy`; ``options``: the fields of :class:`ReadoutOptions`.
    ``gmean``, ``qsat`` may be device buffers of :func:`charge_block_opencl` (``to_host=False``, the
    same ``precision``), then ``shape_in`` = (n, rows_in, nx)."""
    o = ReadoutOptions(**options)
    ipc, extra, bias_map, workspace, precision = o.ipc, o.extra, o.bias_map, o.workspace, o.precision
    shape_in, vector_width = o.shape_in, o.vector_width
    real = np.float32 if precision == "single" else np.float64
    size = np.dtype(real).itemsize
    if shape_in is None:
        n, rows_in, nx = _check_readout_inputs(gmean, rows, halo_top)
        d_gm = opencl.to_device(np.ascontiguousarray(gmean, real),
                                opencl.workspace_buffer(workspace, "ro_gmean", gmean.size * size))
        d_q = opencl.to_device(np.ascontiguousarray(qsat, np.uint8), opencl.workspace_buffer(workspace, "ro_qsat", qsat.size))
    else:
        n, rows_in, nx = _check_readout_inputs(np.empty((0,) + tuple(shape_in[1:])), rows, halo_top)
        n, d_gm, d_q = shape_in[0], gmean, qsat
    key = rng.seed_to_key(seed)
    plane = rows * nx
    # on CPU devices the host arrays are used in place (no copy of the (n, rows, nx) noise block)
    zero_copy = "GPU" not in opencl.device_type()
    if extra is not None:
        extra = np.ascontiguousarray(extra, np.float32)
        if zero_copy and not extra.flags.writeable:
            extra = extra.copy()
        d_x = opencl.host_buffer(extra) if zero_copy else \
            opencl.to_device(extra, opencl.workspace_buffer(workspace, "ro_extra", 4 * n * plane))
    else:
        d_x = opencl.workspace_buffer(workspace, "ro_unused_x", 8)
    if bias_map is not None:
        bias_map = np.array(bias_map, np.float32, order="C")
        d_b = opencl.host_buffer(bias_map) if zero_copy else \
            opencl.to_device(bias_map, opencl.workspace_buffer(workspace, "ro_bias", 4 * plane))
    else:
        d_b = opencl.workspace_buffer(workspace, "ro_unused_b", 8)
    kern = np.zeros(9, real) if ipc is None else np.ascontiguousarray(ipc, real).ravel()
    d_k = opencl.to_device(kern, opencl.workspace_buffer(workspace, "ro_ipc", 72))
    sci = np.empty((n, rows, nx), np.uint16)
    gdq = np.empty((n, rows, nx), np.uint8)
    if zero_copy:
        d_sci, d_gdq = opencl.host_buffer(sci), opencl.host_buffer(gdq)
    else:
        d_sci = opencl.workspace_buffer(workspace, "ro_sci", 2 * n * plane)
        d_gdq = opencl.workspace_buffer(workspace, "ro_gdq", n * plane)
    vw = opencl.preferred_vector_width(16, 2) if vector_width is None else int(vector_width)
    kernel = opencl.get_kernel("ramp_readout.cl", "ramp_readout", (f"-DRNG_VW={vw}",) + opencl.precision_options(precision))
    m = p.nmd[1]
    items = rows * -(-nx // vw)
    state = [opencl.workspace_buffer(workspace, name, nbytes * plane) for name, nbytes in
             (("ro_reset", size), ("ro_z", size), ("ro_sat", 1))]
    head = (d_gm, d_q, d_x, d_b, d_k, d_sci, d_gdq, *state, np.uint32(rows), np.uint32(nx), np.uint32(rows_in),
            np.uint32(halo_top), np.uint32(y0), np.uint32(ny), np.uint32(ramp), np.uint32(key[0]), np.uint32(key[1]))
    tail = (real(p.ron / math.sqrt(m)), real(p.gain), real(p.bias), real(p.ktc_noise),
            real(p.saturation), np.int32(ipc is not None), np.int32(extra is not None),
            np.int32(bias_map is not None))
    for g in range(n):                       # one launch per group: each streams through one plane
        opencl.launch(kernel, (items,), None, *head, np.int32(g), *tail)
    if zero_copy:
        opencl.sync_to_host(d_sci, sci)
        opencl.sync_to_host(d_gdq, gdq)
    else:
        opencl.from_device(sci, d_sci)
        opencl.from_device(gdq, d_gdq)
    return sci, gdq
