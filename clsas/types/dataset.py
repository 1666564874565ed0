"""The Dataset type and its HDF5 file (one file per scan)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import validate as v
from ..physics.beam import Beams
from ..physics.sound import ASSUMED_HUMIDITY_PCT, speed_of_sound, speed_of_sound_source

__all__ = ["Dataset", "load", "FORMAT_VERSION", "UNITS", "json_default", "AIR_FALLBACK", "SOUND_SPEED_STEP"]

log = logging.getLogger(__name__)

# the provenance entry of a dataset that was given neither c_mps nor temperature_c
AIR_FALLBACK = {"step": "assumed_air", "c_mps_source": "speed of sound in air at 20 degC (no c_mps, no temperature_c)"}

# the provenance step of a dataset whose c_mps came from its temperature and humidity
SOUND_SPEED_STEP = "speed_of_sound"

FORMAT_VERSION = 1

# the unit written on each array of the file (its "units" attribute)
UNITS = {
    "signals": "arbitrary (microphone output)",
    "tx_positions": "m",
    "rx_positions": "m",
    "waveform": "arbitrary (speaker drive)",
    "t0_s": "s",
    "stage_positions": "m",
    "timestamps": "s since the Unix epoch",
    "loopback": "arbitrary (loopback input)",
    "background": "arbitrary (microphone output, empty scene)",
    "c_mps": "m/s",
    "temperature_c": "degC",
    "humidity_pct": "percent relative humidity",
}

# per-measurement air: stored as an array when it varies, as an attribute when it does not
_AIR = ("c_mps", "temperature_c", "humidity_pct")


@dataclass
class Dataset:
    """A scan: one recording per bistatic (speaker, microphone) pair.

    Attributes
    ----------
    signals : (n_meas, n_samples) float array
    tx_positions, rx_positions : (n_meas, 3) float64, metres
    fs_hz : sample rate, Hz
    waveform : (n_wave,) transmitted signal at ``fs_hz``
    t0_s : (n_meas,) time of sample 0 after the transmit start (latency included), s; may be
        negative (a transducer group delay removed, see :func:`clsas.preprocess.remove_delay`)
    c_mps : float or (n_meas,) array
        Speed of sound, m/s; default from ``temperature_c`` and ``humidity_pct``
        (:func:`clsas.speed_of_sound`, humid air after Cramer 1993), the formula and humidity
        recorded in the provenance (a ``"speed_of_sound"`` step, e.g. ``c_mps_source =
        "cramer1993 at 50 % RH (assumed: not logged)"``). Given neither ``c_mps`` nor
        ``temperature_c``, the dataset takes air at 20 °C (343.8 m/s at 50 % RH), logs a warning
        naming ``c_mps`` and records :data:`AIR_FALLBACK` in its provenance (a water scan must
        give ``c_mps``). An array gives each measurement its own (air that changes during a
        scan); compression, backprojection and every reconstruction method use it per measurement.
    temperature_c, humidity_pct : float or (n_meas,) array
        Air, as logged; a per-measurement temperature or humidity gives a per-measurement
        ``c_mps``. ``humidity_pct=None`` (the default): not logged, 50 % assumed
        (:data:`clsas.physics.sound.ASSUMED_HUMIDITY_PCT`: indoor air is 30-60 % RH, and the dry-air
        formula is biased low for all of it); the attribute then holds 50.0 and the provenance
        says it was assumed.
    background : (n_meas, n_samples) array, optional
        Recordings of the empty scene taken at the same stops (for background subtraction).
    chirp : chirp parameters (stored as attributes)
    config : the scan or scene configuration as TOML text
    provenance : list of dict
        What made these recordings what they are, oldest first: an importer, each
        preprocessing step with its parameters (stored as JSON in the file).
    beams : clsas.physics.beam.Beams, optional
        The speaker's and microphone's beams and boresights per measurement (stored in the
        file's ``beams`` group); None: omnidirectional (files without the group load as such).
    truth : dict
        What a simulation knows and the dataset does not state (true positions, air, delays;
        see :func:`clsas.simulate`), for scoring estimates such as :func:`clsas.autofocus`.
        Values are numbers, strings or arrays; arrays whose first axis has ``n_meas`` rows
        are per measurement (``subset`` selects them). Stored in the file's ``truth`` group.

    Examples
    --------
    Recordings made elsewhere become a Dataset from their arrays (SI units; one bistatic pair
    per row):

    >>> import numpy as np
    >>> import clsas
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs)
    >>> tx = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    >>> ds = clsas.Dataset(np.zeros((2, 2000)), tx, tx + [0.04, 0.0, 0.0], fs, chirp, temperature_c=21.0)
    >>> _ = ds.save("scan.h5")                 # returns the path written
    >>> clsas.load("scan.h5").signals.shape
    (2, 2000)
    """

    signals: np.ndarray
    tx_positions: np.ndarray
    rx_positions: np.ndarray
    fs_hz: float
    waveform: np.ndarray
    t0_s: np.ndarray | None = None
    c_mps: float | np.ndarray | None = None
    temperature_c: float | np.ndarray | None = None
    humidity_pct: float | np.ndarray | None = None
    stage_positions: np.ndarray | None = None
    timestamps: np.ndarray | None = None
    loopback: np.ndarray | None = None
    chirp: dict = field(default_factory=dict)
    config: str = ""
    background: np.ndarray | None = None
    provenance: list = field(default_factory=list)
    truth: dict = field(default_factory=dict)
    beams: Beams | None = None

    def __post_init__(self) -> None:
        self.fs_hz = v.sampling_rate("fs_hz", self.fs_hz)
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
        if not isinstance(self.provenance, list) or not all(isinstance(p, dict) for p in self.provenance):
            raise TypeError("provenance must be a list of dicts (one per processing step)")
        assumed = self.humidity_pct is None
        self.humidity_pct = _per_meas("humidity_pct", ASSUMED_HUMIDITY_PCT if assumed else self.humidity_pct, n)
        h = np.asarray(self.humidity_pct)
        if np.any((h < 0) | (h > 100)):
            raise ValueError(f"humidity_pct must be in [0, 100], got {h.min():g} to {h.max():g}")
        if self.temperature_c is None:
            if self.c_mps is None and AIR_FALLBACK not in self.provenance:
                log.warning("Dataset: neither c_mps nor temperature_c given; assuming air at 20 degC, "
                            "c_mps = %.1f m/s (give c_mps for any other medium, e.g. 1480 for water)",
                            np.mean(speed_of_sound(20.0, self.humidity_pct)))
                self.provenance = [*self.provenance, dict(AIR_FALLBACK)]
            self.temperature_c = 20.0
        self.temperature_c = _per_meas("temperature_c", self.temperature_c, n)
        if self.c_mps is None:
            self.c_mps = speed_of_sound(self.temperature_c, self.humidity_pct)
            self.provenance = _with_sound_speed_step(self.provenance, self.humidity_pct, assumed)
        self.c_mps = _per_meas("c_mps", self.c_mps, n)
        if np.any(np.asarray(self.c_mps) <= 0):
            raise ValueError(f"c_mps must be > 0, got min {np.min(self.c_mps):g}")
        if self.background is not None:
            self.background = v.array("background", self.background, shape=sig.shape, dtype=None)
        if not isinstance(self.truth, dict) or not all(isinstance(k, str) for k in self.truth):
            raise TypeError("truth must be a dict with str keys")
        for name, shape in (("stage_positions", (n, 3)), ("timestamps", (n,))):
            val = getattr(self, name)
            if val is not None:
                setattr(self, name, v.array(name, val, shape=shape))
        if self.loopback is not None:
            self.loopback = v.array("loopback", self.loopback, ndim=2, dtype=None)
        if self.beams is not None:
            if not isinstance(self.beams, Beams):
                raise TypeError(f"beams must be clsas.physics.beam.Beams or None, got {type(self.beams).__name__}")
            if self.beams.n_meas != n:
                raise ValueError(f"beams must have n_meas={n} boresights, got {self.beams.n_meas}")

    @property
    def n_meas(self) -> int:
        return self.signals.shape[0]

    @property
    def n_samples(self) -> int:
        return self.signals.shape[1]

    @property
    def c_per_meas(self) -> np.ndarray:
        """(n_meas,) speed of sound of each measurement, m/s (a copy)."""
        return np.broadcast_to(np.asarray(self.c_mps, float), (self.n_meas,)).copy()

    @property
    def air_varies(self) -> bool:
        """Whether the speed of sound differs between measurements."""
        return np.ndim(self.c_mps) > 0

    def replace(self, **changes) -> Dataset:
        """A copy with some fields replaced (arrays not named are shared, not copied).

        A new ``temperature_c`` or ``humidity_pct`` without a ``c_mps`` gives a new ``c_mps``
        from the new air (a humidity that was assumed stays assumed)."""
        fields = {k: getattr(self, k) for k in self.__dataclass_fields__}
        if ("temperature_c" in changes or "humidity_pct" in changes) and "c_mps" not in changes:
            fields["c_mps"] = None  # follow the new air
            if "humidity_pct" not in changes and _humidity_assumed(self.provenance):
                fields["humidity_pct"] = None  # still not logged
        fields.update(changes)
        fields["chirp"] = dict(fields["chirp"])
        fields["provenance"] = list(fields["provenance"])
        fields["truth"] = dict(fields["truth"])
        return Dataset(**fields)

    def subset(self, index: slice | np.ndarray) -> Dataset:
        """A dataset holding only the measurements selected by ``index``."""
        opt = {
            k: (None if getattr(self, k) is None else getattr(self, k)[index])
            for k in ("stage_positions", "timestamps", "loopback", "background")
        }
        air = {k: (getattr(self, k)[index] if np.ndim(getattr(self, k)) else getattr(self, k)) for k in _AIR}
        truth = {k: (val[index] if isinstance(val, np.ndarray) and val.ndim and len(val) == self.n_meas else val)
                 for k, val in self.truth.items()}
        return Dataset(
            self.signals[index], self.tx_positions[index], self.rx_positions[index], self.fs_hz,
            self.waveform, self.t0_s[index], chirp=dict(self.chirp), config=self.config,
            provenance=list(self.provenance), truth=truth, **air, **opt,
            beams=None if self.beams is None else self.beams.subset(index),
        )

    def save(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """Write the dataset to an HDF5 file (see the guide, docs/guide/files.md, "Dataset file").

        An existing file is refused (``FileExistsError`` naming it) unless ``overwrite=True``."""
        import h5py

        from ..version import __version__

        path = refuse_existing(path, overwrite, "Dataset.save")
        with h5py.File(path, "w") as f:
            _write_arrays(f, self)
            f.attrs.update(_attrs(self, __version__))
            _write_truth(f, self.truth)
            _write_beams(f, self.beams)
        return path


def refuse_existing(path: str | Path, overwrite: bool, where: str) -> Path:
    """``path`` as a Path; ``FileExistsError`` naming it where it exists and ``overwrite`` is False."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists ({where}: pass overwrite=True to replace it)")
    return path


