"""Measured skin reflectance: the packaged NIST set, user spectra, and how a model compares.

The NIST Reference Data Set of Human Skin Reflectance (Cooksey, Allen & Tsai, J. Res. NIST
122:26, 2017) holds the directional-hemispherical reflectance factor of the inner forearm of
100 volunteers, 379-781 nm every 3 nm, measured with an integrating-sphere spectrophotometer
(spot about 5 mm).  It is packaged as ``clppm.data.nist_skin`` (see clppm/data/README.md).

This module reads it (interpolated linearly onto any model band grid), gives the population
median and 5-95 % band, reads a user's CSV spectrum with clear errors, compares a model
spectrum with the population (spectral RMSE and CIEDE2000 under D65 with the CIE 1931 2°
observer, XYZ from reflectance x D65 through :mod:`clppm.image`), and plots it.
"""
from __future__ import annotations

import functools
import os
import re
from importlib import resources

import numpy as np

from ..config import ConfigError

NIST_FILE = "nist_skin_avg_379_781nm.csv"
NIST_LABEL = "NIST skin reflectance (Cooksey et al. 2017), volar forearm, 100 subjects"
#: Reflectance values a measured spectrum may hold (a factor, not percent).
R_RANGE = (0.0, 1.5)
#: Wavelengths a measured spectrum must cover by default (the model's spectrum).
COVER_NM = (380.0, 780.0)
#: Wavelengths where summaries quote R(λ).
QUOTE_NM = (450.0, 550.0, 650.0, 700.0)


# ----------------------------------------------------------------------------- NIST set
@functools.lru_cache(maxsize=1)
def _nist_raw() -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    text = resources.files("clppm.data.nist_skin").joinpath(NIST_FILE).read_text(encoding="utf-8")
    wl, R, names = _parse_table(text, NIST_FILE)
    return wl, R, tuple(names)


def nist_path() -> str:
    """File system path of the packaged NIST CSV (for messages and the CLI)."""
    return str(resources.files("clppm.data.nist_skin").joinpath(NIST_FILE))


