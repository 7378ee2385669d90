"""Numerical guards, device resources and platform failures.

* Extreme inputs (huge or zero coefficients, g near +-1, n = 1, zero power, light that
  never reaches the viewed region) give finite, non-negative images, accumulators and
  tallies: the raw pixel accumulators are read back from the render's checkpoint.
* A render too big for the device stops before allocating, with the numbers and the options.
* No OpenCL platform says how to get PoCL; a kernel that does not build names the device and
  shows the compiler's log; a device lost mid-render keeps the last checkpoint.
"""
from __future__ import annotations

import copy
import math
import shutil
import warnings

import numpy as np
import pytest

from clppm.output import checkpoint as ckpt
from clppm import cli
from clppm import config as C
from clppm.compute import device as D
from clppm.compute import programs as P
from clppm.integrators import photonpass
from clppm.run import entry
from clppm.scene import volume

H, W = 16, 24

BASE = {
    "model": {"size_mm": [1.0, 1.0], "voxel_um": 5.0, "lateral_voxel_um": 10.0},
    "spectrum": {"start_nm": 450.0, "stop_nm": 650.0, "step_nm": 100.0},
    "light": {"kind": "point", "position_mm": [0.0, 1.0, 2.0]},
    "camera": {"position_mm": [0.5, 0.5, 5.0], "look_at_mm": [0.5, 0.5, 0.0], "fov_deg": 12.0,
               "resolution": [W, H]},
    "render": {"photons": 2000, "initial_photons": 20, "passes": 2, "checkpoint_every": 0},
    "layer": [{"name": "top", "thickness_um": 100.0, "n": 1.4, "mua": 1.0, "mus": 100.0, "g": 0.9},
              {"name": "bottom", "thickness_um": math.inf, "n": 1.4, "mua": 1.0, "mus": 100.0, "g": 0.9}],
}


def _cfg(**changes):
    """BASE with changes given as {"layer.0.mua": 1e5, "light.kind": "pencil", "layers.mua": 0 (both)}."""
    raw = copy.deepcopy(BASE)
    for path, v in changes.items():
        sec, key = path.split(".", 1)
        if sec == "layers":
            for L in raw["layer"]:
                L[key] = v
        elif sec == "layer":
            i, key = key.split(".")
            raw["layer"][int(i)][key] = v
        else:
            raw[sec][key] = v
    return C.validate(raw, "guards")


# ----------------------------------------------------------------------------- extreme inputs
CASES = {
    "mua_huge": {"layers.mua": 1e5},                               # cm^-1: 0.1 um to absorption
    "mua_huge_top_only": {"layer.0.mua": 1e5},
    "mua_zero": {"layers.mua": 0.0},                               # open 1 mm model: photons leave sideways
    "mus_zero": {"layers.mus": 0.0, "render.passes": 1},           # no scattering: nothing stored
    "mus_huge": {"layers.mus": 1e5, "layers.mua": 1e3},
    "g_plus_0.99": {"layers.g": 0.99},
    "g_minus_0.99": {"layers.g": -0.99},
    "g_plus_0.99999": {"layers.g": 0.99999},                       # HG peak ~1e9: fixed-point range
    "g_minus_0.99999": {"layers.g": -0.99999},
    "n_1": {"layers.n": 1.0, "model.n_outside": 1.0},              # no interface at all
    "n_3_over_1": {"layer.0.n": 3.0, "layer.1.n": 1.0},            # strong total internal reflection
    "thin_layer": {"layer.0.thickness_um": 1e-3},                  # thinner than a voxel
    "zero_power": {"light.power_w": 0.0},
    "light_in_surface_plane": {"light.position_mm": [0.0, 1.0, 0.0]},
    "light_below_surface": {"light.position_mm": [0.5, 0.5, -0.2]},
    "camera_looks_away": {"camera.look_at_mm": [0.5, 0.5, 10.0]},  # no sample points
    "one_pixel_one_band": {"camera.resolution": [1, 1], "spectrum.stop_nm": 450.0},
    "spp_4_global_radius": {"camera.spp": 4, "render.radius": "global"},
    "initial_photons_1": {"render.initial_photons": 1},
    "light_misses_model": {"light.kind": "pencil", "light.center_mm": [50.0, 50.0], "render.passes": 1},
    "grazing_wide_beam": {"light.kind": "wide", "light.direction": [1.0, 0.0, -1e-3], "light.center_mm": [0.5, 0.5],
                          "light.width_mm": [2.0, 2.0], "render.passes": 1},
}
# (tried by hand, fine, left out for time: a clear medium mua = mus = 0 renders like mus_zero;
# a camera inside the skin sees a finite, positive image)
ZERO_IMAGE = {"zero_power", "light_misses_model", "camera_looks_away"}


