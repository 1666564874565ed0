"""clsas.Profiles: ``data`` given, or read on first access from the rows left on the device.

The rows here are a stand-in with what Profiles uses of :class:`clsas.cl.DeviceRows` (shape, a
host copy read on first use, ``valid``), counting its reads, so that the type's contract runs
without a device; tests/kernels/test_resident.py runs it on the OpenCL compression's rows.
"""

import dataclasses
import pickle

import numpy as np
import pytest

import clsas


class _Rows:
    """Rows "on a device": ``host`` copies ``values`` on first use (counted in ``reads``)."""

    def __init__(self, values: np.ndarray):
        self.values, self.reads, self.current = values, 0, True
        self.n_rows, self.n_cols = values.shape
        self.queue = object()
        self._host = None

    @property
    def host(self):
        if self._host is None:
            self.reads += 1
            self._host = self.values.copy()
            self._host.flags.writeable = False
        return self._host

    def valid(self, queue, host=None) -> bool:
        return self.current and queue is self.queue and (host is None or (host is self._host
                                                                          and not host.flags.writeable))

    def __getstate__(self) -> dict:  # as DeviceRows: a pickled copy holds nothing
        return {}

    def __setstate__(self, state: dict) -> None:
        self.values, self.reads, self.current, self._host, self.queue = None, 0, False, None, None


def _on_device(rng, n_meas=5, n_lags=12):
    values = (rng.normal(size=(n_meas, n_lags)) + 1j * rng.normal(size=(n_meas, n_lags))).astype(np.complex64)
    rows = _Rows(values)
    prof = clsas.Profiles(None, np.full(n_meas, 1e-3), 1e-5, 25e3, "matched", "opencl",
                          tx_positions=np.zeros((n_meas, 3)), rx_positions=np.zeros((n_meas, 3)), c_mps=343.0,
                          on_device=rows)
    return prof, rows, values


def test_data_is_read_from_the_rows_on_first_access_then_kept(rng):
    prof, rows, values = _on_device(rng)
    assert (prof.n_meas, prof.n_lags) == values.shape and prof.device_rows() is rows
    assert rows.reads == 0  # the shape and the rows are known without a read
    data = prof.data
    assert rows.reads == 1 and np.array_equal(data, values) and not data.flags.writeable
    assert prof.data is data and rows.reads == 1  # read once
    assert prof.device_rows() is rows  # the read copy is the rows' own: they still hold data


def test_rows_no_longer_current_are_not_offered(rng):
    prof, rows, _ = _on_device(rng)
    rows.current = False  # their plan was called again
    assert prof.device_rows() is None


def test_replaced_data_is_never_matched_to_the_rows(rng):
    prof, rows, values = _on_device(rng)
    other = dataclasses.replace(prof, data=values.copy())
    assert other.on_device is rows and other.device_rows() is None
    edited = dataclasses.replace(prof, data=prof.data.copy())  # an array read-only or not: not the rows'
    edited.data.flags.writeable = False
    assert edited.device_rows() is None


def test_replace_reads_with_fields_keeps_the_rows_unread(rng):
    prof, rows, _ = _on_device(rng)
    kept = prof.with_fields(c_mps=340.0, timings_s={"compress": 1.0})
    assert rows.reads == 0 and kept.device_rows() is rows and kept.c_mps == 340.0
    copied = dataclasses.replace(prof, c_mps=340.0)  # copies every field through its attribute: reads
    assert rows.reads == 1 and copied.data is prof.data and copied.device_rows() is rows
    assert kept.data is prof.data  # every holder of the rows gets the one host copy


def test_with_fields_dropping_the_rows_brings_the_data_along(rng):
    prof, rows, values = _on_device(rng)
    alone = prof.with_fields(on_device=None)
    assert rows.reads == 1 and alone.on_device is None and np.array_equal(alone.data, values)


def test_pickled_profiles_carry_their_data(rng):
    prof, rows, values = _on_device(rng)
    back = pickle.loads(pickle.dumps(prof))
    assert rows.reads == 1 and np.array_equal(back.data, values)
    assert back.device_rows() is None  # another process cannot reach the rows
    assert back.n_meas == prof.n_meas and back.method == prof.method


def test_equality_compares_data_read_from_the_rows(rng):
    prof, _, values = _on_device(rng)
    assert prof == prof.with_fields()
    assert prof != prof.with_fields(fc_hz=24e3)
    host = dataclasses.replace(prof, data=values, on_device=None)
    with pytest.raises(ValueError):  # two arrays compare element-wise, as for any Profiles
        bool(prof == host)


def test_data_is_needed_or_rows_holding_it(rng):
    with pytest.raises(ValueError, match="data"):
        clsas.Profiles(None, np.zeros(2), 1e-5, 25e3, "matched", "numpy")
    prof, _, _ = _on_device(rng)
    with pytest.raises(dataclasses.FrozenInstanceError):
        prof.data = np.zeros((5, 12))
