"""Scene and render configuration: TOML in, validated dataclass-like dicts out.

Every key is declared once below with its type, range and default.  Loading
rejects unknown keys (suggesting the nearest valid one), wrong types, values
out of range and files that do not exist, with one :class:`ConfigError` whose
message names the file, the key and the value.  No other module reads TOML.

Units at this boundary: millimetres for scene-scale lengths (model size,
light and camera positions), micrometres for skin-scale lengths (layers,
voxels, relief), cm^-1 for optical coefficients, nanometres for wavelengths.
Everything downstream works in micrometres (the volume's unit).
"""
from __future__ import annotations

import copy
import difflib
import math
import json
import os
import re
import tomllib
from dataclasses import dataclass, make_dataclass
from typing import Any

INF = math.inf
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


class ConfigError(ValueError):
    """A bad configuration value; ``str()`` is the whole user-facing message."""

    def __init__(self, source: str, key: str, value: Any, why: str):
        self.source, self.key, self.value, self.why = source, key, value, why
        super().__init__(f"{source}: {key} = {_short(value)}: {why}")


def _short(value: Any, limit: int = 80) -> str:
    """``repr`` of a value on one line, cut to ``limit`` characters (a whole table can be long)."""
    r = repr(value)
    return r if len(r) <= limit else r[:limit - 3] + "..."


@dataclass(frozen=True)
class F:
    """One config field: type name, default, check."""

    kind: str                       # float int bool str vec2 vec3 ivec2 choice path
    default: Any = None
    lo: float | None = None         # inclusive lower bound
    hi: float | None = None         # inclusive upper bound
    lo_open: bool = False           # lower bound exclusive
    hi_open: bool = False
    choices: tuple = ()
    inf_ok: bool = False
    none_ok: bool = False
    doc: str = ""
    picture: str = "sums"           # what the key changes: "sums" (the accumulated picture),
    #                                 "finish" (only the PNG), "none" (how long, how often to save)


_RANGE_HELP = {(0, None, True): "> 0", (0, None, False): ">= 0"}

