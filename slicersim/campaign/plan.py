# TEMPORARY STUB
import numpy as np
from astropy.table import Table
from slicersim.etc import solve_many
class P: pass
def plan_survey(z, lbda, fluxes, snr, lbda_range, frame, z_switch, fields, config, search, conventions, overhead, efficiency, compression_ratio, target_ids, per_resolution=True, progress=False):
    rows=[]
    out=Table({"target_id":target_ids,"redshift":z})
    for c in ("n","m","d","nramps"): out[c]=np.zeros(len(z),int)
    out["exposure_time"]=np.zeros(len(z)); out["snr"]=np.zeros(len(z)); out["data_volume"]=np.zeros(len(z),np.int64)
    out["field"]=np.where(z<z_switch, fields[0], fields[1])
    for f in set(out["field"]):
        sel=np.asarray(out["field"]==f)
        t=solve_many(lbda,fluxes[sel],snr=snr,lbda_ranges=lbda_range,frame=frame,redshifts=z[sel],config=config,field=f,search=search,conventions=conventions)
        for c in ("n","m","d","nramps","exposure_time","snr"): out[c][sel]=t[c]
        out["data_volume"][sel]=(np.asarray(t["data_volume"])*1e9).astype(np.int64)
    p=P(); p.table=out; p.totals={"exposure_time":float(out["exposure_time"].sum())}
    return p
