"""Fit the skin model's chromophores and scattering to a measured reflectance spectrum.

Four parameters of a layered model (by default the forearm model, configs/forearm.toml):

* ``melanin``: a factor on the melanin fraction of every layer that holds melanin (the basal
  and granular + spinous layers, scaled together; a layer whose melanin and baseline fractions
  add up to 1 keeps that sum);
* ``blood``: a factor on the blood fraction of the dermal layers (every layer with blood except
  a subcutis / hypodermis / fat layer), scaled together;
* ``saturation``: the blood oxygen saturation of those dermal layers;
* ``scattering``: a factor on the Jacques scattering multiplier ``k`` of every layer that uses
  the Jacques recipe.

Forward model: R(λ) from the photon pass (:func:`clppm.analysis.reflectance.trace_bands`) on the
flat version of the model (relief and papillae off, sides infinite), a collimated beam at 8°,
specular included, a fixed number of photons per band and the *same seed in every evaluation*
(common random numbers).  By default the fit is a hybrid (space mapping): a smooth
adding-doubling surrogate of the same layer stack (iadpython; one refractive index, normal
incidence) is fitted with its per-band offset from the photon pass, the offset is re-measured
with the photon pass at the new parameters, and so on until the parameters stop moving; the
offset is exact at the end, so the answer is the photon pass's least-squares fit, at a few
photon-pass evaluations.  ``forward="mc"`` runs the same bounded least squares (scipy's
trust-region reflective solver) directly on the photon pass instead.  Both parametrise the
three factors by their logarithm.

Output: the full input config with the fitted layer values (relief, light, camera and render
settings unchanged) as TOML that :func:`clppm.config.load` and ``clppm render`` accept, a plot
of measured vs fitted, and a JSON report.
"""
from __future__ import annotations

import copy
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from .. import config as C
from ..config import ConfigError

PARAMS = ("melanin", "blood", "saturation", "scattering")
DEFAULT_BANDS = (380.0, 780.0, 20.0)
DEFAULT_PHOTONS = 4000
NOT_DERMIS = ("subcut", "hypoderm", "fat", "adipose")


# ----------------------------------------------------------------------------- model
def default_config_path() -> str:
    """The forearm model that ships in the package (clppm.configs), wherever clppm is installed."""
    return C.shipped_configs()["forearm"]


@dataclass
class FitModel:
    """Which layers each parameter moves, and how a parameter set becomes a config."""

    base: dict
    melanin_layers: list[int]
    blood_layers: list[int]
    scatter_layers: list[int]
    source: str = "<config>"

    @classmethod
    def from_config(cls, cfg: dict, source: str = "<config>") -> "FitModel":
        layers = cfg["layer"]

        def own(L):           # composition-driven (not a homogeneous mua/mus override)
            return L["mua"] is None
        mel = [i for i, L in enumerate(layers) if own(L) and L["melanin"] > 0]
        blood = [i for i, L in enumerate(layers) if own(L) and L["blood"] > 0
                 and not any(w in L["name"].lower() for w in NOT_DERMIS)]
        kl = [i for i, L in enumerate(layers) if own(L) and L["scattering"] == "jacques" and L["k"] > 0]
        for what, idx in (("melanin", mel), ("blood", blood), ("scattering (Jacques k)", kl)):
            if not idx:
                raise ConfigError(source, "layer", what, f"no layer has {what} to fit")
        return cls(cfg, mel, blood, kl, source)

    def bounds(self) -> dict[str, tuple[float, float]]:
        L = self.base["layer"]
        mmax = max(L[i]["melanin"] for i in self.melanin_layers)
        bmax = max(L[i]["blood"] for i in self.blood_layers)
        return {"melanin": (0.02, min(30.0, 1.0 / mmax)), "blood": (0.02, min(20.0, 1.0 / bmax)),
                "saturation": (0.0, 1.0), "scattering": (0.2, 5.0)}

    def start(self) -> dict[str, float]:
        L = self.base["layer"]
        s = [L[i]["saturation"] for i in self.blood_layers]
        return {"melanin": 1.0, "blood": 1.0, "saturation": float(np.mean(s)), "scattering": 1.0}

    def apply(self, p: dict) -> dict:
        """The full config with parameter set ``p`` applied to its layers."""
        cfg = copy.deepcopy(self.base)
        base = self.base["layer"]
        for i in self.melanin_layers:
            L, B = cfg["layer"][i], base[i]
            m = min(1.0, B["melanin"] * p["melanin"])
            if abs(B["melanin"] + B["baseline"] - 1.0) < 1e-9:
                L["baseline"] = max(0.0, 1.0 - m)
            L["melanin"] = m
        for i in self.blood_layers:
            L = cfg["layer"][i]
            L["blood"] = min(1.0, base[i]["blood"] * p["blood"])
            L["saturation"] = min(1.0, max(0.0, p["saturation"]))
        for i in self.scatter_layers:
            cfg["layer"][i]["k"] = base[i]["k"] * p["scattering"]
        return C.validate(cfg, self.source)

    def layer_values(self, p: dict) -> list[dict]:
        cfg = self.apply(p)
        out = []
        for i, L in enumerate(cfg["layer"]):
            d = {"name": L["name"]}
            if i in self.melanin_layers:
                d["melanin"] = L["melanin"]; d["baseline"] = L["baseline"]
            if i in self.blood_layers:
                d["blood"] = L["blood"]; d["saturation"] = L["saturation"]
            if i in self.scatter_layers:
                d["k"] = L["k"]
            if len(d) > 1:
                out.append(d)
        return out