def _humidity_assumed(provenance: list) -> bool:
    """Whether the latest speed-of-sound step of ``provenance`` assumed the humidity."""
    steps = [p for p in provenance if p.get("step") == SOUND_SPEED_STEP]
    return bool(steps and steps[-1].get("humidity_assumed"))


def _with_sound_speed_step(provenance: list, humidity_pct, assumed: bool) -> list:
    """``provenance`` with a step saying how ``c_mps`` came from the temperature (unless its
    latest step says so already)."""
    h = np.asarray(humidity_pct, float)
    step = {"step": SOUND_SPEED_STEP, "c_mps_source": speed_of_sound_source(humidity_pct, assumed),
            "formula": "cramer1993 humid/dry ratio x 331.3 sqrt(1 + T/273.15)",
            "humidity_pct": float(h) if h.ndim == 0 else "per measurement", "humidity_assumed": assumed}
    return provenance if provenance and provenance[-1] == step else [*provenance, step]


def _per_meas(name: str, value, n: int) -> float | np.ndarray:
    """A float, or an (n,) array when the value differs between measurements."""
    if np.ndim(value) == 0:
        return v.finite(name, value)
    arr = v.array(name, value, shape=(n,))
    return float(arr[0]) if np.all(arr == arr[0]) else arr


def _write_truth(f, truth: dict) -> None:
    """The ``truth`` group: arrays as datasets, everything else as attributes (JSON if not a
    number or a string)."""
    if not truth:
        return
    g = f.create_group("truth")
    g.attrs["about"] = "what the simulation knows and the dataset does not state (for scoring estimates)"
    for k, val in truth.items():
        if isinstance(val, np.ndarray):
            g.create_dataset(k, data=val)
        elif isinstance(val, int | float | str | np.generic) and not isinstance(val, bool):
            g.attrs[k] = val
        else:
            g.attrs[f"{k}__json"] = json.dumps(val, default=json_default)


