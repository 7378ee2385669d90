"""``clppm render``: progressive photon mapping, the path tracer, or a Dask cluster."""
from __future__ import annotations

import os
import shlex
import signal
import sys

from ..config import ConfigError
from .options import (EXIT, METHODS_HELP, InputError, add_device, load_config, method_or_spacing,
                      resolution_arg)


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


def _render_config(a) -> dict:
    """The config with every command-line change applied (checked like the file's values)."""
    from .. import config
    cfg = load_config(a.config)
    if a.preview_every is not None:
        cfg = config.override(cfg, "render", "preview_every", a.preview_every)
    for item in a.set or []:
        cfg = config.set_item(cfg, item)
    if a.integrator == "ppm":
        method_or_spacing(a)
        if a.paper:
            cfg = config.paper_mode(cfg)
        for key, flag in (("radius", a.radius), ("estimator", a.estimator), ("storage", a.storage),
                          ("bands_per_path", a.bands_per_path)):
            if flag is not None:
                cfg = config.override(cfg, "render", key, flag)
    return cfg


def render_request(a, cfg: dict):
    """The render the command line asks for, as one :class:`clppm.request.RenderRequest`
    (the run's values checked here: a refusal names the flag)."""
    from ..request import RenderRequest
    kw = dict(passes=a.passes, resolution=a.resolution, seed=a.seed)
    if a.integrator == "ppm":
        scheduler, flag = _scheduler(a)
        kw.update(method=a.method, photons=a.photons, spacing=a.spacing,
                  scheduler=scheduler, devices=a.devices, scheduler_flag=flag)
    else:
        _refuse_ppm_flags(a)
    return RenderRequest.of(cfg, a.integrator, device=a.device, out=a.output, progress=not a.quiet,
                            resume=a.resume, source=os.path.basename(a.config), **kw)


def _check_render_paths(a, cfg):
    """-o, its sidecars, the output set, the inputs, the run's values, --resume against the
    checkpoint, and the scene: everything that can be refused before any work.  Returns the
    request (:func:`render_request`)."""
    from .. import config
    from ..output import paths
    from ..scene import scene
    from ..output.checkpoint import check_matches
    from ..integrators.driver import check_resume_passes
    if a.resume and a.force:
        raise ConfigError("command line", "--force", True, "conflicts with --resume (--resume continues "
                          "the checkpoint, --force starts over): give one of them")
    scene.refuse_inclusions(cfg, os.path.basename(a.config), a.integrator)
    paths.check_render_output(a.output)
    paths.check_inputs_not_outputs(a.output, CONFIG=config.find(a.config),
                                   **{"relief.file": cfg["relief"]["file"], "--resume": a.resume})
    paths.check_output_set(a.output, a.resume, a.force)
    passes = a.passes if a.passes is not None else cfg["render"]["passes"]
    check_resume_passes(a.resume, passes, "--passes" if a.passes is not None else "render.passes")
    req = render_request(a, cfg)
    if a.resume:
        check_matches(a.resume, config=req.config_identity())
    scene.refuse(req.resolved(), os.path.basename(a.config))
    return req


def resume_command(a, checkpoint: str) -> str:
    """The command that continues this render, as a shell line: every option that shaped it."""
    words = ["clppm", "render", a.config, "-o", a.output]
    res = f"{a.resolution[0]}x{a.resolution[1]}" if a.resolution else None
    for flag, v in (("--integrator", None if a.integrator == "ppm" else a.integrator),
                    ("--method", a.method), ("--spacing", a.spacing), ("--passes", a.passes),
                    ("--photons", a.photons), ("--resolution", res), ("--seed", a.seed),
                    ("--preview-every", a.preview_every), ("--estimator", a.estimator),
                    ("--storage", a.storage), ("--bands-per-path", a.bands_per_path),
                    ("--radius", a.radius), ("--device", a.device), ("--devices", a.devices),
                    ("--scheduler", a.scheduler)):
        if v is not None:
            words += [flag, f"{v:g}" if isinstance(v, float) else str(v)]
    if a.paper:
        words.append("--paper")
    for item in a.set or []:
        words += ["--set", item]
    return shlex.join(words + ["--resume", checkpoint])


