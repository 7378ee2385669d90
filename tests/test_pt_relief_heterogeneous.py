"""The path tracer through the relief with inclusions and chromophore maps (kernels/pt.cl:
pt_walk, connect_mnee_sms, mnee_legs_factor; kernels/mnee.h Trace.pe).

Reference: the photon pass's exact exit tally.  Flat layers compare the two through translation
invariance (tests/test_inclusions.py, tests/test_maps.py); a relief with one vessel or a freckle
has none, so here the camera looks straight down from 40 mm at an open 1 mm footprint that
fills its image exactly (pixel centres tile it; the views lean at most 0.7 degrees off the
normal): the image mean is the footprint's mean radiance L(x, up), and a point light 1 m above
the centre gives E over the footprint, so E R_cone / (pi (1 - c^2) share) (R_cone per photon of
the light's cone, share: the footprint's part of it) is the cos-weighted mean of that radiance
over the cone cos > c = 0.98 (edge losses through the open sides are in both).  The two differ
by the cone's angular spread, small here (+0.33 % for the flat semi-infinite slab of
tests/test_pathtracer.py at this c): the tolerance is 3 combined standard errors + 1 %.
Index-matched layers (n 1.4 throughout): no light comes back out unscattered (the path tracer
cannot see it), and the surface's relief (generated furrows, a papillary junction) is what the
manifold connections refract through.
"""
from __future__ import annotations

import math

import pytest

from clppm import config as C
from clppm.integrators import photonpass
from clppm.run import entry
from clppm.scene import volume

FAR = 1000.0                                          # mm: the light above the footprint's centre
E_FAR = 1.0 / (4 * math.pi) / (FAR * 1e-3) ** 2      # W m^-2 per nm below it (one band)
SIZE = 1.0                                            # mm: the footprint, open sides
CAM = 40.0                                            # mm: the camera's height
CONE = 0.98
FURROWS = {"kind": "generated", "depth_um": 20.0, "spacing_um": 200.0, "width_um": 80.0, "seed": 3}


def lay(name, t, mua, mus, g, bottom="flat"):
    return {"name": name, "thickness_um": t, "n": 1.4, "mua": mua, "mus": mus, "g": g,
            "scattering": "none", "bottom": bottom}


def relief_scene(layers, *, inclusions=(), maps=(), res=24, spp=64, passes=2) -> dict:
    s = SIZE
    raw = {"model": {"name": "relief", "size_mm": [s, s], "lateral": "open", "quantize": False,
                     "voxel_um": 5.0, "lateral_voxel_um": 5.0},
           "spectrum": {"start_nm": 500.0, "stop_nm": 500.0, "step_nm": 5.0},
           "relief": FURROWS, "papillae": {"amplitude_um": 15.0, "period_um": 100.0},
           "light": {"kind": "point", "position_mm": [s / 2, s / 2, FAR], "spectrum": "flat"},
           "camera": {"position_mm": [s / 2, s / 2, CAM], "look_at_mm": [s / 2, s / 2, 0.0],
                      "fov_deg": 2 * math.degrees(math.atan(s / 2 / CAM)), "resolution": [res, res]},
           "render": {"passes": passes, "pt_samples_per_pass": spp, "specular": False,
                      "checkpoint_every": 0, "seed": 1},
           "layer": layers}
    if inclusions:
        raw["inclusion"] = list(inclusions)
    if maps:
        raw["map"] = list(maps)
    return C.validate(raw, "relief scene")


def pt_mean(dev, cfg) -> tuple[float, float]:
    """The image mean and its standard error (the paths' own variances: the report's noise)."""
    r = entry.render_pt(cfg, dev=dev)
    assert r.report["manifold_nee"]["solves"] > 0
    m = float(r.spectral[..., 0].mean())
    return m, m * r.report["noise"]["image_mean_Y_rel_se"]


def tally(dev, cfg, photons: int) -> tuple[float, float]:
    """E R_cone / (pi (1 - c^2) share): the footprint's mean radiance from the photon pass."""
    vol = volume.build(cfg, "relief scene")
    assert not vol.flat
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg)
    pp.p["rcone_cos"] = CONE
    rep = photonpass.trace_report(pp, photons, batches=10)
    k = E_FAR / (math.pi * (1 - CONE * CONE)) / pp.emission_share
    return k * rep["Rd_cone"], k * rep["Rd_cone_se"]