SCHEMA: dict[str, dict[str, F]] = {
    "model": {
        "name": F("str", "skin", doc="a label for reports"),
        "size_mm": F("vec2", [10.0, 10.0], lo=0, lo_open=True, hi=1000, doc="lateral extent"),
        "voxel_um": F("float", 5.0, lo=0, lo_open=True, hi=1000, doc="voxel thickness (z)"),
        "lateral_voxel_um": F("float", 5.0, lo=0.05, hi=10000, doc="lateral voxel (column) size"),
        "lateral": F("choice", "open", choices=("open", "periodic", "infinite"),
                     doc="the model's sides: open (light leaves), periodic (wraps), infinite (flat layers only)"),
        "quantize": F("bool", True, doc="snap interfaces to the voxel grid in z (surface = \"voxels\")"),
        "surface": F("choice", "smooth", choices=("smooth", "voxels"),
                     doc="what light crosses: smooth (the Catmull-Rom height fields themselves, exactly; "
                         "the default) or voxels (the paper's staircase of columns, refracting at the "
                         "smooth normals; paper mode)"),
        "n_outside": F("float", 1.0, lo=1.0, hi=3.0, doc="refractive index above the skin"),
        "n_below": F("float", 1.0, lo=1.0, hi=3.0, doc="index below a finite bottom layer"),
    },
    "spectrum": {
        "start_nm": F("float", 380.0, lo=250, hi=1000, doc="first band centre"),
        "stop_nm": F("float", 780.0, lo=250, hi=1000, doc="last band centre"),
        "step_nm": F("float", 5.0, lo=0, lo_open=True, hi=200, doc="band width (at most 512 bands)"),
    },
    "relief": {
        "kind": F("choice", "flat", choices=("flat", "generated", "file"),
                  doc="surface relief: none, generated furrows, or a height map file"),
        "depth_um": F("float", 20.0, lo=0, hi=500, doc="furrow depth"),
        "spacing_um": F("float", 250.0, lo=1, hi=1e5, doc="mean furrow spacing"),
        "width_um": F("float", 20.0, lo=0.1, hi=1e4, doc="furrow width"),
        "seed": F("int", 7, lo=0, hi=2**31 - 1, doc="generated relief's random seed"),
        "file": F("path", None, none_ok=True, doc=".npy, 16-bit PNG or EXR height map"),
        "pixel_um": F("float", 5.0, lo=0, lo_open=True, hi=1e5, doc="height map pixel size"),
        "height_scale_um": F("float", 1.0, lo=0, lo_open=True, hi=1e6, doc="µm per stored unit"),
    },
    "papillae": {
        "amplitude_um": F("float", 0.0, lo=0, hi=500, doc="dermal papillae height (0: a flat junction)"),
        "period_um": F("float", 100.0, lo=1, hi=1e5, doc="dermal papillae period"),
    },
    "light": {
        "kind": F("choice", "point", choices=("point", "pencil", "wide"),
                  doc="point light, collimated pencil beam, or wide collimated beam"),
        "position_mm": F("vec3", [0.0, 10.0, 10.0], lo=-1e4, hi=1e4, doc="point light position"),
        "direction": F("vec3", [0.0, 0.0, -1.0], lo=-1, hi=1, doc="collimated beam direction"),
        "center_mm": F("vec2", [5.0, 5.0], lo=-1e4, hi=1e4, doc="beam centre on the surface"),
        "width_mm": F("vec2", [10.0, 10.0], lo=0, lo_open=True, hi=1e4, doc="wide beam full width"),
        "power_w": F("float", 1.0, lo=0, hi=1e9, doc="emitted power, W (over all bands)"),
        "spectrum": F("choice", "D65", choices=("D65", "flat"), doc="emission spectrum"),
        "band_nm": F("float", None, none_ok=True, lo=250, hi=1000, doc="emit in this band only"),
    },
    "camera": {
        "position_mm": F("vec3", [5.0, 5.0, 30.0], lo=-1e4, hi=1e4, doc="camera position"),
        "look_at_mm": F("vec3", [5.0, 5.0, 0.0], lo=-1e4, hi=1e4, doc="point the camera looks at"),
        "up": F("vec3", [0.0, 1.0, 0.0], lo=-1, hi=1, doc="camera up direction"),
        "fov_deg": F("float", 19.0, lo=0, lo_open=True, hi=170, doc="vertical field of view"),
        "resolution": F("ivec2", [320, 240], lo=1, hi=16384, doc="image width, height in pixels"),
        "spp": F("int", 1, lo=1, hi=1024, doc="jittered eye rays per pixel"),
    },
    "render": {
        "method": F("choice", "e", choices=tuple("abcdef"), doc="sample-point scheme on eye rays (clppm render --help)"),
        "spacing_um": F("float", None, none_ok=True, lo=0, lo_open=True, hi=1e4,
                        doc="equal spacing; overrides a/b/c"),
        "threshold": F("float", 1.25e-3, lo=0, hi=1, hi_open=True,
                       doc="transmittance cut for sample points"),
        "merge": F("choice", "voxel", choices=("voxel", "none"), doc="voxel: one sample point per voxel along a ray"),
        "photons": F("int", 810_000, lo=1, hi=2**30, doc="stored photons per pass"),
        "initial_photons": F("int", 810, lo=1, hi=10**6, doc="photons in the first search"),
        "passes": F("int", 200, lo=1, hi=10**7, doc="progressive passes", picture="none"),
        "alpha": F("float", 0.7, lo=0, hi=1, lo_open=True, hi_open=True, doc="progressive radius reduction"),
        "radius": F("choice", "global", choices=("global", "ppm"),
                    doc="global: Knaus & Zwicker's radius schedule (passes independent: distributable); "
                        "ppm: the per-point radius of Hachisuka et al. (the paper)"),
        "seed": F("int", 1, lo=0, hi=2**63 - 1, doc="random seed (same seed, same device: same bytes)"),
        "specular": F("bool", True, doc="add the surface's specular highlight (GGX)"),
        "roughness": F("float", 0.35, lo=0.01, hi=1.0, doc="GGX roughness of the highlight"),
        "preview_every": F("int", 0, lo=0, hi=10**7, doc="write a preview PNG every K passes (0: never)",
                           picture="none"),
        "checkpoint_every": F("int", 10, lo=0, hi=10**7, doc="checkpoint every K passes (0: only at the end or a signal)",
                              picture="none"),
        "chunk_passes": F("int", 4, lo=1, hi=10**6,
                          doc="passes summed per chunk before the chunk joins the total, here and "
                              "on distributed workers alike (part of the result's bits)"),
        "tile_points": F("int", 0, lo=0, hi=2**32 - 1,
                         doc="with the global radius: the most sample points on the device at a time "
                             "(the eye pass and gather run in tiles of pixels; the same image); "
                             "0: from the device's memory", picture="none"),
        "exposure": F("float", None, none_ok=True, lo=0, lo_open=True, hi=1e12,
                      doc="PNG scale; default: a white diffuser at the image centre = 1", picture="finish"),
        "estimator": F("choice", "beam", choices=("beam", "layer", "clip", "sphere"),
                       doc="beam: each photon integrated along its point's path cell, a horizontal "
                           "disc exact in depth; layer: own-layer photons over the sphere within the "
                           "layer; clip: all photons, sphere clipped at the surface; sphere: the paper"),
        "layout": F("choice", "auto", choices=("auto", "gather", "scatter"),
                     doc="beam estimator: how photon-ray pairs are found and summed (same pairs, "
                         "same fixed-point sums): gather, a work item per pixel querying the photon "
                         "grid; scatter, a work item per photon adding into per-point sums with "
                         "64-bit atomics (needs cl_khr_int64_base_atomics and 9 bands per path, "
                         "else gather); auto: per device type, the faster by measurement "
                         "(docs/gather.md)", picture="none"),
        "store_depth_um": F("float", None, none_ok=True, lo=0, lo_open=True, hi=1e6,
                            doc="store photons only this deep (default: all)"),
        "depth_roulette_um": F("float", 0.0, lo=0, hi=1e6,
                               doc="below the depth that no sample point reaches, Russian roulette "
                                   "(survival 1/2, weight x2; unbiased) when a photon first passes "
                                   "each of six planes this far apart, the first this far below: "
                                   "light that goes deep rarely returns, so its long walks are cut "
                                   "short; it can cost more noise than it saves time "
                                   "(docs/method.md); 0: off"),
        "bands_per_path": F("int", 0, lo=0, hi=512,
                            doc="wavelength bands a photon path carries (hero wavelength sampling; "
                                "must divide the number of bands); 0: the largest divisor up to 9, 1 with [[map]] "
                                "tables (maps are traced with one band per path; more is refused)"),
        "band_sampling": F("choice", "power", choices=("power", "visual"),
                           doc="the hero band's pdf: power (the light's spectrum, the paper) or "
                               "visual (light x CIE colour matching functions, with a floor)"),
        "emission": F("choice", "qmc", choices=("qmc", "random"),
                      doc="qmc: each pass's photons take their band and direction (or footprint) "
                          "from a randomly shifted R3 sequence (stratified, unbiased); random: "
                          "independent uniforms per photon (the paper)"),
        "storage": F("choice", "importance", choices=("importance", "all"),
                     doc="importance: store a scattering event with a probability that follows "
                         "its weight toward the eye (unbiased, weight 1/probability); all: every "
                         "event (the paper)"),
        "store_scale": F("float", 10.0, lo=0, lo_open=True, hi=1e6,
                         doc="importance storage: probability = clamp(scale * importance, "
                             "store_min, 1)"),
        "store_min": F("float", 0.02, lo=0, lo_open=True, hi=1.0,
                       doc="importance storage: the smallest storage probability (bounds weights)"),
        "pt_samples_per_pass": F("int", 16, lo=1, hi=4096,
                                 doc="path tracer (--integrator pt): eye paths per pixel per pass"),
    },
}

LAYER_SCHEMA: dict[str, F] = {
    "name": F("str", None, doc="layer name (required)"),
    "thickness_um": F("float", None, lo=0, lo_open=True, hi=1e6, inf_ok=True,
                      doc="thickness (required; inf: semi-infinite, last layer only; under 1 nm in every "
                          "column, after model.quantize's snapping: the layer is absent, light crosses "
                          "it as if it were not there)"),
    "n": F("float", 1.4, lo=1.0, hi=3.0, doc="refractive index"),
    "melanin": F("float", 0.0, lo=0, hi=1, doc="melanosome volume fraction"),
    "blood": F("float", 0.0, lo=0, hi=1, doc="whole-blood volume fraction"),
    "saturation": F("float", 0.8, lo=0, hi=1, doc="blood oxygen saturation"),
    "baseline": F("float", 0.0, lo=0, hi=1, doc="volume fraction absorbing like bloodless tissue"),
    "scattering": F("choice", "jacques", choices=("jacques", "powerlaw", "none"),
                        doc="jacques: k x Jacques' skin mus; powerlaw: mus' = a (wl/500 nm)^-b; "
                            "none: with mua and mus"),
    "k": F("float", 1.0, lo=0, hi=1e4, doc="jacques: scattering scale"),
    "a": F("float", 0.0, lo=0, hi=1e5, doc="powerlaw: reduced scattering at 500 nm, cm^-1"),
    "b": F("float", 0.0, lo=-10, hi=10, doc="powerlaw: exponent"),
    "g": F("float", None, none_ok=True, lo=-1, hi=1, lo_open=True, hi_open=True,
           doc="anisotropy (unset: Jacques' g(wl))"),
    "bottom": F("choice", "flat", choices=("flat", "surface", "papillae"),
                    doc="bottom interface: flat, following the relief, or relief + papillae"),
    "mua": F("float", None, none_ok=True, lo=0, hi=1e6, doc="homogeneous override, cm^-1"),
    "mus": F("float", None, none_ok=True, lo=0, hi=1e6, doc="homogeneous override, cm^-1"),
}

