"""Helpers shared by the benchmark scripts: JSON-safe values and the machine description."""
import math
import os
import platform
from pathlib import Path

import numpy as np


def jsonable(value):
    """Recursively convert numpy values, tuples and non-finite floats for json."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def cpu_model():
    """The CPU model name (/proc/cpuinfo), else platform.processor()."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def loadavg():
    """1, 5 and 15-minute load averages, or None."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None
