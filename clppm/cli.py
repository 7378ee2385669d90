"""Command line: clppm devices | trace | render | samples | compare | reflectance | fit.

Every command takes ``--device`` (else ``PYOPENCL_CTX``, else the first GPU, else the
first device).  Bad input ends with one line naming the file, key and value (exit 2);
device problems with the device name and what to do (exit 3).
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from .config import ConfigError


def _res(s: str):
    try:
        w, h = s.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--resolution {s!r}: expected WxH, e.g. 320x240") from None


def _add_device(p):
    p.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' as `clppm devices` lists, an implementation "
                   "(pocl, intel, nvidia, ...) or part of its platform or device name")


def cmd_devices(a) -> int:
    from .device import compiler_problem, describe, list_devices, NO_PLATFORM_HELP
    devs = list_devices()
    if not devs:
        print(NO_PLATFORM_HELP, file=sys.stderr)
        return 3
    for ip, idev, plat, dev in devs:
        d = describe(dev)
        print(f"{ip}:{idev}  {d['name']}  [{d['implementation']}: {d['platform']} {d['platform_version']}; "
              f"{d['type']}; {d['compute_units']} CUs; "
              f"{d['global_mem_bytes'] / 2**30:.1f} GiB, max alloc {d['max_alloc_bytes'] / 2**30:.1f} GiB; "
              f"fp64 {'yes' if d['fp64'] else 'no'}; int64 atomics {'yes' if d['int64_atomics'] else 'no'}]")
        why = compiler_problem(dev)
        print(f"      not usable: {why}" if why else "      compiler check: builds kernels")
        if a.kernels and not why:
            from .tiny import print_kernel_report
            print_kernel_report(f"{ip}:{idev}")
    return 0


def _load(path):
    from . import config
    return config.load(path)


def _write_json(path: str, obj) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f, indent=1)


def cmd_trace(a) -> int:
    from . import config, device, paths, transport, volume
    if (a.config is None) == (a.slab is None):
        raise ConfigError("clppm trace", "CONFIG/--slab", None, "give a config file or --slab, not both")
    if a.slab is not None:
        cfg = config.slab_config(a.slab)
        src = "--slab"
    else:
        cfg = _load(a.config)
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
    pp = transport.PhotonPass(dev, vol, cfg)
    rep = transport.trace_report(pp, a.photons, batches=min(a.batches, a.photons))
    rep["device"] = dev.name
    rep["seed"] = cfg["render"]["seed"]
    print(f"{src}: {a.photons} photons on {dev.name} (seed {rep['seed']})")
    for k in ("specular", "Rd", "Tt", "A"):
        print(f"  {k:9s} {rep[k]:.6f} ± {rep[k + '_se']:.6f}")
    print(f"  lost {rep['lost']:.6f}  missed {rep['missed']:.6f}  roulette net {rep['roulette_net']:+.2e}"
          f"  energy balance error {rep['energy_balance_error']:.1e}")
    if len(vol.wl) > 1 and a.bands:
        print("  band    Rd       Tt       A")
        for wl, r in rep["per_band"].items():
            print(f"  {wl:>5s}  {r['Rd']:.4f}  {r['Tt']:.4f}  {r['A']:.4f}")
    if a.json:
        _write_json(a.json, rep)
    return 0


def _scheduler(a) -> tuple[str | None, str]:
    """--scheduler, else CLPPM_SCHEDULER unless a local device was chosen; and its name."""
    if a.scheduler:
        if a.devices or a.device:
            raise ConfigError("command line", "--scheduler", a.scheduler,
                              "give --scheduler, --devices or --device, not two of them")
        return a.scheduler, "--scheduler"
    env = os.environ.get("CLPPM_SCHEDULER") or None
    if a.devices and a.device:
        raise ConfigError("command line", "--devices", a.devices, "give --devices or --device, not both")
    return (None if a.devices or a.device else env), "CLPPM_SCHEDULER"


def cmd_render(a) -> int:
    from . import config
    from . import progressive as render
    cfg = _load(a.config)
    if a.preview_every is not None:
        cfg = config.override(cfg, "render", "preview_every", a.preview_every)
    for item in a.set or []:
        cfg = config.set_item(cfg, item)
    if a.integrator == "pt":
        return _render_pt(a, cfg)
    if a.paper:
        cfg = config.paper_mode(cfg)
    for key, flag in (("radius", a.radius), ("estimator", a.estimator), ("storage", a.storage),
                      ("bands_per_path", a.bands_per_path)):
        if flag is not None:
            cfg = config.override(cfg, "render", key, flag)
    scheduler, flag = _scheduler(a)
    kw = dict(method=a.method, passes=a.passes, photons=a.photons, resolution=a.resolution, seed=a.seed,
              spacing=a.spacing, out=a.output, progress=not a.quiet, resume=a.resume,
              source=os.path.basename(a.config))
    if scheduler or a.devices:
        try:
            from . import executor
        except ImportError as e:
            raise ConfigError("command line", flag if scheduler else "--devices", scheduler or a.devices,
                              f"needs dask.distributed ({e}): pip install 'clppm[dask]'") from None
        try:
            res = executor.render_distributed(cfg, scheduler=scheduler, devices=a.devices,
                                              scheduler_flag=flag, **kw)
        except executor.ExecutorError as e:
            print(f"clppm: error: {e}", file=sys.stderr)
            return 2
    else:
        res = render.render(cfg, device=a.device, **kw)
    r = res.report
    print(f"wrote {a.output} (+ .png, .json): method {r['scheme']}, {r['passes_done']} passes"
          f"{' (interrupted: resume with --resume ' + render.ckpt.default_path(a.output) + ')' if r['interrupted'] else ''}, "
          f"{r['photons_emitted']} photons emitted, {r['sample_points']} sample points, "
          f"{r['seconds']['total']:.1f} s on {r['device']['name']}")
    return 0


def _render_pt(a, cfg) -> int:
    from .checkpoint import default_path
    from .pathtracer import render_pt
    for flag, v in (("--method", a.method), ("--spacing", a.spacing), ("--photons", a.photons),
                    ("--paper", a.paper or None), ("--estimator", a.estimator), ("--storage", a.storage),
                    ("--bands-per-path", a.bands_per_path), ("--radius", a.radius)):
        if v is not None:
            raise ConfigError("command line", flag, v, "applies to --integrator ppm only")
    res = render_pt(cfg, passes=a.passes, resolution=a.resolution, seed=a.seed, device=a.device,
                    out=a.output, progress=not a.quiet, resume=a.resume,
                    source=os.path.basename(a.config))
    r = res.report
    print(f"wrote {a.output} (+ .png, .json): path tracer, {r['passes_done']} passes"
          f"{' (interrupted: resume with --integrator pt --resume ' + default_path(a.output) + ')' if r['interrupted'] else ''}, "
          f"{r['paths_traced']} paths, {r['mean_vertices_per_path']:.1f} vertices per path, "
          f"{r['seconds']['total']:.1f} s on {r['device']['name']}")
    return 0


def cmd_samples(a) -> int:
    from . import device, eyepass, paths, transport, volume
    from . import progressive as render
    from .skin import PAPER_TABLE1
    cfg = render.apply_overrides(_load(a.config), method=a.method, spacing=a.spacing,
                                 resolution=a.resolution)
    paths.check_writable(a.json, "--json")
    vol = volume.build(cfg, os.path.basename(a.config))
    dev = device.open_device(a.device)
    vb = transport.upload_volume(dev, vol)
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
        _write_json(a.json, out)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="clppm", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("devices", help="list OpenCL platforms and devices")
    _add_device(p)
    p.add_argument("--kernels", action="store_true", help="run a tiny scene through every kernel "
                   "on each usable device; print each kernel's private memory, work-group limit and local size")
    p.set_defaults(func=cmd_devices)

    p = sub.add_parser("trace", help="photon pass tallies (Rd, Tt, A, specular) of a config or slab")
    p.add_argument("config", nargs="?")
    p.add_argument("--slab", help="homogeneous slab: mua=10,mus=90,g=0.75,n=1.0,d=0.02 (cm^-1, cm)")
    p.add_argument("--photons", type=int, default=1_000_000)
    p.add_argument("--batches", type=int, default=10, help="batches for the standard errors")
    p.add_argument("--seed", type=int)
    p.add_argument("--bands", action="store_true", help="print the per-band table")
    p.add_argument("--json")
    _add_device(p)
    p.set_defaults(func=cmd_trace)

    p = sub.add_parser("render", help="progressive photon mapping render (or --integrator pt)")
    p.add_argument("config")
    p.add_argument("--integrator", choices=("ppm", "pt"), default="ppm",
                   help="ppm: progressive photon mapping (default); pt: the unbiased path tracer "
                        "(flat scenes, point light; render.pt_samples_per_pass paths per pixel per pass)")
    p.add_argument("--method", choices=list("abcdef"))
    p.add_argument("--spacing", type=float, help="equal spacing in um (any value)")
    p.add_argument("--passes", type=int)
    p.add_argument("--photons", type=int, help="stored photons per pass")
    p.add_argument("--resolution", type=_res)
    p.add_argument("--seed", type=int)
    p.add_argument("--resume", help="continue from a checkpoint (.ckpt.npz)")
    p.add_argument("--preview-every", type=int, help="write a preview PNG every K passes")
    p.add_argument("--paper", action="store_true",
                   help="the paper's design: every scattering event stored, one band per path, the "
                        "sphere estimator, the per-point radius (configs/forearm_paper.toml: with its budget)")
    p.add_argument("--estimator", choices=("beam", "layer", "clip", "sphere"),
                   help="render.estimator (default beam; sphere is the paper's)")
    p.add_argument("--storage", choices=("importance", "all"),
                   help="render.storage: importance-driven (default) or every event (the paper)")
    p.add_argument("--bands-per-path", type=int, help="render.bands_per_path (0: auto, 1: the paper's)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="any config value, e.g. --set render.store_scale=30 (TOML syntax for the value)")
    p.add_argument("--radius", choices=("ppm", "global"),
                   help="render.radius: per-point (ppm) or global (Knaus & Zwicker; needed to distribute)")
    p.add_argument("-o", "--output", default="out/render.exr")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--devices", help="'all' or P:D,P:D: a local Dask cluster, one worker per listed "
                   "device (a device listed twice gets two workers)")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (default: "
                   "$CLPPM_SCHEDULER unless --device/--devices is given)")
    _add_device(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("samples", help="mean sample points per eye ray per layer (Table 1)")
    p.add_argument("config")
    p.add_argument("--method", choices=list("abcdef"))
    p.add_argument("--spacing", type=float)
    p.add_argument("--resolution", type=_res)
    p.add_argument("--json")
    _add_device(p)
    p.set_defaults(func=cmd_samples)

    for extra in ("compare", "reflectance", "fit"):
        try:
            mod = __import__(f"clppm.{extra}", fromlist=["add_parser"])
        except ImportError:
            continue
        mod.add_parser(sub, _add_device)

    a = ap.parse_args(argv)
    from .checkpoint import CheckpointError
    from .device import DeviceError
    try:
        return a.func(a)
    except ConfigError as e:
        print(f"clppm: error: {e}", file=sys.stderr)
        return 2
    except CheckpointError as e:
        print(f"clppm: error: {e}", file=sys.stderr)
        return 2
    except DeviceError as e:
        print(f"clppm: device error: {e}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print("clppm: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
