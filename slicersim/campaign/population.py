# TEMPORARY STUB (not committed)
import numpy as np
from astropy.table import Table
from slicersim.errors import ConfigError
from slicersim.backends import rng
from slicersim.sources.spectra import snia_spectrum
class SNIaPopulation:
    def __init__(self, n, redshift=None, **kw):
        self.n=n; self.redshift=redshift or {"distribution":"uniform","min":0.05,"max":1.5}
    def draw(self, seed):
        ids=np.arange(self.n, dtype=np.int64)
        u=rng.uniform(seed, ids.astype(np.uint64), stream=1)[:,0]
        z=self.redshift["min"]+u*(self.redshift["max"]-self.redshift["min"])
        return Table({"target_id":ids,"redshift":z,"phase":np.zeros(self.n)})
    def spectra(self, table, lbda):
        return np.array([snia_spectrum(float(z), lbda=lbda)[1] for z in table["redshift"]])
    def spectrum(self, row, lbda):
        return snia_spectrum(float(row["redshift"]), lbda=lbda)
    def host(self, row): return None
    def to_spec(self): return {"kind":"snia","n":self.n,"redshift":self.redshift}
def population_from_spec(section, base_dir="."):
    s=dict(section); s.pop("kind",None)
    return SNIaPopulation(s["n"], s.get("redshift"))