def _write_beams(f, beams: Beams | None) -> None:
    """The ``beams`` group: boresights per measurement and each transducer's model as JSON."""
    if beams is None:
        return
    g = f.create_group("beams")
    g.attrs["about"] = "transducer directivity (clsas.physics.beam): one-way patterns and boresights"
    for k, val in beams.specs().items():
        g.attrs[f"{k}_json"] = json.dumps(val)
    for k in ("tx_boresight", "rx_boresight"):
        d = g.create_dataset(k, data=getattr(beams, k))
        d.attrs["units"] = "1 (unit vector)"


def _read_beams(f, n: int) -> Beams | None:
    if "beams" not in f:
        return None
    g = f["beams"]
    return Beams(json.loads(g.attrs["speaker_json"]), json.loads(g.attrs["microphone_json"]),
                 g["tx_boresight"][:n], g["rx_boresight"][:n], n)


def _read_truth(f) -> dict:
    if "truth" not in f:
        return {}
    g = f["truth"]
    out: dict = {k: g[k][()] for k in g}
    for k, val in g.attrs.items():
        if k == "about":
            continue
        if k.endswith("__json"):
            out[k[:-6]] = json.loads(val)
        else:
            out[k] = val.item() if isinstance(val, np.generic) else val
    return out


def _attrs(ds: Dataset, version: str) -> dict:
    attrs = {
        "format_version": FORMAT_VERSION,
        "clsas_version": version,
        "fs_hz": ds.fs_hz,
        "config_toml": ds.config,
        "chirp_json": json.dumps(ds.chirp),
        "provenance_json": json.dumps(ds.provenance, default=json_default),
    }
    for k in _AIR:  # per-measurement values are arrays (see _write_arrays); the mean for readers
        attrs[k] = float(np.mean(getattr(ds, k)))
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
        "background": None if ds.background is None else ds.background.astype(np.float32),
    }
    for k in _AIR:
        if np.ndim(getattr(ds, k)):
            arrays[k] = getattr(ds, k)
    written = {}
    for name, arr in arrays.items():
        if arr is None:
            continue
        d = f.create_dataset(name, data=arr)
        d.attrs["units"] = UNITS[name]
        written[name] = d
    _attach_scales(f, written, ds)