#: the chromophore and scattering keys of a layer that an inclusion has too (its material)
MATERIAL_KEYS = ("melanin", "blood", "saturation", "baseline", "scattering", "k", "a", "b", "g", "mua", "mus")

INCLUSION_SCHEMA: dict[str, F] = {
    "kind": F("choice", None, choices=("vessel", "ellipsoid"),
              doc="vessel: an infinite circular cylinder (a blood vessel); ellipsoid: axis-aligned "
                  "(required). Either is one material with the index of the layer around it: no "
                  "Fresnel at its surface"),
    "center_mm": F("vec2", None, lo=-1e4, hi=1e4,
                   doc="lateral position of the centre, x and y (required; on the model)"),
    "depth_um": F("float", None, lo=0, lo_open=True, hi=1e6,
                  doc="depth of the centre below the mean skin surface (required; above the last "
                      "layer's bottom)"),
    "axis": F("vec3", [1.0, 0.0, 0.0], lo=-1, hi=1, doc="vessel: direction of its axis (not zero)"),
    "radius_um": F("float", 50.0, lo=0, lo_open=True, hi=1e5, doc="vessel: radius"),
    "semi_axes_um": F("vec3", [100.0, 100.0, 50.0], lo=0, lo_open=True, hi=1e5,
                      doc="ellipsoid: semi-axes along x, y, z"),
    **{k: (F("float", 1.0, lo=0, hi=1, doc="whole-blood volume fraction") if k == "blood"
           else F("float", 0.7, lo=0, hi=1, doc="blood oxygen saturation") if k == "saturation"
           else LAYER_SCHEMA[k]) for k in MATERIAL_KEYS},
}
#: inclusions a scene may hold (the walk intersects every one at every step: photon.cl NINC)
MAX_INCLUSIONS = 8
#: the smallest radius or semi-axis (um): ten times kernels/inclusion.h INC_EPS
MIN_INCLUSION_UM = 0.1

#: the chromophores a [[map]] varies across a layer's columns (kernels/maps.h: mu_a is linear in
#: melanin, blood and blood x saturation, so these three per column give every band's absorption)
MAP_QUANTITIES = ("melanin", "blood", "saturation")

SPOT_SCHEMA: dict[str, F] = {
    "center_mm": F("vec2", None, lo=-1e4, hi=1e4, doc="lateral position of the spot's centre, x and y"),
    "radius_um": F("float", None, lo=0, lo_open=True, hi=1e6,
                   doc="1/e radius of the Gaussian: value = background + (peak - background) exp(-(r/radius)^2)"),
    "peak": F("float", None, lo=0, hi=1, doc="the value at the centre"),
}

MAP_SCHEMA: dict[str, F] = {
    "layer": F("str", None, doc="the name of the [[layer]] the map varies (required)"),
    "quantity": F("choice", None, choices=MAP_QUANTITIES,
                  doc="melanin (melanosome volume fraction), blood (whole-blood volume fraction) or "
                      "saturation (blood oxygen saturation) (required)"),
    "kind": F("choice", None, choices=("file", "spots", "constant"),
              doc="file: an image or .npy; spots: Gaussian spots (freckles, nevi) on a background; "
                  "constant: one value everywhere (required)"),
    "value": F("float", None, none_ok=True, lo=0, hi=1,
               doc="constant: the value (required); spots: the background (unset: the layer's own value)"),
    "spots": F("spots", [], doc="spots: a list of {center_mm = [x, y], radius_um = r, peak = v}; "
                                "where spots overlap their excesses over the background add"),
    "file": F("path", None, none_ok=True,
              doc="file: a grayscale PNG or TIFF (8 or 16 bit), an EXR (channel Y, else R) or a .npy; "
                  "row r is y = (r + 0.5) pixel, as relief.file"),
    "low": F("float", 0.0, lo=0, hi=1, doc="file (image): the value of black"),
    "high": F("float", 1.0, lo=0, hi=1, doc="file (image): the value of white (a float image's 1.0); "
                                            "a .npy holds the values themselves"),
    "pixel_um": F("float", None, none_ok=True, lo=0, lo_open=True, hi=1e6,
                  doc="file: the map's pixel size (unset: the map spans the model's footprint); "
                      "bilinear onto the columns where it is not the columns' own grid"),
}
#: maps a scene may hold (one per layer and quantity at most)
MAX_MAPS = 64

#: [render] keys that never change the accumulated picture (``picture="none"`` in the schema):
#: how long to run, how often to save, and the beam gather's layout (its layouts give the same
#: bytes, tests/test_layouts.py).  A checkpoint resumes, a worker's scene is reused, and a cached
#: reference is found whatever they are.
NOT_PICTURE = tuple(k for k, f in SCHEMA["render"].items() if f.picture == "none")
#: [render] keys that change only the finishing (the PNG), not the spectral sums.
FINISHING = tuple(k for k, f in SCHEMA["render"].items() if f.picture == "finish")

#: the Python type of a value of each field kind (the typed views' annotations)
_PY_TYPE = {"float": float, "int": int, "bool": bool, "str": str, "choice": str, "path": str,
            "vec2": list, "vec3": list, "ivec2": list}


def _view(section: str, name: str, doc: str) -> type:
    """A frozen dataclass with one field per key of ``SCHEMA[section]``, typed from the schema,
    so a view cannot drift from the keys it views."""
    fields = [(k, _PY_TYPE[f.kind] | None if f.none_ok else _PY_TYPE[f.kind])
              for k, f in SCHEMA[section].items()]
    cls = make_dataclass(name, fields, frozen=True)
    cls.__doc__ = doc
    return cls


RenderSettings = _view("render", "RenderSettings",
                       "The validated ``[render]`` table as a typed, read-only view: ``rs.passes``.")


def render_settings(cfg: dict) -> "RenderSettings":
    """The ``[render]`` table of a validated config as :class:`RenderSettings`."""
    return RenderSettings(**cfg["render"])


MAX_LAYERS = 16


def is_flat(cfg: dict) -> bool:
    """Flat layers: no surface relief and no wavy junction."""
    return cfg["relief"]["kind"] == "flat" and cfg["papillae"]["amplitude_um"] <= 0
