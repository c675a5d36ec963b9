#!/usr/bin/env python
"""Build slicersim's own Lazuli IFS instrument curves (QE, dispersion, throughput).

Every curve is computed from a small physical model (see README.md in this
folder for the equations and the sources of the public numbers).  The output
is deterministic; run from anywhere:

    python build_curves.py            # writes the curve files here
    python build_curves.py --plot     # also writes curves.png (needs matplotlib)

Only numpy and astropy are needed to build the files.  The TOML configuration
files of this folder are hand-written (values from the slicersim paper table).
"""
import math
import os
import sys

import numpy as np
import astropy.units as u
from astropy.table import Table

HERE = os.path.dirname(os.path.abspath(__file__))
HC_EV_UM = 1.23984198           # h c [eV micron]
K_B_EV = 8.617333262e-5         # Boltzmann constant [eV/K]
_erfc = np.vectorize(math.erfc)

# --------------------------------------------------------------------------- #
# 1. Detector QE: substrate-removed HgCdTe H4RG-10, 1.7 micron cut-off
# --------------------------------------------------------------------------- #
QE = dict(eta_int=0.95,      # internal QE (collection x quantum yield)
          t_det=100.0,       # detector temperature [K]
          lam_cut=1.72,      # 50 % cut-off wavelength [micron]
          dead_nm=3.0,       # effective surface dead layer [nm]
          n_mct=3.5,         # HgCdTe refractive index (NIR)
          n_ar=1.38,         # AR layer index (MgF2-like quarter-wave layer)
          lam_ar=1.2,        # AR coating design wavelength [micron]
          w_ar=1.1)          # AR bandwidth (Gaussian width in ln(lambda))


def hgcdte_gap(x, t):
    """Hansen, Schmit & Casselman (1982) band gap of Hg(1-x)Cd(x)Te [eV]."""
    return -0.302 + 1.93 * x - 0.81 * x**2 + 0.832 * x**3 + 5.35e-4 * t * (1 - 2 * x)


def hgcdte_x(eg, t):
    """Cd fraction x giving band gap eg [eV] at temperature t (bisection)."""
    lo, hi = 0.2, 0.9
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if hgcdte_gap(mid, t) < eg else (lo, mid)
    return 0.5 * (lo + hi)


def hgcdte_alpha(e, x, t):
    """Chu et al. (1992, 1994) Kane-region absorption coefficient [1/cm]."""
    eg = hgcdte_gap(x, t)
    alpha_g = -65.0 + 1.88 * t + (8694.0 - 10.31 * t) * x
    beta = -1.0 + 0.083 * t + (21.0 - 0.13 * t) * x
    return alpha_g * np.exp(np.sqrt(beta * np.clip(e - eg, 0, None)))


def qe_model(lam):
    """QE [e-/photon] at wavelength lam [micron]."""
    p = QE
    t = p["t_det"]
    e = HC_EV_UM / lam
    eg = HC_EV_UM / p["lam_cut"]
    x = hgcdte_x(eg, t)
    # band-gap edge: step in photon energy broadened by kT (Gaussian -> erfc)
    edge = 0.5 * _erfc((eg - e) / (math.sqrt(2.0) * K_B_EV * t))
    # blue loss: carriers generated inside the surface dead layer are lost
    collect = np.exp(-hgcdte_alpha(e, x, t) * p["dead_nm"] * 1e-7)
    # front-surface reflection: NIR-optimised AR coating, bare HgCdTe far from design
    r_bare = ((p["n_mct"] - 1) / (p["n_mct"] + 1)) ** 2
    r_min = ((p["n_mct"] - p["n_ar"] ** 2) / (p["n_mct"] + p["n_ar"] ** 2)) ** 2
    g = np.exp(-(np.log(lam / p["lam_ar"]) / p["w_ar"]) ** 2)
    r_ar = r_bare - (r_bare - r_min) * g
    return np.clip(p["eta_int"] * (1 - r_ar) * collect * edge, 0.0, 1.0)


# --------------------------------------------------------------------------- #
# 2. Dispersion law: fused-silica prism (Malitson 1965 Sellmeier)
# --------------------------------------------------------------------------- #
SELL_B = (0.6961663, 0.4079426, 0.8974794)
SELL_L = (0.0684043, 0.1162414, 9.896161)     # resonance wavelengths [micron]
LAM0 = 0.4                                    # offset zero [micron]
LAM_END = 1.70001                             # last tabulated wavelength [micron]
N_DISP_ROWS = 80
R_MIN_TARGET = 100.0
CBE_K = 1.3 * 2.3 / 2.0                       # dispersion_scale * dr / 2
CBE_DR, EOL_DR = 2.3, 2.5


