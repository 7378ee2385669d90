"""``clppm fit``: its options and output (the fit itself: clppm.analysis.fit)."""
from __future__ import annotations

import json
import os

import numpy as np

from .. import config as C
from ..config import ConfigError
from ..analysis.fit import (DEFAULT_BANDS, DEFAULT_PHOTONS, default_config_path, fit,
                            load_measured, plot_fit, write_toml)
from . import options


def _bands_arg(s: str):
    return options.numbers(s, ":", 3, float, f"--bands {s!r}: expected START:STOP:STEP nm, e.g. 380:780:20")


def _region_arg(s: str):
    return options.numbers(s, ",", 4, int, f"--region {s!r}: expected x0,y0,x1,y1 pixels")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "fit", help="fit melanin, blood, oxygen saturation and scattering to a measured R(λ)",
        description="Least-squares fit of the model's melanin factor (basal + granular layers), "
                    "dermal blood factor, oxygen saturation and Jacques scattering factor to a "
                    "measured reflectance spectrum, with the photon pass on the flat model "
                    "(common random numbers) as forward model. Writes the full config with the "
                    "fitted layers (TOML for clppm render), a plot and a JSON report.")
    p.add_argument("measured", nargs="?",
                   help="CSV wavelength_nm,reflectance (or a multi-column file with --subject); "
                        "leave out to fit a subject of the packaged NIST set")
    p.add_argument("--subject", type=int, help="subject N (NIST: 1..100) / column N")
    p.add_argument("--image", help="instead of MEASURED: a spectral EXR a clppm render wrote (its report "
                                   "beside it); fit the reflectance factor of --region of it")
    p.add_argument("--region", type=_region_arg,
                   help="with --image: x0,y0,x1,y1 pixels (default: the central 50 %% box)")
    p.add_argument("--config", help="model to fit: a config file or shipped name (default: the shipped forearm)")
    p.add_argument("-o", "--output", default="out/fitted.toml", help="fitted config (TOML)")
    p.add_argument("--plot", help="plot file (default: beside --output, .png)")
    p.add_argument("--json", help="report file (default: beside --output, .json)")
    p.add_argument("--photons", type=int, default=DEFAULT_PHOTONS, help="photons per band per evaluation")
    p.add_argument("--bands", type=_bands_arg, default=DEFAULT_BANDS,
                   help="fit bands START:STOP:STEP nm (default 380:780:20)")
    p.add_argument("--angle", type=float,
                   help="incidence angle (default 8°; with --image the light's at the region's centre)")
    p.add_argument("--specular", choices=("included", "excluded"),
                   help="the measurement's specular component: included (SCI, the default) or excluded "
                        "(SCE, the default with --image: an image away from the mirror direction holds "
                        "no first-surface reflection)")
    p.add_argument("--seed", type=int, default=1, help="the common random numbers' seed")
    p.add_argument("--max-iter", type=int, default=6,
                   help="outer iterations (hybrid: photon-pass evaluations - 1) or least-squares iterations (mc)")
    p.add_argument("--forward", choices=("hybrid", "mc"), default="hybrid",
                   help="hybrid: adding-doubling surrogate corrected by the photon pass (default; "
                        "needs iadpython); mc: bounded least squares on the photon pass alone")
    p.add_argument("-q", "--quiet", action="store_true", help="no per-iteration lines")
    options.add_device(p)
    p.set_defaults(func=cmd_fit)


def _image_measurement(a, bands):
    """With --image: the model (--config, else the render's own config, its [[map]] and
    [[inclusion]] tables dropped: the fit's layers are uniform, and their fitted values are the
    region's), its name, the region's reflectance factor and the light's angle there."""
    from ..analysis.reflectance import image_region
    for flag, v in (("MEASURED", a.measured), ("--subject", a.subject)):
        if v is not None:
            raise ConfigError("command line", flag, v, "give a measured spectrum or --image, not both")
    reg = image_region(a.image, a.region)
    if not (reg.wl[0] <= bands[0] and bands[1] <= reg.wl[-1]):
        raise ConfigError("command line", "--bands", ":".join(f"{x:g}" for x in bands),
                          f"must lie within the image's bands {reg.wl[0]:g}-{reg.wl[-1]:g} nm")
    if a.config:
        cfg_path = C.find(a.config)
        cfg, src = C.load(cfg_path), os.path.basename(cfg_path)
    else:
        raw = {k: v for k, v in reg.cfg.items() if k not in ("map", "inclusion")}
        cfg, src = C.validate(raw, a.image), os.path.basename(a.image) + "'s config"
    return cfg, src, (reg.wl, reg.R, reg.label), reg.angle_deg


def _measurement(a, bands):
    """The model, its name and the measurement (wl, R, label): a CSV or NIST subject, or with
    --image a region of a rendered image (whose light sets the default --angle and --specular)."""
    if a.image is None:
        if a.region is not None:
            raise ConfigError("command line", "--region", ",".join(map(str, a.region)),
                              "reads a region of --image, which is not given")
        cfg_path = C.find(a.config) if a.config else default_config_path()
        measured = load_measured(a.measured, a.subject, bands)
        cfg, src = C.load(cfg_path), os.path.basename(cfg_path)
    else:
        cfg, src, measured, angle = _image_measurement(a, bands)
        a.angle = angle if a.angle is None else a.angle
        a.specular = a.specular or "excluded"
    a.angle = 8.0 if a.angle is None else a.angle
    a.specular = a.specular or "included"
    return cfg, src, measured


