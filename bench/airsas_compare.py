"""clsas on the public AirSAS measured scans, against the data owners' delay-and-sum images.

    python -m bench.airsas_compare /work/data/airsas [--scans 20k 5k] [--calibrate] [--out bench/results]

DATA is a local copy of github.com/awreed/CSAS_Deconvolution_INR (at least its folder
``airsas_deconv_pipeline``: ``airsas_data/small_features_cutout_{20k,5k}``, ``bg_{20k,5k}``,
``20k_scene/scene.npy`` and ``20k_scene/fig-a.PNG``); it stays outside this repository.

What it measures (JSON + Markdown + PNG under --out):

1. Handedness of the owners' figure: the "DAS" panel of ``fig-a.PNG`` (colours mapped back
   through viridis to dB) against ``scene.npy`` drawn with row 0 at the top (y growing
   downward, matplotlib's default) and drawn flipped: which one the figure shows, so which
   way up the photo beside it relates to the owners' frame (see ``clsas.io.airsas``).
2. The README's pipeline, exactly (import -> preprocess -> reconstruct, default options, no
   flips), on the owners' pixels (400 x 400 on +-0.3 m, the disc r <= 0.3 m), against
   (20k) the owners' ``scene.npy`` and (both) this script's port of their delay-and-sum
   (written here from reading ``sim_csas_package``'s beamformer and ``airsas_utils``):
   |.|-correlation, their 5 strongest peaks' distances to clsas's local maxima, TCR in the
   target box. The peak distances are given on the owners' 1.5 mm pixels and between pixels
   (``subpixel_peaks``: on pixels alone a peak can be up to 1.1 mm from where it is). The
   owners' frame is the mirror (y -> -y) of clsas's (see 1.); their images are put into
   clsas's frame by that mirror, nothing else.
3. The pipeline with the clock as ``Group Delay`` states it (no ``direct_clock``), and that
   with the owners' ring radius (0.85 m for both transducers instead of SysParams.csv's 0.8485
   and 0.8615 m): the "owners' frame" comparison (their geometry and clock, every other step
   the guide's). ``bench/airsas_ablation.py`` takes the difference apart one ingredient at a time.
5. With ``--calibrate``: ``clsas.focus.calibrate`` of the ring radius, the group delay and the
   transducers' height on each scan (each alone), and the image with the radius applied; and the
   check that trusts no sharpness (``calibrate(..., metric="sectors")``): the ring radius at
   which the images of 8 disjoint 45-degree sectors of the turn agree best, with the guide's
   clock and with the clock as ``Group Delay`` states it.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

import clsas
import clsas.io
from clsas import preprocess as pp

N_PIX, HALF_M = 400, 0.3
BOX = ((-0.07, 0.07), (-0.11, 0.11), None)  # the target: the cork cut-out, in clsas's frame
SCANS = {"20k": ("small_features_cutout_20k", "bg_20k"), "5k": ("small_features_cutout_5k", "bg_5k")}
OWNERS_RADIUS_M = 0.85
OWNERS_OFFSET_MM = (OWNERS_RADIUS_M - 0.5 * (0.8485 + 0.8615)) * 1e3  # from SysParams.csv's mean radius


def owners_axes() -> tuple[np.ndarray, np.ndarray]:
    """Their pixel axis (m) and the disc mask [iy, ix] (``RenderParameters.define_scene_dimensions``)."""
    x = np.linspace(-HALF_M, HALF_M, N_PIX)
    xx, yy = np.meshgrid(x, x)
    return x, xx**2 + yy**2 <= HALF_M**2


def owners_scene(path: Path) -> np.ndarray:
    """``scene.npy`` (values on the disc, meshgrid order) as a complex [iy, ix] array, their frame."""
    x, disc = owners_axes()
    out = np.zeros(disc.size, complex)
    out[np.flatnonzero(disc.ravel())] = np.load(path)
    return out.reshape(disc.shape)


def to_clsas(img_yx: np.ndarray) -> np.ndarray:
    """An owners'-frame [iy, ix] image as clsas's [ix, iy] in clsas's frame (y -> -y)."""
    return img_yx[::-1, :].T


def _readme_pipeline(scan: Path, bg: Path, direct_clock: bool = True) -> clsas.Dataset:
    """Exactly the README's "Your own data" steps for this data (``direct_clock=False``: the
    clock as ``Group Delay`` states it)."""
    ds = clsas.io.import_airsas(scan, background=bg)
    return pp.apply(ds, direct_clock=direct_clock, dc=True, bandpass=True, background=True, common=True,
                    blank_direct=True)


