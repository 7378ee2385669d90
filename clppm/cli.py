"""Command line: clppm devices | config | trace | render | samples | compare | reflectance | fit.

Every command takes ``--device`` (else ``PYOPENCL_CTX``, else the first GPU, else the
first device), ``-q`` and ``-v``.  Exit codes (:data:`EXIT`): 0 a finished job; 1 an internal
error; 2 bad input (one line naming the file, key and value, before any work); 3 a device
problem (the device and what to do); 130 / 143 a render stopped by SIGINT / SIGTERM (what it
had is written, with a checkpoint to resume).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys

from .config import ConfigError

#: exit codes, as the README's table lists them
EXIT = {"ok": 0, "internal": 1, "input": 2, "device": 3, "sigint": 128 + signal.SIGINT,
        "sigterm": 128 + signal.SIGTERM}

#: the six sample-point schemes (paper section 5), one line each for --help
METHODS_HELP = {
    "a": "equal spacing 4 um along the eye ray (the paper's densest)",
    "b": "equal spacing 7 um",
    "c": "equal spacing 14 um",
    "d": "random spacing, mean 1/extinction of the layer, extinction the max over the bands",
    "e": "as d with the mean over the bands (the default)",
    "f": "as d with the min over the bands (the sparsest)",
}


def _res(s: str):
    try:
        w, h = s.lower().split("x")
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--resolution {s!r}: expected WxH, e.g. 320x240") from None


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Examples kept as written; each option's default shown unless its help says it."""

    def _get_help_string(self, action):
        h = action.help or ""
        if (action.default not in (None, False, argparse.SUPPRESS) and "default" not in h
                and action.option_strings and action.nargs != 0):
            h += " (default: %(default)s)"
        return h


class _Parser(argparse.ArgumentParser):
    def __init__(self, *a, **k):
        k.setdefault("formatter_class", _Formatter)
        super().__init__(*a, **k)


def _add_device(p):
    """--device, -q and -v: every command has them (commands in other modules call this too)."""
    p.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' as `clppm devices` lists, an implementation (pocl, "
                        "intel, nvidia, ...) or part of its platform or device name (default: "
                        "$PYOPENCL_CTX, else the first GPU, else the preferred CPU implementation)")
    if "-q" not in p._option_string_actions:
        p.add_argument("-q", "--quiet", action="store_true", help="no progress or status lines")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="details after an error (the full message, a traceback for internal errors)")


def _versions() -> str:
    """clppm, pyopencl and the OpenCL platforms found, one a line."""
    from . import __version__
    lines = [f"clppm {__version__}"]
    try:
        import pyopencl as cl
        lines.append(f"pyopencl {cl.VERSION_TEXT}")
        try:
            plats = cl.get_platforms()
        except cl.Error:
            plats = []
        for pl in plats:
            lines.append(f"OpenCL platform: {pl.name.strip()} ({pl.version.strip()})")
        if not plats:
            lines.append("OpenCL platform: none found (pip install 'clppm[pocl]' gives a CPU one)")
    except ImportError as e:
        lines.append(f"pyopencl: not importable ({e})")
    return "\n".join(lines)


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
    """A config file, or the name of a shipped one (``forearm``)."""
    from . import config
    return config.load(config.find(path))


def _write_json(path: str, obj) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f, indent=1)


def cmd_trace(a) -> int:
    from . import config, device, paths, photonpass, volume
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
    pp = photonpass.PhotonPass(dev, vol, cfg)
    rep = photonpass.trace_report(pp, a.photons, batches=min(a.batches, a.photons))
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


class InputError(ValueError):
    """Bad input whose message is already the whole line (e.g. the executor's)."""


def _method_or_spacing(a) -> None:
    if a.method is not None and a.spacing is not None:
        raise ConfigError("command line", "--method", a.method,
                          f"give --method or --spacing, not both (--spacing {a.spacing:g} is "
                          "equal spacing, i.e. methods a-c at any spacing)")


def _render_config(a) -> dict:
    """The config with every command-line change applied (checked like the file's values)."""
    from . import config
    cfg = _load(a.config)
    if a.preview_every is not None:
        cfg = config.override(cfg, "render", "preview_every", a.preview_every)
    for item in a.set or []:
        cfg = config.set_item(cfg, item)
    if a.integrator == "ppm":
        _method_or_spacing(a)
        if a.paper:
            cfg = config.paper_mode(cfg)
        for key, flag in (("radius", a.radius), ("estimator", a.estimator), ("storage", a.storage),
                          ("bands_per_path", a.bands_per_path)):
            if flag is not None:
                cfg = config.override(cfg, "render", key, flag)
    return cfg


