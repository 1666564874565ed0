from pathlib import Path

import numpy as np
import pytest

import clsas

#: the tests folder (helper kits such as grbl_kit.py live here) and the repository root
TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent


def _opencl_reason() -> str | None:
    """Why the kernel tests cannot run here (None: they run on the default device).

    The default device is one that builds and runs kernels (``clsas.cl.health``); a device named by
    ``PYOPENCL_CTX`` is checked the same way, so a runtime whose compiler cannot target this CPU
    counts as missing, not as a device whose every kernel test fails.
    """
    import os

    from clsas import cl

    if os.environ.get("CLSAS_BACKEND", "").strip() == "numpy":
        return "CLSAS_BACKEND=numpy"
    try:
        queue = cl.get_queue()
    except cl.OpenCLUnavailable as exc:
        return str(exc)
    h = cl.health(queue.device)
    if not h.ok:
        return f"{cl.describe(queue.device)} builds no kernel: {h.reason}. Fix: {h.fix}"
    return None


def opencl_required() -> bool:
    """Whether this run must run kernels (CI, or ``CLSAS_REQUIRE_OPENCL=1``): then a missing device
    fails the run instead of skipping the kernel tests."""
    import os

    if os.environ.get("CLSAS_BACKEND", "").strip() == "numpy":
        return False
    flag = os.environ.get("CLSAS_REQUIRE_OPENCL", "").strip()
    if flag:
        return flag not in ("0", "false", "no")
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


OPENCL_MISSING = _opencl_reason()
needs_opencl = pytest.mark.skipif(OPENCL_MISSING is not None, reason=f"no OpenCL device: {OPENCL_MISSING}")


def pytest_report_header(config):
    from clsas import cl

    if OPENCL_MISSING is None:
        q = cl.get_queue()
        return [f"clsas kernels: OpenCL on {cl.describe(q.device)} ({q.device.platform.version.strip()}, "
                f"driver {q.device.driver_version.strip()})"]
    return [f"clsas kernels: NOT run, NumPy twins only ({OPENCL_MISSING})"]


def pytest_sessionstart(session):
    if OPENCL_MISSING is not None and opencl_required():
        pytest.exit(f"this run must test the OpenCL kernels (CI=true or CLSAS_REQUIRE_OPENCL=1) but no OpenCL "
                    f"device builds them: {OPENCL_MISSING}", returncode=3)


OCLGRIND_DIAGNOSTICS = ("Invalid read", "Invalid write", "Uninitialized", "data race", "Data race",
                        "Invalid access")


def oclgrind_missing() -> str | None:
    """Why kernels cannot run under Oclgrind here (None: its OpenCL platform is installed)."""
    try:
        import pyopencl as cl

        names = [p.name for p in cl.get_platforms()]
    except Exception as exc:  # noqa: BLE001 - no ICD loader or no platform
        return f"no OpenCL platform ({exc})"
    return None if any("Oclgrind" in n for n in names) else "Oclgrind not installed (pip install 'pyopencl[oclgrind]')"


# a small scene file: one point in front of a 9 x 7 raster, a 21 x 21 x 21 grid around it
SCENE_TOML = """
[chirp]
f_start_hz = 20000.0
f_stop_hz = 30000.0
duration_s = 0.002
fs_hz = 96000.0

[aperture]
nx = 9
ny = 7
width_m = 0.4
height_m = 0.3

[[points]]
position_m = [0.02, -0.01, 0.6]

[grid]
x_m = [-0.1, 0.1]
y_m = [-0.1, 0.1]
z_m = [0.5, 0.7]
spacing_m = 0.01
"""

BACKENDS = [
    pytest.param("numpy", id="numpy"),
    pytest.param("opencl", id="opencl", marks=needs_opencl),
]

# tolerance of the float32 kernels against the float64 twins, relative to the peak
TOL = {"compress": 1e-5, "compress_fft": 1e-4, "fmcw": 2e-4, "backproject": 2e-4, "stolt": 2e-4}


