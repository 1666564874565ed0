"""The imaging operator: voxels -> range profiles (forward projection, optionally convolved with the
compressed pulse) and its adjoint (correlation with the pulse, then backprojection), as a
:class:`scipy.sparse.linalg.LinearOperator` that scipy's and PyLops' solvers accept.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from scipy.signal import fftconvolve
from scipy.sparse.linalg import LinearOperator

from .. import cl as _cl
from .. import validate as v
from ..formation import bp_numpy
from ..formation.bp_opencl import BackprojectPlan
from ..physics.beam import BEAM_MODES, Beams, BeamWeights, beam_weights
from ..physics.geometry import VoxelGrid
from ..types.profiles import Profiles
from . import project_numpy as twin
from .project_opencl import ProjectPlan

__all__ = ["ImagingOperator", "compressed_pulse"]

log = logging.getLogger(__name__)


def compressed_pulse(waveform: np.ndarray, fs_hz: float, dtau_s: float, fc_hz: float,
                     rel_floor: float = 1e-3, echo: np.ndarray | None = None) -> np.ndarray:
    """The baseband compressed pulse of ``waveform`` on the profiles' lag grid, centred.

    Computed by clsas's own matched filter (the NumPy twin) on a recording holding the waveform at a
    known delay, so its scale, taper and baseband rotation are those of :func:`clsas.compress`.

    Parameters
    ----------
    waveform : (n_wave,) transmitted signal.
    fs_hz : float
        Sample rate of the recordings, Hz.
    dtau_s : float
        Lag step of the profiles, s (a whole number of samples).
    fc_hz : float
        Baseband rotation of the profiles, Hz.
    rel_floor : float
        Tails below this fraction of the peak are cut (the pulse stays odd-length and centred).
    echo : (n_wave,) array, optional
        The echo as received (e.g. the waveform after air absorption), default the waveform.

    Returns
    -------
    (2 J + 1,) complex128: sample ``J + j`` is the profile ``j`` lags after a unit point echo's delay,
    with that echo's carrier phase removed.
    """
    from ..compression import compress

    step = max(1, int(round(dtau_s * fs_hz)))
    n_wave = len(waveform)
    half = -(-n_wave // step) + 2  # lags of the autocorrelation's support on each side
    delay = (half + 1) * step  # a whole number of lags
    rec = np.zeros((1, delay + n_wave + (half + 2) * step))
    rec[0, delay: delay + n_wave] = waveform if echo is None else echo
    tau_d = delay / fs_hz
    prof = compress(rec, waveform, fs_hz, gate_s=(tau_d - half * step / fs_hz, tau_d + half * step / fs_hz),
                    t0_s=0.0, fc_hz=fc_hz, lag_step=step, backend="numpy")
    k = np.arange(prof.n_lags)
    offset = (tau_d - prof.tau0_s[0]) / prof.dtau_s
    centre = int(round(offset))
    if abs(offset - centre) > 1e-6:
        raise RuntimeError(f"compressed_pulse: delay not on the lag grid (offset {offset})")
    row = prof.data[0] * np.exp(2j * np.pi * fc_hz * tau_d)
    j = k - centre
    keep = np.abs(row) >= rel_floor * np.abs(row).max()
    J = int(np.abs(j[keep]).max())
    out = np.zeros(2 * J + 1, np.complex128)
    sel = np.abs(j) <= J
    out[j[sel] + J] = row[sel]
    return out


def _pair_weights(beams: Beams | None, beam: str | None, floor_db: float, fc_hz: float, c: np.ndarray,
                  n_meas: int) -> BeamWeights | None:
    """The pair weights of ``beam`` for ``beams`` by :class:`clsas.formation.bp.Backprojector`'s rule
    (default ``"limited"`` for directional beams, else ``"none"``); None where nothing is weighted."""
    if beam is not None:
        beam = v.choice("beam", beam, BEAM_MODES)
    floor_db = v.finite("beam_floor_db", floor_db)
    if beams is not None and not isinstance(beams, Beams):
        raise TypeError(f"beams must be clsas.physics.beam.Beams or None, got {type(beams).__name__}")
    mode = beam or ("limited" if beams is not None and not beams.is_omni else "none")
    if beam is None and mode == "limited":
        log.info("imaging operator: the profiles carry directional beams: beam='limited' (pairs above %g dB)",
                 floor_db)
    weights = beam_weights(beams, mode, fc_hz, c, floor_db)
    if weights is not None and len(weights.tx_dir) != n_meas:
        raise ValueError(f"beams must have {n_meas} boresights (one per measurement), got {len(weights.tx_dir)}")
    return weights


class ImagingOperator(LinearOperator):
    """Voxels on ``grid`` -> the profiles of ``profiles``' geometry, and back.

    ``A x``: the forward projection (kernels/project.cl or its twin) of the complex voxel values,
    each profile then convolved with ``pulse``; ``A^H y``: the profiles correlated with ``pulse``,
    then backprojected (kernels/backproject.cl or its twin). Without a pulse, ``A^H`` is exactly
    :func:`clsas.backproject`. Vectors are flat: ``x`` (n_vox,) in the grid's C order, ``y``
    (n_meas * n_lags,).

    Parameters
    ----------
    profiles : Profiles
        The geometry (positions, speeds of sound, ``tau0_s``, ``dtau_s``, ``fc_hz``, ``n_lags``); its
        data is the right-hand side :attr:`data`.
    grid : VoxelGrid
    pulse : (2 J + 1,) complex array, optional
        The compressed pulse on the lag grid (:func:`compressed_pulse`); None: no convolution (a
        voxel's echo is one linearly interpolated sample).
    backend : {"auto", "opencl", "numpy"} or clsas.cl.Selection, optional
    device : optional
        As for :func:`clsas.backproject`.
    beam : {"none", "limited", "weighted"}, optional
        Apodization by the transducers' beams, as :func:`clsas.backproject` takes it: the
        same real two-way weight (or gate) of each voxel-measurement pair in ``A`` and ``A^H``, so
        ``A^H`` stays the exact adjoint and equals beam-weighted backprojection. Default, as bp's:
        ``"limited"`` where the beams are directional, else ``"none"``.
    beam_floor_db : float
        The two-way level of ``beam="limited"``, dB (default -12, as bp's).
    beams : clsas.physics.beam.Beams, optional
        The transducers' beams, default the profiles' (from the dataset).
    """

    def __init__(self, profiles: Profiles, grid: VoxelGrid, *, pulse: np.ndarray | None = None,
                 backend: str | _cl.Selection | None = None, device: Any = None, beam: str | None = None,
                 beam_floor_db: float = -12.0, beams: Beams | None = None):
        if not isinstance(profiles, Profiles):
            raise TypeError(f"profiles must be clsas.Profiles, got {type(profiles).__name__}")
        if not isinstance(grid, VoxelGrid):
            raise TypeError(f"grid must be a clsas.VoxelGrid, got {type(grid).__name__}")
        n = profiles.n_meas
        if profiles.tx_positions is None or profiles.rx_positions is None or profiles.c_mps is None:
            raise ValueError("profiles must carry tx_positions, rx_positions and c_mps (from a Dataset)")
        self.tx = v.array("profiles.tx_positions", profiles.tx_positions, shape=(n, 3))
        self.rx = v.array("profiles.rx_positions", profiles.rx_positions, shape=(n, 3))
        self.c = v.speeds("profiles.c_mps", profiles.c_mps, n)
        self.tau0 = v.array("profiles.tau0_s", profiles.tau0_s, shape=(n,))
        self.dtau = v.positive("profiles.dtau_s", profiles.dtau_s)
        self.fc = v.non_negative("profiles.fc_hz", profiles.fc_hz)
        if profiles.n_lags < 2:
            raise ValueError(f"profiles must have at least 2 lags, got {profiles.n_lags}")
        if pulse is not None:
            pulse = v.array("pulse", pulse, ndim=1, dtype=None, allow_complex=True).astype(np.complex128)
            if len(pulse) % 2 != 1:
                raise ValueError(f"pulse must have an odd length (centred), got {len(pulse)}")
        self.pulse = pulse
        self.weights = _pair_weights(profiles.beams if beams is None else beams, beam, beam_floor_db, self.fc,
                                     self.c, n)
        lut = 0 if self.weights is None else self.weights.luts.shape[1]
        self.grid, self.n_meas, self.n_lags = grid, n, profiles.n_lags
        self.data = np.asarray(profiles.data, np.complex128).ravel()
        self.selection = _cl.select(backend, device)
        self._points = None
        self._fwd = self._adj = None
        if self.selection.opencl:
            self._fwd, self.selection = self.selection.plan(lambda q: ProjectPlan(grid, n, self.n_lags, queue=q,
                                                                                       beam_lut=lut))
        if self.selection.opencl:
            self._adj, self.selection = self.selection.plan(lambda q: BackprojectPlan(grid, n, self.n_lags, queue=q,
                                                                                           beam_lut=lut))
        self.n_forward = self.n_adjoint = 0
        super().__init__(np.complex128, (n * self.n_lags, grid.size))

    @property
    def backend(self) -> str:
        """``"opencl"`` or ``"numpy"``: where the projections run."""
        return self.selection.kind

    def points(self) -> np.ndarray:
        if self._points is None:
            self._points = self.grid.points()
        return self._points

    def project(self, x: np.ndarray) -> np.ndarray:
        """Forward projection of (n_vox,) voxels -> (n_meas, n_lags) profiles, without the pulse."""
        if self._fwd is not None:
            return self._fwd(x, self.tau0, self.dtau, self.fc, self.tx, self.rx, self.c,
                             beam=self.weights).astype(np.complex128)
        return twin.project(x, self.tau0, self.dtau, self.n_lags, self.fc, self.tx, self.rx, self.c, self.points(),
                            beam=self.weights)

    def backproject(self, y: np.ndarray) -> np.ndarray:
        """Backprojection of (n_meas, n_lags) profiles -> (n_vox,) voxels (:func:`clsas.backproject`)."""
        if self._adj is not None:
            return self._adj(y, self.tau0, self.dtau, self.fc, self.tx, self.rx, self.c,
                             beam=self.weights).astype(np.complex128)
        return bp_numpy.backproject(y, self.tau0, self.dtau, self.fc, self.tx, self.rx, self.c, self.points(),
                                    beam=self.weights)

    def _convolve(self, q: np.ndarray, adjoint: bool) -> np.ndarray:
        if self.pulse is None:
            return q
        h = np.conj(self.pulse[::-1]) if adjoint else self.pulse
        J = len(h) // 2
        return fftconvolve(q, h[None, :], axes=1)[:, J: J + self.n_lags]

    def _matvec(self, x: np.ndarray) -> np.ndarray:
        self.n_forward += 1
        q = self.project(np.asarray(x, np.complex128).ravel())
        return self._convolve(q, adjoint=False).ravel()

    def _rmatvec(self, y: np.ndarray) -> np.ndarray:
        self.n_adjoint += 1
        q = self._convolve(np.asarray(y, np.complex128).reshape(self.n_meas, self.n_lags), adjoint=True)
        return self.backproject(q)

    def _adjoint(self) -> LinearOperator:
        return LinearOperator((self.shape[1], self.shape[0]), matvec=self._rmatvec, rmatvec=self._matvec,
                              dtype=np.complex128)

    def norm(self, n_iter: int = 20, seed: int = 0) -> float:
        """Largest singular value by power iteration on ``A^H A`` (an estimate from below; solvers
        that need a step size take 1.02 times it)."""
        rng = np.random.default_rng(seed)
        x = rng.normal(size=self.shape[1]) + 1j * rng.normal(size=self.shape[1])
        s = 0.0
        for _ in range(v.positive_int("n_iter", n_iter)):
            x /= np.linalg.norm(x)
            x = self.rmatvec(self.matvec(x))
            s = float(np.sqrt(np.linalg.norm(x)))
        return s