@pytest.mark.parametrize("case", sorted(CASES))
def test_extreme_inputs_finite(dev, tmp_path, case):
    cfg = _cfg(**CASES[case])
    ck = str(tmp_path / "x.ckpt.npz")
    res = entry.render(cfg, dev=dev, checkpoint_path=ck)
    S = res.spectral
    # the film zeroes non-finite radiance and counts it: the count is the test, not the image
    assert res.report["nonfinite_values_zeroed"] == 0, f"{case}: non-finite spectral radiance"
    assert np.all(S >= 0), f"{case}: negative spectral radiance {S.min()}"
    assert math.isfinite(res.exposure) and res.exposure > 0
    # the raw device accumulators (before any clean-up in the image path)
    st = ckpt.load(ck)
    assert np.all(np.isfinite(st["pix_acc"])) and np.all(st["pix_acc"] >= 0), case
    assert np.all(np.isfinite(st["pt_R"])) and np.all(st["pt_R"] >= 0), case
    assert np.all(np.isfinite(st["pt_N"])) and np.all(st["pt_N"] >= 0), case
    if case in ZERO_IMAGE:
        assert np.all(S == 0), f"{case}: expected a black image, max {S.max()}"
    rep = res.report
    for k in ("photons_emitted", "photons_stored", "gather_pairs", "sample_points"):
        assert isinstance(rep[k], int) and rep[k] >= 0


CASES_TRACE_ONLY = {"mua_mus_zero": {"layers.mua": 0.0, "layers.mus": 0.0}}
TRACE_CASES = ["mua_huge", "mua_zero", "mus_zero", "mua_mus_zero", "mus_huge", "g_plus_0.99",
               "g_minus_0.99", "g_plus_0.99999", "n_1", "n_3_over_1", "thin_layer", "zero_power",
               "light_below_surface", "light_misses_model"]


@pytest.mark.parametrize("case", TRACE_CASES)
def test_extreme_inputs_tallies(dev, case):
    """Photon tallies stay exact (integers), finite as fractions, and balance."""
    cfg = _cfg(**{**CASES, **CASES_TRACE_ONLY}[case])
    vol = volume.build(cfg)
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg)
    rep = photonpass.trace_report(pp, 4000, batches=4)
    for k in ("specular", "Rd", "Tt", "A", "lost", "missed", "roulette_net"):
        assert math.isfinite(rep[k]), (case, k, rep[k])
        assert -1e-9 <= rep[k] <= 1 + 1e-9 or k == "roulette_net", (case, k, rep[k])
    for b in rep["per_band"].values():
        assert all(math.isfinite(v) for v in b.values()), (case, b)
    assert rep["energy_balance_error"] < 1e-9, (case, rep["energy_balance_error"])
    assert all(isinstance(v, int) for row in pp.tallies.counts for v in row)


def test_zero_power_light_report(dev):
    res = entry.render(_cfg(**{"light.power_w": 0.0}), dev=dev)
    assert np.all(res.spectral == 0) and np.all(res.rgb == 0)
    assert res.exposure == 1.0          # no white reference to scale by: unit exposure