class Forward:
    """R(λ) of a parameter set: photon pass on the flat model, common random numbers."""

    def __init__(self, model: FitModel, bands=DEFAULT_BANDS, photons: int = DEFAULT_PHOTONS,
                 seed: int = 1, angle_deg: float = 8.0, specular: bool = True, batches: int = 4,
                 dev=None, device: str | None = None):
        from ..compute.device import open_device
        self.model, self.bands, self.photons = model, tuple(bands), int(photons)
        self.seed, self.angle, self.specular, self.batches = int(seed), float(angle_deg), specular, batches
        self.dev = dev or open_device(device)
        self.cache: dict = {}
        self.evaluations = 0
        self.seconds = 0.0
        self.wl = C.wavelengths({"spectrum": {"start_nm": bands[0], "stop_nm": bands[1],
                                              "step_nm": bands[2]}})

    def __call__(self, p: dict) -> tuple[np.ndarray, np.ndarray]:
        from ..scene import volume
        from .reflectance import measurement_config, trace_bands
        key = tuple(round(float(p[k]), 12) for k in PARAMS)
        if key in self.cache:
            return self.cache[key]
        t0 = time.perf_counter()
        cfg = self.model.apply(p)
        mcfg = measurement_config(cfg, self.angle, bands=self.bands, flat=True, seed=self.seed,
                                  source=self.model.source)
        vol = volume.build(mcfg, self.model.source)
        t = trace_bands(self.dev, vol, mcfg, self.photons, self.batches, self.specular)
        self.evaluations += 1
        self.seconds += time.perf_counter() - t0
        self.cache[key] = (t["R"], t["se"])
        return self.cache[key]