def with_radius(ds: clsas.Dataset, radius_m: float) -> clsas.Dataset:
    """Both transducers moved to ``radius_m`` from the turntable axis (heights kept)."""
    out = []
    for p in (ds.tx_positions, ds.rx_positions):
        q = p.copy()
        q[:, :2] *= (radius_m / np.hypot(p[:, 0], p[:, 1]))[:, None]
        out.append(q)
    return ds.replace(tx_positions=out[0], rx_positions=out[1])


def owners_das(scan: Path, bg: Path, up: int = 100) -> np.ndarray:
    """The owners' delay-and-sum, ported: [iy, ix] complex in their frame.

    Their steps: scan minus empty scan; their shared-response removal (subtract the mean
    over pings, weighted down where a sample's sign or size differs from the mean's); a
    circular matched filter of the analytic signals (1000 samples); each profile upsampled
    ``up`` times by FFT; nearest sample at ``(d_tx + d_rx) / c * fs * up + GD * up``
    (truncated), c = 331.4 + 0.6 T per ping; transducers at radius 0.85 m, angle 90 - a.
    """
    from scipy.signal import hilbert

    ds = clsas.io.import_airsas(scan, background=bg)
    data = ds.signals - ds.background
    cm = data.mean(axis=0, keepdims=True)
    same_sign = np.sign(cm) == np.sign(data)
    beta = np.where(same_sign, 1.0, 1.0 / (1.0 + np.pi**2))
    alpha = 1.0 / (1.0 + (np.abs(cm) - np.abs(data)) ** 2)
    data = data - alpha * beta * np.abs(cm) * np.sign(data)
    n = data.shape[1]
    pulse = np.full(n, 1e-8)
    pulse[: len(ds.waveform)] = ds.waveform
    kernel = np.fft.fft(hilbert(pulse))
    rc = np.fft.ifft(np.fft.fft(hilbert(data, axis=1), axis=1) * np.conj(kernel), axis=1)
    x, disc = owners_axes()
    xx, yy = np.meshgrid(x, x)
    px, py = xx[disc], yy[disc]
    prov = ds.provenance[0]
    gd = prov["group_delay_samples"]
    z_tx = ds.tx_positions[0, 2]
    z_rx = ds.rx_positions[0, 2]
    angles = np.arange(ds.n_meas)  # one ping per degree, 0..359, as the files list them
    temps = np.asarray(ds.temperature_c) * np.ones(ds.n_meas)
    acc = np.zeros(px.size, complex)
    spec = np.fft.fft(rc, axis=1)
    for m in range(ds.n_meas):
        fine = np.zeros(n * up, complex)
        fine[: n // 2] = spec[m, : n // 2]
        fine[n * up - n // 2 + 1:] = spec[m, n // 2 + 1:]
        fine[n // 2] = spec[m, n // 2] / 2
        fine[n * up - n // 2] = spec[m, n // 2] / 2
        prof = np.fft.ifft(fine) * up
        th = np.deg2rad(90.0 - angles[m])
        tx = OWNERS_RADIUS_M * np.array([np.cos(th), np.sin(th)])
        d = np.hypot(px - tx[0], py - tx[1])
        d1 = np.sqrt(d**2 + z_tx**2)
        d2 = np.sqrt(d**2 + z_rx**2)
        c = 331.4 + 0.6 * temps[m]
        tof = ((d1 + d2) / c * ds.fs_hz * up + gd * up).astype(int)
        acc += prof[tof]
    out = np.zeros(disc.shape, complex)
    out[disc] = acc
    return out


def _object_crop(db: np.ndarray, shape=(120, 50), threshold_db=-12.0, sigma=1.5) -> np.ndarray:
    """The image over the bounding box of its pixels above ``threshold_db``, resampled to
    ``shape`` and smoothed (so that two renderings at other scales and offsets compare)."""
    from scipy.ndimage import gaussian_filter

    r, c = np.nonzero(db > threshold_db)
    rows = np.linspace(r.min(), r.max(), shape[0]).round().astype(int)
    cols = np.linspace(c.min(), c.max(), shape[1]).round().astype(int)
    return gaussian_filter(db[np.ix_(rows, cols)], sigma)


def figure_handedness(fig_png: Path, scene_yx: np.ndarray, panel=(slice(57, 266), slice(243, 455))) -> dict:
    """Which way the figure's DAS panel draws ``scene.npy``: the panel (viridis -> dB, -20..0)
    against ``scene.npy`` drawn with row 0 at the top (y growing downward), flipped up-down,
    left-right and turned by 180 degrees; each over the object's bounding box, smoothed
    (the panel is a smaller rendering), correlation of the dB images."""
    import matplotlib
    import matplotlib.image

    rgb = matplotlib.image.imread(fig_png)[panel][..., :3]
    lut = matplotlib.colormaps["viridis"](np.linspace(0, 1, 256))[:, :3]
    idx = np.argmin(((rgb[:, :, None, :] - lut[None, None]) ** 2).sum(-1), axis=-1)
    fig = _object_crop(-20 + 20 * idx / 255.0)
    mag = np.abs(scene_yx)
    db = np.clip(20 * np.log10(np.maximum(mag / mag.max(), 1e-12)), -20, 0)

    def corr(b):
        a, b = fig - fig.mean(), b - b.mean()
        return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))

    out = {"row0_top": corr(_object_crop(db)), "flipped_up_down": corr(_object_crop(db[::-1])),
           "flipped_left_right": corr(_object_crop(db[:, ::-1])), "turned_180": corr(_object_crop(db[::-1, ::-1]))}
    out["figure_shows"] = max(out, key=out.get)
    return out


def local_maxima(mag: np.ndarray, floor: float) -> np.ndarray:
    """(k, 2) indices of the 3 x 3 local maxima of ``mag`` at or above ``floor``."""
    from scipy.ndimage import maximum_filter

    return np.argwhere((mag == maximum_filter(mag, size=3)) & (mag >= floor) & (mag > 0))


def strongest_peaks(mag: np.ndarray, k: int, sep_pix: float) -> np.ndarray:
    cand = local_maxima(mag, 0.0)
    cand = cand[np.argsort(mag[tuple(cand.T)])[::-1]]
    keep: list[np.ndarray] = []
    for c in cand:
        if all(np.hypot(*(c - q)) >= sep_pix for q in keep):
            keep.append(c)
        if len(keep) == k:
            break
    return np.array(keep)


def metrics(img_xy: np.ndarray, ref_xy: np.ndarray) -> dict:
    """|.|-correlation on the disc, the reference's 5 strongest peaks (5 mm apart) against
    clsas's local maxima within -10 dB of its peak, and TCR in ``BOX`` (peak over RMS outside
    the box, on the disc) of both; [ix, iy] arrays in clsas's frame."""
    x, disc_yx = owners_axes()
    disc = disc_yx.T
    a, b = np.abs(img_xy), np.abs(ref_xy)
    a, b = np.where(disc, a, 0), np.where(disc, b, 0)
    corr = float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))
    step = x[1] - x[0]
    ref_pk = strongest_peaks(b, 5, 0.005 / step)
    ours = local_maxima(a, a.max() * 10 ** (-10 / 20))
    dist = [float(np.min(np.hypot(*(ours - p).T)) * step) for p in ref_pk]
    xx, yy = np.meshgrid(x, x, indexing="ij")
    box = (xx >= BOX[0][0]) & (xx <= BOX[0][1]) & (yy >= BOX[1][0]) & (yy <= BOX[1][1])

    def tcr(m):
        return float(20 * np.log10(m[box].max() / np.sqrt(np.mean(m[disc & ~box] ** 2))))

    return {"abs_correlation": corr, "peak_distances_mm": [d * 1e3 for d in dist],
            "peaks_within_3mm": int(sum(d <= 0.003 + 1e-9 for d in dist)),
            "reference_peaks_m": [[float(x[i]), float(x[j])] for i, j in ref_pk],
            "tcr_db": tcr(a), "reference_tcr_db": tcr(b)}


