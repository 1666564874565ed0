"""The Profiles type: complex baseband range profiles, one row per measurement.

What pulse compression (:func:`clsas.compress`) and the per-profile sparse methods produce and
every image formation consumes; immutable once built.

Profiles compressed on OpenCL stay on the device (``on_device``, a :class:`clsas.cl.DeviceRows`)
and reach the host only when something there asks for ``data``: the field is a descriptor
(:class:`_HostData`, a descriptor-typed dataclass field) that reads the rows on first access and
keeps the array, so that backprojection on the same device, which reads the rows there
(:meth:`Profiles.device_rows`), costs no read back at all.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .. import validate as v
from ..physics.signals import analytic

__all__ = ["Profiles", "center_frequency"]


class _HostData:
    """The ``data`` field of :class:`Profiles`: the host array, given or read from the device.

    A descriptor-typed dataclass field: the value given to the constructor is stored (in the
    instance's ``_data``); an array is returned as it is; None (profiles whose rows are on the
    device, ``on_device``) is resolved on first access to the rows' host copy
    (:attr:`clsas.cl.DeviceRows.host`: read once, read-only, the same array for every holder of
    those rows) and stored. Reading the attribute is the only way to the host copy, so
    everything that uses ``data`` (``dataclasses.replace`` without ``data``, ``==``, ``repr``,
    pickling) sees the array; :meth:`Profiles.device_rows` and ``n_meas``/``n_lags`` do not read.
    """

    def __get__(self, obj: Profiles | None, owner: type | None = None) -> np.ndarray:
        if obj is None:
            raise AttributeError("data")  # the class has no default: the field is required
        data = obj.__dict__["_data"]
        if data is None:
            data = obj.on_device.host
            obj.__dict__["_data"] = data
        return data

    def __set__(self, obj: Profiles, value: np.ndarray | None) -> None:
        # only the dataclass __init__ gets here (the frozen class refuses assignments)
        obj.__dict__["_data"] = value


@dataclass(frozen=True)
class Profiles:
    """Complex baseband range profiles, one row per measurement.

    Sample ``k`` of row ``m`` is the echo at delay ``tau0_s[m] + k * dtau_s`` after the
    transmit start, rotated to baseband by ``exp(-j 2 pi fc_hz tau)``.

    Parameters
    ----------
    data : numpy.ndarray or None
        (n_meas, n_lags) complex baseband profiles. None: the rows ``on_device`` hold them, and
        ``data`` is read from there the first time it is asked for (then kept).
    tau0_s : numpy.ndarray
        (n_meas,) delay of each row's first sample after the transmit start, s.
    dtau_s : float
        Lag step, s.
    fc_hz : float
        Carrier the profiles were rotated to baseband by, Hz.
    method, backend : str
        The compression (``"matched"``, ``"fmcw"``, a sparse method) and where it ran.
    tx_positions, rx_positions : numpy.ndarray, optional
        (n_meas, 3) positions, metres (from the dataset).
    c_mps : float or numpy.ndarray, optional
        Speed of sound, m/s, scalar or per measurement.
    timings_s : dict
        Seconds per stage.
    device : str
        The device's name.
    beams : clsas.physics.beam.Beams, optional
        The transducers' beams (from the dataset); None: omnidirectional.
    on_device : clsas.cl.DeviceRows, optional
        ``data`` as the OpenCL compression left it on the device, which backprojection on the
        same device reads there (:meth:`device_rows`: while it still holds ``data``); None: on
        the host only.

    Examples
    --------
    >>> import numpy as np
    >>> import clsas
    >>> fs = 96e3
    >>> chirp = clsas.lfm_chirp(20e3, 30e3, 5e-3, fs, taper=0.1)
    >>> scene = clsas.Scene(np.array([[0.0, 0.0, 1.0]]))
    >>> data = clsas.simulate(scene, clsas.raster_aperture(8, 8, 0.3, 0.3), chirp, fs)
    >>> grid = clsas.VoxelGrid.from_bounds((-0.1, 0.1), (-0.1, 0.1), (0.9, 1.1), 0.01)
    >>> profiles = clsas.compress(data, backend="numpy")
    >>> profiles.data.shape[0], profiles.method
    (64, 'matched')
    """

    data: np.ndarray = _HostData()  # type: ignore[assignment]  # None given: read from on_device when asked
    tau0_s: np.ndarray
    dtau_s: float
    fc_hz: float
    method: str
    backend: str
    tx_positions: np.ndarray | None = None
    rx_positions: np.ndarray | None = None
    c_mps: float | np.ndarray | None = None  # one per measurement where the air changed
    timings_s: dict = field(default_factory=dict)
    device: str = ""
    beams: Any = None  # clsas.physics.beam.Beams of the dataset (None: omnidirectional)
    # clsas.cl.DeviceRows: ``data`` as the OpenCL compression left it on the device (None: host only)
    on_device: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self._held() is None and self.on_device is None:
            raise ValueError("data: an (n_meas, n_lags) array is needed, or the device rows holding it (on_device)")

    def __getstate__(self) -> dict:
        """The fields for pickling, ``data`` as its host array (read from the device here if it
        was not yet): another process cannot reach the device rows."""
        return {**self.__dict__, "_data": self.data}

    @property
    def n_meas(self) -> int:
        return self._shape()[0]

    @property
    def n_lags(self) -> int:
        return self._shape()[1]

    def _held(self) -> np.ndarray | None:
        """``data`` as given or read so far, without reading it: None while it is on the device only."""
        return self.__dict__["_data"]

    def _shape(self) -> tuple[int, ...]:
        """``data``'s shape, without reading it where it is still on the device."""
        data = self._held()
        return (self.on_device.n_rows, self.on_device.n_cols) if data is None else data.shape

    def device_rows(self) -> Any:
        """The rows on the device that hold ``data`` (:class:`clsas.cl.DeviceRows`, which a kernel
        on their queue may read instead of ``data``), or None: none were left there, the plan
        that wrote them has overwritten them since, or ``data`` is another array than theirs
        (given to ``dataclasses.replace``). Reads nothing from the device. The rows were
        computed on the device from checked (finite) recordings, so a kernel that reads them
        needs no host check of ``data``."""
        rows = self.on_device
        if rows is None:
            return None
        return rows if rows.valid(rows.queue, self._held()) else None

    def with_fields(self, **changes: Any) -> Profiles:
        """``dataclasses.replace(self, **changes)``, except that ``data`` still on the device stays
        there (unread) where ``changes`` do not give it; ``dataclasses.replace`` reads it (it
        copies every field through its attribute)."""
        if "data" not in changes and self._held() is None:
            # without the rows (on_device=None given) the data must come along: read it here
            changes["data"] = self.data if changes.get("on_device", self.on_device) is None else None
        return replace(self, **changes)

    def delays_s(self, m: int = 0) -> np.ndarray:
        """Delays of row ``m``'s samples after the transmit start, s."""
        return self.tau0_s[m] + self.dtau_s * np.arange(self.n_lags)

    @classmethod
    def from_range_profiles(
        cls,
        data: np.ndarray,
        *,
        tau0_s: float | np.ndarray,
        dtau_s: float,
        tx_positions: np.ndarray,
        rx_positions: np.ndarray,
        c_mps: float | np.ndarray,
        fc_hz: float | None = None,
        baseband: bool = False,
        method: str = "external",
    ) -> Profiles:
        """Range profiles computed elsewhere (pulse-compressed, deconvolved, ...), ready for
        :func:`clsas.backproject`.

        Parameters
        ----------
        data : (n_meas, n_lags) array
            Real profiles (the matched-filter or deconvolution output at the carrier: their
            analytic signal is taken), complex analytic profiles (``baseband=False``), or
            complex baseband profiles (``baseband=True``, already rotated by
            ``exp(-j 2 pi fc tau)``). NaN or Inf is refused.
        tau0_s : float or (n_meas,) array
            Delay after the transmit start of each row's sample 0, s (a group delay already
            removed); may be negative.
        dtau_s : float
            Delay step between samples, s (``1 / fs`` for profiles at the recording's rate).
        tx_positions, rx_positions : (n_meas, 3) arrays, m
        c_mps : float or (n_meas,) array
            Speed of sound, one per measurement where the air changed.
        fc_hz : float, optional
            Carrier (the rotation frequency to baseband); default the power-weighted mean
            frequency of ``data`` (give it for baseband data, where it cannot be measured).
        baseband : bool
            ``data`` is complex baseband already.
        method : str
            A label for the image's provenance.
        """
        arr = v.array("data", data, ndim=2, dtype=None, allow_complex=True)
        n, k = arr.shape
        if k < 2:
            raise ValueError(f"data must have at least 2 samples per profile, got shape {arr.shape}")
        dtau = v.positive("dtau_s", dtau_s)
        tau0 = np.broadcast_to(np.asarray(tau0_s, float), (n,)).copy()
        v.array("tau0_s", tau0)
        tx = v.array("tx_positions", tx_positions, shape=(n, 3))
        rx = v.array("rx_positions", rx_positions, shape=(n, 3))
        c = v.speeds("c_mps", c_mps, n)
        if baseband and not np.iscomplexobj(arr):
            raise ValueError("baseband=True needs complex data (real data is at the carrier)")
        if baseband and fc_hz is None:
            raise ValueError("fc_hz is required for baseband data (the carrier cannot be measured from it)")
        if not np.iscomplexobj(arr):
            arr = analytic(np.asarray(arr, np.float64))
        if fc_hz is None:
            spec = np.abs(np.fft.fft(arr, axis=1)) ** 2
            f = np.fft.fftfreq(k, dtau)
            fc_hz = float((spec.sum(axis=0) * f).sum() / max(spec.sum(), 1e-300))
        fc = v.non_negative("fc_hz", fc_hz)
        if not baseband and fc >= 0.5 / dtau:  # baseband rows need only the band's width, not the carrier
            raise ValueError(f"fc_hz={fc:g} is at or above the profiles' Nyquist frequency {0.5 / dtau:g}")
        if not baseband:
            tau = tau0[:, None] + dtau * np.arange(k)[None, :]
            arr = arr * np.exp(-2j * np.pi * ((fc * tau) % 1.0))
        return cls(np.asarray(arr, np.complex128), tau0, dtau, fc, method, "numpy", tx_positions=tx,
                   rx_positions=rx, c_mps=c)

    def arrays(self, dtype=None) -> tuple:
        """The fields a formation reads, each checked (finite, the right shape), naming the field.

        Returns ``(data, tau0_s, dtau_s, fc_hz, tx_positions, rx_positions, c_mps)`` with ``c_mps``
        one speed per measurement; ``dtype``: the data's dtype (default as stored). Profiles
        without positions or speed of sound (range profiles alone) are refused.
        """
        n = self.n_meas
        if self.tx_positions is None or self.rx_positions is None or self.c_mps is None:
            raise ValueError("profiles: positions and speed of sound are needed (compress a Dataset, or give them to "
                             "Profiles.from_range_profiles)")
        tx = v.array("profiles.tx_positions", self.tx_positions, shape=(n, 3))
        rx = v.array("profiles.rx_positions", self.rx_positions, shape=(n, 3))
        c = np.broadcast_to(np.asarray(v.speeds("profiles.c_mps", self.c_mps, n), float), (n,)).copy()
        data = v.array("profiles.data", self.data, ndim=2, dtype=dtype, allow_complex=True)
        if data.shape[1] < 2:
            raise ValueError(f"profiles.data must have at least 2 samples per profile, got shape {data.shape}")
        tau0 = v.array("profiles.tau0_s", self.tau0_s, shape=(n,))
        dtau = v.positive("profiles.dtau_s", self.dtau_s)
        fc = v.non_negative("profiles.fc_hz", self.fc_hz)
        return data, tau0, dtau, fc, tx, rx, c

    def carrier(self) -> np.ndarray:
        """Profiles with the carrier restored: the analytic matched-filter output."""
        tau = self.tau0_s[:, None] + self.dtau_s * np.arange(self.n_lags)[None, :]
        return self.data * np.exp(2j * np.pi * self.fc_hz * tau)


def center_frequency(waveform: np.ndarray, fs_hz: float) -> float:
    """Power-weighted mean frequency of ``waveform``, Hz."""
    spec = np.abs(np.fft.rfft(waveform)) ** 2
    f = np.fft.rfftfreq(len(waveform), 1 / fs_hz)
    total = spec.sum()
    if total <= 0:
        raise ValueError("waveform is all zeros")
    return float((f * spec).sum() / total)
