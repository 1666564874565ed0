"""Circular, helical and CSV apertures, several microphones per ping, plane grids."""

import numpy as np
import pytest

import clsas


def _rz(deg):
    t = np.deg2rad(deg)
    return np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("mode, sign", [("turntable", -1.0), ("arc", 1.0)], ids=["turntable", "arc"])
def test_circle_radius_height_and_angles(mode, sign):
    c = np.array([0.1, -0.2, 0.3])
    ap = clsas.circular_aperture(12, 0.8, center_m=c, height_m=0.05, mode=mode, start_deg=10.0)
    rel = ap.stage_positions - c
    np.testing.assert_allclose(np.hypot(rel[:, 0], rel[:, 1]), 0.8)
    np.testing.assert_allclose(rel[:, 2], 0.05)
    az = np.rad2deg(np.arctan2(rel[:, 1], rel[:, 0]))
    want = sign * (10.0 + 30.0 * np.arange(12))  # a full turn: 360 / 12 apart, endpoint excluded
    np.testing.assert_allclose((az - want + 180) % 360 - 180, 0, atol=1e-9)
    assert ap.n_meas == ap.n_stops == 12 and ap.mics_per_stop == 1


def test_partial_arc_includes_both_ends_and_turns_either_way():
    ap = clsas.circular_aperture(5, 1.0, start_deg=0, stop_deg=90, mode="arc")
    az = np.rad2deg(np.arctan2(ap.stage_positions[:, 1], ap.stage_positions[:, 0]))
    np.testing.assert_allclose(az, [0, 22.5, 45, 67.5, 90], atol=1e-9)
    back = clsas.circular_aperture(3, 1.0, start_deg=0, stop_deg=-90, mode="arc")
    az = np.rad2deg(np.arctan2(back.stage_positions[:, 1], back.stage_positions[:, 0]))
    np.testing.assert_allclose(az, [0, -45, -90], atol=1e-9)
    one = clsas.circular_aperture(1, 1.0, start_deg=30, mode="arc")
    np.testing.assert_allclose(one.stage_positions[0], [np.cos(np.pi / 6), 0.5, 0.0], atol=1e-12)