def _check_render_paths(a, cfg) -> None:
    """-o, its sidecars, --resume and --passes against the checkpoint: before any work."""
    from . import paths
    from .driver import check_resume_passes
    paths.check_render_output(a.output)
    passes = a.passes if a.passes is not None else cfg["render"]["passes"]
    check_resume_passes(a.resume, passes, "--passes" if a.passes is not None else "render.passes")


def cmd_render(a) -> int:
    from . import paths
    from .driver import interrupt_signal
    cfg = _render_config(a)
    _check_render_paths(a, cfg)
    with paths.OutputLock(a.output):
        paths.check_checkpoint_free(a.output, a.resume, a.force)
        if a.integrator == "pt":
            res = _render_pt(a, cfg)
        else:
            res = _render_ppm(a, cfg)
    r = res.report
    files = paths.render_outputs(a.output)
    side = ", ".join(os.path.basename(files[k]) for k in ("png", "report", "checkpoint") if k in files)
    what = (f"path tracer, {r['passes_done']} passes, {r['paths_traced']} paths, "
            f"{r['mean_vertices_per_path']:.1f} vertices per path" if a.integrator == "pt" else
            f"method {r['scheme']}, {r['passes_done']} passes, {r['photons_emitted']} photons emitted, "
            f"{r['sample_points']} sample points")
    print(f"wrote {a.output} (+ {side}): {what}, {r['seconds']['total']:.1f} s on {r['device']['name']}")
    if r["interrupted"]:
        sig = interrupt_signal() or signal.SIGINT
        again = " ".join(["clppm render", a.config, "-o", a.output] + (["--integrator pt"] if a.integrator == "pt" else [])
                         + ["--resume", files["checkpoint"]])
        print(f"interrupted by {signal.Signals(sig).name} after pass {r['passes_done']} of "
              f"{r['passes_requested']}: resume with --resume {files['checkpoint']} ({again})")
        return EXIT["sigterm"] if sig == signal.SIGTERM else EXIT["sigint"]
    return EXIT["ok"]


def _render_ppm(a, cfg):
    from . import progressive as render
    scheduler, flag = _scheduler(a)
    kw = dict(method=a.method, passes=a.passes, photons=a.photons, resolution=a.resolution, seed=a.seed,
              spacing=a.spacing, out=a.output, progress=not a.quiet, resume=a.resume,
              source=os.path.basename(a.config))
    if not (scheduler or a.devices):
        return render.render(cfg, device=a.device, **kw)
    try:
        from . import executor
    except ImportError as e:
        raise ConfigError("command line", flag if scheduler else "--devices", scheduler or a.devices,
                          f"needs dask.distributed ({e}): pip install 'clppm[dask]'") from None
    try:
        return executor.render_distributed(cfg, scheduler=scheduler, devices=a.devices,
                                           scheduler_flag=flag, **kw)
    except executor.ExecutorError as e:
        raise InputError(str(e)) from None


def _render_pt(a, cfg):
    from .driver import say
    from .pathtracer import render_pt
    for flag, v in (("--method", a.method), ("--spacing", a.spacing), ("--photons", a.photons),
                    ("--paper", a.paper or None), ("--estimator", a.estimator), ("--storage", a.storage),
                    ("--bands-per-path", a.bands_per_path), ("--radius", a.radius)):
        if v is not None:
            raise ConfigError("command line", flag, v, "applies to --integrator ppm only")
    say(not a.quiet, "path tracer: building the volume...")
    return render_pt(cfg, passes=a.passes, resolution=a.resolution, seed=a.seed, device=a.device,
                     out=a.output, progress=not a.quiet, resume=a.resume,
                     source=os.path.basename(a.config))


def cmd_samples(a) -> int:
    from . import device, eyepass, paths, volume
    from . import progressive as render
    from .skin import PAPER_TABLE1
    _method_or_spacing(a)
    cfg = render.apply_overrides(_load(a.config), method=a.method, spacing=a.spacing,
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
        _write_json(a.json, out)
    return 0


def cmd_config(a) -> int:
    from . import config as C
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


class _Version(argparse.Action):
    def __init__(self, option_strings, dest, **k):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **k)

    def __call__(self, parser, namespace, values, option_string=None):
        print(_versions())
        parser.exit(0)


class _Terminated(BaseException):
    """SIGTERM outside a render's passes (a render finishes its pass and exits 143 itself)."""


def _on_sigterm(sig, frame):
    raise _Terminated


