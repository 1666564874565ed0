"""``clsas devices``: OpenCL devices and their kernel variants, audio devices, serial ports."""

from __future__ import annotations


def cmd_devices(args) -> int:
    from clsas import cl

    if args.clear_cache:
        n = cl.clear_cache()
        print(f"removed {n} kernel-variant verdict(s) from {cl.cache_dir()}")
        n = cl.clear_shapes()
        print(f"removed {n} work-group tuning(s) from {cl.shapes_dir()}")
    rows = cl.list_devices()
    if not rows:
        from clsas.cl.device import FIX_CPU

        print(f"no OpenCL platform found: {FIX_CPU}; the NumPy backend works without one")
    from .common import is_simulator

    for r in rows:
        mark = "*" if r.selected else " "
        sim = (" | SIMULATOR (checks kernels; 100-1000x slower; never chosen by auto)" if is_simulator(r.platform)
               else "")
        print(f"{mark} {r.index}  {r.platform} | {r.device} | {r.kind} | {r.compute_units} CUs | "
              f"{r.global_mem_mib} MiB | fp64 {'yes' if r.fp64 else 'no'} | driver {r.driver} | "
              f"preferred float width {r.preferred_vec} | {r.platform_version} | kernels: "
              + ("build and run" if r.builds else f"DO NOT BUILD: {r.reason}. Fix: {r.fix}") + sim)
    if rows:
        print("(* = used by backend='auto'; choose with --device P:D or PYOPENCL_CTX=P:D)")
    from clsas.cl.runtimes import registration

    for line in registration().lines():
        print(f"pip-installed runtime: {line}")
    if rows and not any(r.builds for r in rows if not is_simulator(r.platform)):
        print(f"no OpenCL device here builds kernels: clsas runs the NumPy twins. Fix: {cl.device.FIX_CPU}")
    from clsas.cl.icd import unregistered_drivers

    listed = " ".join(f"{r.platform} {r.device}" for r in rows if r.kind != "CPU").lower()
    for u in unregistered_drivers():
        if u.vendor.split()[0].lower() in listed:  # registered in a way icd.py does not model
            continue
        print(f"{u.vendor}'s OpenCL driver is installed ({u.library}) but no ICD file registers it, so its GPU "
              f"is not listed (common in containers). Register it (as root): {u.fix}")
    if args.variants and rows:
        _print_variants(cl, [r for r in rows if r.selected] if args.device is None else
                        [r for r in rows if r.index == args.device])
    if not args.opencl_only:
        _print_rig_devices()
    return 0


def _print_variants(cl, rows) -> None:
    """The kernel width each kernel gets on each device, and why wider ones were refused."""
    import importlib

    for module in ("clsas.focus.engine", "clsas.formation.ffbp", "clsas.formation.omega_k"):
        importlib.import_module(module)  # their plans register their kernels in cl.KERNELS
    if not rows:
        raise ValueError("--variants --device: no such device (see the P:D numbers above)")
    for r in rows:
        q = cl.get_queue(r.index)
        print(f"kernel variants on {r.index} {r.device} (verdicts in {cl.cache_dir()}):")
        for name in cl.KERNELS:
            for w in cl.candidate_widths(q.device):
                v = cl.check(q, name, w)
                print(f"  {name:15s} VEC={w:<2d} {'ok  ' if v.ok else 'NO  '} {v.reason} [{v.source}]")
                if v.ok:
                    break


def _print_rig_devices() -> None:
    from clsas.rig.audio import list_audio_devices

    print()
    try:
        rows = list_audio_devices()
    except ImportError as exc:
        print(f"audio devices: unavailable ({exc})")
        rows = None
    if rows is not None:
        print("audio devices (for [audio] device in rig.toml):" if rows else "audio devices: none found")
        for r in rows:
            rates = ", ".join(f"{fs // 1000} kHz" for fs in r["rates_hz"]) or "neither 96 nor 192 kHz"
            print(f"  {r['index']:2d} {r['name']} | {r['hostapi']} | {r['inputs']} in, {r['outputs']} out | "
                  f"default {r['default_hz']:g} Hz | {rates}")
    print()
    try:
        from serial.tools import list_ports
    except ImportError:
        from clsas.validate import install_hint

        print(f"serial ports: unavailable ({install_hint('rig')} for pyserial)")
        return
    ports = list_ports.comports()
    print("serial ports (for [stage] port):" if ports else "serial ports: none found")
    for p in ports:
        print(f"  {p.device} | {p.description} | {p.hwid}")


def add_parser(sub) -> None:
    dv = sub.add_parser("devices", help="list OpenCL devices, audio devices and serial ports")
    dv.add_argument("--opencl-only", action="store_true", help="only the OpenCL devices")
    dv.add_argument("--variants", action="store_true",
                    help="check (or read the stored verdicts of) each kernel's vector width on the device")
    dv.add_argument("--device", default=None, help="P:D: the device for --variants (default: the one auto uses)")
    dv.add_argument("--clear-cache", action="store_true",
                    help="forget the stored kernel-variant verdicts (they are probed again on next use)")
    dv.set_defaults(func=cmd_devices)
