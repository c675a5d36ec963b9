"""Generators of the correlated read noise of :mod:`slicersim.physics.correlated_noise`.

:class:`CorrelatedNoise` gives, for one ramp, the GROUP-AVERAGED correlated noise [e-] of
any block of detector rows — the mean over each group's m reads of the noise added to
every read — with counter-based Philox draws keyed by (seed, ramp, group or frame,
output, segment), so any row blocking returns the same values.

Gaussian streams with a PSD S are synthesised in the Fourier domain: bin k of a length-L
stream at cadence Δt gets X_k = a_k (z₀ + i z₁), a_k = √(L S(f_k) / (4Δt)), f_k = k/(LΔt)
(E|X_k|² = L S_k/(2Δt), so Var x = Σ S_k Δf), then ``scipy.fft.irfft``.  The (z₀, z₁) of
bins 2b, 2b+1 come from the Philox block with counter (index = ramp·2³² + b, stream =
STREAMS["correlated_noise"] + 2¹⁶·component + output, draw = 2¹⁶·group + segment), as two
float32 Box–Muller pairs; :func:`spectral_coefficients_opencl` (``kernels/correlated_noise.cl``)
and its NumPy twin :func:`spectral_coefficients_numpy` agree within a few float ulps.

Methods:

* ``"exact"`` — one stream per output (plus the common one) at the pixel clock over the
  whole ramp, dropped frames included (FFT length ≥ max(2N, 1/(f_min τ)): no wrap-around
  and the model's lowest frequency resolved), read at every pixel's read times and
  averaged over each group's m reads.  Memory ∝ frames × frame_len: small detectors only.
* ``"multirate"`` (default) — the PSD is split, W_L²(f) + W_H²(f) = 1 around ν_c
  (:func:`~slicersim.physics.correlated_noise.crossover_low`).  The low part is a stream
  every q rows over the whole ramp (its PSD divided by sinc⁴(f q t_row) to undo the linear
  interpolation), reduced at once to two numbers per (group, row, stream): the group mean
  of the interpolated values is A + B·j/row_len for the pixel at scan position j.  The
  high part (correlation time ≲ 1/ν_c ≪ tframe, hence independent between frames) is
  drawn per group with PSD W_H²·S/m (the mean of m independent frames) in segments of
  ``segment_rows`` rows overlapping by 2·``taper_rows``, windowed by sin/cos tapers whose
  squares sum to one; a row block needs only the segments it overlaps.  The alternating
  (even/odd) half of ACN is a slow stream times (−1)^j: its low part is a third low stream
  per output, its high part lives near the Nyquist frequency of the high streams.
* ``"group"`` — the high-part machinery with the whole PSD /m per group (no low part): the
  frame-to-frame correlation of the 1/f noise is lost (group means too noisy at low
  frequency: pink power below 1/tframe is divided by m instead of kept).
* ``"white"`` — independent Gaussian per pixel and group with the model's group-mean variance.

Pedestal (per output and frame) and picture frame (template × amplitude per frame) are
drawn per frame and averaged over the group's reads in every method except ``"white"``.
The sum of these parts over a group's rows is :mod:`slicersim.backends.correlated_assembly`.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft

from slicersim import rng
from slicersim.backends import opencl
from slicersim.backends.correlated_assembly import GroupInputs, assemble_numpy, assembly_kernel
from slicersim.backends.dispatch import resolve_backend
from slicersim.backends.spectral_draws import (fft_length, spectral_coefficients_numpy,  # noqa: F401 (re-exported)
                                               spectral_coefficients_opencl, stream_amplitudes)
from slicersim.errors import EffectsError
from slicersim.physics.correlated_noise import (METHODS, CorrelatedNoiseParameters, ReadoutGeometry, acn_half,
                                                crossover_low, group_mean_variance, model_psd, pink_psd,
                                                picture_frame_template)
from slicersim.physics.effects import STREAMS
from slicersim.physics.ramp import macc_frame_schedule

__all__ = ["CorrelatedNoise", "spectral_coefficients_numpy", "spectral_coefficients_opencl",
           "stream_amplitudes", "COMPONENTS", "segment_geometry", "segment_cache_bytes"]

#: component codes of the Philox stream (STREAMS["correlated_noise"] + 2**16·code + output)
COMPONENTS = {"low_common": 0, "low_own": 1, "low_alternating": 2, "high_common": 3, "high_own": 4,
              "exact_common": 5, "exact_own": 6, "frame": 7, "white": 8}
FFT_WORKERS = 2
#: bytes of synthesised segments kept between row blocks (a segment spans several blocks of the
#: ramp driver: each is synthesised once when the blocks come in order)
CACHE_BYTES = 2**28
#: bytes of segment streams synthesised together (spectral draws of several groups in one launch and
#: one FFT call over all their rows)
SYNTH_BYTES = 2**25
#: zero-copy buffers of work arrays and window stacks kept between row blocks (evicted between blocks)
_MAX_WORK_BUFFERS = 64


def segment_geometry(g, S=128, h=12):
    """(S, h, segments per frame, span [samples], FFT length) of the high part's segments of ``S`` rows
    overlapping by ``h`` rows on each side, for the readout geometry ``g``."""
    nseg = -(-g.frame_rows // S)
    span = (S + 2 * h) * g.row_len
    return S, h, nseg, span, fft_length(span + h * g.row_len + g.row_len)


def segment_cache_bytes(params, shape, nmd, tframe):
    """Bytes of the segment cache that keeps one segment of every group between row blocks (the default
    ``multirate`` method): below it, a segment spanning several blocks is synthesised again for each
    (2.6× the spectral draws and FFTs of a 62-group Lazuli ramp with a 85 MB cache)."""
    if isinstance(params, dict):
        params = CorrelatedNoiseParameters(**params)
    g = ReadoutGeometry.from_params(params, shape, tframe)
    return int(nmd[0]) * (g.n_outputs + 1) * segment_geometry(g)[4] * 4


def _stream(component, output=0):
    return STREAMS["correlated_noise"] + (COMPONENTS[component] << 16) + int(output)


# --------------------------------------------------------------------------- the generator
class CorrelatedNoise:
    """Group-averaged correlated read noise of one exposure (see module doc).

    params : :class:`CorrelatedNoiseParameters` (or a dict of its fields);
    shape : (ny, nx) of the full detector; nmd : MACC (n, m, d); tframe : s; seed : int;
    method : one of ``METHODS``; backend : "auto" | "opencl" | "numpy" (spectral draws);
    nu_c [Hz], low_rows (q), segment_rows, taper_rows : multirate tuning (None: defaults,
    ν_c = min(40 Hz, 1/(8 t_row)), q = ⌊1/(8 ν_c t_row)⌋ ≥ 1, 128 and 12 rows).
    """

    def __init__(self, params, shape, nmd, tframe, seed, method="multirate", *, backend="auto", nu_c=None,
                 low_rows=None, segment_rows=128, taper_rows=12, cache_bytes=CACHE_BYTES):
        if isinstance(params, dict):
            params = CorrelatedNoiseParameters(**params)
        if not isinstance(params, CorrelatedNoiseParameters):
            raise EffectsError(f"correlated noise: params must be CorrelatedNoiseParameters or a dict, "
                               f"got {type(params).__name__}")
        if method not in METHODS:
            raise EffectsError(f"correlated noise: unknown method {method!r}; use one of {METHODS}")
        try:
            n, m, d = (int(v) for v in nmd)
        except Exception as exc:
            raise EffectsError(f"correlated noise: nmd must be (n, m, d) integers, got {nmd!r}") from exc
        if n < 1 or m < 1 or d < 0:
            raise EffectsError(f"correlated noise: nmd = {nmd!r} needs n ≥ 1, m ≥ 1, d ≥ 0")
        self.params, self.method, self.seed = params, method, int(seed)
        rng.seed_to_key(self.seed)
        self.geometry = g = ReadoutGeometry.from_params(params, shape, tframe)
        self.nmd = (n, m, d)
        self.backend = resolve_backend(backend)
        self.frames_group, _ = macc_frame_schedule(self.nmd)
        self.nframes = self.frames_group.size
        self.nu_c = float(min(40.0, 1.0 / (8.0 * g.row_time)) if nu_c is None else nu_c)
        self.low_rows = int(max(1, math.floor(1.0 / (8.0 * self.nu_c * g.row_time))) if low_rows is None
                            else low_rows)
        self.segment_rows, self.taper_rows = int(segment_rows), int(taper_rows)
        if not (self.nu_c > 0 and self.low_rows >= 1 and self.segment_rows >= 1 and 0 <= self.taper_rows
                and 2 * self.taper_rows <= self.segment_rows):
            raise EffectsError("correlated noise: tuning needs nu_c > 0, low_rows ≥ 1, segment_rows ≥ 1 and "
                               f"0 ≤ 2·taper_rows ≤ segment_rows, got {self.nu_c}, {self.low_rows}, "
                               f"{self.segment_rows}, {self.taper_rows}")
        self._ey, self._ex = picture_frame_template((g.ny, g.nx))
        self._cache_key, self._cache = None, None
        self._amp = {}                    # spectral amplitudes and windows, by their parameters
        self.cache_bytes = int(cache_bytes)
        self._segment_cache = {}          # (ramp, group, segment) -> (first sample, float32 streams[:, first:])
        self._cache_nbytes = 0
        self._work = None                 # reusable segment work array (_work_buffer)
        self._work_event = None           # the assembly launch still reading it
        self._work_buffers = {}           # zero-copy buffers of work arrays and window stacks (_device_array)
        #: row ranges [y0, y1) the blocks will ask for (a ramp of some rows), None: any; the low part's group
        #: means are then computed on those rows only
        self.rows = None

    # ------------------------------------------------------------------ helpers
    def _coefficients(self, amp, kind, hi, stream, draw):
        if self.backend == "opencl":
            return spectral_coefficients_opencl(amp, kind, hi, stream, draw, self.seed)
        return spectral_coefficients_numpy(amp, kind, hi, stream, draw, self.seed)

    def _synthesize(self, amp, length, kind, hi, stream, draw):
        """float32 (rows, length) streams of the spectral draws (irfft, crops padded bins)."""
        coeff = self._coefficients(amp, kind, hi, stream, draw)
        return sfft.irfft(coeff, n=length, axis=-1, workers=FFT_WORKERS, overwrite_x=True)

    def _frame_terms(self, ramp):
        """Group means of the pedestal (n, n_outputs) and picture-frame amplitude (n,) [e-]."""
        p, g = self.params, self.geometry
        n, m, d = self.nmd
        nout = g.n_outputs
        idx = (np.uint64(ramp) << np.uint64(32)) | np.arange(self.nframes * (nout + 1), dtype=np.uint64)
        z = rng.normal(self.seed, idx, _stream("frame"), 0)[:, 0].reshape(self.nframes, nout + 1)
        reads = self.frames_group >= 0
        ped = np.zeros((n, nout))
        pf = np.zeros(n)
        np.add.at(ped, self.frames_group[reads], z[reads, :nout])
        np.add.at(pf, self.frames_group[reads], z[reads, nout])
        return (p.pedestal * ped / m).astype(np.float32), (p.picture_frame * pf / m).astype(np.float32)

    def _ramp_state(self, ramp):
        key = int(ramp)
        if self._cache_key != key:
            self._cache = None
            state = {"frame": self._frame_terms(key)}
            if self.method == "exact":
                state["exact"] = self._exact_streams(key)
            elif self.method == "multirate":
                state["low"] = self._low_coefficients(key)
            self._cache_key, self._cache = key, state
        return self._cache

    # ------------------------------------------------------------------ exact
    def _exact_length(self, nsamples, dt):
        return sfft.next_fast_len(int(max(2 * nsamples, math.ceil(1.0 / (self.params.f_min * dt)))), real=True)

    def _exact_streams(self, ramp):
        p, g = self.params, self.geometry
        nsamp = self.nframes * g.frame_len
        length = self._exact_length(nsamp, g.dwell)
        amp = np.stack([stream_amplitudes(lambda f: model_psd(f, p, g, "c_pink"), length, g.dwell),
                        stream_amplitudes(lambda f: model_psd(f, p, g, "own"), length, g.dwell)])
        nout = g.n_outputs
        kind = np.array([0] + [1] * nout)
        streams = np.array([_stream("exact_common")] + [_stream("exact_own", o) for o in range(nout)])
        x = self._synthesize(amp, length, kind, np.full(nout + 1, ramp), streams, np.zeros(nout + 1))
        return x[:, :nsamp]

    def _block_exact(self, state, y0, y1, out):
        g = self.geometry
        n, m, d = self.nmd
        streams = state["exact"]
        x = np.arange(g.nx)
        out_of_x = x // g.ncol
        j = g.scan_index(x)
        ys = np.arange(y0, y1)
        for f in np.flatnonzero(self.frames_group >= 0):
            idx = f * g.frame_len + ys[:, None] * g.row_len + j[None, :]
            out[self.frames_group[f]] += streams[0][idx] + streams[1 + out_of_x[None, :], idx]
        out /= m

    # ------------------------------------------------------------------ multirate: low part
    def _low_psds(self):
        p, g = self.params, self.geometry
        dl = self.low_rows * g.row_time
        nu, fm = self.nu_c, p.f_min

        def comp(f):
            return crossover_low(f, nu) / np.sinc(f * dl) ** 4
        return ({"c": lambda f: comp(f) * pink_psd(f, p.c_pink, g, fm),
                 "u": lambda f: comp(f) * (pink_psd(f, p.u_pink, g, fm) + acn_half(f, p.acn, g, fm)),
                 "d": lambda f: comp(f) * acn_half(f, p.acn, g, fm)}, dl)

    def _low_coefficients(self, ramp):
        """float32 (streams, n, ny + 1): group means of the low part, interpolated linearly between
        its samples every q rows, at the start of scan row y (y = ny: the row after the last); the
        pixel at scan position j of row y reads A[y] + (j/row_len)(A[y + 1] − A[y]).  Streams:
        common, own per output, alternating per output."""
        g = self.geometry
        n, m, d = self.nmd
        q = self.low_rows
        psds, dl = self._low_psds()
        rows_total = self.nframes * g.frame_rows
        nlow = rows_total // q + 2
        length = sfft.next_fast_len(int(max(2 * nlow, math.ceil(1.0 / (self.params.f_min * dl)))), real=True)
        amp = np.stack([stream_amplitudes(psds[k], length, dl) for k in ("c", "u", "d")])
        nout = g.n_outputs
        kind = np.array([0] + [1] * nout + [2] * nout)
        streams = np.array([_stream("low_common")] + [_stream("low_own", o) for o in range(nout)]
                           + [_stream("low_alternating", o) for o in range(nout)])
        reads = np.flatnonzero(self.frames_group >= 0).reshape(n, m)
        # linear interpolation at the start of every row r of the ramp (r = frame·frame_rows + y):
        # sample i = r // q, weight (r mod q)/q, evaluated row after row for all rows up to the last
        # read's row ny, then the read frames' rows taken as strided slices (no gathers)
        nrows = int(reads.max()) * g.frame_rows + g.ny + 1
        nint = -(-nrows // q)
        wq = (np.arange(q) / q).astype(np.float32)
        nst = kind.size
        A = np.zeros((nst, n, g.ny + 1), np.float32)
        cols = slice(None)                          # rows y whose A[y] (and A[y + 1]) blocks read
        if self.rows is not None:
            need = np.zeros(g.ny + 1, bool)
            for a, b in self.rows:
                need[a:b + 1] = True
            cols = np.flatnonzero(need)
        batch = max(1, int(2**26 // (length * 4)))
        for s0 in range(0, nst, batch):
            s1 = min(nst, s0 + batch)
            low = self._synthesize(amp, length, kind[s0:s1], np.full(s1 - s0, ramp), streams[s0:s1],
                                   np.zeros(s1 - s0))
            for i, row in enumerate(low):
                a = row[:nint]
                at_rows = ((row[1:nint + 1] - a)[:, None] * wq[None, :] + a[:, None]).reshape(-1)
                frames = np.lib.stride_tricks.as_strided(at_rows, (int(reads.max()) + 1, g.ny + 1),
                                                         (g.frame_rows * 4, 4), writeable=False)
                A[s0 + i][:, cols] = frames[:, cols][reads].mean(axis=1, dtype=np.float64)
        return A

    # ------------------------------------------------------------------ multirate / group: segments
    def _segment_geometry(self):
        return segment_geometry(self.geometry, self.segment_rows, self.taper_rows)

    def _high_amplitudes(self, length):
        key = (self.method, length)
        if key not in self._amp:
            p, g = self.params, self.geometry
            m = self.nmd[1]
            fm, fn = p.f_min, g.f_nyquist
            if self.method == "multirate":
                def wh(f):
                    return 1.0 - crossover_low(f, self.nu_c)
            else:
                def wh(f):
                    return np.ones_like(f)
            c = lambda f: wh(f) * pink_psd(f, p.c_pink, g, fm) / m                       # noqa: E731
            u = lambda f: (wh(f) * (pink_psd(f, p.u_pink, g, fm) + acn_half(f, p.acn, g, fm))   # noqa: E731
                           + wh(fn - f) * acn_half(fn - f, p.acn, g, fm)) / m
            self._amp[key] = np.stack([stream_amplitudes(c, length, g.dwell), stream_amplitudes(u, length, g.dwell)])
        return self._amp[key]

    def _window(self, s, nseg, S, h, span):
        """Window of segment s over its span (samples), squares summing to 1 with neighbours."""
        kind = (s > 0, s < nseg - 1)                       # first, middle and last segments differ
        if (kind, span) not in self._amp:
            self._amp[(kind, span)] = self._window_shape(kind, S, h, span)
        return self._amp[(kind, span)]

    def _window_shape(self, kind, S, h, span):
        rl = self.geometry.row_len
        t = np.arange(span, dtype=np.float64) - h * rl          # sample position relative to the segment's start
        w = np.ones(span)
        if h:
            H = h * rl
            if kind[0]:
                u = np.clip(t / H, -1.0, 1.0)
                w *= np.sin(0.25 * np.pi * (1.0 + u))
            if kind[1]:
                u = np.clip((t - S * rl) / H, -1.0, 1.0)
                w *= np.cos(0.25 * np.pi * (1.0 + u))
        return w.astype(np.float32)

    def _segment_span(self, y0, y1):
        """(first, last) segment whose spans overlap rows y0:y1."""
        S, h, nseg, span, length = self._segment_geometry()
        return max(0, (y0 - h) // S), min(nseg - 1, (y1 - 1 + h) // S)

    def _first_sample(self, s, y):
        """First sample of segment s that rows ≥ y use."""
        return max(0, (y - int(s) * self.segment_rows + self.taper_rows) * self.geometry.row_len)

    def _missing_segments(self, ramp, group, y0, y1):
        """Segments of rows y0:y1 of ``group`` not in the cache (from the samples those rows use)."""
        s_first, s_last = self._segment_span(y0, y1)
        cache = self._segment_cache
        return np.array([s for s in range(s_first, s_last + 1)
                         if (ramp, group, s) not in cache or cache[(ramp, group, s)][0] > self._first_sample(s, y0)],
                        dtype=np.int64)

    def _synthesize_segments(self, ramp, todo):
        """{group: float32 (len(missing), n_out + 1, length)} streams of the segments ``missing`` of each
        (group, missing) in ``todo``, from one batch of spectral draws and one batched FFT."""
        g = self.geometry
        nout = g.n_outputs
        length = self._segment_geometry()[4]
        one = np.array([0] + [1] * nout)
        one_streams = np.array([_stream("high_common")] + [_stream("high_own", o) for o in range(nout)])
        count = sum(m.size for _, m in todo)
        kind = np.tile(one, count)
        streams = np.tile(one_streams, count)
        draw = np.concatenate([np.repeat((int(grp) << 16) | m, nout + 1) for grp, m in todo])
        new = self._synthesize(self._high_amplitudes(length), length, kind, np.full(kind.size, ramp), streams, draw)
        new = new.reshape(count, nout + 1, length)
        out, i = {}, 0
        for grp, m in todo:
            out[grp] = new[i:i + m.size]
            i += m.size
        return out

    def _group_batches(self, ramp, y0, y1):
        """Yield (group, synthesised missing segments or None) for every group, the missing segments of
        up to ``SYNTH_BYTES`` of streams drawn and transformed together (one launch, one FFT call
        over many rows: the FFT's threads share the work)."""
        n = self.nmd[0]
        nout = self.geometry.n_outputs
        length = self._segment_geometry()[4]
        per_group = 2 * (nout + 1) * length * 4
        batch = int(max(1, SYNTH_BYTES // per_group))
        for b0 in range(0, n, batch):
            groups = range(b0, min(n, b0 + batch))
            todo = [(grp, self._missing_segments(ramp, grp, y0, y1)) for grp in groups]
            todo = [(grp, m) for grp, m in todo if m.size]
            fresh = self._synthesize_segments(ramp, todo) if todo else {}
            for grp in groups:
                yield grp, fresh.get(grp)

    def _segments(self, ramp, group, y0, y1, new=None):
        """(first segment, segment streams float32 (nsg, n_out + 1, length), windows (nsg, span))
        of the segments whose spans overlap rows y0:y1 (stream 0 common, 1 + o output o's own).

        ``new``: the streams of this group's missing segments (:meth:`_synthesize_segments`), or
        None to synthesise them here.  Only the samples of rows y0:y1 are filled in (the assembly
        reads no others); the array is this generator's reusable work buffer, valid until the
        next call."""
        g = self.geometry
        S, h, nseg, span, length = self._segment_geometry()
        nout = g.n_outputs
        s_first, s_last = self._segment_span(y0, y1)
        nsg = s_last - s_first + 1
        cache = self._segment_cache
        first_sample = self._first_sample

        def used(s):                                 # samples of segment s that rows y0:y1 use
            return first_sample(s, y0), min(span, (y1 - int(s) * S + h) * g.row_len)
        missing = self._missing_segments(ramp, group, y0, y1)
        absent = set(missing.tolist())
        hit = {s: cache[(ramp, group, s)] for s in range(s_first, s_last + 1) if s not in absent}
        x = self._work_buffer((nsg, nout + 1, length))
        if missing.size:
            if new is None:
                new = self._synthesize_segments(ramp, [(group, missing)])[group]
            for s, streams_s in zip(missing, new):
                lo, hi = used(s)
                x[s - s_first, :, lo:hi] = streams_s[:, lo:hi]
                keep = first_sample(s, y1)           # what later blocks use
                if keep < span:
                    self._cache_put((ramp, group, int(s)), keep, streams_s[:, keep:span])
        for s, (p_from, data) in hit.items():
            lo, hi = used(s)
            x[s - s_first, :, lo:hi] = data[:, lo - p_from:hi - p_from]
        return s_first, x, self._windows(s_first, nsg, nseg, S, h, span)

    def _work_buffer(self, shape):
        """Reusable float32 array of ``shape`` (no fresh pages, hence no page faults, per call);
        first waits for the kernel still reading it (:meth:`_assemble_block_opencl`)."""
        size = int(np.prod(shape))
        if self._work_event is not None:
            self._work_event.wait()
            self._work_event = None
        if self._work is None or self._work.size < size:
            self._work = np.empty(size, np.float32)
            self._work_buffers = {}
        return self._work[:size].reshape(shape)

    def _windows(self, s_first, nsg, nseg, S, h, span):
        key = ("stack", s_first, nsg, nseg, span)
        if key not in self._amp:
            self._amp[key] = np.stack([self._window(s, nseg, S, h, span) for s in range(s_first, s_first + nsg)])
        return self._amp[key]

    def _cache_put(self, key, p_from, streams):
        """Keep a copy of samples p_from: of a segment's streams (``streams``: those samples) while
        the cache has room (else nothing)."""
        old = self._segment_cache.pop(key, None)
        if old is not None:
            self._cache_nbytes -= old[1].nbytes
        if self._cache_nbytes + streams.nbytes <= self.cache_bytes:
            self._segment_cache[key] = (p_from, np.array(streams, np.float32, order="C"))
            self._cache_nbytes += streams.nbytes

    def _evict_segments(self, ramp, y_next):
        """Keep of the cached segments only what a block starting at row ``y_next`` of ``ramp`` and
        later blocks use: other ramps and earlier segments go; a segment is cropped to rows
        ≥ y_next when that frees at least half of it (cropping copies: not at every block)."""
        S, h, rl = self.segment_rows, self.taper_rows, self.geometry.row_len
        first = max(0, (y_next - h) // S)
        for key in list(self._segment_cache):
            p_from, data = self._segment_cache[key]
            keep_from = max(0, (y_next - key[2] * S + h) * rl)
            if key[0] != ramp or key[2] < first or keep_from >= p_from + data.shape[1]:
                del self._segment_cache[key]
                self._cache_nbytes -= data.nbytes
            elif 2 * (keep_from - p_from) >= data.shape[1]:
                self._cache_put(key, keep_from, data[:, keep_from - p_from:])

    def _block_segments(self, state, ramp, y0, y1, out):
        g = self.geometry
        nout, rows = g.n_outputs, y1 - y0
        low = state.get("low")
        ped, pf = state["frame"]
        zeros = np.zeros((rows, nout), np.float32)
        ey, ex = np.ascontiguousarray(self._ey[y0:y1]), self._ex
        if self.backend == "opencl":
            return self._assemble_block_opencl(ramp, y0, y1, low, ped, pf, out)
        for grp, new in self._group_batches(ramp, y0, y1):
            s_first, seg, win = self._segments(ramp, grp, y0, y1, new)
            if low is None:
                la = la2 = aa = aa2 = zeros
            else:
                A, A2 = low[:, grp, y0:y1], low[:, grp, y0 + 1:y1 + 1]        # (streams, rows)
                la = np.ascontiguousarray((A[1:1 + nout] + A[0]).T)
                la2 = np.ascontiguousarray((A2[1:1 + nout] + A2[0]).T)
                aa = np.ascontiguousarray(A[1 + nout:].T)
                aa2 = np.ascontiguousarray(A2[1 + nout:].T)
            assemble_numpy(self, GroupInputs(seg, win, s_first, y0, la, la2, aa, aa2, ped[grp], float(pf[grp]),
                                             ey, ex), out=out[grp])

    def _assemble_block_opencl(self, ramp, y0, y1, low, ped, pf, out):
        """OpenCL ``assemble_group`` of every group of rows y0:y1 into ``out`` (n, rows, nx): the
        block's low-part, pedestal and picture-frame terms of all groups uploaded once, one launch
        per group changing only its segment streams and index, one read-back at the end."""
        g = self.geometry
        n = self.nmd[0]
        nout, rows = g.n_outputs, y1 - y0
        if low is None:
            terms = np.zeros((4, n, rows, nout), np.float32)
        else:
            A, A2 = low[:, :, y0:y1], low[:, :, y0 + 1:y1 + 1]                  # (streams, n, rows)
            terms = np.stack([np.moveaxis(A[1:1 + nout] + A[0], 0, -1), np.moveaxis(A2[1:1 + nout] + A2[0], 0, -1),
                              np.moveaxis(A[1 + nout:], 0, -1), np.moveaxis(A2[1 + nout:], 0, -1)])
        kern, vw, gpu = assembly_kernel(g.ncol)
        if len(self._work_buffers) > _MAX_WORK_BUFFERS:
            # evicted only here, between blocks: the last block's launches are finished (its final wait)
            # and none of this block's is set up.  Evicting inside _device_array released the buffer of
            # the segment just set as argument 0 when the window's insertion crossed the limit: the
            # launch then named a freed cl_mem (PoCL: "PTHREAD ERROR in can_run_command(): Invalid
            # argument", an abort, in campaign workers) or read the freed host memory of a zero-copy one
            self._work_buffers.clear()
        small = [opencl.to_device(np.ascontiguousarray(a, np.float32)) for a in
                 (*terms, ped, pf, self._ey[y0:y1], self._ex)]
        d_out = opencl.scratch_buffer("cn_block", out.nbytes) if gpu else opencl.host_buffer(out)
        S, h, nseg, span, length = self._segment_geometry()
        kern.set_args(None, None, np.int32(0), np.int32(0), np.int32(nseg), np.int32(S), np.int32(h), np.int32(span),
                      np.int32(length), np.int32(y0), np.int32(g.row_len), np.int32(g.ncol), np.int32(nout),
                      np.int32(g.nx), *small[:4], small[4], small[5], small[6], small[7], d_out, np.int32(0),
                      np.int32(rows))
        try:
            for grp, new in self._group_batches(ramp, y0, y1):
                s_first, seg, win = self._segments(ramp, grp, y0, y1, new)
                kern.set_arg(0, self._device_array(seg, "seg", gpu))
                kern.set_arg(1, self._device_array(win, "win", gpu))
                kern.set_arg(2, np.int32(s_first))
                kern.set_arg(3, np.int32(seg.shape[0]))
                kern.set_arg(23, np.int32(grp))
                self._work_event = opencl.launch_prepared(kern, (g.nx // vw, rows))
        finally:
            if self._work_event is not None:
                self._work_event.wait()
                self._work_event = None
        if gpu:
            opencl.from_device(out, d_out)
        else:
            opencl.sync_to_host(d_out, out)
        return out

    def _device_array(self, array, tag, gpu):
        """Buffer of a segment work array or window stack: on CPUs the array itself (zero copy; one
        buffer per array kept while the array lives), on GPUs a copy in a reused device buffer."""
        if gpu:
            return opencl.to_device(np.ascontiguousarray(array), opencl.scratch_buffer(f"cn_{tag}", array.nbytes))
        cache = self._work_buffers
        key = (array.__array_interface__["data"][0], array.nbytes)
        if key not in cache:               # never evicted here: a launch being set up may hold the others
            cache[key] = (array, opencl.host_buffer(array))
        return cache[key][1]

    # ------------------------------------------------------------------ public
    def block(self, ramp, y0, y1):
        """float32 (n_groups, y1 − y0, nx) [e-]: group-averaged correlated noise of rows y0:y1."""
        g = self.geometry
        if isinstance(ramp, bool) or int(ramp) != ramp or not 0 <= int(ramp) < 2**32:
            raise EffectsError(f"correlated noise: ramp must be an integer in [0, 2**32), got {ramp!r}")
        if not (0 <= int(y0) < int(y1) <= g.ny):
            raise EffectsError(f"correlated noise: rows {y0}:{y1} outside the detector's 0:{g.ny}")
        y0, y1, ramp = int(y0), int(y1), int(ramp)
        n = self.nmd[0]
        out = np.zeros((n, y1 - y0, g.nx), np.float32)
        if self.method == "white":
            return self._block_white(ramp, y0, y1, out)
        state = self._ramp_state(ramp)
        if self.method != "exact":
            self._block_segments(state, ramp, y0, y1, out)
            self._evict_segments(ramp, y1)
            return out
        self._block_exact(state, y0, y1, out)
        ped, pf = state["frame"]
        ey, ex = self._ey[y0:y1], self._ex
        for grp in range(n):
            out[grp] += np.repeat(ped[grp], g.ncol)[None, :]
            out[grp] += pf[grp] * (ey[:, None] + ex[None, :])
        return out

    def _block_white(self, ramp, y0, y1, out):
        g = self.geometry
        n, m, d = self.nmd
        sigma = math.sqrt(group_mean_variance(m, self.params, g))
        nb = g.nx
        amp = np.full((1, nb), sigma, np.float32)
        rows = np.arange(y0, y1)
        for grp in range(n):
            coeff = self._coefficients(amp, np.zeros(rows.size, int), np.full(rows.size, ramp),
                                       np.full(rows.size, _stream("white")), (grp << 16) | rows)
            out[grp] = coeff[:, :nb].real
        return out
