"""``clppm devices | config | trace | samples``: the commands that render nothing."""
from __future__ import annotations

import json
import os
import sys

from ..config import ConfigError
from .options import (METHODS_HELP, add_device, load_config, method_or_spacing, resolution_arg,
                      write_json)


def cmd_devices(a) -> int:
    """Each OpenCL device, its compiler check and its known-answer self-test (cached; ``--check``
    reruns it); ``--json`` the same as a list for scripts (CI picks the devices to test on)."""
    from ..compute.device import (NO_PLATFORM_HELP, compiler_problem, describe, device_spec,
                                  list_devices, select_device, self_test)
    devs = list_devices()
    if not devs:
        print(NO_PLATFORM_HELP, file=sys.stderr)
        return 3
    only = None
    if a.device is not None:
        os.environ["CLPPM_SELF_TEST"] = "0"           # choose without testing: tested below
        only = device_spec(select_device(a.device))
    rows = []
    for ip, idev, plat, dev in devs:
        spec = f"{ip}:{idev}"
        if only is not None and spec != only:
            continue
        d = describe(dev)
        why = compiler_problem(dev)
        test = None if why else self_test(dev, spec, rerun=a.check)
        rows.append({"spec": spec, **d, "compiler_problem": why,
                     "self_test": None if test is None else {
                         "passed": test.passed, "seconds": round(test.seconds, 2),
                         "reason": test.reason, "checked": test.checked, "cached": test.cached},
                     "usable": why is None and test.passed})
        if a.json:
            continue
        print(f"{spec}  {d['name']}  [{d['implementation']}: {d['platform']} {d['platform_version']}; "
              f"{d['type']}; {d['compute_units']} CUs; "
              f"{d['global_mem_bytes'] / 2**30:.1f} GiB, max alloc {d['max_alloc_bytes'] / 2**30:.1f} GiB; "
              f"fp64 {'yes' if d['fp64'] else 'no'}; int64 atomics {'yes' if d['int64_atomics'] else 'no'}]",
              flush=True)
        print(f"      not usable: {why}" if why else f"      {test.line()}", flush=True)
        if a.kernels and not why and test.passed:
            from ..checks.tiny import print_kernel_report
            print_kernel_report(spec)
    if a.json:
        print(json.dumps(rows, indent=1))
    return 0


def cmd_trace(a) -> int:
    from .. import config
    from ..compute import device
    from ..output import paths
    from ..integrators import photonpass
    from ..scene import volume
    if (a.config is None) == (a.slab is None):
        raise ConfigError("clppm trace", "CONFIG/--slab", None, "give a config file or --slab, not both")
    slab = None
    if a.slab is not None:
        slab = config.parse_slab(a.slab)
        cfg = config.slab_config(slab)
        src = "--slab"
    else:
        cfg = load_config(a.config)
        src = os.path.basename(a.config)
    if a.seed is not None:
        cfg = config.override(cfg, "render", "seed", a.seed)
    if a.photons <= 0:
        raise ConfigError("command line", "--photons", a.photons, "must be > 0")
    if a.batches < 2:
        raise ConfigError("command line", "--batches", a.batches, "must be >= 2 (standard errors)")
    paths.check_writable(a.json, "--json")
    vol = volume.build(cfg, src)
    dev = device.open_device(a.device)
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg)
    rep = photonpass.trace_report(pp, a.photons, batches=min(a.batches, a.photons))
    rep["device"] = dev.name
    rep["seed"] = cfg["render"]["seed"]
    if slab is not None:
        rep["slab"] = {**{k: getattr(slab, k) for k in ("mua", "mus", "g", "n", "d")},
                       "not_given": list(slab.defaulted)}
        print(f"--slab {slab.text()} (cm^-1, cm)")
    print(f"{src}: {a.photons} photons on {dev.name} (seed {rep['seed']})")
    for k in ("specular", "Rd", "Tt", "A"):
        print(f"  {k:9s} {rep[k]:.6f} ± {rep[k + '_se']:.6f}")
    print(f"  lost {rep['lost']:.6f}  missed {rep['missed']:.6f}  roulette net {rep['roulette_net']:+.2e}"
          f"  energy balance error {rep['energy_balance_error']:.1e}")
    for i, (name, v) in enumerate(rep.get("absorbed_per_inclusion", {}).items()):
        print(f"  absorbed in {name} ({cfg['inclusion'][i]['kind']}) {v:.6f} ± "
              f"{rep['absorbed_per_inclusion_se'][name]:.6f}")
    if len(vol.wl) > 1 and a.bands:
        print("  band    Rd       Tt       A")
        for wl, r in rep["per_band"].items():
            print(f"  {wl:>5s}  {r['Rd']:.4f}  {r['Tt']:.4f}  {r['A']:.4f}")
    if a.json:
        write_json(a.json, rep)
    return 0


def cmd_samples(a) -> int:
    from ..compute import device
    from ..integrators import eyepass
    from ..output import paths
    from ..scene import volume
    from ..request import resolved_config
    from ..scene.skin import PAPER_TABLE1
    method_or_spacing(a)
    cfg = resolved_config(load_config(a.config), method=a.method, spacing=a.spacing,
                          resolution=a.resolution)
    paths.check_writable(a.json, "--json")
    vol = volume.build(cfg, os.path.basename(a.config))
    dev = device.open_device(a.device)
    vb = volume.upload_volume(dev, vol)
    sch = eyepass.scheme(cfg["render"]["method"], cfg["render"]["spacing_um"])
    ed = eyepass.run(dev, vol, vb, cfg, sch)
    pl = ed.per_layer(vol.nl)
    out = {"method": sch.method, "scheme": sch.label(), "threshold": cfg["render"]["threshold"],
           "rays_hit": int(ed.ray_hit.sum()), "sample_points": ed.npoints,
           "per_layer": {n: float(v) for n, v in zip(vol.names, pl)}}
    ref = PAPER_TABLE1.get(sch.method) if a.spacing is None else None
    print(f"{sch.label()}: mean sample points per eye ray ({out['rays_hit']} rays on the skin)")
    for n, v in zip(vol.names, pl):
        pv = ref.get(n) if ref else None
        extra = f"   paper {pv:6.2f}  ({100 * (v / pv - 1):+.0f} %)" if pv else ""
        print(f"  {n:24s} {v:7.2f}{extra}")
    if a.json:
        write_json(a.json, out)
    return 0