def _import_renderers() -> None:
    """Import the renderers (pyopencl, numpy's and colour's native modules) with SIGINT and
    SIGTERM blocked: the handlers raise, and an exception inside a native module's init aborts
    the process (nanobind: "Critical nanobind error", exit -6) instead of exiting 130 / 143.  A
    signal sent meanwhile is delivered as soon as the mask is restored, before the output lock."""
    sigs = {signal.SIGINT, signal.SIGTERM}
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    except (AttributeError, ValueError, OSError):     # no pthread_sigmask, or not the main thread
        old = None
    try:
        from ..integrators import pathtracer  # noqa: F401
        from ..run import entry, progressive  # noqa: F401
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def cmd_render(a) -> int:
    from ..output import paths
    from ..compute.device import DeviceError
    from ..integrators.driver import interrupt_signal
    cfg = _render_config(a)
    req = _check_render_paths(a, cfg)
    first = cfg["render"]["initial_photons"]
    if a.photons is not None and 1 <= a.photons < first and not a.quiet:
        print(f"clppm: note: render.initial_photons lowered from {first} to --photons {a.photons} "
              "(the first search cannot want more photons than a pass stores)", file=sys.stderr)
    _import_renderers()
    files = paths.render_outputs(a.output)
    with paths.OutputLock(a.output):
        said = paths.check_output_set(a.output, a.resume, a.force).apply()
        if said:
            print(f"clppm: {said}", file=sys.stderr)
        try:
            res = _render(a, req)
        except paths.WriteError as e:
            hint = (f": resume with {resume_command(a, e.checkpoint)}" if e.checkpoint else "")
            raise InputError(f"{e}; {e.kept()}{hint}") from None
        except DeviceError as e:
            if getattr(e, "resume_hint", None):          # the whole command, not the flags alone
                raise DeviceError(str(e).replace(e.resume_hint, resume_command(a, e.checkpoint))) from None
            raise
    r = res.report
    side = ", ".join(os.path.basename(files[k]) for k in ("png", "report", "checkpoint") if k in files)
    what = (f"path tracer, {r['passes_done']} passes, {r['paths_traced']} paths, "
            f"{r['mean_vertices_per_path']:.1f} vertices per path" if a.integrator == "pt" else
            f"method {r['scheme']}, {r['passes_done']} passes, {r['photons_emitted']} photons emitted, "
            f"{r['sample_points']} sample points")
    d = r["device"]
    chosen = f" ({d.get('implementation', '?')}: {d['chosen']})" if d.get("chosen") else ""
    print(f"wrote {a.output} (+ {side}): {what}, {r['seconds']['total']:.1f} s on {d['name']}{chosen}")
    for note in d.get("passed_over", ()):
        print(f"clppm: note: {note}", file=sys.stderr)
    if a.integrator != "pt":
        short = short_passes_note(r)
        if short:
            print(f"clppm: note: {short}", file=sys.stderr)
    if r["interrupted"]:
        sig = interrupt_signal() or signal.SIGINT
        print(f"interrupted by {signal.Signals(sig).name} after pass {r['passes_done']} of "
              f"{r['passes_requested']}: resume with {resume_command(a, files['checkpoint'])}")
        return EXIT["sigterm"] if sig == signal.SIGTERM else EXIT["sigint"]
    return EXIT["ok"]


def short_passes_note(r: dict) -> str | None:
    """A line when the passes stored fewer photons than asked for (a pass ends at its emission
    cap, clppm/integrators/photonpass.py), else None."""
    from ..integrators.photonpass import EMIT_PER_TARGET
    asked = int(r["stored_per_pass"]) * int(r["passes_done"])
    if r["photons_stored"] >= asked:
        return None
    return (f"the passes stored {r['photons_stored']:,} of the {asked:,} photons asked for "
            f"(render.photons x passes): little or none of the light reaches what the camera sees, "
            f"and a pass ends after {EMIT_PER_TARGET} emitted photons per photon to store, so the "
            f"image is noisier than its budget")


def _render(a, req):
    """``req`` through the one render entry (:func:`clppm.run.entry.render`); a cluster needs
    dask.distributed, and its errors are one line."""
    from ..integrators.driver import say
    from ..run import entry
    if req.integrator == "pt":
        say(not a.quiet, "path tracer: building the volume...")
        return entry.render(req)
    if req.cluster is None:
        return entry.render(req)
    cl = req.cluster
    try:
        from ..run import executor
    except ImportError as e:
        raise ConfigError("command line", cl.flag if cl.scheduler else "--devices", cl.scheduler or cl.devices,
                          f"needs dask.distributed ({e}): pip install 'clppm[dask]'") from None
    try:
        return entry.render(req)
    except executor.ExecutorError as e:
        raise InputError(str(e)) from None


def _refuse_ppm_flags(a) -> None:
    """The path tracer has no sample points, photons or PPM estimator: their flags are refused."""
    for flag, v in (("--method", a.method), ("--spacing", a.spacing), ("--photons", a.photons),
                    ("--paper", a.paper or None), ("--estimator", a.estimator), ("--storage", a.storage),
                    ("--bands-per-path", a.bands_per_path), ("--radius", a.radius)):
        if v is not None:
            raise ConfigError("command line", flag, v, "applies to --integrator ppm only")


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


def add_parser(sub) -> None:
    p = sub.add_parser("render", help="render a config: progressive photon mapping (or --integrator pt)",
                       description="Render a config file (or a shipped one by name: forearm, cheek, ...).",
                       epilog=RENDER_EPILOG)
    p.add_argument("config", help="config file, or the name of a shipped config (`clppm config --example`)")
    p.add_argument("--integrator", choices=("ppm", "pt"), default="ppm",
                   help="ppm: progressive photon mapping; pt: the unbiased path tracer (a point light; "
                        "flat scenes and relief alike, through relief by manifold next-event estimation; "
                        "render.pt_samples_per_pass paths per pixel per pass)")
    p.add_argument("--method", choices=list("abcdef"),
                   help="sample-point scheme, see below (default: the config's render.method)")
    p.add_argument("--spacing", type=float, help="equal spacing of sample points in um, any value "
                   "(instead of --method; default: the method's)")
    p.add_argument("--passes", type=int, help="passes in all, counting a resumed checkpoint's "
                   "(default: the config's render.passes)")
    p.add_argument("--photons", type=int, help="stored photons per pass (default: the config's render.photons)")
    p.add_argument("--resolution", type=resolution_arg, help="WxH pixels (default: the config's camera.resolution)")
    p.add_argument("--seed", type=int, help="random seed (default: the config's render.seed)")
    p.add_argument("--resume", metavar="CKPT", help="continue from a checkpoint (NAME.ckpt.npz)")
    p.add_argument("--force", action="store_true",
                   help="start over even though files of an earlier render exist under -o's NAME.* (the "
                        "whole set is removed first; not with --resume)")
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
    add_device(p)
    p.set_defaults(func=cmd_render)