class Surrogate:
    """Adding-doubling R(λ) of the flat layer stack (iadpython), a smooth stand-in for the
    photon pass inside the fit.

    One refractive index for the whole stack (``n``; the photon pass has a different index per
    layer), normal incidence, Henyey-Greenstein with delta-M, ``quad_pts`` quadrature angles.
    Its offset from the photon pass is removed by the hybrid fit (see :func:`fit`).  Layer
    matrices are cached, so a parameter that moves a few layers recomputes only those.
    """

    def __init__(self, model: FitModel, wl, n: float = 1.4, quad_pts: int = 8):
        try:
            import iadpython  # noqa: F401
        except ImportError as e:
            raise ImportError(f"the hybrid fit needs iadpython ({e}); pip install iadpython scipy, "
                              "or use --forward mc") from None
        self.model, self.wl, self.quad_pts = model, np.asarray(wl, float), int(quad_pts)
        self.evaluations = 0
        self.seconds = 0.0
        self.set_index(n)

    def set_index(self, n: float) -> None:
        import iadpython
        self.n = float(n)
        s = iadpython.Sample(a=0.5, b=1.0, g=0.0, n=self.n, n_above=1.0, n_below=1.0,
                             quad_pts=self.quad_pts)
        s.update_quadrature()
        self.sample = s
        self.cache: dict = {}
        self.bound = iadpython.start.boundary_layer(s, top=True)

    def _layer(self, a, b, g):
        from iadpython import combine
        key = (round(float(a), 13), round(float(b), 11) if math.isfinite(b) else b, round(float(g), 13))
        rt = self.cache.get(key)
        if rt is None:
            s = self.sample
            s.a, s.b, s.g = float(a), float(b), float(g)
            rt = combine.simple_single_layer_matrices(s)
            if len(self.cache) > 20000:
                self.cache.clear()
            self.cache[key] = rt
        return rt

    def __call__(self, p: dict) -> np.ndarray:
        from iadpython import combine
        from ..scene.volume import layer_optics
        t0 = time.perf_counter()
        cfg = self.model.apply(p)
        mua, mus, g = layer_optics(cfg["layer"], self.wl, self.model.source)       # cm^-1
        d = np.array([L["thickness_um"] for L in cfg["layer"]], float) * 1e-4        # cm
        s = self.sample
        out = np.empty(len(self.wl))
        R01, R10, T01, T10 = self.bound
        for k in range(len(self.wl)):
            R02 = None
            for i in range(len(d)):
                mut = mua[i, k] + mus[i, k]
                a = mus[i, k] / mut if mut > 0 else 0.0
                b = mut * d[i] if mut > 0 else 1e-9
                r, t = self._layer(a, b, g[i, k])
                if R02 is None:
                    R02, R20, T02, T20 = r, r, t, t
                else:
                    R02, R20, T02, T20 = combine.add_layers(s, R02, R20, T02, T20, r, r, t, t)
            Rt, _, Tt, _ = combine.add_slide_above(s, R01, R10, T01, T10, R02, R20, T02, T20)
            out[k] = s.UX1_and_UXU(Rt, Tt)[0]
        self.evaluations += 1
        self.seconds += time.perf_counter() - t0
        return out


# ----------------------------------------------------------------------------- solver
_LOG = {"melanin": True, "blood": True, "saturation": False, "scattering": True}
# finite-difference steps in u (log factors, saturation), in PARAMS order: a few per cent on the
# photon pass, whose common-random-number noise swamps smaller differences; fine on the
# smooth surrogate
_STEP_MC = np.array([0.05, 0.05, 0.04, 0.03])
_STEP_AD = np.full(4, 1e-3)
SURROGATE_ITERATIONS = 60     # hybrid fit: iterations of each surrogate fit (it stops well before)
POOL_RADIUS = 0.3         # hybrid fit: photon-pass offsets within this distance (log factors,
                          # saturation) of the current point are averaged


def _to_u(p):
    return np.array([math.log(p[k]) if _LOG[k] else p[k] for k in PARAMS])


def _to_p(u):
    return {k: (math.exp(v) if _LOG[k] else float(v)) for k, v in zip(PARAMS, u)}


@dataclass
class FitResult:
    params: dict
    params_se: dict
    start: dict
    wl: np.ndarray
    measured: np.ndarray
    fitted: np.ndarray
    fitted_se: np.ndarray
    initial: np.ndarray
    rms: float
    rms_initial: float
    max_abs: float
    iterations: int
    evaluations: int
    seconds: float
    converged: bool
    history: list = field(default_factory=list)
    layers: list = field(default_factory=list)
    delta_e: float | None = None
    delta_e_initial: float | None = None
    label: str = ""
    settings: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "measured": self.label, "params": self.params, "params_se": self.params_se,
            "start": self.start, "layers": self.layers,
            "residual_rms": self.rms, "residual_rms_start": self.rms_initial,
            "residual_max_abs": self.max_abs,
            "delta_e2000_fitted_vs_measured": self.delta_e,
            "delta_e2000_start_vs_measured": self.delta_e_initial,
            "iterations": self.iterations, "photon_pass_evaluations": self.evaluations,
            "seconds": self.seconds, "converged": self.converged, "settings": self.settings,
            "wavelength_nm": self.wl.tolist(), "measured_R": self.measured.tolist(),
            "fitted_R": self.fitted.tolist(), "fitted_R_se": self.fitted_se.tolist(),
            "start_R": self.initial.tolist(), "residual": (self.fitted - self.measured).tolist(),
            "history": self.history,
        }