def test_light_far_from_the_view_gives_black_not_nan(dev):
    """Photons are stored (on a 10 mm model) but none near the 0.2 mm patch the camera sees."""
    cfg = _cfg(**{"model.size_mm": [10.0, 10.0], "light.kind": "pencil", "light.center_mm": [0.5, 0.5],
                  "layers.mua": 1e3, "camera.position_mm": [9.5, 9.5, 5.0],
                  "camera.look_at_mm": [9.5, 9.5, 0.0], "camera.fov_deg": 2.0})
    res = entry.render(cfg, dev=dev)
    assert res.report["photons_stored"] > 0 and res.report["sample_points"] > 0
    assert np.all(res.spectral == 0) and res.report["nonfinite_values_zeroed"] == 0


def test_light_at_the_viewed_point_no_warning(dev):
    cfg = _cfg(**{"light.position_mm": [0.5, 0.5, 0.0]})
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        res = entry.render(cfg, dev=dev)
    assert math.isfinite(res.exposure)


def test_non_absorbing_medium(dev):
    cfg = _cfg(**{"layers.mua": 0.0, "model.lateral": "infinite", "render.passes": 1})
    try:
        res = entry.render(cfg, dev=dev)
    except C.ConfigError as e:         # a clean refusal is acceptable too
        assert "render.photons" in str(e) or "mua" in str(e)
        return
    assert res.report["nonfinite_values_zeroed"] == 0 and np.all(res.spectral >= 0)
    assert res.spectral.max() > 0                     # scattering alone still lights the skin


def test_a_render_whose_passes_stored_less_than_asked_says_so(dev, tmp_path, capsys):
    """A clear, strongly absorbing layer over a black one: the passes end at their emission cap
    (photonpass.EMIT_PER_TARGET) short of render.photons, and the command says so in one note;
    a render that stores its budget says nothing of it."""
    from clppm.cli.render import short_passes_note
    assert short_passes_note({"stored_per_pass": 100, "passes_done": 2, "photons_stored": 200}) is None
    assert "150 of the 200 photons" in short_passes_note(
        {"stored_per_pass": 100, "passes_done": 2, "photons_stored": 150})
    for layers, said in (([dict(name="clear", thickness_um=100.0, n=1.0, mua=1000.0, mus=0.0, g=0.0),
                           dict(name="black", thickness_um=math.inf, n=1.0, mua=1e5, mus=1000.0, g=-0.5)], True),
                         (BASE["layer"], False)):
        raw = copy.deepcopy(BASE)
        raw["layer"] = copy.deepcopy(layers)
        p = tmp_path / "c.toml"
        p.write_text(_toml(raw))
        capsys.readouterr()
        assert cli.main(["render", str(p), "-o", str(tmp_path / "x.png"), "-q", "--force"]) == 0
        err = capsys.readouterr().err
        assert ("photons asked for" in err) == said, err


def test_photon_launches_grow_geometrically(dev):
    """A scene where the first photons store nothing and later ones store 1e5 events each."""
    cfg = _cfg(**{"layers.mua": 10.0})
    vol = volume.build(cfg)
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg, capacity=6496)
    launches, state = [], {"count": 0}

    def events(i):                       # photons 0-3 miss; every later one scatters 1e5 times
        return 0 if i < 4 else 100_000

    def launch(n, offset, pass_index, capacity):
        launches.append(n)
        if n > 4096:                     # what would run for hours on a real device
            raise RuntimeError(f"launched {n} photons after {launches[:-1]}")
        state["count"] += sum(events(i) for i in range(offset, offset + n))

    pp._launch = launch
    pp._count = lambda: state["count"]
    pp._set_count = lambda v: state.__setitem__("count", v)
    pp._flush = lambda emitted, into=None: None
    try:
        pp.run_pass(0, 2000)
    except RuntimeError as e:
        if "launched" in str(e):
            raise AssertionError(str(e)) from None
        # 'one photon overflowed' is the separate fault of test_non_absorbing_medium
    assert max(launches) <= 4096


