"""``clppm reflectance``: its options and output (the measurement itself:
clppm.analysis.reflectance)."""
from __future__ import annotations

import json
import os

import numpy as np

from .. import config as C
from ..config import ConfigError
from ..analysis.reflectance import DEFAULT_ANGLE, method_reflectance, spectral_reflectance
from . import options


def _bands_arg(s: str):
    return options.numbers(s, ":", 3, float, f"--bands {s!r}: expected START:STOP:STEP in nm, e.g. 380:780:10")


def _region_arg(s: str):
    return options.numbers(s, ",", 4, int, f"--region {s!r}: expected x0,y0,x1,y1 pixels")


def _res_arg(s: str):
    return options.resolution(s, f"--resolution {s!r}: expected WxH, e.g. 64x48")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "reflectance",
        help="spectral reflectance R(λ) as an integrating sphere measures it (photon pass), "
             "vs NIST skin; per-method image reflectance with --methods",
        description="R(λ) of a model from the photon pass: collimated beam at --angle, "
                    "specular included or excluded, standard error per band; compared with the "
                    "NIST volar-forearm population. Flat models: laterally infinite, pencil beam. "
                    "Relief/papillae: periodic sides, wide beam over the whole model. "
                    "--methods renders each scheme and divides image radiance by a white "
                    "Lambertian reference.")
    p.add_argument("config")
    p.add_argument("--angle", type=float, default=DEFAULT_ANGLE, help="incidence angle, degrees (default 8)")
    p.add_argument("--specular", choices=("included", "excluded"), default="included",
                   help="specular component included (SCI, default) or excluded (SCE)")
    p.add_argument("--photons", type=int, default=None,
                   help="photons per band for R(λ) (default 5000); with --methods: stored "
                        "photons per render pass (then --band-photons sets the per-band count)")
    p.add_argument("--band-photons", type=int, default=None, help="photons per band for R(λ)")
    p.add_argument("--bands", type=_bands_arg,
                   help="START:STOP:STEP nm (default: the config's); with --methods also the "
                        "renders' spectrum")
    p.add_argument("--flat", action="store_true", help="relief and papillae off (the fit's forward model)")
    p.add_argument("--spot-mm", type=float, help="square beam spot side (relief models / with --port-mm)")
    p.add_argument("--port-mm", type=float, help="square sample port side, flat models (a lower bound)")
    p.add_argument("--seed", type=int, help="random seed (default: the config's render.seed)")
    p.add_argument("--batches", type=int, default=10, help="batches for the standard errors")
    p.add_argument("--methods", help="render these schemes (e.g. a,b,c,d,e,f) and add image reflectance")
    p.add_argument("--passes", type=int, help="render passes (with --methods)")
    p.add_argument("--resolution", type=_res_arg, help="WxH (with --methods)")
    p.add_argument("--region", type=_region_arg, help="x0,y0,x1,y1 pixels (default: central 50 %% box)")
    p.add_argument("--json", help="write the result as JSON")
    p.add_argument("--plot", help="write a plot (PNG/PDF/SVG) over the NIST median and 5-95 %% band")
    p.add_argument("--no-nist", action="store_true", help="skip the NIST comparison")
    options.add_device(p)
    p.set_defaults(func=cmd_reflectance)


def _refuse_methods(cfg: dict, src: str) -> None:
    """The --methods renders (PPM): refused where PPM would be, and with maps (not validated)."""
    from ..scene.scene import refuse_inclusions
    refuse_inclusions(cfg, src, "ppm")
    if cfg.get("map"):
        raise ConfigError(src, "map[0].layer", cfg["map"][0]["layer"],
                          "the --methods renders are not validated with chromophore maps; drop --methods "
                          "(the photon pass's R(λ) sees them) or remove the [[map]] tables")