def solve(resid, u0, box: "_Box", steps, max_iter: int, ftol: float, xtol: float, log=None):
    """Least squares on ``resid(u)`` within the box: scipy's trust-region reflective solver.

    "trf" rather than "lm": the parameters have bounds (saturation in [0, 1], fractions at most
    1) and MINPACK's "lm" takes none.  Its Jacobian: :func:`jacobian` with ``steps``.  At most
    ``max_iter`` iterations, fewer once an iteration lowers the cost by less than ``ftol`` of it
    or moves u by less than about ``xtol``; ``log(iteration, params, rms)`` after each.
    Returns scipy's result with ``iterations``, ``converged`` (a tolerance met, not the
    iteration limit) and ``history`` (the start and the point after each iteration, with their
    RMS).
    """
    from scipy.optimize import least_squares
    history = []

    def f(u):
        r = resid(u)
        if not history:                                      # scipy's first call: the start
            history.append({"params": _to_p(u), "rms": _rms(r)})
        return r

    def after_iteration(intermediate_result):              # scipy passes its state by this name
        x, nit = intermediate_result.x, intermediate_result.nit
        rms = math.sqrt(2.0 * intermediate_result.cost / intermediate_result.fun.size)  # ½ Σ r²
        history.append({"params": _to_p(x), "rms": rms})
        if log:
            log(nit, _to_p(x), rms)
        if nit >= max_iter:
            raise StopIteration
    res = least_squares(f, np.clip(np.asarray(u0, float), box.lo, box.hi),
                        jac=lambda u: jacobian(f, u, box.hi, steps), bounds=(box.lo, box.hi),
                        method="trf", ftol=ftol, xtol=xtol, gtol=1e-12, callback=after_iteration)
    res.converged = res.status > 0           # 1-4: a tolerance; 0, -2: evaluation or iteration cap
    res.history = history
    res.iterations = len(history) - 1
    return res


def jacobian(resid, u, hi, steps) -> np.ndarray:
    """Forward differences of ``resid`` at ``u``, of the absolute ``steps`` in u (backwards
    where a step would pass ``hi``).  Absolute, since scipy's relative ``diff_step`` shrinks
    to machine precision at u = 0 (a factor of 1), where the photon pass's noise needs steps
    of a few per cent."""
    from scipy.optimize import approx_fprime
    u = np.asarray(u, float)
    return approx_fprime(u, resid, np.where(u + steps <= hi, steps, -steps))


@threadpool_limits.wrap(limits=1, user_api="blas")
def fit(measured_wl, measured_R, cfg: dict | None = None, *, photons: int = DEFAULT_PHOTONS,
        bands=DEFAULT_BANDS, seed: int = 1, angle_deg: float = 8.0, specular: bool = True,
        max_iter: int = 6, forward: str = "hybrid", start: dict | None = None, dev=None,
        device: str | None = None, source: str = "<config>", label: str = "",
        log=None) -> tuple[FitResult, FitModel]:
    """Least-squares fit of the four parameters to a measured spectrum (see module docstring).

    ``measured_wl`` / ``measured_R``: the measurement (any grid covering ``bands``), interpolated
    linearly onto the band grid ``bands`` = (start, stop, step) nm.

    ``forward="hybrid"`` (default): space mapping with the adding-doubling :class:`Surrogate`.
    Each outer iteration k traces the photon pass once at the current parameters p_k
    (``photons`` per band, the same seed every time) and fits
    ``AD(p) + [MC(p_k) - AD(p_k)]`` to the measurement; the parameters where that fit stops
    moving make the photon pass itself match the measurement (the correction is exact there).
    At most ``max_iter`` outer iterations, so ``max_iter + 1`` photon-pass evaluations.
    The reported fitted spectrum and residuals are the photon pass's at the final parameters.

    ``forward="mc"``: bounded least squares (:func:`solve`) directly on the photon pass (common
    random numbers, finite differences of 3-5 % steps; ``max_iter`` iterations of about 5
    evaluations each).
    Slower, and rougher: a change of absorption changes every photon's steps, so nearby
    evaluations share less of their noise than CRN promises for long paths.

    BLAS runs on one thread meanwhile (threadpoolctl): the surrogate makes thousands of small
    matrix calls, and on a small CPU shared with the OpenCL runtime's threads, OpenBLAS's
    spinning workers made the hybrid fit several times slower.
    """
    t0 = time.perf_counter()
    if cfg is None:
        path = default_config_path()
        cfg = C.load(path)
        source = os.path.basename(path)
    _check_options(photons, forward)
    model = FitModel.from_config(cfg, source)
    fwd = Forward(model, bands, photons, seed, angle_deg, specular, dev=dev, device=device)
    y = _measured_on_bands(fwd.wl, measured_wl, measured_R, label)
    box = _Box.of(model)
    p0 = box.clip(start_point(model, start))
    R0, _ = fwd(p0)
    settings = {"bands_nm": list(bands), "photons_per_band": photons, "seed": seed,
                "angle_deg": angle_deg, "specular": "included" if specular else "excluded",
                "device": fwd.dev.name, "config": source,
                "layers_melanin": [cfg["layer"][i]["name"] for i in model.melanin_layers],
                "layers_blood": [cfg["layer"][i]["name"] for i in model.blood_layers],
                "layers_k": [cfg["layer"][i]["name"] for i in model.scatter_layers],
                "bounds": box.bounds}
    if forward == "mc":
        sol = _fit_mc(fwd, y, p0, box, max_iter, log)
    else:
        sol = _fit_hybrid(fwd, y, p0, R0, box, max_iter, log)
    settings.update(sol.settings)
    R, se = fwd(sol.p)
    de, de0 = _colour_differences(fwd.wl, R, R0, y)
    settings["mc_se_mean"] = float(np.mean(se))
    settings["photon_pass_seconds"] = fwd.seconds
    res = FitResult(
        params=sol.p, params_se=parameter_errors(sol.J, sol.r, sol.p), start=p0, wl=fwd.wl,
        measured=y, fitted=R, fitted_se=se, initial=R0, rms=_rms(R - y), rms_initial=_rms(R0 - y),
        max_abs=float(np.max(np.abs(R - y))), iterations=sol.iterations, evaluations=fwd.evaluations,
        seconds=time.perf_counter() - t0, converged=sol.converged, history=sol.history,
        layers=model.layer_values(sol.p), delta_e=de, delta_e_initial=de0, label=label,
        settings=settings)
    return res, model


