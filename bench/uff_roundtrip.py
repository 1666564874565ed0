"""A measured scan through UFF and back: sizes, times, and whether anything changed.

    python -m bench.uff_roundtrip /work/data/airsas [--scan 20k] [--out bench/results]

DATA as for ``bench/airsas_compare.py``. The AirSAS scan (with its empty-scene scan) is
imported, written with :func:`clsas.io.export_uff`, read back with :func:`clsas.io.import_uff`
and, where ``pyuff-ustb`` is installed, opened with it. Reported: the UFF matrix (waves x
elements; a turntable fills its diagonal), the file's size against the dataset file's, the
times, the largest change in the recordings (float32 rounding), in positions and in ``t0_s``,
and the complex correlation of the guide's image from the original and from the round trip.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

import clsas  # noqa: E402
import clsas.io  # noqa: E402
from bench.airsas_compare import SCANS, owners_axes
from clsas import preprocess as pp  # noqa: E402


def _image(ds: clsas.Dataset) -> np.ndarray:
    ds = pp.apply(ds, direct_clock=True, dc=True, bandpass=True, background=True, common=True, blank_direct=True)
    x, _ = owners_axes()
    return np.asarray(clsas.reconstruct(ds, clsas.VoxelGrid(x, x, np.array([0.0])), backend="numpy").values)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--scan", default="20k", choices=list(SCANS))
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()
    root = args.data / "airsas_deconv_pipeline" if (args.data / "airsas_deconv_pipeline").is_dir() else args.data
    scan, bg = (root / "airsas_data" / f for f in SCANS[args.scan])
    ds = clsas.io.import_airsas(scan, background=bg)
    out: dict = {"date": time.strftime("%Y-%m-%d"), "host": platform.node() or "unknown", "scan": args.scan,
                 "measurements": ds.n_meas, "samples": ds.n_samples}
    with tempfile.TemporaryDirectory() as tmp:
        h5, uff = Path(tmp, "scan.h5"), Path(tmp, "scan.uff")
        ds.save(h5, overwrite=True)
        t = time.perf_counter()
        clsas.io.export_uff(ds, uff)
        out["export_s"] = time.perf_counter() - t
        t = time.perf_counter()
        back = clsas.io.import_uff(uff)
        out["import_s"] = time.perf_counter() - t
        out["dataset_file_bytes"], out["uff_file_bytes"] = h5.stat().st_size, uff.stat().st_size
        import h5py

        with h5py.File(uff) as f:
            out["uff_matrix_waves_elements"] = list(f["channel_data/data"].shape[:2])
        try:
            import pyuff_ustb

            t = time.perf_counter()
            shape = pyuff_ustb.Uff(str(uff)).read("channel_data").data.shape
            out["pyuff_read_s"], out["pyuff_data_shape"] = time.perf_counter() - t, list(shape)
        except ImportError:
            out["pyuff_read_s"] = None
    out["max_signal_change"] = float(np.max(np.abs(back.signals - ds.signals)))
    out["signal_peak"] = float(np.max(np.abs(ds.signals)))
    out["max_position_change_m"] = float(max(np.abs(back.tx_positions - ds.tx_positions).max(),
                                             np.abs(back.rx_positions - ds.rx_positions).max()))
    out["max_t0_change_s"] = float(np.abs(back.t0_s - ds.t0_s).max())
    a, b = _image(ds).ravel(), _image(back).ravel()
    out["image_complex_correlation"] = float(abs(np.vdot(a, b)) / np.linalg.norm(a) / np.linalg.norm(b))
    out["load_average_1_5_15_min"] = list(os.getloadavg())
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{out['date']}-uff-roundtrip-{args.scan}"
    stem.with_suffix(".json").write_text(json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