def _quadratic_peak(mag: np.ndarray, i: int, j: int) -> tuple[float, float]:
    """Sub-pixel position (fractional indices) of the local maximum at pixel (i, j): a parabola
    through log |.| along each axis over the 3 x 3 neighbourhood; on the image's edge, or where
    the three samples are not a peak (flat), the pixel itself along that axis."""
    def offset(lo: float, mid: float, hi: float) -> float:
        curv = 2 * mid - lo - hi
        return float(np.clip(0.5 * (hi - lo) / curv, -0.5, 0.5)) if curv > 0 else 0.0

    w = np.log(np.maximum(mag, 1e-300))
    di = offset(w[i - 1, j], w[i, j], w[i + 1, j]) if 0 < i < mag.shape[0] - 1 else 0.0
    dj = offset(w[i, j - 1], w[i, j], w[i, j + 1]) if 0 < j < mag.shape[1] - 1 else 0.0
    return i + di, j + dj


def subpixel_peaks(ds: clsas.Dataset, ours_xy: np.ndarray, ref_xy: np.ndarray, backend: str,
                   half_m: float = 0.008, step_m: float = 2.5e-4) -> dict:
    """The peak test without the pixels' 1.5 mm quantisation.

    The reference's 5 strongest peaks (as in :func:`metrics`) are placed between its pixels by
    a parabola through log |.| (it exists only on its pixels); clsas images a 16 mm window
    around each at 0.25 mm and its local maxima there within -10 dB of its image's peak (the
    same floor as :func:`metrics`) are the candidates. A peak with none in its window is a
    miss (distance inf)."""
    x, disc_yx = owners_axes()
    step = x[1] - x[0]
    b = np.abs(np.where(disc_yx.T, ref_xy, 0))
    floor = np.abs(np.where(disc_yx.T, ours_xy, 0)).max() * 10 ** (-10 / 20)
    dist = []
    for i, j in strongest_peaks(b, 5, 0.005 / step):
        fi, fj = _quadratic_peak(b, i, j)
        rx, ry = x[0] + fi * step, x[0] + fj * step
        f = np.arange(-half_m, half_m + step_m / 2, step_m)
        grid = clsas.VoxelGrid(x[i] + f, x[j] + f, np.array([0.0]))
        mag = np.abs(np.asarray(clsas.reconstruct(ds, grid, backend=backend).values)[:, :, 0])
        lm = local_maxima(mag, floor)
        lm = lm[(lm > 0).all(axis=1) & (lm < f.size - 1).all(axis=1)]
        d = np.hypot(x[i] + f[lm[:, 0]] - rx, x[j] + f[lm[:, 1]] - ry)
        dist.append(float(d.min()) if d.size else float("inf"))
    return {"peak_distances_mm": [d * 1e3 for d in dist], "peaks_within_3mm": int(sum(d <= 0.003 + 1e-9 for d in dist)),
            "window_mm": 2e3 * half_m, "step_mm": step_m * 1e3}