D65_RANGE_NM = (300.0, 780.0)     # colour.SDS_ILLUMINANTS["D65"] (spectra.d65)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check(src: str, key: str, v: Any, f: F, base_dir: str) -> Any:
    def bad(why):
        raise ConfigError(src, key, v, why)

    if v is None:
        if f.none_ok:
            return None
        bad("a value is required")
    k = f.kind
    if k == "str":
        if not isinstance(v, str) or not v.strip():
            bad("must be a non-empty string")
        return v
    if k == "bool":
        if not isinstance(v, bool):
            bad("must be true or false")
        return v
    if k == "choice":
        if v not in f.choices:
            near = difflib.get_close_matches(str(v), [str(c) for c in f.choices], 1)
            bad(f"must be one of {', '.join(map(str, f.choices))}"
                + (f" (did you mean '{near[0]}'?)" if near else ""))
        return v
    if k == "path":
        if not isinstance(v, str) or not v:
            bad("must be a file path")
        p = v if os.path.isabs(v) else os.path.join(base_dir, v)
        if not os.path.isfile(p):
            bad(f"file not found ({p!r})")
        return p
    if k in ("vec2", "vec3", "ivec2"):
        n = 3 if k == "vec3" else 2
        if not isinstance(v, (list, tuple)) or len(v) != n:
            bad(f"must be a list of {n} numbers")
        out = []
        for i, x in enumerate(v):
            if k == "ivec2":
                if not isinstance(x, int) or isinstance(x, bool):
                    bad(f"item {i} must be an integer")
            elif not _is_num(x):
                bad(f"item {i} must be a number")
            out.append(_range(src, f"{key}[{i}]", x, f, bad_whole=v))
        return out
    if k == "int":
        if not isinstance(v, int) or isinstance(v, bool):
            bad("must be an integer")
        return _range(src, key, v, f)
    if k == "spots":
        if not isinstance(v, list) or not all(isinstance(t, dict) for t in v):
            bad("must be a list of tables {center_mm = [x, y], radius_um = r, peak = v}")
        return [_section(src, f"{key}[{i}]", t, SPOT_SCHEMA, base_dir) for i, t in enumerate(v)]
    if k == "float":
        if not _is_num(v):
            bad("must be a number")
        try:
            x = float(v)
        except OverflowError:            # an int beyond the float range
            bad(f"must be <= {_fmt(f.hi)}" if f.hi is not None and v > 0 else "out of range")
        return _range(src, key, x, f)
    raise AssertionError(k)


def _range(src, key, x, f: F, bad_whole=None):
    def bad(why):
        raise ConfigError(src, key, x, why)

    if isinstance(x, float) and math.isnan(x):
        bad("must not be NaN")
    if isinstance(x, float) and math.isinf(x):
        if f.inf_ok and x > 0:
            return x
        bad("must be finite")
    if f.lo is not None and (x < f.lo or (f.lo_open and x == f.lo)):
        bad(f"must be {'>' if f.lo_open else '>='} {_fmt(f.lo)}")
    if f.hi is not None and (x > f.hi or (f.hi_open and x == f.hi)):
        bad(f"must be {'<' if f.hi_open else '<='} {_fmt(f.hi)}")
    return x


def _fmt(b) -> str:
    """A bound as the user would type it (exact for integers, short for floats)."""
    if isinstance(b, int) and not isinstance(b, bool):
        return str(b)
    return f"{b:g}"


def _show_key(key: str) -> str:
    """A key as TOML would spell it: bare if it can be, else quoted (one line, visible)."""
    return key if _BARE_KEY.fullmatch(key) else json.dumps(key)


def _unknown(src: str, where: str, key, valid, value: Any = "...") -> ConfigError:
    key = str(key)
    near = difflib.get_close_matches(key, list(valid), 1, 0.5)
    hint = f" (did you mean '{near[0]}'?)" if near else f"; valid keys: {', '.join(sorted(valid))}"
    name = f"{where}.{_show_key(key)}" if where else _show_key(key)
    return ConfigError(src, name, value, f"unknown key{hint}")


def _section(src, name, raw, schema, base_dir):
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(src, name, raw, "must be a table")
    out = {}
    for key in raw:
        if key not in schema:
            raise _unknown(src, name, key, schema, raw[key])
    for key, f in schema.items():
        v = raw.get(key, copy.deepcopy(f.default))
        if key not in raw and f.default is None and not f.none_ok:
            raise ConfigError(src, f"{name}.{key}", None, "missing required key")
        out[key] = _check(src, f"{name}.{key}", v, f, base_dir)
    return out


def validate(raw: dict, source: str = "<config>", base_dir: str = ".") -> dict:
    """Validate a parsed TOML dict; return a complete config with defaults filled."""
    if not isinstance(raw, dict):
        raise ConfigError(source, "<top>", raw, "must be a table")
    valid_top = list(SCHEMA) + ["layer", "inclusion", "map"]
    for key in raw:
        if key not in valid_top:
            raise _unknown(source, "", key, valid_top, raw[key])
    cfg = {name: _section(source, name, raw.get(name), schema, base_dir)
           for name, schema in SCHEMA.items()}
    layers = raw.get("layer")
    if not isinstance(layers, list) or not layers:
        raise ConfigError(source, "layer", layers, "at least one [[layer]] table is required")
    if len(layers) > MAX_LAYERS:
        raise ConfigError(source, "layer", f"{len(layers)} layers", f"at most {MAX_LAYERS} layers")
    cfg["layer"] = [_section(source, f"layer[{i}]", t, LAYER_SCHEMA, base_dir)
                    for i, t in enumerate(layers)]
    if "inclusion" in raw:
        cfg["inclusion"] = _inclusions(source, raw["inclusion"], base_dir)
    if "map" in raw:
        cfg["map"] = _maps(source, raw["map"], base_dir)
    _cross_checks(source, cfg)
    return cfg


def _inclusions(src: str, tables, base_dir: str) -> list[dict]:
    """The ``[[inclusion]]`` tables, validated one by one (present only when the file has them,
    so a config without inclusions is the same dict as before they existed)."""
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(src, "inclusion", tables, "must be [[inclusion]] tables")
    if len(tables) > MAX_INCLUSIONS:
        raise ConfigError(src, "inclusion", f"{len(tables)} inclusions", f"at most {MAX_INCLUSIONS}")
    return [_section(src, f"inclusion[{i}]", t, INCLUSION_SCHEMA, base_dir) for i, t in enumerate(tables)]


