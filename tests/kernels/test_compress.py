"""Pulse compression (kernels/compress.cl): twin equivalence on PoCL, analytic tests, input checks."""

import numpy as np
import pytest
from conftest import BACKENDS, TOL, needs_opencl, width_or_skip

import clsas
from clsas.compression import compress, profile_decimation


def _echo(wave, fs, n_samples, delay_s, amp=1.0, phase=0.0):
    """A recording holding one echo at a fractional delay with a given phase (exact)."""
    n = np.arange(n_samples) / fs
    spec = np.fft.rfft(wave, 4 * n_samples)
    f = np.fft.rfftfreq(4 * n_samples, 1 / fs)
    shifted = np.fft.irfft(spec * np.exp(-2j * np.pi * f * delay_s), 4 * n_samples)[:n_samples]
    # a phase rotation of the echo: Re(e^{j phase} analytic)
    a = clsas.analytic(np.concatenate([shifted, np.zeros(64)]))[:n_samples]
    return amp * np.real(np.exp(1j * phase) * a), n


@needs_opencl
@pytest.mark.parametrize("gate", [None, (0.004, 0.009), (-0.001, 0.05)], ids=["full", "gated", "beyond-edges"])
@pytest.mark.parametrize("n_meas", [1, 7, 37], ids=["1meas", "7meas", "37meas"])
@pytest.mark.parametrize(("algorithm", "lag_step"), [("direct", 1), ("direct", 2), ("direct", 4), ("fft", 1)])
def test_matched_filter_opencl_equals_twin(rng, chirp96, gate, n_meas, algorithm, lag_step):
    """White noise in, every lag: equal to the direct-correlation twin to float32 rounding."""
    wave, fs = chirp96
    sig = rng.normal(size=(n_meas, 1000))
    t0 = rng.uniform(0, 1e-3, n_meas)
    kw = dict(gate_s=gate, t0_s=t0, lag_step=lag_step)
    a = compress(sig, wave, fs, algorithm=algorithm, backend="opencl", **kw)
    b = compress(sig, wave, fs, backend="numpy", **kw)
    assert a.data.shape == b.data.shape
    np.testing.assert_allclose(a.tau0_s, b.tau0_s)
    err = np.abs(a.data - b.data).max() / np.abs(b.data).max()
    assert err < TOL["compress"], err


@needs_opencl
@pytest.mark.parametrize("n_samples", [900, 1700, 3000])  # odd and even log2 of the FFT size
@pytest.mark.parametrize("fs", [96e3, 192e3])
def test_decimating_fft_equals_twin_on_echoes(rng, fs, n_samples):
    """The FFT path keeps N/D bins around the carrier: on band-limited echoes it equals the
    direct twin; on white noise the difference is bounded by the reference's spectrum outside
    the kept band (-60 dB by the choice of D)."""
    wave = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.1)
    d = profile_decimation(wave, fs, 25e3)
    assert d >= 2
    x = sum(_echo(wave, fs, n_samples, tau, amp, ph)[0]
            for tau, amp, ph in [(1.1e-3, 1.0, 0.3), (3.7e-3, 0.5, 2.0), (4.0e-3, 1e-3, -1.0)])
    sig = np.stack([x, np.roll(x, 17), 0.5 * x]) + 1e-3 * rng.normal(size=(3, n_samples))
    kw = dict(gate_s=(0.5e-3, 6e-3), fc_hz=25e3)
    a = compress(sig, wave, fs, algorithm="fft", backend="opencl", **kw)
    b = compress(sig, wave, fs, backend="numpy", **kw)
    assert a.dtau_s == b.dtau_s == d / fs
    err = np.abs(a.data - b.data).max() / np.abs(b.data).max()
    assert err < TOL["compress_fft"], err
    noise = rng.normal(size=(3, n_samples))
    a = compress(noise, wave, fs, algorithm="fft", backend="opencl", **kw)
    b = compress(noise, wave, fs, backend="numpy", **kw)
    assert np.abs(a.data - b.data).max() / np.abs(b.data).max() < 2e-3