def cmd_reflectance(a) -> int:
    from ..analysis import nist
    from ..output import paths
    from ..compute.device import open_device
    cfg = C.load(C.find(a.config))
    src = os.path.basename(a.config)
    spec = a.specular == "included"
    if a.methods:
        band_photons = a.band_photons or 5000
    else:
        band_photons = a.band_photons or a.photons or 5000
    for name, v in (("--photons", a.photons), ("--band-photons", a.band_photons),
                    ("--passes", a.passes), ("--batches", a.batches)):
        if v is not None and v <= 0:
            raise ConfigError("command line", name, v, "must be > 0")
    if a.methods:
        _refuse_methods(cfg, src)
    paths.check_writable(a.json, "--json")
    paths.check_plot(a.plot, "--plot")
    paths.check_distinct(**{"--json": a.json, "--plot": a.plot})
    dev = open_device(a.device)
    bands = a.bands
    res = spectral_reflectance(cfg, photons=band_photons, angle_deg=a.angle, specular=spec,
                               spot_mm=a.spot_mm, port_mm=a.port_mm, bands=bands, flat=a.flat,
                               seed=a.seed, batches=a.batches, dev=dev, source=src)
    out = {"config": os.path.abspath(a.config), "photon_pass": res.to_dict()}
    print(f"{src}: R(λ) from the photon pass, {res.photons} photons per band, {len(res.wl)} bands, "
          f"{res.seconds:.1f} s on {res.device}")
    print(f"  {res.geometry}")
    print("  band nm      R       ±SE     Rd    specular")
    step = max(1, len(res.wl) // 41)
    for i in range(0, len(res.wl), step):
        print(f"  {res.wl[i]:7g}  {res.R[i]:.4f}  {res.se[i]:.4f}  {res.Rd[i]:.4f}  {res.specular[i]:.4f}")
    cmp = None
    if not a.no_nist and len(res.wl) > 1:
        cmp = nist.compare(res.wl, res.R)
        out["nist"] = cmp
        print("vs " + nist.NIST_LABEL + ":")
        for line in nist.summary_lines(cmp):
            print(line)
    curves = {}
    if a.methods:
        print(f"rendering methods {a.methods} ...")
        mr = method_reflectance(cfg, a.methods, passes=a.passes, photons=a.photons,
                                resolution=a.resolution, region=a.region, specular=spec,
                                band_photons=band_photons, seed=a.seed, bands=a.bands, dev=dev,
                                source=src, log=lambda s: print(s, flush=True))
        out["images"] = mr
        wl = np.asarray(mr["wavelength_nm"])
        tr = np.asarray(mr["photon_pass"]["R"])
        print(f"  image region {mr['region']} of {mr['resolution'][0]}x{mr['resolution'][1]}, "
              f"{mr['passes']} passes x {mr['photons_per_pass']} photons; photon pass at "
              f"{mr['photon_pass']['angle_deg']:.1f}° incidence")
        q = [w for w in nist.QUOTE_NM if wl.min() <= w <= wl.max()]
        print("  method  " + "  ".join(f"{w:>6g}" for w in q) + "   mean|ΔR|  blue/red bias")
        print("  photon  " + "  ".join(f"{np.interp(w, wl, tr):6.3f}" for w in q))
        for m, v in mr["methods"].items():
            Rm = np.asarray(v["R"])
            bias = v.get("blue_red_bias")
            print(f"  {m:6s}  " + "  ".join(f"{np.interp(w, wl, Rm):6.3f}" for w in q)
                  + f"   {v['mean_abs_diff']:.4f}   {'' if bias is None else f'{100 * bias:+.1f} %'}")
            curves[f"image, method {m}"] = (wl, Rm)
        curves["photon pass at the render's incidence"] = (wl, tr)
    if a.json:
        d = os.path.dirname(os.path.abspath(a.json))
        os.makedirs(d, exist_ok=True)
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
        print(f"wrote {a.json}")
    if a.plot:
        nist.plot(a.plot, res.wl, res.R, res.se,
                  label=f"{src} photon pass ({'SCI' if spec else 'SCE'}, {res.angle_deg:g}°)",
                  curves=curves, nearest=cmp["nearest_subject"] if cmp else None,
                  title=f"{src}: R(λ) vs NIST volar forearm skin")
        print(f"wrote {a.plot}")
    return 0