TOP_EPILOG = """\
examples:
  clppm render forearm -o out/forearm.exr          the shipped forearm scene (a few minutes)
  clppm render forearm --resolution 64x48 --passes 2 --photons 20000 -o out/smoke.png
                                                   a smoke test (under a minute)
  clppm config --example forearm > my.toml         a complete config to edit
  clppm config --schema                            every config key: type, default, range, meaning
  clppm trace --slab mua=10,mus=90,g=0.75,n=1.0,d=0.02
  clppm COMMAND --help                             that command's options

exit codes: 0 finished; 1 internal error; 2 bad input; 3 device error;
            130 interrupted (SIGINT); 143 terminated (SIGTERM)
"""

RENDER_EPILOG = "sample-point methods (--method, render.method):\n" + "".join(
    f"  {m}  {t}\n" for m, t in METHODS_HELP.items()) + """
outputs of -o NAME.exr: NAME.exr (spectral + linear sRGB EXR), NAME.png (sRGB), NAME.json (run
report), NAME.ckpt.npz (checkpoint); -o NAME.png writes the PNG, .json and .ckpt.npz only.

examples:
  clppm render forearm -o out/forearm.exr
  clppm render forearm --method b --passes 20 -o out/b.exr
  clppm render forearm -o out/forearm.exr --resume out/forearm.ckpt.npz --passes 12
  clppm render configs/forearm_flat.toml --integrator pt --passes 50 -o out/pt.exr
  clppm render forearm --set layer.0.n=1.45 --set render.seed=3 -o out/n145.png
  clppm render forearm --paper -o out/paper.exr
"""


def _parser_render(sub) -> None:
    p = sub.add_parser("render", help="render a config: progressive photon mapping (or --integrator pt)",
                       description="Render a config file (or a shipped one by name: forearm, cheek, ...).",
                       epilog=RENDER_EPILOG)
    p.add_argument("config", help="config file, or the name of a shipped config (`clppm config --example`)")
    p.add_argument("--integrator", choices=("ppm", "pt"), default="ppm",
                   help="ppm: progressive photon mapping; pt: the unbiased path tracer "
                        "(flat scenes, point light; render.pt_samples_per_pass paths per pixel per pass)")
    p.add_argument("--method", choices=list("abcdef"),
                   help="sample-point scheme, see below (default: the config's render.method)")
    p.add_argument("--spacing", type=float, help="equal spacing of sample points in um, any value "
                   "(instead of --method; default: the method's)")
    p.add_argument("--passes", type=int, help="passes in all, counting a resumed checkpoint's "
                   "(default: the config's render.passes)")
    p.add_argument("--photons", type=int, help="stored photons per pass (default: the config's render.photons)")
    p.add_argument("--resolution", type=_res, help="WxH pixels (default: the config's camera.resolution)")
    p.add_argument("--seed", type=int, help="random seed (default: the config's render.seed)")
    p.add_argument("--resume", metavar="CKPT", help="continue from a checkpoint (NAME.ckpt.npz)")
    p.add_argument("--force", action="store_true",
                   help="start over even though -o's checkpoint of an earlier render exists (it is replaced)")
    p.add_argument("--preview-every", type=int, metavar="K",
                   help="write NAME.preview.png every K passes (default: the config's render.preview_every)")
    p.add_argument("--paper", action="store_true",
                   help="the paper's design: every scattering event stored, one band per path, the "
                        "sphere estimator, the per-point radius (configs/forearm_paper.toml: with its budget)")
    p.add_argument("--estimator", choices=("beam", "layer", "clip", "sphere"),
                   help="render.estimator (default: the config's; beam in the default mode, sphere the paper's)")
    p.add_argument("--storage", choices=("importance", "all"),
                   help="render.storage: importance-driven or every event (the paper) (default: the config's)")
    p.add_argument("--bands-per-path", type=int,
                   help="render.bands_per_path (0: auto, 1: the paper's) (default: the config's)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="any config value, SECTION.KEY=VALUE or layer.N.KEY=VALUE (N: index of the "
                        "[[layer]], from 0), e.g. --set render.store_scale=30 --set layer.0.n=1.45; "
                        "TOML syntax for the value; repeatable")
    p.add_argument("--radius", choices=("ppm", "global"),
                   help="render.radius: per-point (ppm) or global (Knaus & Zwicker; needed to distribute) "
                        "(default: the config's)")
    p.add_argument("-o", "--output", default="out/render.exr",
                   help="NAME.exr (spectral + RGB EXR, and NAME.png) or NAME.png (the PNG alone); "
                        "NAME.json and NAME.ckpt.npz beside it")
    p.add_argument("--devices", help="'all' or P:D,P:D: a local Dask cluster, one worker per listed "
                   "device (a device listed twice gets two workers)")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (default: "
                   "$CLPPM_SCHEDULER unless --device/--devices is given)")
    _add_device(p)
    p.set_defaults(func=cmd_render)


def _parser_simple(sub) -> None:
    p = sub.add_parser("devices", help="list OpenCL platforms and devices (P:D for --device)")
    _add_device(p)
    p.add_argument("--kernels", action="store_true", help="run a tiny scene through every kernel "
                   "on each usable device; print each kernel's private memory, work-group limit and local size")
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
    _add_device(p)
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("trace", help="photon pass tallies (Rd, Tt, A, specular) of a config or slab")
    p.add_argument("config", nargs="?", help="config file or shipped name (or --slab)")
    p.add_argument("--slab", help="homogeneous slab: mua=10,mus=90,g=0.75,n=1.0,d=0.02 (cm^-1, cm)")
    p.add_argument("--photons", type=int, default=1_000_000, help="photons to trace")
    p.add_argument("--batches", type=int, default=10, help="batches for the standard errors")
    p.add_argument("--seed", type=int, help="random seed (default: the config's render.seed)")
    p.add_argument("--bands", action="store_true", help="print the per-band table")
    p.add_argument("--json", help="write the tallies as JSON to this file")
    _add_device(p)
    p.set_defaults(func=cmd_trace)

    p = sub.add_parser("samples", help="mean sample points per eye ray per layer (Table 1)")
    p.add_argument("config", help="config file or shipped name")
    p.add_argument("--method", choices=list("abcdef"),
                   help="sample-point scheme (default: the config's render.method): "
                        + "; ".join(f"{m} {t}" for m, t in METHODS_HELP.items()))
    p.add_argument("--spacing", type=float, help="equal spacing in um instead of --method")
    p.add_argument("--resolution", type=_res, help="WxH eye rays (default: the config's camera.resolution)")
    p.add_argument("--json", help="write the counts as JSON to this file")
    _add_device(p)
    p.set_defaults(func=cmd_samples)


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="clppm", epilog=TOP_EPILOG,
                 description=__doc__.splitlines()[0] + "\n\nsample-point methods (render --method):\n"
                 + "".join(f"  {m}  {t}\n" for m, t in METHODS_HELP.items()))
    ap.add_argument("--version", action=_Version, help="clppm, pyopencl and the OpenCL platforms found")
    sub = ap.add_subparsers(dest="cmd", metavar="COMMAND", parser_class=_Parser)
    _parser_simple(sub)
    _parser_render(sub)
    for extra in ("compare", "reflectance", "fit"):
        mod = __import__(f"clppm.{extra}", fromlist=["add_parser"])
        mod.add_parser(sub, _add_device)
    return ap