def _maps(src: str, tables, base_dir: str) -> list[dict]:
    """The ``[[map]]`` tables, validated one by one (present only when the file has them, so a
    config without maps is the same dict as before they existed)."""
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise ConfigError(src, "map", tables, "must be [[map]] tables")
    if len(tables) > MAX_MAPS:
        raise ConfigError(src, "map", f"{len(tables)} maps", f"at most {MAX_MAPS}")
    return [_section(src, f"map[{i}]", t, MAP_SCHEMA, base_dir) for i, t in enumerate(tables)]


def _check_maps(src: str, cfg: dict) -> None:
    """Each map names a layer of the config whose chromophores it can vary, once per quantity,
    with the keys its kind needs.  A file's contents and the spots' sums are checked where the
    volume is built, before any tracing (clppm.scene.maps)."""
    names = [L["name"] for L in cfg["layer"]]
    seen = {}
    for i, m in enumerate(cfg.get("map", [])):
        key = f"map[{i}]"
        if m["layer"] not in names:
            near = difflib.get_close_matches(m["layer"], names, 1, 0.5)
            raise ConfigError(src, f"{key}.layer", m["layer"], "no such layer"
                              + (f" (did you mean '{near[0]}'?)" if near else "") + f"; layers: {', '.join(names)}")
        L = cfg["layer"][names.index(m["layer"])]
        if L["mua"] is not None:
            raise ConfigError(src, f"{key}.layer", m["layer"], "the layer's absorption is a homogeneous "
                              "override (mua, mus), not chromophores: a map cannot vary it")
        both = (m["layer"], m["quantity"])
        if both in seen:
            raise ConfigError(src, f"{key}.quantity", m["quantity"],
                              f"map[{seen[both]}] already maps the {m['quantity']} of {m['layer']!r}")
        seen[both] = i
        if m["kind"] == "constant" and m["value"] is None:
            raise ConfigError(src, f"{key}.value", None, "a constant map needs its value")
        if m["kind"] == "spots" and not m["spots"]:
            raise ConfigError(src, f"{key}.spots", [], "a spots map needs at least one spot")
        if m["kind"] == "file" and m["file"] is None:
            raise ConfigError(src, f"{key}.file", None, "a file map needs its file")
        if m["kind"] != "file" and m["file"] is not None:
            raise ConfigError(src, f"{key}.file", m["file"], f"only a file map reads a file (kind = {m['kind']!r})")


def _check_inclusions(src: str, cfg: dict) -> None:
    """Each inclusion's centre inside the model (on its footprint unless the sides are infinite,
    above the last layer's bottom), a vessel's axis not zero, a material's overrides paired."""
    bottom = sum(L["thickness_um"] for L in cfg["layer"])
    w, h = cfg["model"]["size_mm"]
    bounded = cfg["model"]["lateral"] != "infinite"
    for i, inc in enumerate(cfg.get("inclusion", [])):
        key = f"inclusion[{i}]"
        if inc["depth_um"] >= bottom:
            raise ConfigError(src, f"{key}.depth_um", inc["depth_um"],
                              f"the centre is below the model's bottom ({bottom:g} um deep)")
        x, y = inc["center_mm"]
        if bounded and not (0.0 <= x <= w and 0.0 <= y <= h):
            raise ConfigError(src, f"{key}.center_mm", inc["center_mm"],
                              f"outside the model (x, y in [0, {w:g}] x [0, {h:g}] mm)")
        if inc["kind"] == "vessel" and sum(c * c for c in inc["axis"]) == 0:
            raise ConfigError(src, f"{key}.axis", inc["axis"], "must not be zero")
        sizes = [("radius_um", inc["radius_um"])] if inc["kind"] == "vessel" else \
            [(f"semi_axes_um[{j}]", s) for j, s in enumerate(inc["semi_axes_um"])]
        for name, size in sizes:
            if size < MIN_INCLUSION_UM:
                raise ConfigError(src, f"{key}.{name}", size,
                                  f"must be >= {MIN_INCLUSION_UM:g} um (the walk resolves an inclusion's "
                                  "surface to 0.01 um)")
        if (inc["mua"] is None) != (inc["mus"] is None):
            which = "mus" if inc["mus"] is None else "mua"
            raise ConfigError(src, f"{key}.{which}", None, "mua and mus override together (homogeneous material)")
        if inc["scattering"] == "none" and inc["mus"] is None:
            raise ConfigError(src, f"{key}.scattering", "none", "needs mua and mus (homogeneous material)")
        if inc["mua"] is not None and inc["g"] is None:
            raise ConfigError(src, f"{key}.g", None, "a homogeneous material (mua, mus) needs g")
        if inc["scattering"] == "powerlaw" and inc["mus"] is None and inc["a"] <= 0:
            raise ConfigError(src, f"{key}.a", inc["a"], "powerlaw scattering needs a > 0")