# ----------------------------------------------------------------------------- device memory
class _FakeDevice:
    name = "Tiny Test Device"

    def __init__(self, global_mib, alloc_mib):
        self._info = {"global_mem_bytes": global_mib * 2**20, "max_alloc_bytes": alloc_mib * 2**20}

    def info(self):
        return dict(self._info)


def test_check_alloc_fits():
    D.check_alloc(_FakeDevice(64, 16), {"a": 10 * 2**20, "b": 15 * 2**20})
    D.check_alloc(_FakeDevice(64, 16), {})


@pytest.mark.parametrize("needs,why", [
    ({"stored photons": 20 * 2**20, "pixels": 2**20}, "max alloc"),     # one buffer too big
    ({f"b{i}": 15 * 2**20 for i in range(5)}, "global"),                # too much in all
])
def test_check_alloc_too_big(needs, why):
    with pytest.raises(D.DeviceError) as ei:
        D.check_alloc(_FakeDevice(64, 16), needs)
    msg = str(ei.value)
    total = sum(needs.values()) / 2**20
    assert f"{total:.1f} MiB" in msg
    assert "64 MiB" in msg and "16 MiB" in msg and "Tiny Test Device" in msg
    for opt in ("--photons", "--resolution", "--method"):
        assert opt in msg
    for name in needs:
        assert name in msg


def _small_device(monkeypatch, global_mib, alloc_mib):
    real = D.describe

    def describe(device):
        d = real(device)
        d["global_mem_bytes"], d["max_alloc_bytes"] = global_mib * 2**20, alloc_mib * 2**20
        return d
    monkeypatch.setattr(D, "describe", describe)


def test_render_stops_before_allocating(dev, monkeypatch, tmp_path):
    _small_device(monkeypatch, 8, 2)
    built = []
    monkeypatch.setattr(photonpass.PhotonPass, "__init__",
                        lambda *a, **k: built.append(1) or pytest.fail("allocated before the check"))
    cfg = _cfg(**{"render.photons": 100_000})
    with pytest.raises(D.DeviceError, match=r"needs [0-9.]+ MiB .* 8 MiB global memory .* 2 MiB"):
        entry.render(cfg, dev=dev, out=str(tmp_path / "x.exr"))
    assert not built and not (tmp_path / "x.exr").exists()


def test_cli_too_many_photons_exit_3(dev, tmp_path, capsys):
    """The real device: a photon count whose buffers exceed its largest allocation."""
    info = dev.info()
    photons = int(info["max_alloc_bytes"] / 32 * 1.5)
    if photons > 2**30:
        pytest.skip("this device can hold the largest allowed photon count")
    p = tmp_path / "c.toml"
    p.write_text(_toml(BASE))
    capsys.readouterr()
    rc = cli.main(["render", str(p), "--photons", str(photons), "-o", str(tmp_path / "x.exr"), "-q"])
    err = capsys.readouterr().err
    assert rc == 3, err
    assert err.startswith("clppm: device error: this render needs ")
    assert "MiB" in err and "--photons" in err and info["name"] in err


def test_huge_resolution_checked_before_eye_pass(dev, monkeypatch):
    _small_device(monkeypatch, 64, 16)
    from clppm.integrators import eyepass
    monkeypatch.setattr(eyepass, "run", lambda *a, **k: pytest.fail("eye pass ran before the memory check"))
    cfg = _cfg(**{"camera.resolution": [4096, 4096]})
    with pytest.raises(D.DeviceError, match="MiB"):
        entry.render(cfg, dev=dev)


# ----------------------------------------------------------------------------- platform failures
def test_no_platform_devices_command(monkeypatch, capsys):
    monkeypatch.setattr(D, "list_devices", lambda: [])
    capsys.readouterr()
    assert cli.main(["devices"]) == 3
    err = capsys.readouterr().err
    assert "pip install" in err and "pocl" in err.lower()