def cmd_config(a) -> int:
    from .. import config as C
    if a.markdown and not a.schema:
        raise ConfigError("command line", "--markdown", True, "goes with --schema")
    if a.schema:
        print(C.schema_markdown() if a.markdown else C.schema_text(), end="")
        return 0
    ship = C.shipped_configs()
    if a.example is not None:
        name = a.example[:-5] if a.example.endswith(".toml") else a.example
        if not name:
            for n, path in ship.items():
                print(f"{n:20s} {_summary(path)}")
            return 0
        if name not in ship:
            raise ConfigError("command line", "--example", a.example,
                              f"no such shipped config (one of {', '.join(ship)})")
        with open(ship[name]) as f:
            print(f.read(), end="")
        return 0
    if a.file is None:
        if a.set:
            raise ConfigError("command line", "--set", a.set[0], "needs a config FILE")
        print(C.to_toml(C.defaults(), "clppm's defaults: every key and its default value.\n"
                        "A config needs at least one [[layer]] with a name and thickness_um;\n"
                        "`clppm config --example forearm` prints a complete one."), end="")
        return 0
    path = C.find(a.file)
    cfg = C.load(path)
    for item in a.set or []:
        cfg = C.set_item(cfg, item)
    print(C.to_toml(cfg, f"{path} as clppm reads it: every key, defaults filled in"
                         + (f", with --set {' '.join(a.set)}" if a.set else "")), end="")
    return 0


def _summary(path: str) -> str:
    """A shipped config's first comment sentence (its header says what it is)."""
    text = []
    with open(path) as f:
        for line in f:
            if not line.startswith("#"):
                break
            text.append(line.lstrip("# ").strip())
    first = " ".join(text).split(". ")[0].split(":")[0]
    return first if len(first) <= 100 else first[:97] + "..."


def add_parsers(sub) -> None:
    p = sub.add_parser("devices", help="list OpenCL platforms and devices (P:D for --device)")
    add_device(p)
    p.add_argument("--kernels", action="store_true", help="run a tiny scene through every kernel "
                   "on each usable device; print each kernel's private memory, work-group limit and local size")
    p.add_argument("--check", action="store_true", help="rerun each device's known-answer self-test "
                   "(else its cached result is shown; it runs by itself the first time a device, "
                   "driver or clppm version is used)")
    p.add_argument("--json", action="store_true", help="the devices, their checks and self-tests "
                       "as JSON (spec, name, implementation, ..., self_test, usable)")
    p.set_defaults(func=cmd_devices)

    p = sub.add_parser("config", help="print the defaults, a config as clppm reads it, a shipped "
                       "config, or the schema of every key",
                       epilog="examples:\n  clppm config                      the defaults\n"
                              "  clppm config forearm              the shipped forearm, every key resolved\n"
                              "  clppm config --example            list the shipped configs\n"
                              "  clppm config --example cheek      the shipped cheek.toml as written\n"
                              "  clppm config --schema --markdown  the reference page docs/config.md\n")
    p.add_argument("file", nargs="?", help="config file or shipped name: print it with every default filled in")
    p.add_argument("--schema", action="store_true", help="every key: type, default, range, meaning")
    p.add_argument("--markdown", action="store_true", help="with --schema: as the Markdown page docs/config.md")
    p.add_argument("--example", nargs="?", const="", metavar="NAME",
                   help="print a shipped config as written (no NAME: list them)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="with FILE: change a value, as render --set")
    add_device(p)
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("trace", help="photon pass tallies (Rd, Tt, A, specular) of a config or slab")
    p.add_argument("config", nargs="?", help="config file or shipped name (or --slab)")
    p.add_argument("--slab", help="homogeneous slab: mua=10,mus=90,g=0.75,n=1.0,d=0.02 (cm^-1, cm)")
    p.add_argument("--photons", type=int, default=1_000_000, help="photons to trace")
    p.add_argument("--batches", type=int, default=10, help="batches for the standard errors")
    p.add_argument("--seed", type=int, help="random seed (default: the config's render.seed)")
    p.add_argument("--bands", action="store_true", help="print the per-band table")
    p.add_argument("--json", help="write the tallies as JSON to this file")
    add_device(p)
    p.set_defaults(func=cmd_trace)

    p = sub.add_parser("samples", help="mean sample points per eye ray per layer (Table 1)")
    p.add_argument("config", help="config file or shipped name")
    p.add_argument("--method", choices=list("abcdef"),
                   help="sample-point scheme (default: the config's render.method): "
                        + "; ".join(f"{m} {t}" for m, t in METHODS_HELP.items()))
    p.add_argument("--spacing", type=float, help="equal spacing in um instead of --method")
    p.add_argument("--resolution", type=resolution_arg, help="WxH eye rays (default: the config's camera.resolution)")
    p.add_argument("--json", help="write the counts as JSON to this file")
    add_device(p)
    p.set_defaults(func=cmd_samples)
