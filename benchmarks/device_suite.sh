#!/usr/bin/env bash
# GPU suite: the kernel/twin tests and the ramp benchmarks on a lent NVIDIA machine, in one call.
#
# Run from the repository root on the device machine (see the `device` tool), with the wheels of
# the packages its image lacks in .whl/ (pyopencl, astropy, sncosmo, dask, distributed and their
# pure-Python needs) and $OUT set:
#
#     bash benchmarks/device_suite.sh [STEP ...]     # steps: diag tests ramp_effects reduce_speed each
#                                                    #        ramp_paths (not run by default)
#
# The wheels (cp312, manylinux; the device image has numpy, scipy, h5py, matplotlib, pytest):
#     echo /.whl/ >> .git/info/exclude
#     python3 -m pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
#       --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
#       --platform any -d /tmp/whl pyopencl astropy sncosmo dask distributed
#     then copy into .whl/: pyopencl pytools platformdirs siphash24 astropy astropy_iers_data pyerfa
#     sncosmo extinction dask distributed partd locket tblib zict tornado lazy_importer looseversion
#     importlib_metadata (18 MB; carry [".whl"] in the device call).
#
# Every step has its own time limit and writes into /tmp/res, packed after each step into
# $OUT/results.tgz (so a step cut short still returns the earlier ones); the log is $OUT/log.txt.
# Exits 3 without running anything when pyopencl finds no GPU (no NVIDIA OpenCL ICD).
set -u
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT" /tmp/res
exec > >(tee -a "$OUT/log.txt") 2>&1
STEPS=${*:-diag tests ramp_effects reduce_speed each}
T0=$(date +%s)
stamp() { echo "== [$(( $(date +%s) - T0 )) s] $*"; }
pack() { tar czf "$OUT/results.tgz" -C /tmp res; }

stamp setup
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 2
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 SLICERSIM_DEVICE=${SLICERSIM_DEVICE:-nvidia}
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee /tmp/res/gpu.txt
# NVIDIA's OpenCL library may be present without an ICD file: register it for the wheel's loader.
if ! python3 -c "import pyopencl as cl; assert any(d.type & cl.device_type.GPU for p in cl.get_platforms() for d in p.get_devices())" 2>/dev/null; then
  lib=$(ls /usr/lib/x86_64-linux-gnu/libnvidia-opencl.so.1 /usr/local/nvidia/lib64/libnvidia-opencl.so.1 \
        /usr/local/nvidia/lib/libnvidia-opencl.so.1 2>/dev/null | head -1)
  [ -z "$lib" ] && lib=$(find / -xdev -name 'libnvidia-opencl.so*' 2>/dev/null | head -1)
  echo "registering NVIDIA OpenCL ICD: ${lib:-none found}"
  [ -n "$lib" ] && mkdir -p /tmp/icd && echo "$lib" > /tmp/icd/nvidia.icd && export OCL_ICD_VENDORS=/tmp/icd
fi
python3 -m slicersim info | tee /tmp/res/info.txt
python3 -c "import pyopencl as cl; assert any(d.type & cl.device_type.GPU for p in cl.get_platforms() for d in p.get_devices())" \
  || { echo "no OpenCL GPU: stopping"; pack; exit 3; }
python3 - <<'EOF' | tee /tmp/res/cpu.txt
import os, platform
print(open("/proc/cpuinfo").read().split("model name")[1].split("\n")[0].strip(": "), os.cpu_count(), "CPUs")
EOF
pack

for step in $STEPS; do
  case $step in
  diag)    # the random streams against the twin: where they differ, and the Poisson counts
    stamp "diag (random streams, GPU vs twin)"
    SLICERSIM_TRUST_DEVICE=1 PYOPENCL_COMPILER_OUTPUT=1 timeout 90 python3 benchmarks/_device_diag.py 2>&1 | grep -v 'overriding noinline\|CompilerWarning\|lambda: self._prg\|succeeded, but said\|^$' | tail -70 | tee /tmp/res/diag.txt ;;
  tests)   # every kernel against its NumPy twin, on the GPU
    stamp "tests (kernel twins on the GPU)"
    timeout ${TESTS_TIMEOUT:-170} python3 -m pytest -q -rf -p no:cacheprovider --maxfail=25 --timeout 120 -o addopts="" \
      tests/test_opencl_runtime.py tests/test_rng_noise.py tests/test_band_variance_kernel.py \
      tests/test_lsf_convolution.py tests/test_psf.py tests/test_cube_builder.py tests/test_ramps.py \
      tests/test_ramp_effects_kernels.py tests/test_correlated_noise.py tests/test_mapper.py \
      tests/test_etc_exact.py tests/test_rectify.py tests/test_projection_cache.py tests/test_gls_extraction.py 2>&1 | tee /tmp/res/tests_full.txt | tail -40 | tee /tmp/res/tests.txt ;;
  ramp_effects)   # issue 9: full-detector (64,8,0) ramp, plain vs --effects lazuli
    stamp "ramp_effects 4096 (64,8,0)"
    timeout 200 python3 benchmarks/ramp_effects.py --side 4096 --nmd 64 8 0 --out /tmp/res/ramp_effects ;;
  reduce_speed)   # issue 11: reducing a full-detector ramp vs simulating it
    stamp "reduce_speed 4096 (64,8,0)"
    timeout 150 python3 benchmarks/reduce_speed.py --size 4096 --nmd 64 8 0 --out /tmp/res/reduce_speed ;;
  ramp_paths)   # run 7: the ramp kernel vs its twin by rate class and row offset, the extended self-check
    stamp "ramp_paths (ramp kernel vs twin, path by path)"
    SLICERSIM_TRUST_DEVICE=1 timeout ${RAMP_PATHS_TIMEOUT:-120} python3 benchmarks/_device_ramp_paths.py 2>&1 \
      | grep -v 'CompilerWarning\|lambda: self._prg\|^$' | tee /tmp/res/ramp_paths.txt ;;
  each)    # where the time goes: each effect alone, 2048²
    stamp "ramp_effects 2048 --each"
    timeout 120 python3 benchmarks/ramp_effects.py --side 2048 --nmd 64 8 0 --each --out /tmp/res/ramp_effects_each ;;
  *) echo "unknown step $step" ;;
  esac
  pack
done
stamp done