def _cross_checks(src: str, cfg: dict) -> None:
    sp = cfg["spectrum"]
    if sp["stop_nm"] < sp["start_nm"]:
        raise ConfigError(src, "spectrum.stop_nm", sp["stop_nm"], "must be >= spectrum.start_nm")
    nbf = (sp["stop_nm"] - sp["start_nm"]) / sp["step_nm"] + 1     # inf for a tiny step
    if not nbf < 512.5:
        nbs = f"{nbf:.0f}" if math.isfinite(nbf) else "too many"
        raise ConfigError(src, "spectrum.step_nm", sp["step_nm"], f"gives {nbs} bands; at most 512")
    layers = cfg["layer"]
    for i, L in enumerate(layers[:-1]):
        if math.isinf(L["thickness_um"]):
            raise ConfigError(src, f"layer[{i}].thickness_um", L["thickness_um"],
                              "only the last layer may be semi-infinite")
    for i, L in enumerate(layers):
        if L["scattering"] == "powerlaw" and L["mus"] is None and L["a"] <= 0:
            raise ConfigError(src, f"layer[{i}].a", L["a"], "powerlaw scattering needs a > 0")
        if (L["mua"] is None) != (L["mus"] is None):
            which = "mus" if L["mus"] is None else "mua"
            raise ConfigError(src, f"layer[{i}].{which}", None,
                              "mua and mus override together (homogeneous layer)")
        if L["scattering"] == "none" and L["mus"] is None:
            raise ConfigError(src, f"layer[{i}].scattering", "none", "needs mua and mus (homogeneous layer)")
    m = cfg["model"]
    varying = cfg["relief"]["kind"] != "flat" or cfg["papillae"]["amplitude_um"] > 0
    if m["lateral"] == "infinite" and varying:
        raise ConfigError(src, "model.lateral", "infinite",
                          "needs a flat model (relief.kind = 'flat', papillae.amplitude_um = 0); "
                          "use 'periodic' or 'open'")
    if cfg["relief"]["kind"] == "file" and cfg["relief"]["file"] is None:
        raise ConfigError(src, "relief.file", None, "relief.kind = 'file' needs relief.file")
    cam = cfg["camera"]
    nrays = cam["resolution"][0] * cam["resolution"][1] * cam["spp"]
    if nrays > 2**31 - 1:                  # the kernels index eye rays with 32-bit integers
        raise ConfigError(src, "camera.spp", cam["spp"],
                          f"{cam['resolution'][0]}x{cam['resolution'][1]} pixels x {cam['spp']} gives "
                          f"{nrays} eye rays; at most {2**31 - 1}")
    d = [a - b for a, b in zip(cam["look_at_mm"], cam["position_mm"])]
    if math.sqrt(sum(x * x for x in d)) == 0:
        raise ConfigError(src, "camera.look_at_mm", cam["look_at_mm"], "equals camera.position_mm")
    for key in ("up",):
        if sum(x * x for x in cam[key]) == 0:
            raise ConfigError(src, f"camera.{key}", cam[key], "must not be zero")
    if sum(x * x for x in cfg["light"]["direction"]) == 0:
        raise ConfigError(src, "light.direction", cfg["light"]["direction"], "must not be zero")
    if cfg["light"]["kind"] != "point" and cfg["light"]["direction"][2] >= 0:
        raise ConfigError(src, "light.direction", cfg["light"]["direction"],
                          "a collimated beam must point down (z component < 0)")
    b = cfg["light"]["band_nm"]
    if b is not None and not (sp["start_nm"] - 1e-9 <= b <= sp["stop_nm"] + 1e-9):
        raise ConfigError(src, "light.band_nm", b, "outside the spectrum range")
    if cfg["light"]["spectrum"] == "D65":
        # colour's CIE D65 table covers 300-780 nm and silently holds its end values beyond
        lo, hi = D65_RANGE_NM
        last = sp["start_nm"] + sp["step_nm"] * (int(round((sp["stop_nm"] - sp["start_nm"])
                                                           / sp["step_nm"])))
        if sp["start_nm"] < lo - 1e-9:
            raise ConfigError(src, "spectrum.start_nm", sp["start_nm"],
                              f"outside the D65 light's data ({lo:g}-{hi:g} nm); "
                              "use light.spectrum = 'flat' or start_nm >= 300")
        if last > hi + 1e-9:
            raise ConfigError(src, "spectrum.stop_nm", sp["stop_nm"],
                              f"outside the D65 light's data ({lo:g}-{hi:g} nm; last band "
                              f"{last:g} nm); use light.spectrum = 'flat' or stop_nm <= 780")
    nb = int(round((sp["stop_nm"] - sp["start_nm"]) / sp["step_nm"])) + 1
    C = cfg["render"]["bands_per_path"]
    if C and nb % C:
        ok = [d for d in range(1, nb + 1) if nb % d == 0]
        raise ConfigError(src, "render.bands_per_path", C,
                          f"must divide the {nb} bands (one of {', '.join(map(str, ok[:12]))})")
    if cfg["render"]["initial_photons"] > cfg["render"]["photons"]:
        raise ConfigError(src, "render.initial_photons", cfg["render"]["initial_photons"],
                          "must not exceed render.photons")
    _check_inclusions(src, cfg)
    _check_maps(src, cfg)


def load(path: str) -> dict:
    """Read and validate a TOML config file, or a shipped config by name (``"forearm"``; as
    :func:`find` finds it, so as ``clppm render`` does).

    Returns a dict of sections (``render``, ``camera``, ``light``, ...; every key, defaults
    filled, lengths as in the file: docs/config.md) and ``layer``, a list of one dict per
    ``[[layer]]`` table, outermost first.  Raises :class:`ConfigError` naming the file, the key
    and the value for an unknown key, a wrong type, a value out of range or a missing file.

    >>> cfg = load("forearm")
    >>> [L["name"] for L in cfg["layer"]][:3], cfg["layer"][2]["melanin"]
    (['stratum corneum', 'granular + spinous', 'basal'], 0.1)
    """
    path = find(path)
    src = os.path.basename(path)
    try:
        with open(path, "rb") as f:
            raw = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(src, "<file>", path, "file not found") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(src, "<toml>", str(e), "not valid TOML") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(src, "<file>", path, f"cannot be read ({e})") from None
    return validate(raw, src, os.path.dirname(os.path.abspath(path)))


def set_item(cfg: dict, item: str, source: str = "--set") -> dict:
    """A copy of ``cfg`` with one value changed by ``SECTION.KEY=VALUE``, ``layer.N.KEY=VALUE``,
    ``inclusion.N.KEY=VALUE`` or ``map.N.KEY=VALUE`` (N: index into those tables;
    VALUE in TOML syntax, a bare word is a string), validated like the file's value.  ``cfg`` itself is left unchanged, as by
    :func:`override`: ``cfg = set_item(cfg, "layer.0.n=1.45")``.  The same strings as
    ``clppm render --set``; raises :class:`ConfigError` for an unknown key or a bad value."""
    key_part = item.split("=", 1)[0].strip()
    section_part, _, rest = key_part.partition(".")
    if "=" not in item or not section_part or not rest:
        raise ConfigError("command line", source, item,
                          "expected SECTION.KEY=VALUE or layer.N.KEY=VALUE, "
                          "e.g. render.passes=20 or layer.0.n=1.45")
    path, text = (x.strip() for x in item.split("=", 1))
    section, key = path.split(".", 1)
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text
    if section in ("layer", "inclusion", "map"):
        index, _, key = key.partition(".")
        return override_table(cfg, section, index, key, value, source)
    return override(cfg, section, key, value, source)


def override_layer(cfg: dict, index, key: str, value: Any, source: str = "--set") -> dict:
    """Set ``layer[index].key`` (validated like the file's value)."""
    return override_table(cfg, "layer", index, key, value, source)


def override_table(cfg: dict, kind: str, index, key: str, value: Any, source: str = "--set") -> dict:
    """Set ``kind[index].key``, kind "layer", "inclusion" or "map" (validated like the file's value)."""
    schema = {"layer": LAYER_SCHEMA, "inclusion": INCLUSION_SCHEMA, "map": MAP_SCHEMA}[kind]
    tables = cfg.get(kind, [])
    n = len(tables)
    names = ", ".join(f"{i} " + (t["name"] if kind == "layer" else t["kind"] if kind == "inclusion"
                                 else f"{t['layer']} {t['quantity']}") for i, t in enumerate(tables))
    try:
        i = int(index)
    except ValueError:
        i = -1
    if not 0 <= i < n:
        raise ConfigError(source, f"{kind}.{index}", value,
                          f"no such {kind}: give an index 0..{n - 1} ({names})" if n
                          else f"no such {kind}: the config has no [[{kind}]] table")
    if key not in schema:
        near = difflib.get_close_matches(key, list(schema), 1, 0.5)
        raise ConfigError(source, f"{kind}.{i}.{_show_key(key) if key else '<key>'}", value,
                          "unknown key" + (f" (did you mean '{near[0]}'?)" if near else "")
                          + f"; valid keys: {', '.join(schema)}")
    out = copy.deepcopy(cfg)
    out[kind][i][key] = _check(source, f"{kind}[{i}].{key}", value, schema[key], ".")
    _cross_checks(source, out)
    return out


