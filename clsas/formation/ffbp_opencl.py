"""OpenCL plans for kernels/ffbp.cl, and the pipeline that keeps every level on the device.

:class:`FfbpLeafPlan` and :class:`FfbpMergePlan` each run one kernel and, called with host
arrays, return what their NumPy twins return (:mod:`clsas.formation.ffbp_numpy`); that is how
they are tested. :class:`FfbpPipeline` chains them for a whole tree with the sub-images kept on
the device (two buffers, children and parents, swapped level by level); only the image comes back.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ..cl import Plan
from ..physics.geometry import VoxelGrid
from . import ffbp_numpy as twin
from .bp_opencl import BeamPlan, carrier_records, selftest_beam_weights
from .ffbp_tree import BLOCK, Level, Tree

__all__ = ["FfbpLeafPlan", "FfbpMergePlan", "FfbpPipeline", "leaf_beam_selftest"]


class _LevelTables:
    """A level's node tables on the device."""

    def __init__(self, plan: Plan, level: Level):
        self.level = level
        self.geom = plan.upload(level.geom, np.float32)
        self.ints = plan.upload(level.ints, np.int32)
        self.blocks = plan.upload(level.block_node(), np.int32)
        self.size = level.size


def _profiles(plan: Plan, data, tau0_s, dtau_s, fc_hz, tx, rx, c_mps):
    """Device copies of the profiles as backproject.cl takes them (records rotated by the
    carrier at each sample, :func:`~clsas.formation.bp_opencl.carrier_records`), the positions
    with the path scale in tx's w lane, the zero-delay indices and the sub-sample phase step."""
    n_lags = data.shape[1]
    pairs, dtau_s, phi = carrier_records(data, max(2, n_lags), tau0_s, dtau_s, fc_hz)
    d_pairs = plan.upload(pairs, np.complex64)
    return (d_pairs, np.int32(pairs.shape[1]), *_geometry(plan, tau0_s, dtau_s, tx, rx, c_mps), np.float32(phi))


def _geometry(plan: Plan, tau0_s, dtau_s: float, tx, rx, c_mps) -> tuple:
    """Device copies of the positions (the path scale ``1 / (c dtau)`` in tx's w lane) and of the
    zero-delay indices ``tau0 / dtau``, for records at lag step ``dtau_s``."""
    n = len(tx)
    c = np.broadcast_to(np.asarray(c_mps, float), (n,))
    pos4 = np.zeros((2, n, 4), np.float32)
    pos4[0, :, :3] = tx
    pos4[0, :, 3] = 1.0 / (c * dtau_s)
    pos4[1, :, :3] = rx
    return (plan.upload(pos4[0], np.float32), plan.upload(pos4[1], np.float32),
            plan.upload(np.asarray(tau0_s) / dtau_s, np.float32))


def _complex(host: np.ndarray) -> np.ndarray:
    return host.view(np.complex64).reshape(-1)


