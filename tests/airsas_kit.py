"""Write synthetic AirSAS scan folders in the published files' exact layout (the files of
github awreed/CSAS_Deconvolution_INR, airsas_deconv_pipeline/airsas_data/): number formats,
header, two microphone columns, the waveform name with 'tukeywin'."""

from pathlib import Path

import numpy as np

import clsas

# the published scans' SysParams.csv, as written there (MATLAB-style engineering notation)
SYSPARAMS = """Speaker x,0.000000E+0
Speaker y,-848.500000E-3
Speaker z,285.000000E-3
Mic1 x,0.000000E+0
Mic1 y,-861.500000E-3
Mic1 z,247.000000E-3
Mic2 x,0.000000E+0
Mic2 y,-861.500000E-3
Mic2 z,216.000000E-3
Center x,0.000000E+0
Center y,0.000000E+0
Center z,177.500000E-3
Fs,100.000000E+3
Group Delay,62.329317E+0
Input Range,0.000000E+0
Output Range,3.500000E+0
Input Device,USB-4431
Output Device,USB-4431
Bit Depth,24
"""
WAVE_NAME = "LFM_3.00E+4Hz_1.00E+4Hz_1.00E-3s_5.00E-1V_tukeywin_1.00E-1"
SPEAKER, MIC1, CENTER = np.array([0, -0.8485, 0.285]), np.array([0, -0.8615, 0.247]), np.array([0, 0, 0.1775])
HEIGHT_M = 0.150
GD_SAMPLES = 62.329317
# an asymmetric target (an L) off the axis (what is on the axis is the same in every ping):
# its handedness shows in the image
TARGET = np.array([[0.02, 0.01, 0.0], [0.08, 0.01, 0.0], [0.02, 0.04, 0.0]])  # off the axis


def truth_positions(p, angles_deg):
    """The published convention, written out: the rig point p at turntable angle a is at
    R_z(+a)(p - Center) + (0, 0, height) in the target's frame."""
    a = np.deg2rad(angles_deg)
    d = p - CENTER
    return np.c_[np.cos(a) * d[0] - np.sin(a) * d[1], np.sin(a) * d[0] + np.cos(a) * d[1],
                 np.full(len(a), d[2] + HEIGHT_M)]


def write_scan(folder: Path, pings: int = 36, *, target: np.ndarray | None = TARGET, room_seed: int = 7) -> np.ndarray:
    """An AirSAS folder: ``target`` (or nothing: an empty scene) on the turntable, plus the direct
    sound and a static room echo, the same in every ping (what an empty-scene scan also
    records). Returns the angles."""
    folder.mkdir(parents=True)
    angles = np.arange(pings) * 360.0 / pings
    temps = np.full(pings, 21.622)
    wave = clsas.lfm_chirp(30e3, 10e3, 1e-3, 100e3, 0.1)
    tx, rx = truth_positions(SPEAKER, angles), truth_positions(MIC1, angles)
    n = 1000
    sig = np.zeros((pings, n))
    if target is not None:
        ds = clsas.simulate(clsas.Scene(target, np.ones(len(target))), clsas.Aperture(tx, rx, tx), wave, 100e3,
                            n_samples=n, t0_s=-GD_SAMPLES / 100e3, temperature_c=temps, snr_db=40, seed=1)
        sig += ds.signals
    level = 1e-3 if target is None else float(np.abs(sig).max())
    room = np.zeros(n)  # a static echo 1.2 m of path away, 3x the target's peak, in every ping
    k = int(GD_SAMPLES + 1.2 / 344.2 * 100e3)
    room[k:k + len(wave)] = 3 * wave * level
    # the direct sound: a point halfway between speaker and microphone (path |tx - rx|), in the
    # rig's frame (it does not turn), 10x the target's peak
    fixed = clsas.Aperture(np.tile(SPEAKER, (pings, 1)), np.tile(MIC1, (pings, 1)), np.tile(SPEAKER, (pings, 1)))
    direct = clsas.simulate(clsas.Scene((0.5 * (SPEAKER + MIC1))[None, :]), fixed, wave, 100e3, n_samples=n,
                            t0_s=-GD_SAMPLES / 100e3, temperature_c=temps, absorption=False).signals
    sig += 10 * level * direct / np.abs(direct).max()
    sig += room + np.random.default_rng(room_seed).normal(0, 1e-6, n)
    for i in range(pings):  # two columns, like the published Flight files (mic 2: a tone here)
        cols = np.c_[sig[i], 0.005 + 1e-4 * np.sin(np.arange(n))]
        np.savetxt(folder / f"Flight-{i + 1:06d}.csv", cols, fmt="%.9f", delimiter=",")
    rows = ["Flight #,Angle,Height,Temp,Waveform"]
    rows += [f"{i + 1:.3f},{angles[i]:.3f},{HEIGHT_M * 1e3:.3f},{temps[i]:.3f},0.000" for i in range(pings)]
    (folder / "Coordinates.csv").write_text("\n".join(rows) + "\n")
    (folder / "SysParams.csv").write_text(SYSPARAMS)
    (folder / "WaveformParams.csv").write_text(WAVE_NAME + "\n")
    np.savetxt(folder / "Waveforms.csv", wave[:, None], fmt="%.9f")
    return angles