def _rms(d) -> float:
    return float(np.sqrt(np.mean(d ** 2)))


def _check_options(photons: int, forward: str) -> None:
    if photons < 100:
        raise ConfigError("command line", "--photons", photons, "must be >= 100 for a fit")
    if forward not in ("hybrid", "mc"):
        raise ConfigError("command line", "--forward", forward, "must be hybrid or mc")


def _measured_on_bands(wl, measured_wl, measured_R, label: str) -> np.ndarray:
    """The measurement interpolated linearly onto the fit bands (which it must cover)."""
    mw = np.asarray(measured_wl, float)
    if wl[0] < mw.min() - 1e-9 or wl[-1] > mw.max() + 1e-9:
        raise ConfigError(label or "measured spectrum", "wavelength_nm", f"{mw.min():g}-{mw.max():g} nm",
                          f"does not cover the fit bands {wl[0]:g}-{wl[-1]:g} nm")
    return np.interp(wl, mw, np.asarray(measured_R, float))


@dataclass
class _Box:
    """The parameters' bounds, as parameters and in the solver's variables u."""

    bounds: dict
    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def of(cls, model: FitModel) -> "_Box":
        b = model.bounds()
        return cls(b, _to_u({k: b[k][0] for k in PARAMS}), _to_u({k: b[k][1] for k in PARAMS}))

    def clip(self, p: dict) -> dict:
        return {**p, **{k: min(max(p[k], self.bounds[k][0]), self.bounds[k][1]) for k in PARAMS}}


def start_point(model: FitModel, start: dict | None) -> dict:
    """The model's own values, with ``start`` over them."""
    p0 = dict(model.start())
    if start:
        p0.update(start)
    return p0


@dataclass
class _Solution:
    """Where a solver stopped: parameters, residual and Jacobian there (for the standard
    errors), and its record."""

    p: dict
    r: np.ndarray
    J: np.ndarray | None
    iterations: int
    converged: bool
    history: list
    settings: dict


def _fit_mc(fwd: "Forward", y, p0: dict, box: _Box, max_iter: int, log) -> _Solution:
    """Least squares directly on the photon pass."""
    def resid(u):
        return fwd(_to_p(u))[0] - y
    res = solve(resid, _to_u(p0), box, _STEP_MC, max_iter, 1e-4, 0.1 * _STEP_MC.min(), log)
    note = ("photon pass, flat model (relief/papillae off), laterally infinite, "
            "pencil beam, common random numbers; least squares on it directly")
    return _Solution(_to_p(res.x), res.fun, res.jac, res.iterations, res.converged, res.history,
                     {"forward": note})


