"""The Dataset type and its HDF5 file (one file per scan)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import _validate as v
from .physics import speed_of_sound

__all__ = ["Dataset", "load", "FORMAT_VERSION"]

FORMAT_VERSION = 1

_UNITS = {
    "signals": "arbitrary (microphone output)",
    "tx_positions": "m",
    "rx_positions": "m",
    "waveform": "arbitrary (speaker drive)",
    "t0_s": "s",
    "stage_positions": "m",
    "timestamps": "s since the Unix epoch",
    "loopback": "arbitrary (loopback input)",
}


@dataclass
class Dataset:
    """A scan: one recording per bistatic (speaker, microphone) pair.

    Attributes
    ----------
    signals : (n_meas, n_samples) float array
    tx_positions, rx_positions : (n_meas, 3) float64, metres
    fs_hz : sample rate, Hz
    waveform : (n_wave,) transmitted signal at ``fs_hz``
    t0_s : (n_meas,) time of sample 0 after the transmit start (latency included), s
    c_mps : speed of sound; default from ``temperature_c``
    temperature_c, humidity_pct : air
    chirp : chirp parameters (stored as attributes)
    config : the scan or scene configuration as TOML text
    """

    signals: np.ndarray
    tx_positions: np.ndarray
    rx_positions: np.ndarray
    fs_hz: float
    waveform: np.ndarray
    t0_s: np.ndarray | None = None
    c_mps: float | None = None
    temperature_c: float = 20.0
    humidity_pct: float = 50.0
    stage_positions: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    loopback: np.ndarray | None = None
    chirp: dict = field(default_factory=dict)
    config: str = ""

    def __post_init__(self) -> None:
        self.fs_hz = v.positive("fs_hz", self.fs_hz)
        sig = v.array("signals", self.signals, ndim=2, dtype=None)
        if not np.issubdtype(sig.dtype, np.floating):
            sig = sig.astype(np.float64)
        self.signals = sig
        n = sig.shape[0]
        self.tx_positions = v.array("tx_positions", self.tx_positions, shape=(n, 3))
        self.rx_positions = v.array("rx_positions", self.rx_positions, shape=(n, 3))
        self.waveform = v.array("waveform", self.waveform, ndim=1)
        self.t0_s = (
            np.zeros(n)
            if self.t0_s is None
            else v.array("t0_s", np.broadcast_to(np.asarray(self.t0_s, float), (n,)).copy())
        )
        if self.c_mps is None:
            self.c_mps = speed_of_sound(self.temperature_c)
        self.c_mps = v.positive("c_mps", self.c_mps)
        for name, shape in (("stage_positions", (n, 3)), ("timestamps", (n,))):
            val = getattr(self, name)
            if val is not None:
                setattr(self, name, v.array(name, val, shape=shape))
        if self.loopback is not None:
            self.loopback = v.array("loopback", self.loopback, ndim=2, dtype=None)

    @property
    def n_meas(self) -> int:
        return self.signals.shape[0]

    @property
    def n_samples(self) -> int:
        return self.signals.shape[1]

    def subset(self, index: slice | np.ndarray) -> Dataset:
        """A dataset holding only the measurements selected by ``index``."""
        opt = {
            k: (None if getattr(self, k) is None else getattr(self, k)[index])
            for k in ("stage_positions", "timestamps", "loopback")
        }
        return Dataset(
            self.signals[index], self.tx_positions[index], self.rx_positions[index], self.fs_hz,
            self.waveform, self.t0_s[index], self.c_mps, self.temperature_c, self.humidity_pct,
            chirp=dict(self.chirp), config=self.config, **opt,
        )

    def save(self, path: str | Path) -> Path:
        """Write the dataset to an HDF5 file (see README, "Dataset file")."""
        import h5py

        from . import __version__

        path = Path(path)
        with h5py.File(path, "w") as f:
            _write_arrays(f, self)
            f.attrs.update(_attrs(self, __version__))
        return path


def _attrs(ds: Dataset, version: str) -> dict:
    attrs = {
        "format_version": FORMAT_VERSION,
        "clsas_version": version,
        "fs_hz": ds.fs_hz,
        "c_mps": ds.c_mps,
        "temperature_c": ds.temperature_c,
        "humidity_pct": ds.humidity_pct,
        "config_toml": ds.config,
        "chirp_json": json.dumps(ds.chirp),
    }
    for k, val in ds.chirp.items():
        if isinstance(val, int | float | str):
            attrs[f"chirp_{k}"] = val
    return attrs


def _write_arrays(f, ds: Dataset) -> None:
    arrays = {
        "signals": ds.signals.astype(np.float32),
        "tx_positions": ds.tx_positions,
        "rx_positions": ds.rx_positions,
        "waveform": ds.waveform,
        "t0_s": ds.t0_s,
        "stage_positions": ds.stage_positions,
        "timestamps": ds.timestamps,
        "loopback": ds.loopback,
    }
    for name, arr in arrays.items():
        if arr is None:
            continue
        d = f.create_dataset(name, data=arr)
        d.attrs["units"] = _UNITS[name]


def load(path: str | Path) -> Dataset:
    """Read a dataset written by :meth:`Dataset.save` (or by ``clsas acquire``)."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no dataset file at {path}")
    with h5py.File(path, "r") as f:
        if "signals" not in f:
            raise ValueError(f"{path} is not a clsas dataset (no 'signals' array)")
        a = f.attrs
        version = int(a.get("format_version", 0))
        if version > FORMAT_VERSION:
            raise ValueError(
                f"{path} has format_version {version}; this clsas reads up to {FORMAT_VERSION}"
            )

        def get(name):
            return f[name][()] if name in f else None

        n = f["signals"].shape[0]
        # a scan in progress may have grown its arrays ahead of 'signals': trim to it
        def trim(x):
            return None if x is None else x[:n]

        return Dataset(
            signals=f["signals"][()],
            tx_positions=trim(get("tx_positions")),
            rx_positions=trim(get("rx_positions")),
            fs_hz=float(a["fs_hz"]),
            waveform=get("waveform"),
            t0_s=trim(get("t0_s")),
            c_mps=float(a["c_mps"]) if "c_mps" in a else None,
            temperature_c=float(a.get("temperature_c", 20.0)),
            humidity_pct=float(a.get("humidity_pct", 50.0)),
            stage_positions=trim(get("stage_positions")),
            timestamps=trim(get("timestamps")),
            loopback=trim(get("loopback")),
            chirp=json.loads(a.get("chirp_json", "{}")),
            config=str(a.get("config_toml", "")),
        )
