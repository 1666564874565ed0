"""Removal of what every recording shares (clsas.preprocess.remove_common): the rings of
static clutter on a simulated turntable scan go; on a planar scan of a target in front, part
of the wanted echo goes too (the documented loss)."""

import numpy as np
import pytest

import clsas
from clsas import preprocess as pp
from clsas.synthesis.synthetic import turntable_scan


def _ring_and_target(image, scan):
    """Peak |image| in the target's box, and the RMS |image| on the annulus (r 0.13-0.2 m)
    where the room clutter's rings lie, outside the box."""
    x, y = np.meshgrid(image.grid.x_m, image.grid.y_m, indexing="ij")
    mag = np.abs(image.values[:, :, 0])
    box = scan.target_box_m
    inside = (x >= box[0, 0]) & (x <= box[0, 1]) & (y >= box[1, 0]) & (y <= box[1, 1])
    r = np.hypot(x, y)
    ring = (r > 0.13) & (r < 0.2) & ~inside
    return float(mag[inside].max()), float(np.sqrt(np.mean(mag[ring] ** 2)))


@pytest.fixture(scope="module")
def still_air():
    # still air: a static echo is then the same in every ping (see remove_common's notes)
    return turntable_scan(90, temperature_c=(20.0, 20.0), snr_db=40)


def test_turntable_rings_are_removed(still_air):
    scan = still_air
    alone = turntable_scan(90, temperature_c=(20.0, 20.0), snr_db=40, clutter_db=-300, direct_db=-300, dc=0.0,
                           hum=0.0)  # the same target, nothing else
    grid = clsas.VoxelGrid.from_bounds((-0.2, 0.2), (-0.2, 0.2), (0, 0), 0.004)

    def steps(ds):
        return pp.apply(ds, group_delay_s=scan.group_delay_s, dc=True, bandpass=True)

    base = steps(scan.dataset)
    cleaned = pp.remove_common(base)
    t0, ring0 = _ring_and_target(clsas.reconstruct(base, grid, backend="numpy"), scan)
    t1, ring1 = _ring_and_target(clsas.reconstruct(cleaned, grid, backend="numpy"), scan)
    ta, ring_a = _ring_and_target(clsas.reconstruct(steps(alone.dataset), grid, backend="numpy"), scan)
    # the clutter's rings (12 dB above the target) drop by more than 20 dB, to within 3 dB
    # of the target-only image's sidelobes there ...
    assert 20 * np.log10(ring0 / ring1) > 20
    assert 20 * np.log10(ring1 / ring_a) < 3
    # ... and the target keeps its peak within 1 dB (it turns with the table: little is shared)
    assert abs(20 * np.log10(t1 / ta)) < 1.0
    assert cleaned.provenance[-1]["step"] == "common"
    med = pp.remove_common(base, "median")
    t2, ring2 = _ring_and_target(clsas.reconstruct(med, grid, backend="numpy"), scan)
    assert 20 * np.log10(ring0 / ring2) > 15 and abs(20 * np.log10(t2 / ta)) < 1.0


def _planar_loss_db(width_m, n, range_m):
    """Peak loss (dB) of a point's image, ``range_m`` in front of an n x n planar scan."""
    ap = clsas.raster_aperture(n, n, width_m, width_m)
    wave = clsas.lfm_chirp(20e3, 30e3, 2e-3, 96e3, 0.1)
    ds = clsas.simulate(clsas.Scene(np.array([[0.0, 0.0, range_m]])), ap, wave, 96e3, n_samples=1400, snr_db=40,
                        seed=3)
    grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (range_m, range_m), 0.005)
    before = clsas.reconstruct(ds, grid, backend="numpy")
    after = clsas.reconstruct(pp.remove_common(ds), grid, backend="numpy")
    return 20 * np.log10(np.abs(after.values).max() / np.abs(before.values).max())


def test_planar_scan_loses_wanted_signal():
    """A static target in front of a planar scan: the mean over stops holds the part of its
    echo that does not change from stop to stop. With a small aperture far from the target
    (0.1 m at 1.5 m: the delay changes by a quarter wavelength across it) most of the echo
    is shared and the peak drops by more than 10 dB (16 dB measured); with a wide aperture
    close to it (0.3 m at 0.5 m: many wavelengths) almost nothing is lost (0.03 dB)."""
    assert _planar_loss_db(0.1, 8, 1.5) < -10.0
    assert _planar_loss_db(0.3, 16, 0.5) > -0.5


def test_remove_common_checks():
    scan = turntable_scan(12, snr_db=40)
    ds = scan.dataset
    out = pp.remove_common(ds)
    np.testing.assert_allclose(out.signals.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(out.signals, ds.signals - ds.signals.mean(axis=0))
    with pytest.raises(ValueError, match="statistic"):
        pp.remove_common(ds, "mode")
    with pytest.raises(ValueError, match="t0_s"):
        pp.remove_common(ds.replace(t0_s=np.linspace(0, 1e-4, ds.n_meas)))
    with pytest.raises(ValueError, match="at least 2"):
        pp.remove_common(ds.subset(slice(0, 1)))
    with_bg = pp.attach_background(ds, scan.background)
    assert np.allclose(pp.remove_common(with_bg).background.mean(axis=0), 0.0)
    # apply(common=) runs it after the background subtraction
    steps = [p["step"] for p in pp.apply(with_bg, background=True, common="median", blank_direct=True).provenance]
    assert steps[-3:] == ["background", "common", "blank_direct"]
    assert pp.apply(ds, common=True).provenance[-1]["statistic"] == "mean"


def test_clock_from_direct_finds_a_hidden_delay():
    """turntable_scan hides a 62.33-sample group delay: the direct sound gives it back."""
    scan = turntable_scan(24, snr_db=40)
    fixed = pp.clock_from_direct(scan.dataset, max_delay_s=1e-3)
    np.testing.assert_allclose(fixed.t0_s, -scan.group_delay_s, atol=0.05 / scan.dataset.fs_hz)
    step = fixed.provenance[-1]
    assert step["step"] == "direct_clock" and step["found"] == 24 and step["spread_s"] < 1e-6
    # a group delay stated 30 us short: the clock finds the rest, for the scan and its background
    again = pp.apply(scan.dataset, group_delay_s=scan.group_delay_s - 3e-5, direct_clock=True,
                     background=scan.background)
    np.testing.assert_allclose(again.t0_s, -scan.group_delay_s, atol=0.05 / scan.dataset.fs_hz)
    assert [p["step"] for p in again.provenance][-3:] == ["group_delay", "direct_clock", "background"]
    assert again.provenance[-1]["rms_after"] < 0.2 * again.provenance[-1]["rms_before"]  # aligned: it cancels
    with pytest.raises(ValueError, match="direct sound was not found"):
        pp.clock_from_direct(pp.blank_direct(pp.remove_delay(scan.dataset, scan.group_delay_s)))