def _fit_hybrid(fwd: "Forward", y, p0: dict, R0, box: _Box, max_iter: int, log) -> _Solution:
    """Space mapping: the adding-doubling surrogate, corrected by the photon pass's offset at
    each outer iteration, fitted until the parameters stop moving."""
    sur = Surrogate(fwd.model, fwd.wl)
    offset0 = calibrate_index(sur, p0, R0)
    hist = [{"params": dict(p0), "rms": _rms(R0 - y), "surrogate_offset_rms": offset0}]
    p, its, conv = _space_mapping(fwd, sur, y, p0, box, max_iter, log, hist)
    r = fwd(p)[0] - y
    J = jacobian(lambda uu: sur(_to_p(uu)) - y, _to_u(p), box.hi, _STEP_AD)
    settings = {"forward": ("hybrid: adding-doubling surrogate (iadpython, one index "
                            f"n = {sur.n:g}, normal incidence, {sur.quad_pts} quadrature angles) "
                            "corrected per band by the photon pass (flat model, laterally "
                            "infinite, pencil beam, common random numbers) at each outer "
                            "iteration; residuals are the photon pass's"),
                "surrogate_index": sur.n, "surrogate_offset_rms_start": offset0,
                "surrogate_evaluations": sur.evaluations, "surrogate_seconds": sur.seconds}
    return _Solution(p, r, J, its, conv, hist, settings)


def calibrate_index(sur: Surrogate, p0: dict, R0) -> float:
    """Set the surrogate's single index to the layer index whose adding-doubling spectrum is
    nearest the photon pass at the start (a calibration, not a fit parameter); returns that
    RMS offset."""
    best = None
    for n in sorted({round(float(L["n"]), 4) for L in sur.model.base["layer"]}):
        sur.set_index(n)
        e = _rms(sur(p0) - R0)
        if best is None or e < best[0]:
            best = (e, n)
    sur.set_index(best[1])
    return best[0]


def _space_mapping(fwd: "Forward", sur: Surrogate, y, p0: dict, box: _Box, max_iter: int,
                   log, hist: list) -> tuple[dict, int, bool]:
    """The outer iterations of the hybrid fit (appending to ``hist``): the best parameters the
    photon pass saw, the iterations run, and whether they converged."""
    p, u = dict(p0), _to_u(p0)
    best_p, best_rms = dict(p0), hist[0]["rms"]
    conv, its, stale = False, 0, 0
    pts = []                                   # (u, offset) at every photon-pass point
    for its in range(1, max_iter + 1):
        Rm, _ = fwd(p)
        pts.append((u.copy(), Rm - sur(p)))
        near, delta = pooled_offset(pts, u)

        def resid(uu, delta=delta):
            return sur(_to_p(uu)) + delta - y
        # to 1e-6 of the cost (u to ~1e-4, well inside the outer loop's 2e-3)
        un = solve(resid, u, box, _STEP_AD, SURROGATE_ITERATIONS, 1e-6, 0.1 * _STEP_AD.min()).x
        moved = float(np.max(np.abs(un - u)))
        u, p = un, _to_p(un)
        Rn, _ = fwd(p)
        rms = _rms(Rn - y)
        hist.append({"params": dict(p), "rms": rms, "moved": moved, "pooled": near,
                     "surrogate_offset_rms": _rms(delta)})
        if log:
            log(its, p, rms)
        if rms < best_rms:
            best_p, best_rms, stale = dict(p), rms, 0
        else:
            stale += 1
        if moved < 2e-3 or stale >= 2:     # fixed point, or at the photon-noise floor
            conv = True
            break
    return best_p, its, conv


def pooled_offset(pts: list, u) -> tuple[int, np.ndarray]:
    """The mean photon-pass offset of the points within :data:`POOL_RADIUS` of ``u``, and how
    many: the offset moves slowly with the parameters, its photon noise does not, so nearby
    points average the noise down."""
    near = [d for uj, d in pts if np.max(np.abs(uj - u)) < POOL_RADIUS]
    return len(near), np.mean(near, axis=0)