def image(ds: clsas.Dataset, backend: str) -> np.ndarray:
    x, _ = owners_axes()
    grid = clsas.VoxelGrid(x, x, np.array([0.0]))
    return np.asarray(clsas.reconstruct(ds, grid, backend=backend).values)[:, :, 0]


def run_scan(name: str, root: Path, backend: str, calibrate: bool) -> tuple[dict, dict]:
    """Everything measured on one scan, and the images for the picture."""
    scan, bg = (root / "airsas_data" / f for f in SCANS[name])
    t = time.perf_counter()
    ds = _readme_pipeline(scan, bg)
    ours = image(ds, backend)
    t_ours = time.perf_counter() - t
    port = to_clsas(owners_das(scan, bg))
    air = [p for p in ds.provenance if p.get("step") == "speed_of_sound"]
    row: dict = {"scan": name, "pings": ds.n_meas, "time_import_preprocess_image_s": t_ours,
                 "c_mean_mps": float(ds.c_per_meas.mean()),
                 "c_mps_source": air[-1]["c_mps_source"] if air else "as the dataset states it",
                 "vs_port": metrics(ours, port)}
    row["vs_port"]["subpixel"] = subpixel_peaks(ds, ours, port, backend)
    pics = {"clsas (README pipeline)": ours, "owners' delay-and-sum (port)": port}
    shipped = root / f"{name}_scene" / "scene.npy"
    if shipped.is_file():
        theirs = to_clsas(owners_scene(shipped))
        row["vs_scene_npy"] = metrics(ours, theirs)
        row["vs_scene_npy"]["subpixel"] = subpixel_peaks(ds, ours, theirs, backend)
        xs, disc = owners_axes()
        p, s = port[disc.T], theirs[disc.T]
        row["port_vs_scene_npy_complex_correlation"] = float(abs(np.vdot(p, s)) / np.linalg.norm(p) / np.linalg.norm(s))
    stated = _readme_pipeline(scan, bg, direct_clock=False)
    row["direct_sound_t0_shift_s"] = float(ds.t0_s[0] - stated.t0_s[0])
    row["stated_clock_vs_port"] = metrics(image(stated, backend), port)
    owners_r = image(with_radius(stated, OWNERS_RADIUS_M), backend)
    row["owners_radius_vs_port"] = metrics(owners_r, port)
    pics[f"clsas, Group Delay as stated, radius {OWNERS_RADIUS_M} m"] = owners_r
    if calibrate:
        row["sector_agreement"] = {"guide clock": sector_agreement(ds, backend),
                                   "Group Delay as stated": sector_agreement(stated, backend)}
        row["calibration"], fixed = calibrations(ds, backend)
        calibrated = image(fixed, backend)
        row["calibrated_vs_port"] = metrics(calibrated, port)
        pics[f"clsas, radius calibrated ({row['calibration']['radius']['estimate'] * 1e3:+.1f} mm)"] = calibrated
    return row, pics