class FfbpLeafPlan(BeamPlan):
    """The ``ffbp_leaf`` kernel: leaf sub-images by exact backprojection of their measurements.

    With ``beam_lut`` > 0 it is built with kernels/beam.cl's ``-DBEAM`` for ``n_meas``
    measurements: each pair is weighted by its two-way beam at the sample's position (calls
    then take ``beam``, a :class:`clsas.physics.beam.BeamWeights` in tree order).
    """

    KERNEL = "ffbp_leaf"
    SOURCES = ("common.cl", "beam.cl", "ffbp.cl")

    def __init__(self, queue=None, vec=None, beam_lut: int = 0, n_meas: int = 0):
        self.beam_lut, self.n_meas = int(beam_lut), int(n_meas)
        if self.beam_lut and self.n_meas < 1:
            raise ValueError(f"n_meas must be >= 1 for a plan with a beam, got {n_meas!r}")
        super().__init__(queue, vec)
        self.alloc_beam(self.n_meas)

    def launch_level(self, prof, tables: _LevelTables, kref: float, d_out, beam_args: tuple = ()):
        # VEC samples per work-item (BLOCK, the level's padding unit, is a multiple of every VEC)
        return self.launch((tables.size // self.vec,), *prof, tables.geom, tables.ints, tables.blocks,
                           np.float32(kref), d_out, *beam_args, local_size=(BLOCK // self.vec,))

    def __call__(self, data, tau0_s, dtau_s, fc_hz, tx, rx, c_mps, level: Level, kref: float,
                 beam=None) -> np.ndarray:
        """Same arguments as :func:`clsas.formation.ffbp_numpy.form_leaves`; (level.size,) complex64."""
        beam_args = self.beam_args(beam)
        self.begin()
        prof = _profiles(self, data, tau0_s, dtau_s, fc_hz, tx, rx, c_mps)
        tables = _LevelTables(self, level)
        d_out = self.alloc(8 * level.size)
        self.launch_level(prof, tables, kref, d_out, beam_args)
        return _complex(self.read(d_out, (level.size, 2), np.float32))

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """Leaves of a depth-2 tree over 20 bistatic pairs, each with its own speed of sound;
        voxels inside and outside the profile windows."""
        args, tree, _ = _selftest_scene()
        leaves = tree.levels[-1]
        got = cls(queue, vec)(*args, leaves, tree.kref)
        want = twin.form_leaves(*args, leaves, tree.kref)
        if not (np.any(want == 0) and np.any(want != 0)):
            raise RuntimeError("selftest scene must have samples inside and outside the profile windows")
        return float(np.abs(got - want).max() / np.abs(want).max())


class FfbpMergePlan(Plan):
    """The ``ffbp_merge`` kernel with ``taps`` points per axis: parents from children, or the
    image on a Cartesian grid from the top sub-images."""

    KERNEL = "ffbp_merge"
    SOURCES = ("common.cl", "beam.cl", "ffbp.cl")

    def __init__(self, taps: int = 4, queue=None, vec=None):
        if taps not in (2, 4, 6):
            raise ValueError(f"taps must be 2, 4 or 6, got {taps!r}")
        self.taps = taps
        super().__init__(queue, vec)

    def defines(self) -> dict:
        """``TAPS`` where it is not the source's default of 4 (that program is the leaf kernel's too)."""
        return {} if self.taps == 4 else {"TAPS": self.taps}

    def upload_tables(self, tables) -> tuple:
        return tuple(self.upload(t, np.float32) for t in tables)

    def check_tables(self, tables) -> None:
        """``ValueError`` unless both weight tables have this plan's number of taps."""
        if tables[0].shape[1] != self.taps or tables[1].shape[1] != self.taps:
            raise ValueError(f"tables: {tables[0].shape[1]} and {tables[1].shape[1]} taps, the plan has {self.taps}")

    def launch_level(self, d_vals, children: _LevelTables, parents: _LevelTables, d_tables, kref: float, d_out):
        zero4 = np.zeros(4, np.float32)
        return self.launch((parents.size,), d_vals, children.geom, children.ints, parents.geom, parents.ints,
                           parents.blocks, *d_tables, np.float32(kref), np.int32(0), zero4, zero4, np.int32(1),
                           np.int32(1), np.int32(0), np.int32(0), d_out, local_size=(BLOCK,))

    def launch_grid(self, d_vals, children: _LevelTables, grid: VoxelGrid, d_tables, kref: float, d_out):
        n_pad = -(-grid.size // BLOCK) * BLOCK
        origin = np.array([grid.x_m[0], grid.y_m[0], grid.z_m[0], 0], np.float32)
        step = np.array([*grid.spacing(), 0], np.float32)
        return self.launch((n_pad,), d_vals, children.geom, children.ints, children.geom, children.ints,
                           children.blocks, *d_tables, np.float32(kref), np.int32(1), origin, step,
                           np.int32(grid.shape[1]), np.int32(grid.shape[2]), np.int32(grid.size),
                           np.int32(children.level.n_nodes), d_out, local_size=(BLOCK,))

    def __call__(self, values: np.ndarray, children: Level, parents: Level | None, kref: float, tables,
                 grid: VoxelGrid | None = None) -> np.ndarray:
        """As :func:`clsas.formation.ffbp_numpy.merge` (``parents`` given) or
        :func:`~clsas.formation.ffbp_numpy.to_grid` (``grid`` given); complex64."""
        self.check_tables(tables)
        self.begin()
        d_vals = self.upload(np.asarray(values, np.complex64), np.complex64)
        d_tables = self.upload_tables(tables)
        ct = _LevelTables(self, children)
        if grid is not None:
            n_pad = -(-grid.size // BLOCK) * BLOCK
            d_out = self.alloc(8 * n_pad)
            self.launch_grid(d_vals, ct, grid, d_tables, kref, d_out)
            return _complex(self.read(d_out, (n_pad, 2), np.float32))[: grid.size]
        pt = _LevelTables(self, parents)
        d_out = self.alloc(8 * parents.size)
        self.launch_level(d_vals, ct, pt, d_tables, kref, d_out)
        return _complex(self.read(d_out, (parents.size, 2), np.float32))

    @classmethod
    def selftest(cls, queue, vec: int) -> float:
        """A merge of 16 leaves into 4 parents and the 4 parents onto a 5 x 4 x 3 grid (not a
        multiple of the block), cubic least-squares weights."""
        args, tree, grid = _selftest_scene()
        tables = (twin.weight_table(4, 2.0), twin.weight_table(4, 2.0))
        leaves = twin.form_leaves(*args, tree.levels[1], tree.kref)
        plan = cls(4, queue, vec)
        got = plan(leaves, tree.levels[1], tree.levels[0], tree.kref, tables)
        want = twin.merge(leaves, tree.levels[1], tree.levels[0], tree.kref, tables)
        err = np.abs(got - want).max() / np.abs(want).max()
        got = plan(want, tree.levels[0], None, tree.kref, tables, grid=grid)
        want = twin.to_grid(want, tree.levels[0], grid.points(), tree.kref, tables)
        return float(max(err, np.abs(got - want).max() / np.abs(want).max()))


def _selftest_scene():
    """20 bistatic pairs on a jittered 5 x 4 patch, random profiles, a depth-2 tree (factor 2)."""
    from .ffbp_tree import build_tree

    rng = np.random.default_rng(11)
    fs = 96e3
    xy = np.stack(np.meshgrid(np.linspace(-0.06, 0.06, 5), np.linspace(-0.04, 0.04, 4)), -1).reshape(-1, 2)
    tx = np.c_[xy + rng.normal(0, 0.003, xy.shape), rng.normal(0, 0.003, len(xy))]
    rx = tx + [0.03, 0.0, 0.0]
    c = 343.0 + rng.uniform(-2, 2, len(tx))
    n_lags = 24
    prof = (rng.normal(size=(len(tx), n_lags)) + 1j * rng.normal(size=(len(tx), n_lags))) * np.hanning(n_lags)
    grid = VoxelGrid(np.linspace(-0.04, 0.04, 5), np.linspace(-0.03, 0.03, 4), np.linspace(0.3, 0.36, 3))
    centre = np.array([0.0, 0.0, 0.33])
    path = np.linalg.norm(centre - tx, axis=1) + np.linalg.norm(centre - rx, axis=1)
    tau0 = path / c - (n_lags // 2) / (fs / 2)
    tree = build_tree(tx, rx, c, grid.bounds(), (20e3, 30e3), depth=2, factor=2, oversample=1.5,
                      range_oversample=1.5, taps=4)
    o = tree.order
    args = (prof[o], tau0[o], 2 / fs, 25e3, tx[o], rx[o], c[o])
    return args, tree, grid


def leaf_beam_selftest(queue, vec: int, mode: str = "weighted") -> float:
    """The leaf selftest's tree through the beam variant (-DBEAM; the bp selftest's beams, one
    tilt per measurement, in tree order), ``mode`` "weighted" or "limited"; error against the
    twin relative to the peak."""
    args, tree, _ = _selftest_scene()
    w = selftest_beam_weights(np.random.default_rng(5), mode, len(args[0]))
    leaves = tree.levels[-1]
    plan = FfbpLeafPlan(queue, vec, beam_lut=w.luts.shape[1], n_meas=len(args[0]))
    got = plan(*args, leaves, tree.kref, beam=w)
    want = twin.form_leaves(*args, leaves, tree.kref, w)
    if mode == "limited":  # the gate must drop samples the omnidirectional leaves keep, and keep some
        omni = twin.form_leaves(*args, leaves, tree.kref)
        if not (np.any((want == 0) & (omni != 0)) and np.any(want != 0)):
            raise RuntimeError("beam selftest: the gate must drop some samples and keep others")
    return float(np.abs(got - want).max() / np.abs(want).max())


class FfbpPipeline:
    """Both kernels and the device buffers of one tree and grid: construct once, call per profile set."""

    def __init__(self, tree: Tree, grid: VoxelGrid, n_lags: int, tables, queue=None, beam_lut: int = 0,
                 n_meas: int = 0):
        self.tree, self.grid, self.n_lags = tree, grid, n_lags
        taps = tables[0].shape[1]
        self.leaf = FfbpLeafPlan(queue, beam_lut=beam_lut, n_meas=n_meas)
        self.merge = FfbpMergePlan(taps, self.leaf.queue)
        self.merge.check_tables(tables)
        self.d_tables = self.merge.upload_tables(tables)
        self.levels = [_LevelTables(self.merge, lev) for lev in tree.levels]
        biggest = max(lev.size for lev in tree.levels)
        self.bufs = [self.merge.alloc(8 * biggest), self.merge.alloc(8 * biggest)]
        self.n_pad = -(-grid.size // BLOCK) * BLOCK
        self.d_image = self.merge.alloc(8 * self.n_pad)
        self.timings_s: dict = {}
        self.device = self.merge.device

    def __call__(self, data, tau0_s, dtau_s, fc_hz, tx, rx, c_mps,
                 progress: Callable[[int, int], None] | None = None, beam=None) -> np.ndarray:
        """Image profiles given in tree order (as the twin takes them; ``beam`` too): (n_vox,) complex64."""
        t0 = time.perf_counter()
        prof = _profiles(self.leaf, data, tau0_s, dtau_s, fc_hz, tx, rx, c_mps)
        return self._levels(prof, [], progress, beam, t0)

    def from_device(self, rows, records, order, tau0_s, dtau_s: float, fc_hz: float, tx, rx, c_mps,
                    progress: Callable[[int, int], None] | None = None, beam=None) -> np.ndarray:
        """Image profiles another plan left on this queue's device (:class:`clsas.cl.DeviceRows`, in
        their own order): ``records`` (a :class:`~clsas.formation.bp_opencl.RecordsPlan` with
        ``row_map``) makes the carrier records there in tree order (``order``: the tree's row of
        each; ``tau0_s``, the positions, speeds and ``beam`` already in tree order), and the leaf
        kernel reads them. Only the geometry and one value per measurement go to the device."""
        if rows.n_rows != len(order) or not records.row_map or records.queue is not self.leaf.queue:
            raise ValueError("rows and records: a row-map records plan on this pipeline's queue, for "
                             f"{len(order)} rows, is needed")
        t0 = time.perf_counter()
        evt, fine, phi = records.enqueue(rows.buffer, rows.stride, rows.n_cols, tau0_s, dtau_s, fc_hz, row_of=order)
        prof = (records.d_pairs, np.int32(records.n_rec), *_geometry(self.leaf, tau0_s, fine, tx, rx, c_mps),
                np.float32(phi))
        return self._levels(prof, [("ffbp_records", evt)], progress, beam, t0)

    def _levels(self, prof: tuple, events: list, progress, beam, t0: float) -> np.ndarray:
        """The leaves from the device profiles ``prof``, every merge and the grid; the image read back
        once. ``events``: launches before the leaves (named), timed with the levels'."""
        tree, kref = self.tree, self.tree.kref
        beam_args = self.leaf.beam_args(beam)
        total = tree.depth + 1
        cur = 0
        events.append(("ffbp_leaves", self.leaf.launch_level(prof, self.levels[-1], kref, self.bufs[cur],
                                                             beam_args)))
        if progress is not None:
            events[-1][1].wait()
            progress(1, total)
        for d in range(tree.depth - 1, 0, -1):
            evt = self.merge.launch_level(self.bufs[cur], self.levels[d], self.levels[d - 1], self.d_tables, kref,
                                          self.bufs[1 - cur])
            events.append(("ffbp_merges", evt))
            cur = 1 - cur
            if progress is not None:
                evt.wait()
                progress(total - d, total)
        events.append(("ffbp_grid", self.merge.launch_grid(self.bufs[cur], self.levels[0], self.grid, self.d_tables,
                                                           kref, self.d_image)))
        out = self.merge.read(self.d_image, (self.n_pad, 2), np.float32, after=[e for _, e in events])
        if progress is not None:
            progress(total, total)
        timings = {"ffbp_device": time.perf_counter() - t0}
        for name, evt in events:
            key = name + "_kernel"
            timings[key] = timings.get(key, 0.0) + Plan.seconds(evt)
        self.timings_s = timings
        return _complex(out)[: self.grid.size]