def silica_n(lam):
    l2 = lam**2
    return np.sqrt(1 + sum(b * l2 / (l2 - c**2) for b, c in zip(SELL_B, SELL_L)))


def silica_dn(lam):
    """dn/dlambda [1/micron]."""
    l2 = lam**2
    dn2 = sum(-2 * b * c**2 * lam / (l2 - c**2) ** 2 for b, c in zip(SELL_B, SELL_L))
    return dn2 / (2 * silica_n(lam))


_LFINE = np.linspace(LAM0, LAM_END, 20001)
# offset = S (n(lam0) - n(lam)); S fixed so that min R = 100 for the CBE usage
DISP_SCALE = R_MIN_TARGET * CBE_DR / (CBE_K * np.min(-_LFINE * silica_dn(_LFINE)))


def offset_model(lam):
    """Detector offset [10-micron pixels] along the dispersion, 0 at LAM0."""
    return DISP_SCALE * (silica_n(LAM0) - silica_n(lam))


def resolving_power(lam, dispersion_scale=1.3, dr=CBE_DR):
    """R = lam / (dlam/dpix) / dr with dpix/dlam = K do/dlam, K = scale dr / 2."""
    k = dispersion_scale * dr / 2.0
    return lam * k * DISP_SCALE * (-silica_dn(lam)) / dr


def n_bins(dispersion_scale=1.3, dr=CBE_DR, lrange=(0.4, 1.7)):
    k = dispersion_scale * dr / 2.0
    return int(round(k * (offset_model(lrange[1]) - offset_model(lrange[0])))) + 1


# --------------------------------------------------------------------------- #
# 3. Throughput: protected-silver mirrors, fused-silica prism, fixed losses
# --------------------------------------------------------------------------- #
# Drude (free electrons) + one Lorentz oscillator (Ag 4d->5sp interband edge)
AG = dict(eps_inf=2.5, wp_ev=9.0, gamma_ev=0.08,     # background, plasma, damping [eV]
          d_eps=1.0, w0_ev=4.6, g0_ev=0.3,           # interband oscillator
          n_over=1.46)                               # SiO2-like protective overcoat
N_TEL = 4                                  # telescope mirrors M1-M4
N_SPEC = {"narrow": [5, 4, 1, 1, 3],       # paper Table: optics n-elements
          "wide": [5, 6, 1, 1, 3]}
SIGMA_NM = dict(tel=2.0, spec=3.0, ifu=6.0)  # rms micro-roughness [nm]
PRISM_PASS, PRISM_T = 2, 0.97              # double pass; AR-coated surface pair
CONTAM_BOL = 0.995                         # particulate/molecular, per surface
FIXED = {"narrow": 0.90, "wide": 0.92}     # slicer diffraction + vignetting
LAM_UV_CUT = 0.35                          # no transmission below [micron]


def silver_reflectance(lam):
    """Normal-incidence reflectance of dielectric-protected silver (Drude-Lorentz)."""
    p = AG
    w = HC_EV_UM / lam
    eps = (p["eps_inf"] - p["wp_ev"] ** 2 / (w * (w + 1j * p["gamma_ev"]))
           + p["d_eps"] * p["w0_ev"] ** 2 / (p["w0_ev"] ** 2 - w**2 - 1j * w * p["g0_ev"]))
    nm = np.sqrt(eps)
    return np.abs((nm - p["n_over"]) / (nm + p["n_over"])) ** 2


def scatter(lam, sigma_nm):
    """Total integrated scatter loss of a surface (Davies 1954 / Bennett & Porteus 1961)."""
    return np.exp(-(4 * np.pi * sigma_nm * 1e-3 / lam) ** 2)


def throughput_model(lam, field, eol=False):
    """Telescope + spectrograph transmission (no QE) at lam [micron]."""
    rag = silver_reflectance(lam)
    n = N_SPEC[field]
    nsurf = N_TEL + sum(n)
    t = (rag * CONTAM_BOL) ** nsurf
    t *= scatter(lam, SIGMA_NM["tel"]) ** N_TEL
    t *= scatter(lam, SIGMA_NM["ifu"]) ** n[1]
    t *= scatter(lam, SIGMA_NM["spec"]) ** (sum(n) - n[1])
    t *= PRISM_T ** PRISM_PASS * FIXED[field]
    if eol:
        t *= 0.97 * (1 - 0.15 * np.exp(-(lam * 1e4 - 3500.0) / 1500.0))
    return np.where(lam < LAM_UV_CUT, 0.0, t)


# --------------------------------------------------------------------------- #
# 4. Writers
# --------------------------------------------------------------------------- #
def write_ecsv(name, cols, comment):
    tab = Table(cols)
    tab.meta["comments"] = [comment]
    tab.write(os.path.join(HERE, name), format="ascii.ecsv", overwrite=True)