def cmd_fit(a) -> int:
    from ..output import paths
    bands = a.bands
    if not (bands[2] > 0 and bands[1] >= bands[0]):
        raise ConfigError("command line", "--bands", ":".join(f"{x:g}" for x in bands),
                          "needs START <= STOP and STEP > 0")
    cfg, src, (wl, R, label) = _measurement(a, bands)
    for name, v in (("--photons", a.photons), ("--max-iter", a.max_iter)):
        if v <= 0:
            raise ConfigError("command line", name, v, "must be > 0")
    if not 0 <= a.angle <= 85:
        raise ConfigError("command line", "--angle", a.angle, "must be in 0..85 degrees")
    base = os.path.splitext(a.output)[0]
    plot_path = a.plot or base + ".png"
    json_path = a.json or base + ".json"
    if not a.output.lower().endswith(".toml"):
        raise ConfigError("command line", "-o/--output", a.output, "must end in .toml (the fitted config)")
    paths.check_writable(a.output, "-o/--output")
    paths.check_plot(plot_path, "--plot")
    paths.check_writable(json_path, "--json")
    paths.check_distinct(**{"-o/--output": a.output, "--plot": plot_path, "--json": json_path})

    def log(it, p, rms):
        if not a.quiet:
            print(f"  iteration {it}: melanin ×{p['melanin']:.4g}  blood ×{p['blood']:.4g}  "
                  f"S {p['saturation']:.4f}  scattering ×{p['scattering']:.4g}  RMS {rms:.5f}", flush=True)
    if not a.quiet:
        print(f"fitting {src} to {label}: {a.photons} photons per band, bands "
              f"{bands[0]:g}-{bands[1]:g} nm every {bands[2]:g} nm, {a.angle:g}°, specular {a.specular}")
    res, model = fit(wl, R, cfg, photons=a.photons, bands=bands, seed=a.seed, angle_deg=a.angle,
                     specular=a.specular == "included", max_iter=a.max_iter, forward=a.forward,
                     device=a.device,
                     source=src, label=label, log=log)
    fitted_cfg = model.apply(res.params)
    p, pse = res.params, res.params_se
    header = [
        f"clppm fit: {src} fitted to {label}",
        f"melanin x{p['melanin']:.5g}, blood x{p['blood']:.5g}, saturation {p['saturation']:.5g}, "
        f"scattering x{p['scattering']:.5g}",
        f"residual RMS {res.rms:.5f} (start {res.rms_initial:.5f}), max |residual| {res.max_abs:.5f}, "
        f"CIEDE2000 {res.delta_e if res.delta_e is not None else float('nan'):.2f}",
        f"forward model: {a.forward}, photon pass on the flat model, {a.photons} photons/band, bands "
        f"{bands[0]:g}:{bands[1]:g}:{bands[2]:g} nm, seed {a.seed}, {a.angle:g} deg, specular {a.specular}",
    ]
    write_toml(fitted_cfg, a.output, header)
    native = None
    mw = np.asarray(wl); sel = (mw >= bands[0] - 10) & (mw <= bands[1] + 10)
    native = (mw[sel], np.asarray(R)[sel])
    plot_fit(plot_path, res, native, title=f"{src} fitted to {label}")
    rep = res.to_dict()
    rep["output"] = os.path.abspath(a.output)
    os.makedirs(os.path.dirname(os.path.abspath(json_path)), exist_ok=True)
    with open(json_path, "w") as f:
        json.dump(rep, f, indent=1)

    def fmt_se(k):
        return "" if pse.get(k) is None else f" ± {pse[k]:.3g}"
    print(f"{label}: {res.iterations} iterations, {res.evaluations} photon-pass evaluations, "
          f"{res.seconds:.1f} s ({'converged' if res.converged else 'iteration limit'})")
    print(f"  melanin ×{p['melanin']:.4g}{fmt_se('melanin')}   blood ×{p['blood']:.4g}{fmt_se('blood')}   "
          f"S {p['saturation']:.3f}{fmt_se('saturation')}   "
          f"scattering ×{p['scattering']:.4g}{fmt_se('scattering')}")
    for L in res.layers:
        vals = ", ".join(f"{k} {v:.4g}" for k, v in L.items() if k != "name")
        print(f"    {L['name']}: {vals}")
    de = "" if res.delta_e is None else f", CIEDE2000 {res.delta_e:.2f} (start {res.delta_e_initial:.2f})"
    print(f"  residual RMS {res.rms:.4f} (start {res.rms_initial:.4f}), max |residual| "
          f"{res.max_abs:.4f}{de}; MC standard error per band ~{res.settings['mc_se_mean']:.4f}")
    print(f"wrote {a.output}, {plot_path}, {json_path}")
    return 0