def calibrations(ds: clsas.Dataset, backend: str) -> tuple[dict, clsas.Dataset]:
    """Radius, group delay and height by focus (each with the others as stated), on a grid
    over the target box; the dataset with the radius applied."""
    from clsas.focus.calibrate import calibrate as cal_fn

    grid = clsas.VoxelGrid.from_bounds(BOX[0], BOX[1], (0.0, 0.0), 0.0015)
    out, fixed = {}, ds
    for par, span, step in (("radius", 0.02, 0.002), ("group_delay", 1.2e-4, 6e-6), ("height", 0.08, 0.008)):
        t = time.perf_counter()
        applied, cal = cal_fn(ds, grid, par, span=span, step=step, apply=par == "radius", backend=backend)
        out[par] = {**cal.as_dict(), "time_s": time.perf_counter() - t}
        if par == "radius":
            fixed = applied
    return out, fixed


def sector_agreement(ds: clsas.Dataset, backend: str) -> dict:
    """The ring radius at which 8 disjoint sectors of the turn image alike over the target box:
    :func:`clsas.focus.calibrate.calibrate` with ``metric="sectors"`` (+-20 mm in 2 mm steps)."""
    from clsas.focus.calibrate import calibrate as cal_fn

    grid = clsas.VoxelGrid.from_bounds(BOX[0], BOX[1], (0.0, 0.0), 0.0015)
    t = time.perf_counter()
    _, cal = cal_fn(ds, grid, "radius", span=0.02, step=0.002, metric="sectors", backend=backend)
    return {**cal.as_dict(), "time_s": time.perf_counter() - t}


