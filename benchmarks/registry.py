"""The benchmark registry: one :class:`Benchmark` per script of ``benchmarks/``, with the question it
answers, its baseline, its acceptance and the arguments of its smallest size (``--smoke``).

``benchmarks/run.py`` runs what is registered here; ``tests/benchmarks/test_registry.py`` checks that
every ``benchmarks/*.py`` is registered (or listed in :data:`NOT_BENCHMARKS`) and that every entry's
smoke arguments parse.  ``_*.py`` files are private runners or plugins used by a benchmark.
"""
from dataclasses import dataclass


@dataclass(frozen=True)
class Check:
    """A machine-checkable acceptance: ``value(<out>/<result>.json at key) <op> threshold``.

    ``key`` is a dotted path into the JSON (``summary.speedup``); ``op`` one of ``<=``, ``>=``, ``==``.
    """
    result: str
    key: str
    op: str
    threshold: object

    def evaluate(self, data):
        """True / False, or None when the key is absent (e.g. the reference was skipped)."""
        value = data
        for part in self.key.split("."):
            if not isinstance(value, dict) or part not in value:
                return None
            value = value[part]
        if value is None:
            return None
        if self.op == "<=":
            return value <= self.threshold
        if self.op == ">=":
            return value >= self.threshold
        if self.op == "==":
            return value == self.threshold
        raise ValueError(f"unknown op {self.op!r}")


@dataclass(frozen=True)
class Benchmark:
    """One registered benchmark.

    ``smoke``: arguments of its smallest size (seconds, not minutes), ``--out DIR`` is added by the
    runner.  ``smoke_only_help``: no size small enough for CI exists (full-detector runs with no size
    knob): the smoke run only checks that it starts and parses (``--help``), with the reason in
    ``note``.  ``smoke_network``: arguments replacing ``smoke`` when a reference venv may be
    installed (``run.py --network``); without it smoke runs our side only.  ``out_arg``: the
    script takes ``--out DIR``.  ``network``: the full
    run installs reference releases from PyPI into ``benchmarks/.refvenv*``.  ``device``: meant for
    an accelerator (runs on PoCL too).
    """
    name: str
    question: str
    baseline: str
    acceptance: str
    smoke: tuple = ()
    check: Check = None
    network: bool = False
    device: bool = False
    smoke_only_help: bool = False
    smoke_network: tuple = None
    timeout: int = 180
    note: str = ""
    out_arg: bool = True

    @property
    def script(self):
        return f"{self.name}.py"