# the named dimensions of each array (HDF5 dimension scales, so that netCDF readers such as
# xarray's h5netcdf engine see named dimensions instead of phony_dim_*)
_DIMS = {
    "signals": ("measurement", "sample"),
    "background": ("measurement", "sample"),
    "tx_positions": ("measurement", "xyz"),
    "rx_positions": ("measurement", "xyz"),
    "stage_positions": ("measurement", "xyz"),
    "t0_s": ("measurement",),
    "timestamps": ("measurement",),
    "c_mps": ("measurement",),
    "temperature_c": ("measurement",),
    "humidity_pct": ("measurement",),
    "waveform": ("waveform_sample",),
    "loopback": ("loopback_measurement", "loopback_sample"),
}


def _attach_scales(f, written: dict, ds: Dataset) -> None:
    """Create one dimension-scale dataset per named dimension and attach it to the arrays."""
    import h5py

    lengths: dict[str, int] = {}
    for name, d in written.items():
        for dim, n in zip(_DIMS.get(name, ()), d.shape, strict=False):
            lengths.setdefault(dim, n)
    scales = {}
    for dim, n in lengths.items():
        if dim == "xyz":
            s = f.create_dataset(dim, data=["x", "y", "z"], dtype=h5py.string_dtype())
            s.attrs["long_name"] = "position component"
        else:
            s = f.create_dataset(dim, data=np.arange(n, dtype=np.int64))
            s.attrs["long_name"] = f"{dim.replace('_', ' ')} index"
        s.attrs["units"] = "1"
        s.make_scale(dim)
        scales[dim] = s
    for name, d in written.items():
        for i, dim in enumerate(_DIMS.get(name, ())[: d.ndim]):
            if d.shape[i] == lengths[dim]:
                d.dims[i].attach_scale(scales[dim])


