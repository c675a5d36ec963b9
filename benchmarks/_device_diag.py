"""Random streams of the selected OpenCL device against the NumPy twin (run by device_suite.sh):
how many uniforms and Gaussians differ and by how much, and the Poisson counts' mean and variance."""
import numpy as np

from slicersim.backends import noise as cn

un, zn = cn.uniform_normal_draw(100001, 2**63 + 12345, 5, 2, backend="numpy")
uc, zc = cn.uniform_normal_draw(100001, 2**63 + 12345, 5, 2, backend="opencl")
for name, a, b in (("uniform", un, uc), ("normal", zn, zc)):
    d = np.abs(a - b)
    print(name, "differing:", int((a != b).sum()), "of", a.size, "max |diff|", float(d.max()),
          "max relative", float((d / np.maximum(np.abs(a), 1e-300)).max()))
for mu in (1e-3, 1.0, 30.0, 1e4):
    k = cn.poisson_draw(np.full(100000, mu), seed=7, backend="opencl")
    kn = cn.poisson_draw(np.full(100000, mu), seed=7, backend="numpy")
    print("poisson", mu, "mean", k.mean(), "var", k.var(), "numpy mean", kn.mean(),
          "identical", bool(np.array_equal(k, kn)))
