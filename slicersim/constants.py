"""Physical constants used throughout slicersim (SI unless the name says otherwise)."""
import math

#: Planck constant [J s]
H_PLANCK = 6.62607015e-34
#: speed of light [m/s]
C_LIGHT = 299792458.0
#: Boltzmann constant [J/K]
K_BOLTZMANN = 1.380649e-23
#: h c in erg Angstrom (photon energy = HC_ERG_AA / lambda[AA])
HC_ERG_AA = H_PLANCK * 1e7 * C_LIGHT * 1e10
#: radians per arcsecond
ARCSEC = math.pi / 648000.0
#: first zero of J1 divided by pi (Airy ring radius 1.22 lambda/D)
AIRY_RHO = 1.2196698912665045
#: reference wavelength of the chromatic PSF width [AA]
LBDA_REF_AA = 10000.0
#: Gaussian sigma of the Airy core in units of the Airy radius (reference convention 0.8/2.35)
AIRY_SIGMA_FACTOR = 0.8 / 2.35