def test_no_platform_select_and_render(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(D, "list_devices", lambda: [])
    with pytest.raises(D.DeviceError) as ei:
        D.select_device()
    assert "pip install" in str(ei.value) and "pocl" in str(ei.value).lower()
    p = tmp_path / "c.toml"
    p.write_text(_toml(BASE))
    capsys.readouterr()
    rc = cli.main(["render", str(p), "--device", "7:7", "-o", str(tmp_path / "x.exr"), "-q"])
    err = capsys.readouterr().err
    assert rc == 3
    assert err.startswith("clppm: device error: no OpenCL platform found") and "pocl" in err.lower()


def test_get_platforms_error_means_no_platform(monkeypatch):
    """pyopencl raises PLATFORM_NOT_FOUND_KHR when no ICD is installed."""
    import pyopencl as cl

    def boom():
        raise cl.LogicError("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")
    monkeypatch.setattr(cl, "get_platforms", boom)
    assert D.list_devices() == []
    with pytest.raises(D.DeviceError, match="pocl"):
        D.select_device()


def test_pyopencl_missing(monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "pyopencl", None)       # import pyopencl -> ImportError
    with pytest.raises(D.DeviceError, match="pyopencl is not installed"):
        D.list_devices()


def test_unknown_device_spec(dev):
    with pytest.raises(D.DeviceError, match="clppm devices"):
        D.select_device("99:0")
    with pytest.raises(D.DeviceError, match="no implementation, platform or device name contains"):
        D.select_device("no such accelerator")


BROKEN = """
__kernel void broken(__global float* a) {
    a[get_global_id(0)] = this_identifier_is_undeclared * 2.0f;
}
"""


def test_kernel_build_failure_names_device_and_log(dev, monkeypatch, tmp_path):
    (tmp_path / "broken_guard_test.cl").write_text(BROKEN)
    monkeypatch.setattr(P, "kernel_dir", lambda: str(tmp_path))
    with pytest.raises(D.DeviceError) as ei:
        dev.build("broken_guard_test.cl", {"NB": 3, "GUARD_TEST": 1})
    msg = str(ei.value)
    assert "broken_guard_test.cl" in msg
    assert dev.name in msg
    assert "this_identifier_is_undeclared" in msg          # the compiler's log
    assert "-DNB=3" in msg


def test_kernel_source_missing(dev, monkeypatch, tmp_path):
    monkeypatch.setattr(P, "kernel_dir", lambda: str(tmp_path))
    with pytest.raises(D.DeviceError, match="missing_guard_test.cl cannot be read .* reinstall"):
        dev.build("missing_guard_test.cl", {"NB": 3})


def test_kernels_build_from_a_path_with_spaces(dev, monkeypatch, tmp_path):
    """An install under 'Program Files' etc.: -I cannot carry a blank, so headers are inlined."""
    src = D.kernel_dir()
    kdir = tmp_path / "My Programs" / "clppm kernels"
    shutil.copytree(src, kdir, ignore=shutil.ignore_patterns("__pycache__", "*.py"))
    monkeypatch.setattr(P, "kernel_dir", lambda: str(kdir))
    prg = dev.build("gather.cl", {"NB": 3, "NL": 2, "FLAT": True, "SPACE_TEST": 1})
    assert "gather" in [k.function_name for k in prg.all_kernels()]
    # an error inside a header still points at the header's own line
    (kdir / "bad_header.h").write_text("\n\nint x = not_declared_here;\n")
    (kdir / "uses_bad.cl").write_text('#include "bad_header.h"\n__kernel void k(void) {}\n')
    with pytest.raises(D.DeviceError, match=r"bad_header.h:3"):
        dev.build("uses_bad.cl", {"SPACE_TEST": 2})


# ----------------------------------------------------------------------------- device lost mid-render
class _DeviceLost:
    """Make photon pass ``at`` (1-based) fail the way a lost device does."""

    def __init__(self, at):
        import pyopencl as cl
        self.at, self.real, self.cl = at, photonpass.PhotonPass.run_pass, cl

    def __call__(self, pp, pass_index, target, tallies=None):
        from clppm.integrators.ppm import CAL_PASS
        if pass_index != CAL_PASS and pass_index + 1 >= self.at:
            raise self.cl.RuntimeError("clEnqueueNDRangeKernel failed: DEVICE_NOT_AVAILABLE")
        return self.real(pp, pass_index, target, tallies)


def _lost_setup(monkeypatch, tmp_path, at=3):
    lost = _DeviceLost(at)
    monkeypatch.setattr(photonpass.PhotonPass, "run_pass", lambda pp, i, t, tallies=None: lost(pp, i, t, tallies))
    p = tmp_path / "c.toml"
    raw = copy.deepcopy(BASE)
    raw["render"].update(passes=5, checkpoint_every=1)
    p.write_text(_toml(raw))
    return p, tmp_path / "x.exr", ckpt.default_path(str(tmp_path / "x.exr"))


def test_device_lost_keeps_checkpoint(dev, monkeypatch, tmp_path, capsys):
    p, out, ck = _lost_setup(monkeypatch, tmp_path)
    capsys.readouterr()
    assert cli.main(["render", str(p), "-o", str(out), "-q"]) == 3     # a device error
    st = ckpt.load(ck)
    assert st["pass_index"] == 2         # passes 1 and 2 finished; pass 3 was lost
    monkeypatch.undo()
    # ... and the kept checkpoint resumes to the uninterrupted bytes
    capsys.readouterr()
    assert cli.main(["render", str(p), "--resume", ck, "-o", str(out), "-q"]) == 0
    ref = tmp_path / "ref.exr"
    assert cli.main(["render", str(p), "-o", str(ref), "-q"]) == 0
    assert out.read_bytes() == ref.read_bytes()


def test_device_lost_clean_message(dev, monkeypatch, tmp_path, capsys):
    p, out, ck = _lost_setup(monkeypatch, tmp_path)
    capsys.readouterr()
    rc = cli.main(["render", str(p), "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert rc == 3
    assert err.startswith("clppm: device error: ")
    assert dev.name in err and "--resume" in err and "x.ckpt.npz" in err


# ----------------------------------------------------------------------------- helpers
def _toml(raw: dict) -> str:
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float) and math.isinf(v):
            return "inf"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(v)
    out = []
    for sec, t in raw.items():
        if sec == "layer":
            continue
        out.append(f"[{sec}]")
        out += [f"{k} = {val(v)}" for k, v in t.items()]
    for L in raw["layer"]:
        out.append("[[layer]]")
        out += [f"{k} = {val(v)}" for k, v in L.items()]
    return "\n".join(out) + "\n"


def test_memory_check_counts_the_multi_band_photon_record():
    """A path carrying C bands stores C-1 extra float weights per photon: the memory check counts
    32 + 4 (C - 1) bytes per stored photon (and 4 more sorted), so 9 bands need twice the bytes."""
    from clppm.integrators import ppm
    raw = copy.deepcopy(BASE)
    cfgs = {}
    for C_ in (1, 9):
        r = copy.deepcopy(raw)
        r["render"]["bands_per_path"] = C_
        r["spectrum"] = {"start_nm": 380.0, "stop_nm": 780.0, "step_nm": 5.0}
        cfgs[C_] = C.validate(r, "test")
    vol = volume.build(cfgs[1])
    n1 = ppm.device_needs(cfgs[1], vol, 0, 1)
    n9 = ppm.device_needs(cfgs[9], vol, 0, 1)
    cap = int(cfgs[1]["render"]["photons"] * 1.2) + 4096
    assert n1["stored photons"] == 32 * cap and n9["stored photons"] == 64 * cap
    assert n9["sorted photons"] == 68 * cap
    # the pixel x band sums: one while the render's passes fit in one chunk, else two
    npix, nb = 100, len(vol.wl)
    one = ppm.device_needs(C.override(cfgs[1], "render", "passes", 4), vol, 0, npix)["pixel accumulators"]
    two = ppm.device_needs(C.override(cfgs[1], "render", "passes", 5), vol, 0, npix)["pixel accumulators"]
    assert cfgs[1]["render"]["chunk_passes"] == 4
    assert one == npix * nb * 8 + npix * 8 and two == 2 * one