def test_profile_decimation_keeps_interpolation_loss_under_half_a_db():
    for fs, expect in [(96e3, 2), (192e3, 4), (48e3 * 8, 8)]:
        wave = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
        d = profile_decimation(wave, fs, 25e3)
        assert d == expect
        # worst case of linear interpolation at the 30 kHz band edge, 5 kHz from the carrier
        x = 5e3 * d / fs
        assert 20 * np.log10(np.sinc(x)) > -0.5
    # a hard-edged chirp spreads energy far from the band: keep the full rate
    assert profile_decimation(clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, taper=0.0), 96e3, 25e3) == 1


@needs_opencl
def test_fmcw_opencl_equals_twin(rng):
    fs = 96e3
    chirp = {"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": 20e-3}
    wave = clsas.lfm_chirp(20e3, 30e3, 20e-3, fs)
    sig = rng.normal(size=(3, 2400))
    a = compress(sig, wave, fs, method="fmcw", chirp=chirp, gate_s=(1e-3, 4e-3), backend="opencl")
    b = compress(sig, wave, fs, method="fmcw", chirp=chirp, gate_s=(1e-3, 4e-3), backend="numpy")
    err = np.abs(a.data - b.data).max() / np.abs(b.data).max()
    assert err < TOL["fmcw"], err


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("method", ["matched", "fmcw"])
def test_echo_peaks_at_its_delay_with_its_phase(backend, method):
    """An echo at delay tau with phase phi gives |P| peaked at tau and arg P = phi - 2 pi fc tau."""
    fs = 96e3
    dur = 20e-3 if method == "fmcw" else 3e-3
    wave = clsas.lfm_chirp(20e3, 30e3, dur, fs)
    chirp = {"f_start_hz": 20e3, "f_stop_hz": 30e3, "duration_s": dur}
    tau, phi = 4.321e-3, 0.7
    x, _ = _echo(wave, fs, 3000, tau, 1.0, phi)
    p = compress(x[None], wave, fs, method=method, chirp=chirp, gate_s=(2e-3, 7e-3), backend=backend)
    mag = np.abs(p.data[0])
    k = int(np.argmax(mag))
    # parabolic interpolation of the peak
    y0, y1, y2 = mag[k - 1 : k + 2]
    frac = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    tau_hat = p.tau0_s[0] + (k + frac) * p.dtau_s
    assert tau_hat == pytest.approx(tau, abs=0.1 / fs)  # parabolic-fit bias, 0.17 mm of range

    # phase: for an echo on the sample grid, P(tau) = |A| exp(j (phi - 2 pi fc tau))
    tau = 415 / fs
    x, _ = _echo(wave, fs, 3000, tau, 1.0, phi)
    p = compress(x[None], wave, fs, method=method, chirp=chirp, gate_s=(2e-3, 7e-3), backend=backend)
    k = int(round((tau - p.tau0_s[0]) / p.dtau_s))
    assert k == int(np.argmax(np.abs(p.data[0])))
    expected = phi - 2 * np.pi * p.fc_hz * tau
    assert np.angle(p.data[0, k] * np.exp(-1j * expected)) == pytest.approx(0, abs=0.03)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gated_profile_is_a_slice_of_the_full_one(chirp96, rng, backend):
    wave, fs = chirp96
    # band-limited echoes: the FFT path's frequency-domain decimation is then exact
    x = _echo(wave, fs, 1200, 4.2e-3)[0] + _echo(wave, fs, 1200, 5.1e-3, 0.3, 1.0)[0]
    sig = np.stack([x, -x]) + 1e-4 * rng.normal(size=(2, 1200))
    full = compress(sig, wave, fs, backend=backend)
    part = compress(sig, wave, fs, gate_s=(3e-3, 6e-3), backend=backend)
    k0 = int(round((part.tau0_s[0] - full.tau0_s[0]) / full.dtau_s))
    np.testing.assert_allclose(part.data, full.data[:, k0 : k0 + part.n_lags], atol=2e-5 * np.abs(full.data).max())
    assert part.n_lags < full.n_lags / 2