def width_or_skip(kernel: str, vec: int) -> None:
    """Skip unless the device layer verified ``kernel`` at width ``vec`` on the default device."""
    from clsas import cl

    queue = cl.get_queue()
    verdict = cl.check(queue, kernel, vec)
    if not verdict.ok:
        if opencl_required() and not any(cl.check(queue, kernel, w).ok for w in cl.candidate_widths(queue.device)):
            pytest.fail(f"{kernel}: {cl.describe(queue.device)} accepts no vector width "
                        f"({', '.join(map(str, cl.candidate_widths(queue.device)))}): {verdict.reason}")
        pytest.skip(f"{kernel} at VEC={vec} is not usable on this device: {verdict.reason}")


@pytest.fixture(scope="session", autouse=True)
def _variant_cache(tmp_path_factory):
    """Kernel-variant verdicts go to a directory of this session, not the user's cache."""
    import os

    old = os.environ.get("CLSAS_CACHE_DIR")
    os.environ["CLSAS_CACHE_DIR"] = str(tmp_path_factory.mktemp("clsas-cache"))
    yield
    if old is None:
        os.environ.pop("CLSAS_CACHE_DIR", None)
    else:
        os.environ["CLSAS_CACHE_DIR"] = old


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def chirp96():
    fs = 96e3
    return clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.1), fs


def bp_kernel_case(rng, nz: int = 37):
    """The bp kernel tests' scene: 9 x 5 x ``nz`` voxels (37: not a multiple of any width or
    work-group, work-items in one z row and across a row's end; 32: rows aligned to every width),
    voxels in and out of the window, upsampled profiles (2 carrier cycles per sample), a speed of
    sound per measurement. Returns ``(grid, (prof, tau0, dtau, fc, tx, rx, c))``."""
    grid = clsas.VoxelGrid(np.linspace(-0.1, 0.1, 9), np.linspace(-0.05, 0.05, 5), np.linspace(0.3, 0.7, nz))
    n, n_lags, dtau = 12, 40, 1 / 24e3
    tx = np.c_[rng.uniform(-0.2, 0.2, (n, 2)), np.zeros(n)]
    rx = tx + [0.03, 0, 0]
    c = rng.uniform(340, 346, n)
    prof = rng.normal(size=(n, n_lags)) + 1j * rng.normal(size=(n, n_lags))
    tau0 = 0.8 / 343 - 20 * dtau + rng.uniform(-3, 3, n) * dtau
    return grid, (prof, tau0, dtau, 25e3, tx, rx, c)


def small_dataset(points, amplitudes=None, nx=9, ny=7, width=0.4, height=0.3, snr_db=None, walls=(),
                  visible=None, duration_s=2e-3, fs=96e3, humidity_pct=50.0):
    w = clsas.lfm_chirp(20e3, 30e3, duration_s, fs, taper=0.1)
    ap = clsas.raster_aperture(nx, ny, width, height)
    scene = clsas.Scene(np.asarray(points, float), amplitudes, visible, walls, humidity_pct=humidity_pct)
    return clsas.simulate(scene, ap, w, fs, snr_db=snr_db,
                          chirp={"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": duration_s})


@pytest.fixture(scope="session")
def grbl_exe(tmp_path_factory):
    """The real GRBL 1.1h firmware built with grbl-sim (tests/grbl_kit.py); skips without the kit."""
    from grbl_kit import build_grbl

    return build_grbl(tmp_path_factory.mktemp("grbl_real"))


def pytest_collection_modifyitems(config, items):
    """Markers that say what a test needs, applied where the need is declared, so that ``-m opencl``,
    ``-m oclgrind`` and ``-m hw`` select what they say: a test skipped without an OpenCL device
    (``needs_opencl``, or the ``opencl`` backend parameter) is ``opencl``; a test that runs the real
    GRBL firmware (``grbl_exe``) or the rig is ``hw``."""
    for item in items:
        skips = [m for m in item.iter_markers("skipif") if str(m.kwargs.get("reason", "")).startswith("no OpenCL")]
        if skips:
            item.add_marker(pytest.mark.opencl)
        if "grbl_exe" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.hw)
        if item.get_closest_marker("oclgrind") is not None:
            item.add_marker(pytest.mark.opencl)
