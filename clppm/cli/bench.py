"""``clppm bench``: photons/ms on the standard scenes and the gather's pairs/s, per device."""
from __future__ import annotations

import json
import sys

from ..config import ConfigError
from .options import add_device


def _devices(a) -> tuple[list, list]:
    """([(spec, Device)], [{"spec", "reason"}]): ``--devices all`` every device that passes its
    compiler check and self-test (the others skipped with the reason), else ``--device``'s."""
    from ..compute import device
    if a.devices is None:
        dev = device.open_device(a.device)
        return [(device.device_spec(dev.device), dev)], []
    if a.device is not None:
        raise ConfigError("command line", "--devices", a.devices, "give --device or --devices, not both")
    if a.devices != "all":
        raise ConfigError("command line", "--devices", a.devices, "expected 'all'")
    usable, skipped = [], []
    for ip, idev, _, d in device.list_devices():
        spec = f"{ip}:{idev}"
        why = device.device_problem(d, spec)
        if why is None:
            usable.append((spec, device.open_device(spec)))
        else:
            skipped.append({"spec": spec, "device": d.name.strip(), "reason": why})
    if not usable:
        raise device.DeviceError("no device passed its self-test: "
                                 + "; ".join(f"{s['spec']} {s['reason']}" for s in skipped))
    return usable, skipped


def cmd_bench(a) -> int:
    from ..analysis import bench
    from ..version import __version__
    if a.repeats is not None and a.repeats < 1:
        raise ConfigError("command line", "--repeats", a.repeats, "must be >= 1")
    sizes = bench.Sizes.quick() if a.quick else bench.Sizes()
    if a.repeats is not None:
        sizes.repeats = a.repeats
    devs, skipped = _devices(a)
    out = {"clppm": __version__, "quick": a.quick, "repeats": sizes.repeats,
           "devices": [], "skipped": skipped}
    for s in skipped:
        print(f"{s['spec']}  {s['device']}: skipped, {s['reason']}", file=sys.stderr)
    for spec, dev in devs:
        entry = bench.device_bench(dev, sizes, spec, gather=not a.no_gather)
        out["devices"].append(entry)
        if not a.json:
            print("\n".join(bench.speed_lines(entry)), flush=True)
    if a.json:
        print(json.dumps(out, indent=1))
    return 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "bench", help="photons/ms on the MCML slab and the forearm, the gather's pairs/s, per device",
        epilog="examples:\n  clppm bench --quick               the selected device, a short run\n"
               "  clppm bench --devices all --json   every device that passes its self-test, as JSON\n\n"
               "Times exclude the program builds (a warm-up launch first); each rate is the fastest\n"
               "of --repeats timed runs, the median beside it.")
    p.add_argument("--devices", metavar="all", help="'all': every device that passes its self-test "
                   "(default: the one --device selects)")
    p.add_argument("--quick", action="store_true", help="a short run (under a minute per device "
                   "on 2 CPU cores): fewer photons, a 32x24 gather")
    p.add_argument("--repeats", type=int, help="timed runs per measurement (default: 5, --quick 3)")
    p.add_argument("--no-gather", action="store_true", help="photons/ms only (the gather's set-up "
                   "builds the forearm's eye pass and photon grid)")
    p.add_argument("--json", action="store_true", help="the results as JSON on stdout (clppm, quick, "
                   "repeats, devices: spec, device, implementation, version, scenes, gather; skipped)")
    add_device(p)
    p.set_defaults(func=cmd_bench)