def load_nist() -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(wavelengths nm (N,), reflectance factors (N, 100), subject names) at the native 3 nm."""
    wl, R, names = _nist_raw()
    return wl.copy(), R.copy(), list(names)


def nist_on(wl) -> tuple[np.ndarray, list[str]]:
    """All subjects interpolated linearly onto ``wl`` (nm, inside 379-781): (len(wl), 100)."""
    w0, R, names = _nist_raw()
    wl = np.asarray(wl, float)
    if wl.min() < w0[0] - 1e-9 or wl.max() > w0[-1] + 1e-9:
        raise ValueError(f"NIST data cover {w0[0]:g}-{w0[-1]:g} nm; asked for "
                         f"{wl.min():g}-{wl.max():g} nm")
    out = np.stack([np.interp(wl, w0, R[:, j]) for j in range(R.shape[1])], axis=1)
    return out, list(names)


def subject(n: int, wl=None) -> tuple[np.ndarray, np.ndarray]:
    """Subject ``n`` (1..100): (wl, R) at the native grid, or interpolated onto ``wl``."""
    w0, R, names = _nist_raw()
    if not 1 <= int(n) <= R.shape[1]:
        raise ConfigError("NIST skin set", "--subject", n, f"must be 1..{R.shape[1]}")
    r = R[:, int(n) - 1]
    if wl is None:
        return w0.copy(), r.copy()
    wl = np.asarray(wl, float)
    return wl, np.interp(wl, w0, r)


def population(wl=None) -> dict:
    """Median and 5th / 95th percentiles over the 100 subjects at ``wl`` (default native)."""
    if wl is None:
        wl, R, _ = load_nist()
    else:
        wl = np.asarray(wl, float)
        R, _ = nist_on(wl)
    p5, med, p95 = np.percentile(R, [5.0, 50.0, 95.0], axis=1)
    return {"wl": wl, "median": med, "p5": p5, "p95": p95}


# ----------------------------------------------------------------------------- CSV spectra
_NUM = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


def _split(line: str) -> list[str]:
    if "," in line:
        parts = line.split(",")
    elif ";" in line:
        parts = line.split(";")
    else:
        parts = line.split()
    return [p.strip().strip('"').strip("'") for p in parts]


def _parse_table(text: str, src: str):
    """Numbers of a delimited text table: (first column, other columns (N, K), column names)."""
    rows, names, ncol = [], None, None
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = _split(s)
        while parts and parts[-1] == "":            # trailing delimiter
            parts.pop()
        if not rows and names is None and parts and not _NUM.match(parts[0]):
            names = parts[1:]                        # a header line
            ncol = len(parts)
            continue
        if ncol is None:
            ncol = len(parts)
        if len(parts) != ncol:
            raise ConfigError(src, f"line {lineno}", s,
                              f"has {len(parts)} columns; the file's first line has {ncol}")
        vals = []
        for p in parts:
            if not _NUM.match(p):
                raise ConfigError(src, f"line {lineno}", s, f"{p!r} is not a number")
            vals.append(float(p))
        rows.append(vals)
    if not rows:
        raise ConfigError(src, "<data>", "", "no numeric rows (expected wavelength_nm,reflectance)")
    a = np.array(rows, float)
    if a.shape[1] < 2:
        raise ConfigError(src, "<columns>", a.shape[1],
                          "only one column: expected two columns, wavelength_nm,reflectance")
    if names is None or len(names) != a.shape[1] - 1:
        names = [f"column_{j + 1}" for j in range(a.shape[1] - 1)]
    return a[:, 0], a[:, 1:], names


def read_spectrum(path: str, subject: int | None = None,
                  cover_nm: tuple[float, float] | None = COVER_NM) -> tuple[np.ndarray, np.ndarray, str]:
    """A measured reflectance spectrum from a CSV: (wavelengths nm, reflectance, label).

    Two columns, ``wavelength_nm,reflectance`` (comma, semicolon, tab or spaces; an optional
    header line; ``#`` comments).  A file with several reflectance columns (the NIST layout)
    needs ``subject``: the column named ``subject_N``, else the N-th reflectance column.
    Reflectance is a factor in [0, 1.5] (not percent); wavelengths must be distinct and cover
    ``cover_nm`` (default 380-780 nm).  Any problem raises :class:`ConfigError` naming the
    file and the problem.
    """
    src = str(path)
    if not os.path.isfile(path):
        raise ConfigError(src, "<file>", str(path), "file not found")
    try:
        with open(path, encoding="utf-8-sig") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(src, "<file>", str(path), f"cannot be read as text ({e})") from None
    wl, cols, names = _parse_table(text, src)
    k = cols.shape[1]
    if subject is None:
        if k != 1:
            raise ConfigError(src, "<columns>", k + 1,
                              f"{k} reflectance columns; choose one with --subject N "
                              f"(1..{k}) or give a two-column wavelength_nm,reflectance file")
        j, label = 0, os.path.basename(src)
    else:
        n = int(subject)
        want = f"subject_{n}"
        if want in names:
            j = names.index(want)
        elif 1 <= n <= k:
            j = n - 1
        else:
            raise ConfigError(src, "--subject", n, f"the file has reflectance columns 1..{k}")
        label = f"{os.path.basename(src)} {names[j]}"
    R = cols[:, j]
    return _check_spectrum(src, wl, R, cover_nm) + (label,)


def _check_spectrum(src, wl, R, cover_nm):
    if not np.all(np.isfinite(wl)):
        raise ConfigError(src, "wavelength_nm", "nan/inf", "wavelengths must be finite numbers")
    if not np.all(np.isfinite(R)):
        i = int(np.flatnonzero(~np.isfinite(R))[0])
        raise ConfigError(src, f"reflectance at {wl[i]:g} nm", R[i], "must be a finite number")
    if len(wl) < 2:
        raise ConfigError(src, "<data>", len(wl), "needs at least two wavelengths")
    order = np.argsort(wl, kind="stable")
    wl, R = wl[order], R[order]
    d = np.flatnonzero(np.diff(wl) == 0)
    if d.size:
        raise ConfigError(src, "wavelength_nm", float(wl[d[0]]), "appears twice")
    lo, hi = R_RANGE
    bad = np.flatnonzero((R < lo) | (R > hi))
    if bad.size:
        i = int(bad[0])
        hint = " (percent? give reflectance as a factor, e.g. 0.35 for 35 %)" if R[i] > hi else ""
        raise ConfigError(src, f"reflectance at {wl[i]:g} nm", float(R[i]),
                          f"outside [{lo:g}, {hi:g}]{hint}")
    if wl[0] <= 0:
        raise ConfigError(src, "wavelength_nm", float(wl[0]), "must be > 0 (nanometres)")
    if cover_nm is not None:
        a, b = cover_nm
        if wl[0] > a + 1e-9 or wl[-1] < b - 1e-9:
            unit_hint = " (wavelengths in µm? give nanometres)" if wl[-1] < 10 else ""
            raise ConfigError(src, "wavelength_nm", f"{wl[0]:g}-{wl[-1]:g} nm",
                              f"does not cover {a:g}-{b:g} nm{unit_hint}")
    return wl, R


# ----------------------------------------------------------------------------- colour
def _colour_grid(wl) -> np.ndarray:
    wl = np.asarray(wl, float)
    lo, hi = max(380.0, float(wl.min())), min(780.0, float(wl.max()))
    if hi - lo < 5.0:
        raise ValueError(f"colour needs a spectrum across the visible; have {lo:g}-{hi:g} nm")
    return np.arange(lo, hi + 1e-9, 5.0)


def reflectance_xyz(wl, R, grid=None) -> tuple[np.ndarray, np.ndarray]:
    """(XYZ, white XYZ) of reflectance ``R`` (..., len(wl)) under D65, CIE 1931 2°, white Y=1.

    ``R`` is interpolated linearly onto a 5 nm grid inside both ``wl`` and 380-780 nm; the
    white is the perfect reflector under the same D65 and grid (so Lab is relative to it).
    """
    from ..scene import colorimetry
    from ..scene.spectra import d65
    wl = np.asarray(wl, float)
    g = _colour_grid(wl) if grid is None else grid
    R = np.asarray(R, float)
    Rg = np.apply_along_axis(lambda r: np.interp(g, wl, r), -1, R)
    S = np.asarray(d65(g), float)
    white = colorimetry.spectral_to_xyz(S, g)
    k = 1.0 / white[1]
    return colorimetry.spectral_to_xyz(Rg * S, g) * k, white * k


def delta_e(wl, Ra, Rb) -> np.ndarray:
    """CIEDE2000 between reflectance spectra ``Ra`` and ``Rb`` (D65, 2°)."""
    from ..scene import colorimetry
    xa, w = reflectance_xyz(wl, Ra)
    xb, _ = reflectance_xyz(wl, Rb)
    return colorimetry.delta_e2000(xa, xb, white_XYZ=w)


def lab(wl, R) -> np.ndarray:
    from ..scene import colorimetry
    x, w = reflectance_xyz(wl, R)
    return colorimetry.xyz_to_lab(x, white_XYZ=w)


def compare(wl, R, band_nm: tuple[float, float] = (450.0, 700.0)) -> dict:
    """How a model spectrum ``R`` on bands ``wl`` compares with the NIST population.

    Spectral RMSE is over the model bands inside the NIST range; colour differences are
    CIEDE2000 under D65 (2°) on a 5 nm grid.  The nearest subject is the one with the least
    spectral RMSE (the one with the least ΔE is reported too).  ``inside`` says whether R lies
    within the population's 5-95 % band at every model band in ``band_nm``.
    """
    wl = np.asarray(wl, float)
    R = np.asarray(R, float)
    w0, _, _ = _nist_raw()
    use = (wl >= w0[0] - 1e-9) & (wl <= w0[-1] + 1e-9)
    wl_u, R_u = wl[use], R[use]
    subj, names = nist_on(wl_u)
    pop = population(wl_u)
    rmse_med = float(np.sqrt(np.mean((R_u - pop["median"]) ** 2)))
    rmse_all = np.sqrt(np.mean((subj - R_u[:, None]) ** 2, axis=0))
    j = int(np.argmin(rmse_all))
    # colour on the common 5 nm grid (NIST from its native 3 nm data)
    g = _colour_grid(wl_u)
    w0n, Rn, _ = _nist_raw()
    Rsub_g = np.stack([np.interp(g, w0n, Rn[:, k]) for k in range(Rn.shape[1])], axis=0)
    med_g = np.median(Rsub_g, axis=0)
    Rm_g = np.interp(g, wl_u, R_u)
    from ..scene import colorimetry
    xm, white = reflectance_xyz(g, Rm_g, grid=g)
    xmed, _ = reflectance_xyz(g, med_g, grid=g)
    xs, _ = reflectance_xyz(g, Rsub_g, grid=g)
    de_all = colorimetry.delta_e2000(np.broadcast_to(xm, xs.shape), xs, white_XYZ=white)
    de_med = float(colorimetry.delta_e2000(xm, xmed, white_XYZ=white))
    jde = int(np.argmin(de_all))
    sel = (wl_u >= band_nm[0] - 1e-9) & (wl_u <= band_nm[1] + 1e-9)
    below = wl_u[sel & (R_u < pop["p5"])]
    above = wl_u[sel & (R_u > pop["p95"])]
    return {
        "reference": NIST_LABEL,
        "bands_compared": int(use.sum()),
        "rmse_median": rmse_med,
        "delta_e2000_median": de_med,
        "nearest_subject": names[j],
        "rmse_nearest": float(rmse_all[j]),
        "delta_e2000_nearest": float(de_all[j]),
        "least_delta_e_subject": names[jde],
        "delta_e2000_least": float(de_all[jde]),
        "lab_model": [float(v) for v in colorimetry.xyz_to_lab(xm, white_XYZ=white)],
        "lab_median": [float(v) for v in colorimetry.xyz_to_lab(xmed, white_XYZ=white)],
        "inside_5_95": {"range_nm": list(band_nm), "inside": bool(below.size == 0 and above.size == 0),
                        "below_p5_nm": [float(v) for v in below],
                        "above_p95_nm": [float(v) for v in above]},
        "at_nm": {f"{q:g}": {"model": _interp_or_none(q, wl, R),
                             "median": _interp_or_none(q, pop["wl"], pop["median"]),
                             "p5": _interp_or_none(q, pop["wl"], pop["p5"]),
                             "p95": _interp_or_none(q, pop["wl"], pop["p95"])}
                  for q in QUOTE_NM},
    }


def _interp_or_none(q, wl, R):
    wl = np.asarray(wl, float)
    if q < wl.min() - 1e-9 or q > wl.max() + 1e-9:
        return None
    return float(np.interp(q, wl, R))


# ----------------------------------------------------------------------------- plot
def plot(path: str, wl, R, se=None, label: str = "model", curves: dict | None = None,
         nearest: str | None = None, title: str | None = None) -> None:
    """R(λ) over the NIST population median and 5-95 % band (PNG/PDF/SVG by extension).

    ``curves``: more spectra {label: (wl, R) or (wl, R, se)} drawn on top (e.g. per method);
    ``nearest``: a subject name (``subject_N``) to draw as a thin line.
    """
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    pop = population()
    fig, ax = plt.subplots(figsize=(7.5, 4.8), dpi=120)
    ax.fill_between(pop["wl"], pop["p5"], pop["p95"], color="0.85", label="NIST 5-95 %")
    ax.plot(pop["wl"], pop["median"], color="0.35", lw=1.5, label="NIST median")
    if nearest:
        n = int(nearest.split("_")[-1])
        sw, sr = subject(n)
        ax.plot(sw, sr, color="0.5", lw=0.9, ls="--", label=f"nearest: {nearest}")
    wl = np.asarray(wl, float)
    R = np.asarray(R, float)
    if se is not None and np.any(np.asarray(se) > 0):
        ax.errorbar(wl, R, yerr=2 * np.asarray(se, float), color="C3", lw=1.6, elinewidth=0.8,
                    capsize=1.5, label=f"{label} (±2 SE)")
    else:
        ax.plot(wl, R, color="C3", lw=1.6, label=label)
    for i, (name, c) in enumerate((curves or {}).items()):
        cw, cr = np.asarray(c[0], float), np.asarray(c[1], float)
        ax.plot(cw, cr, lw=1.1, color=f"C{i % 10 if i % 10 != 3 else 9}", marker=".", ms=3,
                label=name)
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("reflectance factor")
    ax.set_xlim(min(380.0, wl.min()), max(780.0, wl.max()))
    top = max([float(np.nanmax(R))] + [float(np.nanmax(np.asarray(c[1], float)))
                                       for c in (curves or {}).values()])
    ax.set_ylim(0.0, min(1.6, max(0.8, top * 1.05)))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title or "Spectral reflectance vs NIST volar forearm skin", fontsize=10)
    fig.tight_layout()
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def summary_lines(cmp: dict) -> list[str]:
    """Human-readable lines for a :func:`compare` result."""
    ins = cmp["inside_5_95"]
    out = []
    q = "  ".join(f"{k} nm {v['model']:.3f} (median {v['median']:.3f}, 5-95 % "
                  f"{v['p5']:.3f}-{v['p95']:.3f})" for k, v in cmp["at_nm"].items()
                  if v["model"] is not None and v["median"] is not None)
    out.append(f"  R at {q}")
    where = "inside" if ins["inside"] else "NOT inside"
    extra = ""
    if not ins["inside"]:
        parts = []
        if ins["below_p5_nm"]:
            parts.append(f"below 5 % at {_ranges(ins['below_p5_nm'])} nm")
        if ins["above_p95_nm"]:
            parts.append(f"above 95 % at {_ranges(ins['above_p95_nm'])} nm")
        extra = ": " + "; ".join(parts)
    out.append(f"  {where} the NIST 5-95 % band over {ins['range_nm'][0]:g}-{ins['range_nm'][1]:g} nm"
               + extra)
    out.append(f"  vs median: RMSE {cmp['rmse_median']:.4f}, ΔE2000 {cmp['delta_e2000_median']:.2f}")
    out.append(f"  nearest subject {cmp['nearest_subject']}: RMSE {cmp['rmse_nearest']:.4f}, "
               f"ΔE2000 {cmp['delta_e2000_nearest']:.2f} (least ΔE: {cmp['least_delta_e_subject']} "
               f"{cmp['delta_e2000_least']:.2f})")
    L = cmp["lab_model"]; M = cmp["lab_median"]
    out.append(f"  L*a*b* model {L[0]:.1f} {L[1]:.1f} {L[2]:.1f}; median {M[0]:.1f} {M[1]:.1f} {M[2]:.1f}")
    return out


def _ranges(vals) -> str:
    vals = sorted(vals)
    if not vals:
        return ""
    step = min(np.diff(vals)) if len(vals) > 1 else 0
    groups, start, prev = [], vals[0], vals[0]
    for v in vals[1:]:
        if v - prev > step * 1.01:
            groups.append((start, prev)); start = v
        prev = v
    groups.append((start, prev))
    return ", ".join(f"{a:g}" if a == b else f"{a:g}-{b:g}" for a, b in groups)