def build_qe():
    lam = np.round(np.arange(0.35, 1.85 + 1e-9, 0.005), 3)
    qe = np.round(qe_model(lam), 5)
    cols = [Table.Column(lam, name="wavelength", unit=u.micron),
            Table.Column(qe, name="qe", description="[e-/photon]")]
    write_ecsv("qe_h4rg_1p7.ecsv", cols,
               "slicersim model: substrate-removed HgCdTe H4RG-10, 1.7 micron cut-off")


def build_dispersion():
    lam = np.linspace(LAM0, LAM_END, N_DISP_ROWS).round(6)
    off = np.round(offset_model(lam), 5)
    cols = [Table.Column(lam, name="wavelength", unit=u.micron),
            Table.Column(off, name="offset", unit=u.pix,
                         description="Offset in pixel of 10 microns")]
    write_ecsv("dispersion_prism.ecsv", cols,
               "slicersim model: fused-silica prism (Malitson 1965), Rmin=100 at scale 1.3")


def build_throughput():
    wave = np.arange(3000, 20001, 10)
    lam = wave * 1e-4
    for tag, eol in (("cbe", False), ("eol", True)):
        nar = throughput_model(lam, "narrow", eol)
        wid = throughput_model(lam, "wide", eol)
        with open(os.path.join(HERE, f"throughput_{tag}.csv"), "w") as fh:
            fh.write("wavelength,narrow,wide\n")
            for w, a, b in zip(wave, nar, wid):
                fh.write(f"{w:d},{a:.6f},{b:.6f}\n")


def summary():
    lam = np.linspace(0.4, 1.7, 13001)
    lines = ["| quantity | CBE | EOL |", "|---|---|---|"]
    rc, re_ = resolving_power(lam), resolving_power(lam, dr=EOL_DR)
    lines.append(f"| wavelength bins (4000-17000 A) | {n_bins()} | {n_bins(dr=EOL_DR)} |")
    lines.append(f"| R min (at micron) | {rc.min():.1f} ({lam[rc.argmin()]:.3f}) "
                 f"| {re_.min():.1f} ({lam[re_.argmin()]:.3f}) |")
    lines.append(f"| R at 0.4 / 1.7 micron | {rc[0]:.1f} / {rc[-1]:.1f} | {re_[0]:.1f} / {re_[-1]:.1f} |")
    for l0 in (0.4, 0.5, 1.0, 1.5, 1.7):
        a = [throughput_model(np.array([l0]), f, e)[0] for e in (False, True) for f in ("narrow", "wide")]
        lines.append(f"| throughput narrow / wide at {l0} micron | {a[0]:.3f} / {a[1]:.3f} "
                     f"| {a[2]:.3f} / {a[3]:.3f} |")
    for l0 in (0.4, 0.5, 1.0, 1.5, 1.7, 1.75, 1.8):
        lines.append(f"| QE at {l0} micron | {qe_model(np.array([l0]))[0]:.3f} | same |")
    lines.append(f"| dispersion offset at 1.70001 micron [px] | {offset_model(LAM_END):.2f} | same |")
    return "\n".join(lines)


def plot(path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    lam = np.linspace(0.35, 1.85, 1501)
    ld = lam[(lam >= 0.4) & (lam <= 1.7)]
    fig, ax = plt.subplots(3, 1, figsize=(7, 9), sharex=True)
    ax[0].plot(ld, resolving_power(ld), label="CBE (dr=2.3)")
    ax[0].plot(ld, resolving_power(ld, dr=EOL_DR), "--", label="EOL (dr=2.5)")
    ax[0].set_ylabel("R = lambda / dlambda / dr")
    for f, c in (("narrow", "C0"), ("wide", "C1")):
        ax[1].plot(lam, throughput_model(lam, f), c, label=f"{f} CBE")
        ax[1].plot(lam, throughput_model(lam, f, True), c + "--", label=f"{f} EOL")
        ax[2].plot(lam, throughput_model(lam, f) * qe_model(lam), c, label=f"T x QE {f} CBE")
    ax[1].set_ylabel("throughput (no QE)")
    ax[2].plot(lam, qe_model(lam), "k", label="QE H4RG-10 1.7um")
    ax[2].set_ylabel("efficiency")
    ax[2].set_xlabel("wavelength [micron]")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main(argv):
    build_qe()
    build_dispersion()
    build_throughput()
    print(summary())
    if "--plot" in argv:
        plot(os.path.join(HERE, "curves.png"))


if __name__ == "__main__":
    main(sys.argv[1:])