B = Benchmark
BENCHMARKS = [
    # --- ETC and conventions -------------------------------------------------------------------
    B("etc_vs_reference", "Does our ETC choose the same readouts as slicersim 1.0.0, and how much faster?",
      "slicersim==1.0.0 in its own venv, same targets, same run",
      "identical readouts 50/50 and ≥ 300× faster per target (warm, CPU time)",
      smoke=("--n", "2", "--repeat", "1", "--skip-reference"),
      smoke_network=("--n", "2", "--repeat", "1"),
      check=Check("etc_vs_reference", "summary.speedup_batch_reference_cpu_warm", ">=", 300), network=True),
    B("conventions_vs_reference", "How do exposure times differ between our two conventions and 1.0.0 / 1.4.2?",
      "slicersim 1.0.0 and 1.4.2 (own venvs), same targets", "informational (differences explained per row)",
      smoke=("--skip-survey", "--skip-reference"), network=True),
    B("etc_snr_bound", "How far is the closed loop's SNR from the best any pipeline can reach (issue 11)?",
      "the ETC's own pixel-variance model (exact, no Monte Carlo)", "informational",
      smoke=("--redshifts", "0.5", "--ncols", "58"), timeout=300),
    B("survey_vs_paper", "Do our survey time and data volume match the paper's?",
      "the paper's numbers and 1.0.0's cases in ../shared/reference", "informational",
      smoke=("--n", "20")),
    # --- scenes, cubes, PSF --------------------------------------------------------------------
    B("cube_vs_reference", "How fast and how close are our cubes to slicersim 1.0.0's?",
      "slicersim==1.0.0 in its own venv, same run",
      "Airy cube ≥ 50×, Gaussian ≥ 20×, extracted spectrum ≥ 100× faster",
      smoke=("--repeat", "1", "--skip-reference"), smoke_network=("--repeat", "1"), network=True),
    B("sources_vs_142", "Do our power-law targets match slicersim 1.4.2's?",
      "slicersim==1.4.2 in its own venv, same cases", "informational (agreement per row)",
      smoke=("--skip-reference",), smoke_network=(), network=True),
    B("scenes_vs_142", "Do our host galaxies and galaxy targets match slicersim 1.4.2's?",
      "slicersim==1.4.2 in its own venv, same run", "informational (agreement per row)",
      smoke=("--skip-reference",), smoke_network=(), network=True, timeout=300),
    B("calibration_vs_142", "Do our calibration exposures (QTH, Fabry–Perot) match slicersim 1.4.2's?",
      "slicersim==1.4.2 in its own venv, same lamp", "informational (agreement per row)",
      smoke=("--skip-image",), smoke_network=("--skip-image",), network=True,
      note="always needs the 1.4.2 venv: skipped in smoke unless it is cached or --network is given"),
    B("psf_speed_accuracy", "Which PSF oversampling gives the cube accuracy we need at what cost?",
      "an o = 31 oracle; 1.0.0's grid; NumPy twin", "informational (default 'auto' on the Pareto front)",
      smoke=("--repeat", "1", "--oracle", "3", "--no-numpy-above", "1", "--skip-extra"), timeout=300),
    B("convolution_speed", "Direct or FFT convolution of host cubes, and where is the crossover?",
      "SciPy (ndimage / fft) on the same cube", "method='auto' picks the faster one",
      smoke=("--repeat", "1", "--check-planes", "1", "--sizes", "5", "9")),
    B("precision", "What does single precision gain per kernel family, at what error?",
      "the same call in double precision, same run", "errors within SINGLE_PRECISION_ERRORS",
      smoke=("--repeat", "1", "--ramp-side", "128"), timeout=300),
    B("detector_image", "How accurate and fast is our cube → detector mapper?",
      "NumPy twin; 1.0.0's traces (../shared/reference) and painter (--reference)",
      "traces agree to < 1e-6 px; OpenCL = NumPy to 1e-12",
      smoke=("--repeat", "1", "--skip-numpy"), timeout=300),
    B("rectify_speed_accuracy", "LSQ or drizzle rectification of the full detector: accuracy vs time?",
      "drizzle on the same stack, same run", "informational",
      smoke_only_help=True, note="full 4096² rectification of both fields, no size knob (minutes)"),
    # --- ramps and files -----------------------------------------------------------------------
    B("ramp_throughput", "How many pixel-frames per second does the ramp kernel sustain?",
      "its NumPy twin; dense vs sparse path", "informational",
      smoke=("--repeat", "1", "--twin-rows", "4", "--skip-full"), timeout=300),
    B("ramp_speed_accuracy", "Which Poisson approximations are accurate enough, and how much do they save?",
      "exact per-frame Poisson increments", "informational",
      smoke=("--side", "64", "--repeat", "1")),
    B("ramp_compression", "Which HDF5 filter compresses raw ramps best for its write cost?",
      "uncompressed (data_volume)", "informational",
      smoke=("--side", "256", "--repeat", "1")),
    B("ramp_effects", "What do the detector effects cost a full-detector ramp?",
      "the plain ramp, same run", "`all` ≤ 2× plain; peak memory ≤ 1.5 GB",
      smoke=("--side", "256", "--nmd", "4", "2", "0")),
    B("ramp_memory", "What is the peak memory of a full-detector ramp from a target (issue 9)?",
      "the git revision before the projection-table cache", "≤ 1.5 GB",
      smoke_only_help=True, note="five fresh full-detector ramps, one at an old git revision (minutes)"),
    B("checksum_cost", "What do Fletcher-32 checksums cost a raw-ramp HDF5 write (issue 26)?",
      "the same writer without fletcher32, alternated", "≤ 10 % more time",
      smoke=("--side", "256", "--ngroups", "2", "--repeat", "1", "--compression", "none", "--no-e2e")),
    B("metadata_checksum_cost", "What do HDF5 metadata checksums cost simulate and fit_ramps (issue 33)?",
      "HDF5's earliest format (no metadata checksums), same run", "ratio ≤ 1.02",
      smoke=("--side", "256", "--ngroups", "2", "--repeat", "1")),
    B("correlated_noise", "Which correlated-noise generator is accurate enough for its speed?",
      "the exact frame stream; the NGHXRG model PSD", "informational",
      smoke=("--ramps", "1", "--groups", "1"), timeout=300),
    B("refpix_slopes", "How much correlated-noise variance does the reference-pixel correction remove?",
      "the model variance before correction", "informational",
      smoke=("--groups", "2", "--ramps", "1"), timeout=300,
      out_arg=False, note="prints JSON lines only (no result file, no --out)"),
    # --- reduction and closed loop ------------------------------------------------------------
    B("reduce_speed", "Does reducing a full-detector ramp cost no more than simulating it (issue 11)?",
      "simulate() of the same ramp, same process", "fit_ramps time ≤ simulate time",
      smoke=("--size", "256", "--nmd", "4", "2", "0", "--twin-rows", "4"),
      check=Check("reduce_speed", "goal_met", "==", True)),
    B("reduce_spectra_speed", "Does `slicersim reduce --spectra` cost no more than simulating the ramp (issue 30)?",
      "`slicersim ramp` of the same target, same run (and `--baseline REV`: an earlier revision)",
      "reduce --spectra / ramp ≤ 1 (CPU), spectrum unchanged within its errors",
      smoke_only_help=True, note="full-detector `slicersim ramp` + `reduce --spectra` subprocesses (minutes)"),
    B("ramp_vs_romanisim", "Are our ramps with cosmic rays and IPC ≥ 8× romanisim per CPU-second (issue 30)?",
      "romanisim.l1.make_l1 (0.15, its own venv) on the same image, same run", "ratio ≥ 8 (CPU-s per pixel-read)",
      smoke_only_help=True, network=True,
      note="installs romanisim (GalSim, …) into benchmarks/.venv-romanisim on first use"),
    B("closed_loop", "Do raw ramps → rates → cubes → spectra recover the truth?",
      "the input spectra (truth)", "bias within the Monte Carlo error",
      smoke=("--nbins", "2", "--no-effects"), timeout=420),
    B("closed_loop_bias", "Where does the closed loop's bias come from (issue 11)?",
      "the same rates reduced twice (model / data weights)", "informational",
      smoke_only_help=True, note="its summary needs ≥ 2 full-detector realisations (≈ 1 CPU-minute each)"),
    B("closed_loop_template", "Does the forward-modelled template remove the extraction bias?",
      "the default fitted coarse-PSF extraction, same ramps", "template bias within MC error",
      smoke=("--redshifts", "0.5", "--seeds", "1"), timeout=420),
    B("closed_loop_defaults", "Is the CLI with its defaults unbiased, as a new user runs it?",
      "the ETC's SNR and the truth", "|ratio − 1| ≤ max(1 %, 3 σ_mean)",
      smoke_only_help=True, note="full-detector `slicersim ramp` + `reduce` subprocesses (minutes per seed)"),
    # --- campaigns and Monte Carlo ------------------------------------------------------------
    B("monte_carlo", "How fast is a new target + noisy Airy cube per Monte Carlo draw (issue 8)?",
      "an older git revision (--baseline), alternating processes", "informational",
      smoke=("--runs", "1")),
    B("campaign", "How many noisy cubes per second does a campaign produce, vs the old loop?",
      "the single-process loop at git revision 61a7a28 (before the campaign layer)", "informational",
      smoke_only_help=True, note="needs the full git history and runs 8 campaigns (minutes)"),
    B("mock_survey", "How long does a 100-SN Ia mock survey take on this machine, and how much disk?",
      "none (absolute figure, extrapolated from --n SNe)", "≤ 1 h wall for 100 SNe on the 2-core VM",
      smoke_only_help=True, note="full-detector ramps with effects, one per SN (≈ 1 min each)"),
]

#: scripts of benchmarks/ that are not benchmarks (the runner and this registry)
NOT_BENCHMARKS = {
    "registry": "this registry",
    "run": "the runner",
}

BY_NAME = {b.name: b for b in BENCHMARKS}