@pytest.mark.parametrize("mode", ["turntable", "arc"])
def test_local_frame_looks_at_the_axis(mode):
    n, r = 8, 1.0
    look = clsas.circular_aperture(n, r, mode=mode, tx_offset_m=(0, 0, 0.1), rx_offset_m=(0, 0.05, 0))
    # local z points at the axis: 0.1 m closer; local y is up
    np.testing.assert_allclose(np.hypot(*look.tx_positions[:, :2].T), r - 0.1)
    np.testing.assert_allclose(look.tx_positions[:, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(look.rx_positions - look.stage_positions, np.tile([0, 0, 0.05], (n, 1)), atol=1e-12)
    side = clsas.circular_aperture(n, r, mode=mode, tx_offset_m=(0.03, 0, 0), rx_offset_m=(0, 0, 0))
    ex = side.tx_positions - side.stage_positions
    ez = -side.stage_positions / r
    ey = np.tile([0.0, 0.0, 1.0], (n, 1))
    np.testing.assert_allclose(np.linalg.norm(ex, axis=1), 0.03)
    # right-handed local frame x = y cross z, as the raster rig's (x, y, z) facing +z
    np.testing.assert_allclose(ex / 0.03, np.cross(ey, ez), atol=1e-12)


def test_turntable_is_the_rig_turning_the_other_way():
    """Target at p turned by theta, rig fixed in the room == rig at -theta around the still target."""
    p = np.array([0.12, -0.05, 0.02])
    n = 36
    ap = clsas.circular_aperture(n, 0.9, height_m=0.01, mode="turntable", stop_deg=360)
    fixed = clsas.circular_aperture(1, 0.9, height_m=0.01, mode="turntable")
    for i, theta in enumerate(10.0 * np.arange(n)):
        q = _rz(theta) @ p  # where the target is in the room
        assert np.linalg.norm(ap.tx_positions[i] - p) == pytest.approx(np.linalg.norm(fixed.tx_positions[0] - q))
        assert np.linalg.norm(ap.rx_positions[i] - p) == pytest.approx(np.linalg.norm(fixed.rx_positions[0] - q))


def test_several_microphones_per_ping():
    mics = np.array([[0.02, 0.0, 0.0], [0.0, 0.04, 0.0], [-0.03, 0.0, 0.01]])
    ap = clsas.circular_aperture(6, 1.0, rx_offsets_m=mics)
    single = [clsas.circular_aperture(6, 1.0, rx_offset_m=tuple(m)) for m in mics]
    assert (ap.n_meas, ap.n_stops, ap.mics_per_stop, len(ap)) == (18, 6, 3, 18)
    for j, s in enumerate(single):  # stop-major: measurement i * k + j is microphone j at stop i
        np.testing.assert_allclose(ap.rx_positions[j::3], s.rx_positions)
        np.testing.assert_allclose(ap.tx_positions[j::3], s.tx_positions)
        np.testing.assert_allclose(ap.stage_positions[j::3], s.stage_positions)
    assert len(np.unique(ap.stage_positions.round(12), axis=0)) == 6


def test_raster_takes_several_microphones_too():
    mics = [[0.02, 0.0, 0.0], [0.0, 0.03, 0.0]]
    ap = clsas.raster_aperture(3, 2, 0.2, 0.1, rx_offsets_m=mics)
    one = clsas.raster_aperture(3, 2, 0.2, 0.1)
    assert (ap.n_meas, ap.n_stops, ap.mics_per_stop) == (12, 6, 2)
    np.testing.assert_allclose(ap.rx_positions[0::2], one.rx_positions)
    np.testing.assert_allclose(ap.rx_positions[1::2], one.stage_positions + [0.0, 0.03, 0.0])
    np.testing.assert_allclose(ap.tx_positions[1::2], one.tx_positions)
    with pytest.raises(ValueError, match="rx_offset_m .* rx_offsets_m"):
        clsas.raster_aperture(3, 2, 0.2, 0.1, rx_offset_m=(0.02, 0, 0), rx_offsets_m=mics)


def test_helix_pitch_and_count():
    ap = clsas.helical_aperture(24, 2.5, 0.7, 0.04, height_m=0.1, mode="arc", rx_offsets_m=[[0.02, 0, 0]] * 2)
    assert ap.n_stops == 60 and ap.n_meas == 120
    st = ap.stage_positions[::2]
    np.testing.assert_allclose(np.hypot(st[:, 0], st[:, 1]), 0.7)
    np.testing.assert_allclose(st[24:, 2] - st[:-24, 2], 0.04)  # one turn later: one pitch higher
    np.testing.assert_allclose(st[24:, :2], st[:-24, :2], atol=1e-12)  # same angle
    np.testing.assert_allclose(np.diff(st[:, 2]), 0.04 / 24)
    assert st[0, 2] == pytest.approx(0.1)
    flat = clsas.circular_aperture(24, 0.7, height_m=0.1, mode="arc")
    np.testing.assert_allclose(st[:24, :2], flat.stage_positions[:, :2], atol=1e-12)


@pytest.mark.parametrize(
    "make, err, match",
    [
        (lambda: clsas.circular_aperture(0, 1.0), ValueError, "n must"),
        (lambda: clsas.circular_aperture(2.0, 1.0), TypeError, "n must"),
        (lambda: clsas.circular_aperture(8, 0.0), ValueError, "radius_m"),
        (lambda: clsas.circular_aperture(8, np.nan), ValueError, "radius_m"),
        (lambda: clsas.circular_aperture(8, 1.0, height_m=np.inf), ValueError, "height_m"),
        (lambda: clsas.circular_aperture(8, 1.0, mode="spin"), ValueError, "mode"),
        (lambda: clsas.circular_aperture(8, 1.0, stop_deg=720), ValueError, "helical"),
        (lambda: clsas.circular_aperture(8, 1.0, stop_deg=0), ValueError, "stop_deg"),
        (lambda: clsas.circular_aperture(8, 1.0, tx_offset_m=(0, 0)), ValueError, "tx_offset_m"),
        (lambda: clsas.circular_aperture(8, 1.0, rx_offsets_m=[0.02, 0, 0]), ValueError, "rx_offsets_m"),
        (lambda: clsas.circular_aperture(8, 1.0, center_m=(0, np.nan, 0)), ValueError, "center_m"),
        (lambda: clsas.helical_aperture(8, 0.0, 1.0, 0.1), ValueError, "turns"),
        (lambda: clsas.helical_aperture(8, 0.01, 1.0, 0.1), ValueError, "at least one stop"),
        (lambda: clsas.helical_aperture(8, 1.0, 1.0, np.nan), ValueError, "pitch_m"),
        (lambda: clsas.helical_aperture(0, 1.0, 1.0, 0.1), ValueError, "n_per_turn"),
        (lambda: clsas.Aperture(np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)), 2), ValueError,
         "mics_per_stop"),
    ],
    ids=["n0", "n-float", "r0", "r-nan", "h-inf", "mode", "span", "no-span", "offset-shape", "mics-shape",
         "center-nan", "turns0", "too-few", "pitch-nan", "npt0", "k-divides"],
)
def test_apertures_reject_bad_input(make, err, match):
    with pytest.raises(err, match=match):
        make()