def picture(path: Path, name: str, pics: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(pics), figsize=(4.2 * len(pics), 4.6))
    for ax, (title, img) in zip(axes, pics.items(), strict=True):
        mag = np.abs(img)
        db = 20 * np.log10(np.maximum(mag / mag.max(), 1e-6))
        ax.imshow(db.T, origin="lower", extent=(-HALF_M, HALF_M, -HALF_M, HALF_M), vmin=-25, vmax=0)
        ax.set_xlim(-0.12, 0.12)
        ax.set_ylim(-0.16, 0.16)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x (m)")
    axes[0].set_ylabel(f"{name}: y (m), seen from above")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def markdown(out: dict) -> str:
    h = out["handedness"]
    lines = [f"# clsas on the AirSAS measured scans ({out['date']}, {out['host']}, backend {out['backend']})", "",
             "Handedness: the owners' figure's DAS panel against their scene.npy drawn four ways "
             f"(correlation of dB images): {', '.join(f'{k} {v:.3f}' for k, v in h.items() if k != 'figure_shows')}"
             f" -> the figure shows {h['figure_shows']}.", "",
             "Peaks: the reference's 5 strongest against clsas's local maxima within -10 dB, first on "
             "the owners' 1.5 mm pixels, then between pixels (theirs placed by a parabola through log |.|; "
             "clsas imaged at 0.25 mm in a 16 mm window around each: `subpixel_peaks`).", "",
             "| scan | against | |.|-corr | peaks within 3 mm, on pixels (distances, mm) "
             "| between pixels (distances, mm) | TCR clsas | TCR theirs |",
             "|---|---|---|---|---|---|---|"]
    for row in out["scans"]:
        for key, label in (("vs_scene_npy", "README pipeline vs scene.npy"), ("vs_port", "README pipeline vs port"),
                           ("stated_clock_vs_port", "Group Delay as stated vs port"),
                           ("owners_radius_vs_port", "owners' frame (radius 0.85 m, Group Delay as stated) vs port"),
                           ("calibrated_vs_port", "radius calibrated vs port")):
            if key in row:
                m = row[key]
                d = ", ".join(f"{x:.1f}" for x in m["peak_distances_mm"])
                sub = m.get("subpixel")
                fine = (f"{sub['peaks_within_3mm']}/5 ({', '.join(f'{x:.1f}' for x in sub['peak_distances_mm'])})"
                        if sub else "-")
                lines.append(f"| {row['scan']} | {label} | {m['abs_correlation']:.3f} | {m['peaks_within_3mm']}/5 "
                             f"({d}) | {fine} | {m['tcr_db']:.1f} dB | {m['reference_tcr_db']:.1f} dB |")
    for row in out["scans"]:
        if "port_vs_scene_npy_complex_correlation" in row:
            lines.append(f"\nPort of the owners' delay-and-sum vs their scene.npy ({row['scan']}): complex "
                         f"correlation {row['port_vs_scene_npy_complex_correlation']:.5f}.")
        if "c_mps_source" in row:
            lines.append(f"\nSpeed of sound ({row['scan']}): {row['c_mean_mps']:.2f} m/s on average over the pings, "
                         f"{row['c_mps_source']}.")
        lines.append(f"\nDirect sound ({row['scan']}): sample 0 is {row['direct_sound_t0_shift_s'] * 1e6:+.1f} us "
                     "later than Group Delay says (at the stated speaker-microphone spacing).")
        for par, c in row.get("calibration", {}).items():
            k, u = (1e6, "us") if c["unit"] == "s" else (1e3, "mm")
            lines.append(f"\nCalibration by focus, {par} ({row['scan']}): {c['estimate'] * k:+.2f} {u} +- "
                         f"{c['uncertainty'] * k:.2f} {u} (halves {c['halves'][0] * k:+.2f}, {c['halves'][1] * k:+.2f} "
                         f"{u}){'; at the edge of the range' if c['at_edge'] else ''}, {c['time_s']:.0f} s.")
        for clock, sa in row.get("sector_agreement", {}).items():
            pts = zip(sa["offsets"], sa["metric_values"], strict=True)
            curve = ", ".join(f"{o * 1e3:+.0f}: {m:.3f}" for o, m in pts)
            lines.append(f"\nSectors agree best ({row['scan']}, {clock}; calibrate(metric='sectors'): 8 disjoint "
                         f"sectors, mean |.|-correlation of every pair over the target box) at a ring radius offset "
                         f"of {sa['estimate'] * 1e3:+.2f} mm +- {sa['uncertainty'] * 1e3:.2f} mm (halves "
                         f"{sa['halves'][0] * 1e3:+.2f}, {sa['halves'][1] * 1e3:+.2f} mm; the owners' 0.85 m is "
                         f"{OWNERS_OFFSET_MM:+.0f} mm on average), {sa['time_s']:.0f} s: {curve}.")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path, help="local copy of CSAS_Deconvolution_INR (or its airsas_deconv_pipeline)")
    ap.add_argument("--scans", nargs="+", default=list(SCANS), choices=list(SCANS))
    ap.add_argument("--calibrate", action="store_true", help="also calibrate the ring radius by focus")
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()
    root = args.data / "airsas_deconv_pipeline" if (args.data / "airsas_deconv_pipeline").is_dir() else args.data
    out = {"date": time.strftime("%Y-%m-%d"), "host": platform.node() or "unknown", "backend": args.backend,
           "box_m": BOX[:2], "scans": []}
    shipped = root / "20k_scene"
    out["handedness"] = figure_handedness(shipped / "fig-a.PNG", owners_scene(shipped / "scene.npy"))
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{out['date']}-airsas"
    for name in args.scans:
        row, pics = run_scan(name, root, args.backend, args.calibrate)
        out["scans"].append(row)
        picture(stem.with_name(f"{stem.name}-{name}.png"), name, pics)
        print(json.dumps(row, indent=1), flush=True)
    stem.with_suffix(".json").write_text(json.dumps(out, indent=1))
    stem.with_suffix(".md").write_text(markdown(out))
    print(markdown(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