def test_compress_rejects_bad_input(chirp96):
    wave, fs = chirp96
    sig = np.zeros((2, 500))
    bad = sig.copy()
    bad[1, 3] = np.nan
    with pytest.raises(ValueError, match="signals contains 1 NaN"):
        compress(bad, wave, fs, backend="numpy")
    with pytest.raises(ValueError, match="signals must be 2-D"):
        compress(sig[0], wave, fs, backend="numpy")
    with pytest.raises(ValueError, match="fs_hz"):
        compress(sig, wave, 0.0, backend="numpy")
    with pytest.raises(ValueError, match="method"):
        compress(sig, wave, fs, method="magic", backend="numpy")
    with pytest.raises(ValueError, match="fmcw needs chirp parameters|chirp lacks"):
        compress(sig, wave, fs, method="fmcw", backend="numpy")
    with pytest.raises(ValueError, match="gate_s"):
        compress(sig, wave, fs, gate_s=(5e-3, 1e-3), backend="numpy")
    with pytest.raises(ValueError, match="backend"):
        compress(sig, wave, fs, backend="cuda")
    with pytest.raises(ValueError, match="lag_step must be a power of two"):
        compress(sig, wave, fs, lag_step=3, backend="numpy")
    with pytest.raises(ValueError, match="algorithm"):
        compress(sig, wave, fs, algorithm="fast", backend="numpy")


@needs_opencl
@pytest.mark.parametrize("vec", [4, 8, 16], ids=lambda v: f"vec{v}")
@pytest.mark.parametrize("kernel", ["matched_filter", "fmcw_dechirp", "matched_fft"])
def test_every_compress_kernel_equals_twin_at_every_width(rng, chirp96, kernel, vec):
    """Each kernel at each vector width the device layer accepts (others skip with its reason)."""
    from clsas import cl
    from clsas.compression import compress_numpy as twin
    from clsas.compression import fft_layout
    from clsas.compression.compress_opencl import FftMatchedPlan, FmcwPlan, MatchedFilterPlan

    width_or_skip(kernel, vec)
    wave, fs = chirp96
    ref_a = clsas.analytic(wave)
    sig = rng.normal(size=(2 * vec + 5, 1500))  # more rows than one FFT work-item holds
    n_meas, n = sig.shape
    rot0 = np.exp(-2j * np.pi * rng.uniform(size=n_meas))
    q = cl.get_queue()
    if kernel == "fmcw_dechirp":
        slope = 10e3 / 2e-3
        ref = np.conj(ref_a) * np.hanning(len(ref_a))
        taus = 1e-3 + np.arange(203) / fs
        rvp = np.exp(1j * rng.uniform(size=len(taus)))
        got = FmcwPlan(n_meas, n, ref, slope, fs, taus, rvp, queue=q, vec=vec)(sig)
        want = twin.fmcw_dechirp(sig, ref, slope, fs, taus, rvp)
        tol = TOL["fmcw"]
    else:
        lag0, n_lags = -50, 1601  # past both edges of the recording
        rot = np.exp(-2j * np.pi * 0.26 * np.arange(n_lags))
        want = twin.matched_filter(sig, np.conj(ref_a), lag0, n_lags, rot, rot0)
        if kernel == "matched_filter":
            got = MatchedFilterPlan(n_meas, n, np.conj(ref_a), lag0, n_lags, rot, rot0, queue=q, vec=vec)(sig)
            tol = TOL["compress"]
        else:
            lay = fft_layout(ref_a, fs, 25e3, 0, n, lag0, 1, n_lags, rot)
            plan = FftMatchedPlan(n_meas, n, lay, rot0, queue=q, vec=vec, max_scratch_bytes=16 * lay.n_fft * vec)
            assert plan.vec == vec and plan.items == 1  # several batches
            got = plan(sig)
            tol = TOL["compress_fft"]
    err = np.abs(got - want).max() / np.abs(want).max()
    assert err < tol, err