def test_csv_round_trip(tmp_path):
    ap = clsas.circular_aperture(10, 0.9, height_m=0.2, rx_offsets_m=[[0.02, 0, 0], [0, 0.05, 0]])
    back = clsas.aperture_from_csv(ap.to_csv(tmp_path / "ap.csv"))
    for name in ("tx_positions", "rx_positions", "stage_positions"):
        np.testing.assert_array_equal(getattr(back, name), getattr(ap, name))


def test_csv_stage_layout_in_mm_with_offsets_comments_and_renamed_columns(tmp_path):
    path = tmp_path / "stops.csv"
    path.write_text("# turntable log\nangle, X [mm] ,Y [mm],Z [mm]\n\n0, 1000, 0, 50\n90,0,1000,50\n")
    ap = clsas.aperture_from_csv(path, units="mm", columns={"x": "x [mm]", "y": "Y [mm]", "z": "Z [MM]"},
                                 tx_offset_m=(0, 0, 0.01), rx_offsets_m=[[0.01, 0, 0], [-0.01, 0, 0]])
    assert (ap.n_stops, ap.mics_per_stop) == (2, 2)
    np.testing.assert_allclose(ap.stage_positions[::2], [[1.0, 0, 0.05], [0, 1.0, 0.05]])
    np.testing.assert_allclose(ap.tx_positions[::2], [[1.0, 0, 0.06], [0, 1.0, 0.06]])
    np.testing.assert_allclose(ap.rx_positions[:2], [[1.01, 0, 0.05], [0.99, 0, 0.05]])


def test_csv_bistatic_layout_without_stage_uses_the_speaker(tmp_path):
    path = tmp_path / "pairs.csv"
    path.write_text("TX_X,tx_y,tx_z,rx_x,rx_y,rx_z\n0,0,0,0.1,0,0\n0,0,0,0,0.1,0\n")
    ap = clsas.aperture_from_csv(path)
    np.testing.assert_allclose(ap.stage_positions, 0.0)
    np.testing.assert_allclose(ap.rx_positions, [[0.1, 0, 0], [0, 0.1, 0]])