def override(cfg: dict, section: str, key: str, value: Any, source: str = "command line") -> dict:
    """Set one validated value (used by command-line flags)."""
    if section not in SCHEMA:
        raise _unknown(source, "", section, list(SCHEMA) + ["layer"], value)
    schema = SCHEMA[section]
    if key not in schema:
        raise _unknown(source, section, key, schema, value)
    out = copy.deepcopy(cfg)
    out[section][key] = _check(source, f"{section}.{key}", value, schema[key], ".")
    _cross_checks(source, out)
    return out


#: the paper's design: every scattering event stored, one band per photon path, the plain
#: sphere estimator, the per-point progressive radius (Kamatani & Kawai; Hachisuka et al. 2008)
PAPER_MODE = {"storage": "all", "estimator": "sphere", "radius": "ppm", "bands_per_path": 1,
              "band_sampling": "power", "emission": "random", "depth_roulette_um": 0.0}
#: the paper's model: light walks the 5 um voxels (the interfaces' staircase)
PAPER_MODEL = {"surface": "voxels"}


def paper_mode(cfg: dict, source: str = "--paper") -> dict:
    """``cfg`` with the paper's photon storage, estimator and radius (:data:`PAPER_MODE`) on the
    paper's voxel model (:data:`PAPER_MODEL`)."""
    for k, v in PAPER_MODE.items():
        cfg = override(cfg, "render", k, v, source)
    for k, v in PAPER_MODEL.items():
        cfg = override(cfg, "model", k, v, source)
    return cfg


def bands_per_path(cfg: dict) -> int:
    """render.bands_per_path, with 0 resolved to the largest divisor of the band count <= 9, or
    to 1 with chromophore maps (kernels/maps.h: their delta tracking carries one band per path)."""
    C = int(cfg["render"]["bands_per_path"])
    if C:
        return C
    if cfg.get("map"):
        return 1
    nb = len(wavelengths(cfg))
    return max(d for d in range(1, min(nb, 9) + 1) if nb % d == 0)


def wavelengths(cfg: dict):
    import numpy as np
    sp = cfg["spectrum"]
    nb = int(round((sp["stop_nm"] - sp["start_nm"]) / sp["step_nm"])) + 1
    return sp["start_nm"] + sp["step_nm"] * np.arange(nb)


#: what ``--slab`` assumes for the keys it does not get, and what that means
SLAB_DEFAULTS = {"n": (1.0, "index matched to the air outside"), "d": (INF, "semi-infinite")}


@dataclass(frozen=True)
class Slab:
    """A homogeneous slab as ``--slab`` gave it: cm^-1, cm; ``defaulted``: keys not given."""

    mua: float
    mus: float
    g: float
    n: float
    d: float
    defaulted: tuple[str, ...] = ()

    def text(self) -> str:
        """The slab on one line, as traced, saying which values were not given."""
        vals = " ".join(f"{k}={getattr(self, k):g}" for k in ("mua", "mus", "g", "n", "d"))
        if not self.defaulted:
            return vals
        return vals + "; not given: " + ", ".join(f"{k} ({SLAB_DEFAULTS[k][1]})" for k in self.defaulted)


def parse_slab(spec: str, source: str = "--slab") -> Slab:
    """``mua=10,mus=90,g=0.75,n=1.0,d=0.02`` (cm^-1, cm): each key once; mua, mus, g required;
    n and d default to :data:`SLAB_DEFAULTS` (the result says which were not given)."""
    vals: dict[str, float] = {}
    allowed = ("mua", "mus", "g", "n", "d")
    for item in filter(None, (s.strip() for s in spec.split(","))):
        if "=" not in item:
            raise ConfigError(source, _show_key(item), item, "expected key=value")
        k, v = (s.strip() for s in item.split("=", 1))
        if k not in allowed:
            near = difflib.get_close_matches(k, allowed, 1)
            raise ConfigError(source, _show_key(k), v, "unknown key" + (
                f" (did you mean '{near[0]}'?)" if near else f"; valid: {', '.join(allowed)}"))
        if k in vals:
            raise ConfigError(source, k, v, f"given twice (first {k}={vals[k]:g}); give each key once")
        try:
            vals[k] = float(v)
        except ValueError:
            raise ConfigError(source, k, v, "must be a number") from None
    for k in ("mua", "mus", "g"):
        if k not in vals:
            raise ConfigError(source, k, None, "missing required key")
    defaulted = tuple(k for k in SLAB_DEFAULTS if k not in vals)
    return Slab(**{k: vals.get(k, SLAB_DEFAULTS.get(k, (None,))[0]) for k in allowed}, defaulted=defaulted)


def slab_config(spec: "str | Slab", source: str = "--slab") -> dict:
    """A homogeneous slab from ``mua=10,mus=90,g=0.75,n=1.0,d=0.02`` (cm^-1, cm) or a
    :class:`Slab`.  Leaving out ``d`` gives a semi-infinite medium, ``n`` the index 1.0.
    Normal collimated pencil beam, air outside, one band."""
    slab = parse_slab(spec, source) if isinstance(spec, str) else spec
    d_um = slab.d * 1e4 if math.isfinite(slab.d) else INF
    raw = {
        "model": {"name": "slab", "lateral": "infinite", "quantize": False},
        "spectrum": {"start_nm": 500.0, "stop_nm": 500.0, "step_nm": 5.0},
        "light": {"kind": "pencil", "direction": [0.0, 0.0, -1.0], "spectrum": "flat",
                  "center_mm": [0.0, 0.0]},
        "layer": [{"name": "slab", "thickness_um": d_um, "n": slab.n,
                   "mua": slab.mua, "mus": slab.mus, "g": slab.g,
                   "scattering": "none"}],
    }
    return validate(raw, source)


# ----------------------------------------------------------------------------- shipped configs
def shipped_configs() -> dict[str, str]:
    """The configs that ship in the package (``clppm.configs``): name -> file path."""
    from importlib import resources
    root = resources.files("clppm.configs")
    return {f.name[:-5]: str(f) for f in sorted(root.iterdir(), key=lambda f: f.name)
            if f.name.endswith(".toml")}