def parameter_errors(J, r, p: dict) -> dict:
    """Standard errors of the parameters from the Jacobian at the solution (None where the
    covariance is singular); the delta method for the log factors."""
    dof = max(1, r.size - len(PARAMS))
    s2 = float(r @ r) / dof
    try:
        cov = np.linalg.inv(J.T @ J) * s2 if J is not None else None
    except np.linalg.LinAlgError:
        cov = None
    pse = {}
    for j, k in enumerate(PARAMS):
        if cov is None or not np.isfinite(cov[j, j]) or cov[j, j] < 0:
            pse[k] = None
        else:
            sd = math.sqrt(cov[j, j])
            pse[k] = sd * p[k] if _LOG[k] else sd          # delta method for the log factors
    return pse


def _colour_differences(wl, R, R0, y) -> tuple[float | None, float | None]:
    """CIEDE2000 of the fitted and of the starting spectrum against the measurement (None
    where the bands do not allow it)."""
    from . import nist
    try:
        return float(nist.delta_e(wl, R, y)), float(nist.delta_e(wl, R0, y))
    except ValueError:
        return None, None


# ----------------------------------------------------------------------------- TOML out
def to_toml(cfg: dict, header: list[str] | None = None) -> str:
    """A validated config as TOML text (every key written; None values left out)."""
    lines = [f"# {h}" if h else "#" for h in (header or [])]
    if lines:
        lines.append("")
    for sec, schema in C.SCHEMA.items():
        lines.append(f"[{sec}]")
        for key in schema:
            v = cfg[sec].get(key)
            if v is not None:
                lines.append(f"{key} = {C.toml_value(v)}")
        lines.append("")
    for L in cfg["layer"]:
        lines.append("[[layer]]")
        for key in C.LAYER_SCHEMA:
            v = L.get(key)
            if v is not None:
                lines.append(f"{key} = {C.toml_value(v)}")
        lines.append("")
    return "\n".join(lines)


def write_toml(cfg: dict, path: str, header: list[str] | None = None) -> None:
    text = to_toml(cfg, header)
    import tomllib
    C.validate(tomllib.loads(text), path, os.path.dirname(os.path.abspath(path)))   # round trip
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)


# ----------------------------------------------------------------------------- plot
def plot_fit(path: str, res: FitResult, native: tuple | None = None, title: str | None = None) -> None:
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(7.5, 6.0), dpi=120, sharex=True,
                                  gridspec_kw={"height_ratios": [3, 1]})
    if native is not None:
        ax.plot(native[0], native[1], color="0.2", lw=1.4, label=f"measured: {res.label}")
    else:
        ax.plot(res.wl, res.measured, color="0.2", lw=1.4, label=f"measured: {res.label}")
    ax.plot(res.wl, res.initial, color="C0", lw=1.0, ls="--", marker=".", ms=3,
            label=f"start (RMS {res.rms_initial:.4f})")
    ax.errorbar(res.wl, res.fitted, yerr=2 * res.fitted_se, color="C3", lw=1.6, marker="o", ms=3,
                capsize=1.5, label=f"fitted (RMS {res.rms:.4f}, ±2 SE)")
    p = res.params
    txt = (f"melanin ×{p['melanin']:.3g}  blood ×{p['blood']:.3g}  "
           f"S = {p['saturation']:.3f}  scattering ×{p['scattering']:.3g}")
    ax.text(0.02, 0.97, txt, transform=ax.transAxes, va="top", fontsize=8)
    ax.set_ylabel("reflectance factor")
    ax.set_ylim(0, max(0.8, float(np.max(res.measured)) * 1.1))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(title or "Fit of the skin model to a measured spectrum", fontsize=10)
    ax2.axhline(0, color="0.5", lw=0.8)
    ax2.plot(res.wl, res.fitted - res.measured, color="C3", marker="o", ms=3)
    ax2.set_ylabel("fitted − measured")
    ax2.set_xlabel("wavelength (nm)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


# ----------------------------------------------------------------------------- CLI


def load_measured(path: str | None, subject: int | None, bands) -> tuple[np.ndarray, np.ndarray, str]:
    from . import nist
    cover = (float(bands[0]), float(bands[1]))
    if path is None:
        if subject is None:
            raise ConfigError("clppm fit", "MEASURED", None,
                              "give a measured CSV, or --subject N for the packaged NIST set")
        wl, R = nist.subject(subject)
        return wl, R, f"NIST subject_{subject}"
    return nist.read_spectrum(path, subject, cover)