@pytest.mark.parametrize(
    "text, kwargs, match",
    [
        ("tx_x,tx_y,tx_z,rx_x,rx_y\n1,2,3,4,5\n", {}, r"line 1: missing column\(s\) rx_z"),
        ("a,b\n1,2\n", {}, r"line 1: missing column\(s\) x, y, z"),
        ("x,y,z\n1,2,3\n\n1,two,3\n", {}, r"line 4, column 'y': 'two' is not a number"),
        ("x,y,z\n1,2,nan\n", {}, r"line 2, column 'z': 'nan' is NaN or infinite"),
        ("x,y,z\n1,2,\n", {}, r"line 2, column 'z': the field is empty"),
        ("x,y,z\n1,2\n", {}, r"line 2: 2 field\(s\)"),
        ("x,y,z\n", {}, "no data rows"),
        ("# only a comment\n", {}, "no header"),
        ("tx_x,tx_y,tx_z,rx_x,rx_y,rx_z\n0,0,0,1,1,1\n", {"tx_offset_m": (0, 0, 0)}, "x,y,z layout"),
        ("x,y,z\n1,2,3\n", {"units": "cm"}, "units"),
        ("x,y,z\n1,2,3\n", {"columns": {"X": "x"}}, "unknown key 'X'"),
    ],
    ids=["missing-rx_z", "missing-xyz", "not-a-number", "nan", "empty-field", "short-row", "no-rows",
         "empty-file", "offsets-with-pairs", "units", "columns-key"],
)
def test_csv_errors_name_file_line_and_column(tmp_path, text, kwargs, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as info:
        clsas.aperture_from_csv(path, **kwargs)
    if "units" not in kwargs and "columns" not in kwargs:
        assert "bad.csv" in str(info.value)


def test_csv_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        clsas.aperture_from_csv(tmp_path / "none.csv")


@pytest.mark.parametrize(
    "axis, shape, fixed",
    [("z", (5, 3, 1), 2), ("y", (5, 1, 3), 1), ("x", (1, 5, 3), 0)],
    ids=["horizontal", "vertical-xz", "vertical-yz"],
)
def test_plane_grids(axis, shape, fixed):
    g = clsas.VoxelGrid.plane(axis, at_m=0.25, u_m=(-0.1, 0.1), v_m=(0.0, 0.1), spacing_m=0.05)
    assert g.shape == shape
    b = g.bounds()
    np.testing.assert_allclose(b[fixed], [0.25, 0.25])
    inplane = [i for i in range(3) if i != fixed]
    np.testing.assert_allclose(b[inplane], [[-0.1, 0.1], [0.0, 0.1]], atol=1e-12)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"axis": "w"}, "axis"),
        ({"u_m": (0.1, -0.1)}, "u_m bounds are inverted"),
        ({"v_m": (0.0, np.nan)}, "v_m"),
        ({"spacing_m": 0.0}, "spacing_m"),
        ({"at_m": np.inf}, "at_m"),
    ],
    ids=["axis", "inverted-u", "nan-v", "zero-spacing", "inf-at"],
)
def test_plane_rejects_bad_input(kwargs, match):
    args = {"axis": "z", "at_m": 0.0, "u_m": (-0.1, 0.1), "v_m": (-0.1, 0.1), "spacing_m": 0.01} | kwargs
    with pytest.raises(ValueError, match=match):
        clsas.VoxelGrid.plane(**args)


@pytest.mark.parametrize("mode", ["turntable", "arc"])
def test_turntable_scan_images_a_point_near_the_axis(mode):
    fs = 96e3
    chirp = clsas.lfm_chirp(20e3, 30e3, 2e-3, fs, taper=0.1)
    target = np.array([0.03, -0.02, 0.1])
    ap = clsas.circular_aperture(90, 1.0, height_m=0.1, mode=mode, rx_offsets_m=[[0.02, 0, 0], [0, 0.03, 0]])
    ds = clsas.simulate(clsas.Scene(target[None]), ap, chirp, fs)
    grid = clsas.VoxelGrid.plane("z", at_m=0.1, u_m=(-0.1, 0.1), v_m=(-0.1, 0.1), spacing_m=0.01)
    image = clsas.reconstruct(ds, grid, backend="numpy")
    peak = image.peaks(1)[0].position_m
    assert np.all(np.abs(peak - target) <= 0.5 * 0.01 + 1e-9), peak