def load(path: str | Path) -> Dataset:
    """Read a dataset written by :meth:`Dataset.save` (or by ``clsas acquire``).

    Parameters
    ----------
    path : str or pathlib.Path
        The HDF5 file.

    Returns
    -------
    Dataset

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> tx = np.zeros((1, 3))
    >>> _ = clsas.Dataset(np.zeros((1, 100)), tx, tx + 0.04, 96e3, np.ones(10)).save("one.h5")
    >>> clsas.load("one.h5").fs_hz
    96000.0
    """
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no dataset file at {path}")
    with h5py.File(path, "r") as f:
        _check_format(f, path)
        return _read_dataset(f)


def _check_format(f, path: Path) -> None:
    """Refuse a file that is not a clsas dataset, or one of a newer format than this clsas reads."""
    if "signals" not in f:
        raise ValueError(f"{path} is not a clsas dataset (no 'signals' array)")
    version = int(f.attrs.get("format_version", 0))
    if version > FORMAT_VERSION:
        raise ValueError(f"{path} has format_version {version}; this clsas reads up to {FORMAT_VERSION}")


def _read_dataset(f) -> Dataset:
    """The Dataset in an open dataset file (arrays a scan in progress grew ahead of ``signals`` trimmed to it)."""
    a = f.attrs
    n = f["signals"].shape[0]

    def get(name):
        return f[name][()] if name in f else None

    def trim(x):
        return None if x is None else x[:n]

    air = {k: trim(get(k)) if k in f else (float(a[k]) if k in a else None) for k in _AIR}
    air = {k: val for k, val in air.items() if val is not None}
    return Dataset(
        signals=f["signals"][()],
        tx_positions=trim(get("tx_positions")),
        rx_positions=trim(get("rx_positions")),
        fs_hz=float(a["fs_hz"]),
        waveform=get("waveform"),
        t0_s=trim(get("t0_s")),
        **air,
        stage_positions=trim(get("stage_positions")),
        timestamps=trim(get("timestamps")),
        loopback=trim(get("loopback")),
        background=trim(get("background")),
        chirp=json.loads(a.get("chirp_json", "{}")),
        config=str(a.get("config_toml", "")),
        provenance=json.loads(a.get("provenance_json", "[]")),
        truth={k: (trim(val) if isinstance(val, np.ndarray) and val.ndim and len(val) > n else val)
               for k, val in _read_truth(f).items()},
        beams=_read_beams(f, n),
    )


def json_default(obj):
    """``json.dumps``'s ``default=`` for the provenance: NumPy scalars and arrays as numbers and
    lists, anything else as its ``str``."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


