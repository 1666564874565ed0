"""A dataset file that grows one stop at a time (the scan's HDF5 file).

The layout is the Dataset file's (``clsas.load`` and ``clsas reconstruct`` read a scan in
progress as it is), plus ``stop_index`` (the stop each measurement belongs to). Each stop is
written with ``signals`` last and the file is flushed before the next move, so after a crash
the arrays may only run ahead of ``signals``; opening the file to resume trims them back.
A rig with ``[beams]`` also grows the ``beams`` group's boresights a stop at a time (the
transducers' models are its attributes, written once).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..types.dataset import FORMAT_VERSION, UNITS

__all__ = ["ScanFile"]

log = logging.getLogger(__name__)

_AUX = ("tx_positions", "rx_positions", "t0_s", "stage_positions", "timestamps", "loopback", "stop_index")
_BORESIGHTS = ("beams/tx_boresight", "beams/rx_boresight")


class ScanFile:
    """Append-only writer of a scan's dataset file; use :meth:`create` or :meth:`resume`."""

    def __init__(self, f, n_mics: int) -> None:
        self._f = f
        self.n_mics = n_mics
        self.path = Path(f.filename)

    @classmethod
    def create(cls, path: str | Path, *, fs_hz: float, waveform: np.ndarray, n_samples: int, n_mics: int,
               n_stops: int, temperature_c: float, humidity_pct: float, c_mps: float, chirp: dict,
               config_text: str, beams=None) -> ScanFile:
        """A new scan file; ``beams`` (:class:`clsas.physics.beam.Beams`, any measurements) gives the
        transducers' models to store, their boresights come with each stop."""
        import h5py

        from ..version import __version__

        f = h5py.File(path, "w")
        chunk = max(1, min(64, 2**20 // max(1, 4 * n_samples)))
        shapes = {
            "signals": ((n_samples,), np.float32), "tx_positions": ((3,), np.float64),
            "rx_positions": ((3,), np.float64), "t0_s": ((), np.float64), "stage_positions": ((3,), np.float64),
            "timestamps": ((), np.float64), "loopback": ((n_samples,), np.float32), "stop_index": ((), np.int32),
        }
        for name, (tail, dtype) in shapes.items():
            d = f.create_dataset(name, shape=(0, *tail), maxshape=(None, *tail), dtype=dtype, chunks=(chunk, *tail))
            d.attrs["units"] = UNITS.get(name, "1 (0-based stop number)")
        wf = f.create_dataset("waveform", data=np.asarray(waveform, float))
        wf.attrs["units"] = UNITS["waveform"]
        f.attrs.update({
            "format_version": FORMAT_VERSION, "clsas_version": __version__, "fs_hz": float(fs_hz),
            "c_mps": float(c_mps), "temperature_c": float(temperature_c), "humidity_pct": float(humidity_pct),
            "config_toml": config_text, "chirp_json": json.dumps(chirp), "n_stops_planned": int(n_stops),
            "n_mics": int(n_mics), "complete": False,
        })
        for k, val in chirp.items():
            f.attrs[f"chirp_{k}"] = val
        if beams is not None:
            g = f.create_group("beams")
            g.attrs["about"] = "transducer directivity (clsas.physics.beam): one-way patterns and boresights"
            for k, val in beams.specs().items():
                g.attrs[f"{k}_json"] = json.dumps(val)
            for name in _BORESIGHTS:
                d = f.create_dataset(name, shape=(0, 3), maxshape=(None, 3), dtype=np.float64, chunks=(chunk, 3))
                d.attrs["units"] = "1 (unit vector)"
        f.flush()
        return cls(f, n_mics)

    @classmethod
    def resume(cls, path: str | Path, config_text: str) -> ScanFile:
        """Open a partial scan to continue it; trims whatever ran ahead of ``signals``."""
        import h5py

        path = Path(path)
        try:
            f = h5py.File(path, "r+")
        except OSError as exc:
            raise ValueError(f"cannot open {path} to resume it ({exc}); it may be damaged: "
                             "start a new file and keep this one") from exc
        if "stop_index" not in f or "n_mics" not in f.attrs:
            f.close()
            raise ValueError(f"{path} was not written by clsas acquire, so it cannot be resumed")
        if str(f.attrs["config_toml"]) != config_text:
            f.close()
            raise ValueError(f"{path} was acquired with a different rig configuration; resume it with the "
                             "same rig.toml (the one stored in the file's 'config_toml' attribute)")
        n_mics = int(f.attrs["n_mics"])
        n = f["signals"].shape[0] - f["signals"].shape[0] % n_mics
        for name in ("signals", *_AUX, *(b for b in _BORESIGHTS if b in f)):
            if f[name].shape[0] != n:
                log.info("trimming %s from %d to %d rows (a stop in flight when the scan stopped)",
                         name, f[name].shape[0], n)
                f[name].resize(n, axis=0)
        f.flush()
        return cls(f, n_mics)

    @property
    def stops_done(self) -> int:
        return self._f["signals"].shape[0] // self.n_mics

    @property
    def n_stops_planned(self) -> int:
        return int(self._f.attrs["n_stops_planned"])

    def done_stop_indices(self) -> np.ndarray:
        return self._f["stop_index"][::self.n_mics]

    @property
    def has_beams(self) -> bool:
        return "beams" in self._f

    def append(self, stop: int, *, signals: np.ndarray, tx_m: np.ndarray, rx_m: np.ndarray, t0_s: float,
               stage_m: np.ndarray, timestamp: float, loopback: np.ndarray, beams=None) -> None:
        """Write one stop (``n_mics`` measurements) and flush; ``beams`` (:class:`clsas.physics.beam.Beams`
        of the stop's measurements) where the file was created with beams."""
        f, m = self._f, self.n_mics
        if (beams is not None) != self.has_beams:
            raise ValueError(f"beams: {self.path} was created {'with' if self.has_beams else 'without'} transducer "
                             f"beams, and stop {stop} comes {'with' if beams is not None else 'without'} them")
        n = f["signals"].shape[0]
        rows = {
            "tx_positions": np.repeat(np.asarray(tx_m, float)[None, :], m, 0),
            "rx_positions": np.asarray(rx_m, float).reshape(m, 3),
            "t0_s": np.full(m, t0_s),
            "stage_positions": np.repeat(np.asarray(stage_m, float)[None, :], m, 0),
            "timestamps": np.full(m, timestamp),
            "loopback": np.repeat(np.asarray(loopback, np.float32)[None, :], m, 0),
            "stop_index": np.full(m, stop, np.int32),
        }
        if beams is not None:
            if beams.n_meas != m:
                raise ValueError(f"beams: {beams.n_meas} boresights for a stop of {m} measurements")
            rows["beams/tx_boresight"] = beams.tx_boresight
            rows["beams/rx_boresight"] = beams.rx_boresight
        for name, val in rows.items():
            f[name].resize(n + m, axis=0)
            f[name][n:] = val
        f["signals"].resize(n + m, axis=0)  # last: a stop is in the file once its signals are
        f["signals"][n:] = np.asarray(signals, np.float32).reshape(m, -1)
        f.flush()

    def close(self, complete: bool = False) -> None:
        if self._f.id.valid:
            if complete:
                self._f.attrs["complete"] = True
            self._f.flush()
            self._f.close()