def _device_line(e, verbose: bool) -> str:
    """A device error on one line: its indented detail lines only with --verbose."""
    lines = str(e).splitlines()
    if verbose:
        return str(e)
    return " ".join(ln.strip() for ln in lines if ln and not ln[0].isspace())


def main(argv=None) -> int:
    ap = build_parser()
    argv = sys.argv[1:] if argv is None else [str(x) for x in argv]
    if not argv:
        ap.print_help(sys.stderr)
        return EXIT["input"]
    a = ap.parse_args(argv)
    if a.cmd is None:
        ap.error("give a COMMAND")
    from .checkpoint import CheckpointError
    from .device import DeviceError
    verbose = getattr(a, "verbose", False)
    try:
        old = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:                       # not the main thread
        old = None
    try:
        return a.func(a)
    except (ConfigError, CheckpointError, InputError) as e:
        print(f"clppm: error: {e}", file=sys.stderr)
        return EXIT["input"]
    except DeviceError as e:
        print(f"clppm: device error: {_device_line(e, verbose)}", file=sys.stderr)
        return EXIT["device"]
    except KeyboardInterrupt:
        print("clppm: interrupted", file=sys.stderr)
        return EXIT["sigint"]
    except _Terminated:
        print("clppm: terminated", file=sys.stderr)
        return EXIT["sigterm"]
    except Exception as e:                   # a bug: one line, the traceback with --verbose
        if verbose:
            import traceback
            traceback.print_exc()
        print(f"clppm: internal error: {type(e).__name__}: {' '.join(str(e).split())}"
              + ("" if verbose else " (--verbose shows the traceback)"), file=sys.stderr)
        return EXIT["internal"]
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)


if __name__ == "__main__":
    sys.exit(main())