def agree(dev, cfg, photons: int):
    got, se = pt_mean(dev, cfg)
    ref, seref = tally(dev, cfg, photons)
    tol = 3 * math.hypot(se, seref) + 0.01 * ref
    assert abs(got - ref) < tol, (got, se, ref, seref, tol)
    return got, ref, tol


#: stratum corneum over an epidermis with a papillary junction, over the dermis: index-matched
STACK = [lay("sc", 20.0, 20.0, 300.0, 0.85, "surface"), lay("epi", 60.0, 10.0, 250.0, 0.8, "papillae"),
         lay("derm", math.inf, 5.0, 200.0, 0.8)]

#: a wide, densely scattering vessel 25 um under the surface's mean plane, across the footprint's
#: middle half and the three layers: mu_t 2005 /cm against the layers' 205-320
VESSEL = {"kind": "vessel", "center_mm": [SIZE / 2, SIZE / 2], "depth_um": 275.0, "axis": [0.0, 1.0, 0.0],
          "radius_um": 250.0, "mua": 5.0, "mus": 2000.0, "g": 0.9, "scattering": "none"}


@pytest.mark.once     # ~40 s on 2 cores (a relief build of the path tracer and 3 M photons)
@pytest.mark.slow
def test_path_tracer_matches_the_photon_tally_through_a_vessel_on_relief(dev):
    """The path tracer's walk into and out of the vessel and its manifold light connections,
    each leg (vertex to the first interface point, between interface points, to the surface)
    walked through the vessel, against the photon pass's exit tally (measured: 1.004 of it on
    Intel's runtime and PoCL, tolerance 6 %).  The first assert catches connections that ignore
    the vessel's extra optical depth (tried by hand, mnee_legs_factor without its exp(-od): the
    image mean 2.7 times the tally), and would catch a walk that does not see the vessel (the
    photons' tally with it is 1.76 times that without); the second, that the vessel matters at
    all (so the first is not vacuous): the tally without it is over 5 tolerances away."""
    cfg = relief_scene(STACK, inclusions=[VESSEL])
    got, ref, tol = agree(dev, cfg, 2_000_000)
    without, _ = tally(dev, relief_scene(STACK), 1_000_000)
    assert abs(without - ref) > 5 * tol, (without, ref, tol)


#: chromophore layers (n 1.4): an epidermis with a papillary junction and a freckle map of melanin
#: in it (two spots up to 0.8 against the layer's own 0.02), over the dermis
SKIN = [{"name": "epidermis", "thickness_um": 70.0, "n": 1.4, "melanin": 0.02, "baseline": 0.5,
         "bottom": "papillae"},
        {"name": "dermis", "thickness_um": math.inf, "n": 1.4, "blood": 0.02, "saturation": 0.8}]
FRECKLES = {"layer": "epidermis", "quantity": "melanin", "kind": "spots",
            "spots": [{"center_mm": [0.45 * SIZE, 0.5 * SIZE], "radius_um": 300.0, "peak": 0.8},
                      {"center_mm": [0.75 * SIZE, 0.3 * SIZE], "radius_um": 120.0, "peak": 0.3}]}


@pytest.mark.once     # ~35 s on 2 cores
@pytest.mark.slow
def test_path_tracer_matches_the_photon_tally_with_a_map_on_relief(dev):
    """The path tracer's delta tracking through the freckle map and its manifold light
    connections, each leg in the epidermis ratio-tracked through the map (map_leg_factor),
    against the photon pass's exit tally (measured: 1.018 of it on Intel's runtime and PoCL,
    tolerance 6.8 %).  The first assert catches connections that ignore the map (tried by hand,
    mnee_legs_factor without map_leg_factor: the image mean 1.47 times the tally), and would
    catch a walk that does not see it (the tally with the map is 0.2 of that without); the
    second, that the map matters at all: the tally without it is over 5 tolerances away."""
    cfg = relief_scene(SKIN, maps=[FRECKLES])
    got, ref, tol = agree(dev, cfg, 2_000_000)
    without, _ = tally(dev, relief_scene(SKIN), 1_000_000)
    assert abs(without - ref) > 5 * tol, (without, ref, tol)