def find(name: str) -> str:
    """A config file: ``name`` itself when it is a file, else a shipped config of that name
    (``forearm`` or ``forearm.toml``; a folder of that name in the working directory does not
    hide it); else a one-line ConfigError listing the shipped ones."""
    name = os.fspath(name)
    if os.path.isfile(name):
        return name
    stem = name[:-5] if name.endswith(".toml") else name
    ship = shipped_configs()
    if os.sep not in name and stem in ship:
        return ship[stem]
    why = "is a folder, not a config file" if os.path.isdir(name) else "file not found"
    raise ConfigError(os.path.basename(name) or repr(name), "<file>", name,
                      f"{why} (shipped configs: {', '.join(ship)})")


# ----------------------------------------------------------------------------- TOML out
def toml_value(v) -> str:
    """One value of a validated config as TOML (bool, number, inf, string, array)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):                     # an inline table (a map's spot)
        return "{" + ", ".join(f"{_show_key(k)} = {toml_value(x)}" for k, x in v.items() if x is not None) + "}"
    raise TypeError(type(v))


def _toml_table(head: str, table: dict, schema: dict[str, F]) -> list[str]:
    out = [head]
    for k, f in schema.items():
        v = table.get(k)
        if v is None:
            out.append(f"# {k} = (unset{'' if f.none_ok else ': required'})")
        else:
            out.append(f"{k} = {toml_value(v)}")
    return out + [""]


def to_toml(cfg: dict, header: str = "") -> str:
    """A complete config (every key, defaults filled) as TOML that :func:`validate` reads back
    to the same dict; an unset optional value is a comment."""
    lines = [f"# {h}" for h in header.splitlines()] + ([""] if header else [])
    for name, schema in SCHEMA.items():
        lines += _toml_table(f"[{name}]", cfg.get(name, {}), schema)
    for L in cfg.get("layer", [{}]):
        lines += _toml_table("[[layer]]", L, LAYER_SCHEMA)
    for inc in cfg.get("inclusion", []):
        lines += _toml_table("[[inclusion]]", inc, INCLUSION_SCHEMA)
    for m in cfg.get("map", []):
        lines += _toml_table("[[map]]", m, MAP_SCHEMA)
    return "\n".join(lines).rstrip() + "\n"


def defaults() -> dict:
    """Every section's defaults and one layer with its defaults (name, thickness unset)."""
    out = {name: {k: copy.deepcopy(f.default) for k, f in schema.items()} for name, schema in SCHEMA.items()}
    out["layer"] = [{k: copy.deepcopy(f.default) for k, f in LAYER_SCHEMA.items()}]
    return out


# ----------------------------------------------------------------------------- the schema as text
def _type_name(f: F) -> str:
    return {"float": "float", "int": "int", "bool": "bool", "str": "string", "path": "path",
            "vec2": "[float, float]", "vec3": "[float, float, float]", "ivec2": "[int, int]",
            "choice": "choice", "spots": "[{spot}, ...]"}[f.kind]


def _range_text(f: F) -> str:
    if f.kind == "choice":
        return " / ".join(map(str, f.choices))
    if f.lo is None and f.hi is None:
        return ""
    lo = f"{_fmt(f.lo)} {'<' if f.lo_open else '<='} " if f.lo is not None else ""
    hi = f" {'<' if f.hi_open else '<='} {_fmt(f.hi)}" if f.hi is not None else ""
    extra = " or inf" if f.inf_ok else ""
    return f"{lo}x{hi}{extra}" + (" (each)" if f.kind.startswith(("vec", "ivec")) else "")


def _default_text(f: F) -> str:
    if f.default is None:
        return "unset" if f.none_ok else "required"
    return toml_value(f.default)


_TABLES = [("layer", LAYER_SCHEMA), ("inclusion", INCLUSION_SCHEMA), ("map", MAP_SCHEMA),
           ("map spot", SPOT_SCHEMA)]


def schema_rows() -> list[tuple[str, str, str, str, str]]:
    """(key, type, default, range, meaning) of every config key, from :data:`SCHEMA`."""
    rows = []
    for name, schema in list(SCHEMA.items()) + _TABLES:
        for k, f in schema.items():
            key = (f"[[{name}]].{k}" if name in ("layer", "inclusion", "map")
                   else f"[[map]].spots.{k}" if name == "map spot" else f"{name}.{k}")
            rows.append((key, _type_name(f), _default_text(f), _range_text(f), f.doc))
    return rows


def schema_text() -> str:
    """The schema as aligned plain text (``clppm config --schema``)."""
    rows = [("key", "type", "default", "range", "meaning")] + schema_rows()
    w = [max(len(r[i]) for r in rows) for i in range(4)]
    return "\n".join("  ".join(c.ljust(w[i]) for i, c in enumerate(r[:4])) + "  " + r[4]
                     for r in rows).rstrip() + "\n"


def schema_markdown() -> str:
    """The config reference page (docs/config.md), generated: ``clppm config --schema --markdown``."""
    def cell(x):
        return x.replace("|", "\\|") if x else ""
    out = ["# Config reference", "",
           "<!-- generated by `clppm config --schema --markdown > docs/config.md`; "
           "tests/test_outputs.py fails when this page and clppm/config.py's SCHEMA differ -->", "",
           "A config is a TOML file with the sections below and one `[[layer]]` table per layer, top "
           "first (at most 16). Every key is optional unless its default says *required*. Units: mm for "
           "scene-scale lengths, µm for skin-scale lengths, cm^-1 for optical coefficients, nm for "
           "wavelengths. `clppm config FILE` prints a file with every default filled in; "
           "`--set SECTION.KEY=VALUE` / `--set layer.N.KEY=VALUE` changes one value on the command line. "
           "Optional `[[inclusion]]` tables (at most 8) bury a vessel or an ellipsoid of chromophores of "
           "its own in the layers (docs/method.md, Inclusions). Optional `[[map]]` tables vary a layer's "
           "melanin, blood or oxygen saturation from column to column: an image or .npy file, Gaussian "
           "spots (`spots` items: `center_mm`, `radius_um`, `peak`) or a constant (docs/method.md, "
           "Chromophore maps).", ""]
    for name, schema in list(SCHEMA.items()) + _TABLES:
        out += [f"## `[[{name}]]`" if name in ("layer", "inclusion", "map")
                else "## `[[map]].spots` items" if name == "map spot" else f"## `[{name}]`", "",
                "| key | type | default | range | meaning |", "|---|---|---|---|---|"]
        for k, f in schema.items():
            out.append(f"| `{k}` | {_type_name(f)} | `{_default_text(f)}` | {cell(_range_text(f))} "
                       f"| {cell(f.doc)} |")
        out.append("")
    return "\n".join(out).rstrip() + "\n"
