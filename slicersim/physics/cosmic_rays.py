"""Cosmic-ray hits on an H4RG: Poisson events per frame, straight tracks through the HgCdTe
absorber, Landau–Vavilov (Moyal) energy loss in every pixel crossed.

Model (every quantity a parameter of :class:`CosmicRayParameters`):

* **Rate** R = 5 cm⁻² s⁻¹, the galactic-cosmic-ray rate at L2 assumed for JWST (JWST User
  Documentation, "Cosmic rays"; Robberto 2009, JWST-STScI-001928, the JWST HgCdTe cosmic-ray
  library).  Events per frame ~ Poisson(R · A_det · t_frame), A_det = n_y n_x p².
* **Geometry**: pixel pitch p = 10 µm (H4RG-10); absorber thickness t = 6 µm (substrate-removed
  Teledyne HgCdTe absorbers are a few µm to ≈ 10 µm thick; Beletic et al. 2008, Proc. SPIE
  7021, 70210H).  Isotropic flux crossing a plane: dN/dΩ ∝ cos θ, i.e. cos θ = √u, φ = 2πu′;
  entry point uniform on the detector; the track runs straight from the top to the bottom of the
  absorber (lateral length t·tan θ), clipped where it leaves the detector.  The 3-D path length
  in each pixel crossed is that pixel's share of the track, t / cos θ in total.
* **Ions**: galactic cosmic rays by number ≈ 87 % protons, 12 % He, 1 % heavier nuclei (Simpson
  1983, Ann. Rev. Nucl. Part. Sci. 33, 323); the heavier ones are represented by oxygen
  (z = 8, the CNO group dominates them).  All at βγ = 3 (near minimum ionisation; the GCR flux
  peaks at ≈ 1–2 GeV/nucleon).
* **Energy loss** in a segment of length s (Landau–Vavilov, thin absorber: κ = ξ/W_max ≪ 0.01):
  most probable value (PDG Review of Particle Physics, "Passage of particles through matter",
  eq. 34.12, after Bichsel 1988)

      Δ_p = ξ [ln(2 m_e c² β²γ² / I) + ln(ξ / I) + j − β² − δ(βγ)],   j = 0.200,
      ξ   = (K/2) ⟨Z/A⟩ z² ρ s / β²,   K = 0.307075 MeV mol⁻¹ cm²,

  and the straggling Δ = Δ_p + ξ λ with λ drawn from the Moyal (1955) approximation of the
  Landau density, f(λ) = exp(−(λ + e^−λ)/2)/√(2π), sampled exactly as λ = −ln z², z ~ N(0, 1)
  (z² is χ²₁).  Its mode is Δ_p and its mean Δ_p + (γ_E + ln 2) ξ.  The Moyal tail falls faster
  than Landau's (a mild under-estimate of the rare very large deposits).
* **Hg₁₋ₓCdₓTe** with x = 0.6 (1.7 µm cut-off at 100 K, Hansen, Schmit & Casselman 1982, J.
  Appl. Phys. 53, 7099): ⟨Z/A⟩ from the composition, density linear between HgTe (8.08 g cm⁻³)
  and CdTe (5.85 g cm⁻³), mean excitation energy by Bragg additivity of the elements' I (Hg
  800 eV, Cd 469 eV, Te 485 eV; PDG atomic and nuclear properties), density effect δ from the
  Sternheimer & Peierls (1971) general parametrisation.
* **Charge**: electrons = Δ / ε, with the e–h pair creation energy ε = 2.8 E_g + 0.6 eV (Klein
  1968, J. Appl. Phys. 39, 2029), E_g(x, T) of Hansen et al. (1982).

Randomness is counter-based (:mod:`slicersim.rng`), stream ``STREAMS["cosmic_rays"] +
sub``, index ``ramp << 32 | frame``: the number of events of a frame is a Poisson draw (sub 0);
event k's entry point (sub 1), direction (sub 2) and ion (sub 3) use draw k; the Moyal variate of
its j-th pixel uses sub 4, draw ``k << 13 | j >> 1`` (Box–Muller branch j & 1).  The deposits of a
(ramp, frame) therefore never depend on chunking, on other frames or on other effects.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from slicersim import rng, validation
from slicersim.errors import EffectsError
from slicersim.physics.effects import STREAMS, check_number

__all__ = ["CosmicRayParameters", "DEPOSIT_DTYPE", "cosmic_ray_events", "cosmic_ray_tracks",
           "cosmic_ray_deposits", "track_segments", "segment_electrons", "most_probable_loss",
           "bichsel_most_probable", "expected_events_per_frame", "landau_xi",
           "pair_creation_energy", "band_gap", "density_effect", "hgcdte_properties"]

#: one row per pixel crossed (also used for persistence): full-detector (y, x), frame from the reset
DEPOSIT_DTYPE = np.dtype([("ramp", "<u4"), ("frame", "<u4"), ("y", "<u2"), ("x", "<u2"),
                          ("electrons", "<f4")])

K_BETHE = 0.307075            # MeV mol⁻¹ cm² (4π N_A r_e² m_e c², PDG)
ME_C2 = 0.51099895e6          # eV, electron rest energy
BICHSEL_J = 0.200             # Bichsel's constant in the most-probable-loss formula (PDG 34.12)
MOYAL_MEAN = 0.5772156649015329 + math.log(2.0)   # E[λ] of the Moyal density (γ_E + ln 2)
MOYAL_VAR = math.pi ** 2 / 2.0                    # Var[λ] of the Moyal density
# (Z, A [g/mol], I [eV]) of the elements (PDG atomic and nuclear properties)
ELEMENTS = {"Hg": (80, 200.592, 800.0), "Cd": (48, 112.414, 469.0), "Te": (52, 127.60, 485.0)}
RHO_HGTE, RHO_CDTE = 8.08, 5.85                   # g cm⁻³ (Capper 1994, EMIS datareview 10)

SUB_COUNT, SUB_ENTRY, SUB_DIRECTION, SUB_ION, SUB_STRAGGLING = 0, 1, 2, 3, 4
MAX_SEGMENT_BITS = 13          # j >> 1 < 2¹³: up to 16384 pixels per track
MAX_EVENTS_PER_FRAME = 1 << 19  # k < 2¹⁹ (k << 13 fits in the 32-bit draw word)


@validation.checked_fields(error=EffectsError)
@dataclass(kw_only=True)
class CosmicRayParameters:
    """Cosmic-ray model (see the module docstring for sources).

    rate : events cm⁻² s⁻¹;  pixel_pitch, thickness : µm;  cd_fraction : x of Hg₁₋ₓCdₓTe;
    temperature : K (band gap);  beta_gamma : βγ of every ion;  species : ((z, fraction), ...)
    by number (fractions sum to 1);  pair_energy : eV per e–h pair (None: Klein's rule).
    """

    rate: float = 5.0
    pixel_pitch: float = 10.0
    thickness: float = 6.0
    cd_fraction: float = 0.6
    temperature: float = 100.0
    beta_gamma: float = 3.0
    species: tuple = ((1, 0.87), (2, 0.12), (8, 0.01))
    pair_energy: float | None = None

    def __post_init__(self):
        self.rate = check_number("cosmic_rays.rate [cm⁻² s⁻¹]", self.rate, 0.0, 1e6)
        self.pixel_pitch = check_number("cosmic_rays.pixel_pitch [µm]", self.pixel_pitch, 0.0, 1e3, low_open=True)
        self.thickness = check_number("cosmic_rays.thickness [µm]", self.thickness, 0.0, 1e3, low_open=True)
        self.cd_fraction = check_number("cosmic_rays.cd_fraction", self.cd_fraction, 0.2, 1.0)
        self.temperature = check_number("cosmic_rays.temperature [K]", self.temperature, 4.0, 300.0)
        self.beta_gamma = check_number("cosmic_rays.beta_gamma", self.beta_gamma, 0.3, 1e5)
        try:
            pairs = [tuple(p) for p in self.species]
        except TypeError:
            pairs = None
        if not pairs or any(len(p) != 2 for p in pairs):
            raise EffectsError(f"cosmic_rays.species must be a list of (charge z, fraction) pairs, "
                               f"got {validation.short_repr(self.species)}")
        species = tuple((validation.integer("cosmic_rays.species charge z", z, low=1, high=92, error=EffectsError),
                         check_number(f"cosmic_rays.species fraction of z={z}", f, 0.0, 1.0)) for z, f in pairs)
        if abs(sum(f for _, f in species) - 1.0) > 1e-9:
            raise EffectsError(f"cosmic_rays.species fractions must sum to 1, got "
                               f"{sum(f for _, f in species):.12g}")
        self.species = species
        if self.pair_energy is not None:
            self.pair_energy = check_number("cosmic_rays.pair_energy [eV]", self.pair_energy, 0.1, 100.0)

    def to_dict(self):
        d = asdict(self)
        d["species"] = [list(s) for s in self.species]
        return d

    @property
    def electrons_per_ev(self):
        return 1.0 / (pair_creation_energy(self.cd_fraction, self.temperature)
                      if self.pair_energy is None else self.pair_energy)


# --------------------------------------------------------------------------- material
def band_gap(x, temperature):
    """E_g [eV] of Hg₁₋ₓCdₓTe at T [K] (Hansen, Schmit & Casselman 1982)."""
    return -0.302 + 1.93 * x - 0.81 * x ** 2 + 0.832 * x ** 3 + 5.35e-4 * temperature * (1.0 - 2.0 * x)


def pair_creation_energy(x, temperature):
    """Mean energy per electron–hole pair ε = 2.8 E_g + 0.6 eV (Klein 1968) [eV]."""
    return 2.8 * band_gap(x, temperature) + 0.6


def hgcdte_properties(x):
    """(⟨Z/A⟩ [mol g⁻¹], density ρ [g cm⁻³], mean excitation energy I [eV]) of Hg₁₋ₓCdₓTe."""
    atoms = {"Hg": 1.0 - x, "Cd": x, "Te": 1.0}                       # atoms per formula unit
    mass = {el: n * ELEMENTS[el][1] for el, n in atoms.items()}        # g per mole of formula units
    total = sum(mass.values())
    z_over_a = sum(mass[el] / total * ELEMENTS[el][0] / ELEMENTS[el][1] for el in atoms)
    ln_i = sum(mass[el] / total * ELEMENTS[el][0] / ELEMENTS[el][1] * math.log(ELEMENTS[el][2])
               for el in atoms) / z_over_a                             # Bragg additivity
    density = RHO_HGTE + (RHO_CDTE - RHO_HGTE) * x
    return z_over_a, density, math.exp(ln_i)


def density_effect(beta_gamma, z_over_a, density, mean_excitation):
    """Density-effect correction δ(βγ) of a solid (Sternheimer & Peierls 1971 general formula)."""
    plasma = 28.816 * math.sqrt(density * z_over_a)                   # ħω_p [eV]
    cbar = 2.0 * math.log(mean_excitation / plasma) + 1.0
    x0 = 0.2 if cbar < 5.215 else 0.326 * cbar - 1.5                   # I ≥ 100 eV branch
    x1, m = 3.0, 3.0
    a = (cbar - 4.606 * x0) / (x1 - x0) ** m
    x = math.log10(beta_gamma)
    if x < x0:
        return 0.0
    delta = 4.6052 * x - cbar
    return delta + a * (x1 - x) ** m if x < x1 else delta


def landau_xi(path_um, z, params):
    """Landau width ξ [eV] of a segment of length ``path_um`` [µm] for an ion of charge z."""
    z_over_a, density, _ = hgcdte_properties(params.cd_fraction)
    bg2 = params.beta_gamma ** 2
    beta2 = bg2 / (1.0 + bg2)
    grams = density * np.asarray(path_um, float) * 1e-4               # g cm⁻²
    return 0.5 * K_BETHE * 1e6 * z_over_a * np.asarray(z, float) ** 2 * grams / beta2


def bichsel_most_probable(xi, beta_gamma, mean_excitation, delta):
    """Most probable energy loss Δ_p = ξ [ln(2 m_e c² β²γ²/I) + ln(ξ/I) + j − β² − δ] [eV] of any
    absorber (PDG eq. 34.12), clipped at 0 (the formula fails for sub-eV ξ).  ξ, I in eV."""
    bg2 = beta_gamma ** 2
    beta2 = bg2 / (1.0 + bg2)
    xi = np.asarray(xi, float)
    with np.errstate(divide="ignore"):
        log_xi = np.log(np.maximum(xi, 1e-300) / mean_excitation)
    return np.maximum(xi * (math.log(2.0 * ME_C2 * bg2 / mean_excitation) + log_xi + BICHSEL_J - beta2 - delta),
                      0.0)


def most_probable_loss(path_um, z, params):
    """Most probable energy loss Δ_p [eV] of an ion of charge z in ``path_um`` µm of HgCdTe."""
    z_over_a, density, mean_i = hgcdte_properties(params.cd_fraction)
    delta = density_effect(params.beta_gamma, z_over_a, density, mean_i)
    return bichsel_most_probable(landau_xi(path_um, z, params), params.beta_gamma, mean_i, delta)


# --------------------------------------------------------------------------- events
def _check_call(seed, ramp, nframes, tframe, shape):
    rng.seed_to_key(seed)
    ramp = validation.integer("ramp", ramp, low=0, high=2 ** 32 - 1, error=EffectsError)
    nframes = validation.integer("nframes", nframes, low=0, high=2 ** 32 - 1, error=EffectsError)
    tframe = check_number("tframe [s]", tframe, 0.0, low_open=True)
    shape = validation.shape("shape (detector)", shape, max_side=8192, error=EffectsError)
    return ramp, nframes, tframe, shape


def _frame_index(ramp, frames):
    return (np.uint64(ramp) << np.uint64(32)) | np.asarray(frames, np.uint64)


def expected_events_per_frame(tframe, shape, params):
    """Mean number of events per frame R · n_y n_x p² · t_frame."""
    area_cm2 = shape[0] * shape[1] * (params.pixel_pitch * 1e-4) ** 2
    return params.rate * area_cm2 * tframe


def cosmic_ray_events(seed, ramp, nframes, tframe, shape, params):
    """Number of cosmic-ray events in each frame of a ramp: int64 (nframes,)."""
    ramp, nframes, tframe, shape = _check_call(seed, ramp, nframes, tframe, shape)
    mean = expected_events_per_frame(tframe, shape, params)
    if mean > MAX_EVENTS_PER_FRAME / 2:
        raise EffectsError(f"cosmic_rays.rate {params.rate} gives {mean:.3g} events per frame on this "
                           f"detector; at most {MAX_EVENTS_PER_FRAME // 2} are supported")
    if nframes == 0 or mean == 0.0:
        return np.zeros(nframes, np.int64)
    counts = rng.poisson(np.full(nframes, mean), seed, _frame_index(ramp, np.arange(nframes)),
                         STREAMS["cosmic_rays"] + SUB_COUNT)
    return counts.astype(np.int64)


def cosmic_ray_tracks(seed, ramp, nframes, tframe, shape, params):
    """Every event of a ramp: dict of arrays ``frame, k`` (event number in its frame), entry point
    ``x0, y0`` [pixels, full detector], ``cos_theta``, ``phi`` [rad] and ion charge ``z``."""
    counts = cosmic_ray_events(seed, ramp, nframes, tframe, shape, params)
    ramp, shape = int(ramp), tuple(int(v) for v in shape)
    frame = np.repeat(np.arange(counts.size, dtype=np.int64), counts)
    k = np.arange(frame.size, dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
    index = _frame_index(ramp, frame)
    draw = k.astype(np.uint32)
    base = STREAMS["cosmic_rays"]
    entry = rng.uniform(seed, index, base + SUB_ENTRY, draw)
    direction = rng.uniform(seed, index, base + SUB_DIRECTION, draw)
    u_ion = rng.uniform(seed, index, base + SUB_ION, draw)[:, 0]
    charges = np.array([z for z, _ in params.species], np.int64)
    cumulative = np.cumsum([f for _, f in params.species])
    ion = np.minimum(np.searchsorted(cumulative, u_ion, side="right"), charges.size - 1)
    return {"frame": frame, "k": k, "x0": entry[:, 0] * shape[1], "y0": entry[:, 1] * shape[0],
            "cos_theta": np.sqrt(direction[:, 0]),                       # pdf 2 cos θ on [0, 1]
            "phi": 2.0 * math.pi * direction[:, 1], "z": charges[ion]}


def _line_crossings(p0, step, s_end):
    """(event, s) of every grid line x = integer strictly between the two ends of each track
    p(s) = p0 + s·step, s ∈ (0, s_end)."""
    end = p0 + s_end * step
    first = np.floor(np.minimum(p0, end)) + 1.0
    count = np.maximum(np.ceil(np.maximum(p0, end)) - first, 0.0).astype(np.int64)
    event = np.repeat(np.arange(p0.size), count)
    line = first[event] + (np.arange(event.size) - np.repeat(np.cumsum(count) - count, count))
    return event, (line - p0[event]) / step[event]


def track_segments(tracks, shape, params):
    """Pixels crossed by each track: dict of ``event`` (row of ``tracks``), ``j`` (order along the
    track from the entry), ``y, x`` (pixel) and ``length`` (3-D path length in that pixel) [µm]."""
    ny, nx = shape
    mu = tracks["cos_theta"]
    tan_theta = np.sqrt(np.maximum(1.0 - mu * mu, 0.0)) / mu
    lateral = params.thickness / params.pixel_pitch * tan_theta         # pixels, over the full depth
    dx, dy = lateral * np.cos(tracks["phi"]), lateral * np.sin(tracks["phi"])
    x0, y0 = tracks["x0"], tracks["y0"]
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = np.where(dx > 0, (nx - x0) / dx, np.where(dx < 0, -x0 / dx, np.inf))
        sy = np.where(dy > 0, (ny - y0) / dy, np.where(dy < 0, -y0 / dy, np.inf))
    s_end = np.minimum(1.0, np.minimum(sx, sy))                         # clipped at the detector edge
    nev = mu.size
    ex, sxs = _line_crossings(x0, dx, s_end)
    ey, sys_ = _line_crossings(y0, dy, s_end)
    event = np.concatenate([np.arange(nev), ex, ey, np.arange(nev)])
    s = np.concatenate([np.zeros(nev), sxs, sys_, s_end])
    order = np.lexsort((s, event))
    event, s = event[order], s[order]
    same = event[1:] == event[:-1]
    ds = np.where(same, s[1:] - s[:-1], 0.0)
    keep = np.nonzero(ds > 0.0)[0]
    ev = event[keep]
    mid = 0.5 * (s[keep] + s[keep + 1])
    x = np.clip(np.floor(x0[ev] + mid * dx[ev]), 0, nx - 1).astype(np.int64)
    y = np.clip(np.floor(y0[ev] + mid * dy[ev]), 0, ny - 1).astype(np.int64)
    starts = np.searchsorted(ev, np.arange(nev))
    j = np.arange(ev.size) - starts[ev]
    length = ds[keep] * (params.thickness / mu[ev])                     # µm
    return {"event": ev, "j": j, "y": y, "x": x, "length": length}


def segment_electrons(seed, ramp, tracks, segments, params):
    """Electrons deposited in each segment: (Δ_p + ξ λ)/ε, λ ~ Moyal keyed by (ramp, frame, k, j)."""
    ev, j = segments["event"], segments["j"]
    if np.any(j >= 2 << MAX_SEGMENT_BITS):
        raise EffectsError("a cosmic-ray track crosses more than 16384 pixels (detector too large)")
    z = tracks["z"][ev]
    index = _frame_index(int(ramp), tracks["frame"][ev])
    draw = ((tracks["k"][ev].astype(np.uint64) << np.uint64(MAX_SEGMENT_BITS))
            | (j.astype(np.uint64) >> np.uint64(1))).astype(np.uint32)
    gauss = rng.normal(seed, index, STREAMS["cosmic_rays"] + SUB_STRAGGLING, draw)
    zn = np.where(j & 1, gauss[:, 1], gauss[:, 0])
    moyal = -np.log(np.maximum(zn * zn, 1e-300))
    energy = most_probable_loss(segments["length"], z, params) + landau_xi(segments["length"], z, params) * moyal
    return np.maximum(energy, 0.0) * params.electrons_per_ev


def cosmic_ray_deposits(seed, ramp, nframes, tframe, shape, params):
    """Charge deposited by cosmic rays in one ramp: structured array of :data:`DEPOSIT_DTYPE`, one
    row per pixel crossed by each event (two events in one pixel and frame give two rows), frame
    counted from the reset (dropped frames included), full-detector (y, x), sorted by (y, x,
    frame).  The charge of frame f is deposited during that frame: reads ≥ f see it."""
    tracks = cosmic_ray_tracks(seed, ramp, nframes, tframe, shape, params)
    shape = tuple(int(v) for v in shape)
    if tracks["frame"].size == 0:
        return np.zeros(0, DEPOSIT_DTYPE)
    seg = track_segments(tracks, shape, params)
    electrons = segment_electrons(seed, ramp, tracks, seg, params)
    frame = tracks["frame"][seg["event"]]
    order = np.lexsort((frame, seg["x"], seg["y"]))
    out = np.empty(order.size, DEPOSIT_DTYPE)
    out["ramp"] = int(ramp)
    out["frame"] = frame[order]
    out["y"] = seg["y"][order]
    out["x"] = seg["x"][order]
    out["electrons"] = electrons[order]
    return out
