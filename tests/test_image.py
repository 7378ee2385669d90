"""Tests for clppm.image: colorimetry, EXR/PNG I/O and height-map loading."""

import json
import warnings

import numpy as np
import pytest

import colour
import OpenEXR

from clppm.scene import colorimetry
from clppm import image

WL = np.arange(380.0, 781.0, 5.0)  # 81 bands


def _d65(wl):
    sd = colour.SDS_ILLUMINANTS["D65"]
    return np.asarray(sd[wl], dtype=np.float64)


# ---------------------------------------------------------------- colorimetry


def test_cmfs_match_colour_table():
    c = colorimetry.cmfs(WL)
    assert c.shape == (81, 3)
    table = colour.MSDS_CMFS[colorimetry.CMFS_NAME]
    np.testing.assert_allclose(c, table[WL], rtol=0, atol=1e-12)
    # Outside the table: zero, not extrapolated.
    assert np.all(colorimetry.cmfs([300.0, 900.0]) == 0)
    # Interpolated (non-integer) wavelengths lie between neighbours' values.
    y = colorimetry.cmfs([555.0, 555.5, 556.0])[:, 1]
    assert min(y[0], y[2]) - 1e-6 <= y[1] <= max(y[0], y[2]) + 1e-6


def test_d65_chromaticity():
    XYZ = colorimetry.spectral_to_xyz(_d65(WL), WL)
    xy = XYZ[:2] / XYZ.sum()
    ref = colour.CCS_ILLUMINANTS[colorimetry.CMFS_NAME]["D65"]
    np.testing.assert_allclose(xy, [0.3127, 0.3290], atol=2e-3)
    np.testing.assert_allclose(xy, ref, atol=2e-3)


def test_spectral_to_xyz_vectorised_and_uniform_grid():
    L = np.random.default_rng(1).random((2, 3, WL.size))
    XYZ = colorimetry.spectral_to_xyz(L, WL)
    assert XYZ.shape == (2, 3, 3)
    np.testing.assert_allclose(XYZ[1, 2], colorimetry.spectral_to_xyz(L[1, 2], WL))
    with pytest.raises(ValueError):
        colorimetry.spectral_to_xyz(L[..., :10], WL[[0, 1, 2, 3, 4, 5, 6, 7, 8, 10]])
    with pytest.raises(ValueError):
        colorimetry.spectral_to_xyz(L, WL[:-1])


def test_white_reflector_under_d65_is_srgb_white():
    E = _d65(WL)
    refl = np.ones_like(WL)
    XYZ_w = colorimetry.spectral_to_xyz(E, WL)
    XYZ = colorimetry.spectral_to_xyz(refl * E, WL) / XYZ_w[1]
    np.testing.assert_allclose(XYZ[1], 1.0, atol=1e-12)
    rgb = colorimetry.xyz_to_linear_srgb(XYZ)
    np.testing.assert_allclose(rgb, [1.0, 1.0, 1.0], atol=1e-2)
    np.testing.assert_allclose(colorimetry.linear_srgb_to_xyz(rgb), XYZ, atol=1e-10)


def test_srgb_matrix_round_trip_vectorised():
    rgb = np.random.default_rng(2).random((4, 5, 3))
    XYZ = colorimetry.linear_srgb_to_xyz(rgb)
    assert XYZ.shape == rgb.shape
    np.testing.assert_allclose(colorimetry.xyz_to_linear_srgb(XYZ), rgb, atol=1e-12)
    # (1,1,1) maps to the D65 white.
    np.testing.assert_allclose(colorimetry.linear_srgb_to_xyz([1, 1, 1]), colorimetry.D65_XYZ, atol=1e-4)


def test_encode_srgb():
    assert round(float(colorimetry.encode_srgb(0.5)) * 255) in (187, 188, 189)
    np.testing.assert_allclose(colorimetry.encode_srgb([-1.0, 0.0, 1.0, 5.0]), [0, 0, 1, 1])
    out = colorimetry.encode_srgb([np.nan, np.inf])
    np.testing.assert_array_equal(out, [0.0, 1.0])


def test_uv_prime():
    XYZ = np.array([[0.2, 0.3, 0.4], [0.9, 0.5, 0.1]])
    uv = colorimetry.xyz_to_uv_prime(XYZ)
    ref = colour.xy_to_Luv_uv(colour.XYZ_to_xy(XYZ))
    np.testing.assert_allclose(uv, ref, atol=1e-12)
    # D65 white: (0.1978, 0.4683).
    np.testing.assert_allclose(colorimetry.xyz_to_uv_prime(colorimetry.D65_XYZ), [0.19784, 0.46834], atol=1e-4)


def test_lab_and_delta_e2000():
    white = colorimetry.D65_XYZ * 3.0  # any absolute scale, shared by colour and white
    lab_w = colorimetry.xyz_to_lab(white, white)
    np.testing.assert_allclose(lab_w, [100, 0, 0], atol=1e-8)
    # Sharma, Wu & Dalal (2005) test pair 1: dE00 = 2.0425.
    lab1 = np.array([50.0, 2.6772, -79.7751])
    lab2 = np.array([50.0, 0.0, -82.7485])
    xy_w = colour.XYZ_to_xy(white)
    x1 = colour.Lab_to_XYZ(lab1, illuminant=xy_w) * white[1]
    x2 = colour.Lab_to_XYZ(lab2, illuminant=xy_w) * white[1]
    np.testing.assert_allclose(colorimetry.xyz_to_lab(x1, white), lab1, atol=1e-9)
    de = colorimetry.delta_e2000(x1, x2, white)
    assert abs(float(de) - 2.0425) < 1e-4
    # Vectorised over leading axes; identical colours give exactly 0.
    a = np.stack([x1, x2, x1])[None]
    b = np.stack([x2, x2, x1])[None]
    de_v = colorimetry.delta_e2000(a, b, white)
    assert de_v.shape == (1, 3)
    np.testing.assert_allclose(de_v, [[2.0425, 0.0, 0.0]], atol=1e-4)
    assert de_v[0, 1] == 0 and de_v[0, 2] == 0


def test_black_produces_no_nan():
    black = np.zeros((2, 2, 3))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # also: no divide-by-zero warnings
        lab = colorimetry.xyz_to_lab(black)
        uv = colorimetry.xyz_to_uv_prime(black)
        de = colorimetry.delta_e2000(black, black)
        de2 = colorimetry.delta_e2000(black, np.ones(3) * 0.5)
        rgb = colorimetry.xyz_to_linear_srgb(black)
        enc = colorimetry.encode_srgb(rgb)
        xyz = colorimetry.spectral_to_xyz(np.zeros((2, WL.size)), WL)
    for a in (lab, uv, de, de2, rgb, enc, xyz):
        assert np.all(np.isfinite(a))
    np.testing.assert_array_equal(lab, 0.0)
    np.testing.assert_array_equal(de, 0.0)
    # Black's u'v' is defined as the white point's.
    np.testing.assert_allclose(uv, np.broadcast_to(colorimetry.xyz_to_uv_prime(colorimetry.D65_XYZ), uv.shape))


# ---------------------------------------------------------------- EXR / PNG I/O


def _test_image(h=6, w=7, n=81, seed=3):
    rng = np.random.default_rng(seed)
    rgb = (rng.random((h, w, 3)) * 10).astype(np.float32)
    rgb[0, 0] = [0.0, 1e-30, 3.4e38]  # tiny/huge float32 values survive exactly
    spec = (rng.random((h, w, n)) * 0.1).astype(np.float32)
    return rgb, spec


def test_spectral_channel_names():
    assert image.spectral_channel_name(380) == "S0.380,000000nm"
    assert image.spectral_channel_name(555.5) == "S0.555,500000nm"
    assert image.parse_spectral_channel_name("S0.380,000000nm") == (0, 380.0)
    assert image.parse_spectral_channel_name("S0.550nm") == (0, 550.0)
    s, w = image.parse_spectral_channel_name("S1.0,5um")
    assert s == 1 and abs(w - 500.0) < 1e-9
    assert image.parse_spectral_channel_name("R") is None
    assert image.parse_spectral_channel_name("T.550nm") is None


def test_exr_round_trip(tmp_path):
    rgb, spec = _test_image()
    hdr = {"clppm_params": json.dumps({"photons": 1000000, "seed": 7}), "note": "héllo"}
    p = tmp_path / "img.exr"
    image.write_exr(p, rgb, spectral=spec, wl=WL, header=hdr)

    with OpenEXR.File(str(p), separate_channels=True) as f:
        names = set(f.channels())
        assert f.header()["compression"] == OpenEXR.ZIP_COMPRESSION
    expected = {"R", "G", "B"} | {f"S0.{int(w)},000000nm" for w in WL}
    assert names == expected
    assert "S0.380,000000nm" in names and "S0.780,000000nm" in names

    d = image.read_exr(p)
    assert d["rgb"].dtype == np.float32 and d["spectral"].dtype == np.float32
    np.testing.assert_array_equal(d["rgb"], rgb)
    np.testing.assert_array_equal(d["spectral"], spec)
    np.testing.assert_array_equal(d["wl"], WL)
    assert d["header"] == {**hdr, "spectralLayoutVersion": "1.0"}
    assert json.loads(d["header"]["clppm_params"])["seed"] == 7


def test_exr_rgb_only_and_float64_input(tmp_path):
    rgb = np.random.default_rng(4).random((3, 4, 3))  # float64, non-contiguous slices
    p = tmp_path / "rgb.exr"
    image.write_exr(p, rgb)
    d = image.read_exr(p)
    np.testing.assert_array_equal(d["rgb"], rgb.astype(np.float32))
    assert d["spectral"] is None and d["wl"] is None and d["header"] == {}


def test_exr_bad_arguments(tmp_path):
    rgb, spec = _test_image(n=5)
    with pytest.raises(ValueError):
        image.write_exr(tmp_path / "a.exr", rgb[..., :2])
    with pytest.raises(ValueError):
        image.write_exr(tmp_path / "a.exr", rgb, spectral=spec)  # no wl
    with pytest.raises(ValueError):
        image.write_exr(tmp_path / "a.exr", rgb, spectral=spec, wl=WL)  # N mismatch
    with pytest.raises(ValueError):
        image.write_exr(tmp_path / "a.exr", rgb, header={"compression": "none"})
    with pytest.raises(TypeError):
        image.write_exr(tmp_path / "a.exr", rgb, header={"n": 3})
    with pytest.raises(ValueError, match="nothere.exr"):
        image.read_exr(tmp_path / "nothere.exr")


def test_exr_deterministic_bytes(tmp_path):
    rgb, spec = _test_image()
    hdr = {"params": json.dumps({"a": 1})}
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    image.write_exr(a, rgb, spectral=spec, wl=WL, header=hdr)
    image.write_exr(b, rgb.copy(), spectral=spec.copy(), wl=WL.copy(), header=dict(hdr))
    assert a.read_bytes() == b.read_bytes()


def test_png_value_and_determinism(tmp_path):
    from PIL import Image

    rgb = np.full((4, 5, 3), 0.5)
    rgb[0, 0] = [0.0, 1.0, 2.0]
    rgb[0, 1] = [np.nan, -1.0, 0.25]
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    image.write_png(a, rgb)
    image.write_png(b, rgb.copy())
    assert a.read_bytes() == b.read_bytes()
    with Image.open(a) as im:
        assert im.mode == "RGB" and im.size == (5, 4)
        px = np.array(im)
    assert abs(int(px[2, 2, 0]) - 188) <= 1
    np.testing.assert_array_equal(px[0, 0], [0, 255, 255])
    assert px[0, 1, 0] == 0 and px[0, 1, 1] == 0
    # exposure scales linear values before encoding
    image.write_png(a, np.full((2, 2, 3), 0.25), exposure=2.0)
    with Image.open(a) as im:
        assert abs(int(np.array(im)[0, 0, 0]) - 188) <= 1


# ---------------------------------------------------------------- height maps


def test_heightmap_npy(tmp_path):
    h = np.random.default_rng(5).random((8, 9)) * 3.0 - 1.0
    p = tmp_path / "h.npy"
    np.save(p, h)
    out = image.load_heightmap(p)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, h)
    np.save(tmp_path / "h3.npy", np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="h3.npy"):
        image.load_heightmap(tmp_path / "h3.npy")
    bad = h.copy()
    bad[1, 1] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(ValueError, match="nan.npy"):
        image.load_heightmap(tmp_path / "nan.npy")


def test_heightmap_png16_and_png8(tmp_path):
    from PIL import Image

    h = np.arange(12 * 10, dtype=np.int64).reshape(12, 10) * 547 % 65536
    h[0, 0], h[0, 1], h[0, 2] = 0, 65535, 65534
    h16 = h.astype(np.uint16)
    p = tmp_path / "h16.png"
    Image.fromarray(h16).save(p)  # mode I;16 -> 16-bit grayscale PNG
    out = image.load_heightmap(p)
    assert out.dtype == np.float64
    np.testing.assert_array_equal(out, h16.astype(np.float64))
    assert out.max() == 65535

    h8 = (h % 256).astype(np.uint8)
    p8 = tmp_path / "h8.png"
    Image.fromarray(h8).save(p8)
    np.testing.assert_array_equal(image.load_heightmap(p8), h8.astype(np.float64))

    prgb = tmp_path / "rgb.png"
    Image.fromarray(np.zeros((3, 3, 3), np.uint8)).save(prgb)
    with pytest.raises(ValueError, match="rgb.png"):
        image.load_heightmap(prgb)


def test_heightmap_exr(tmp_path):
    h = (np.random.default_rng(6).random((5, 6)) * 100).astype(np.float32)
    # Y channel
    p = tmp_path / "hy.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"Y": h}) as f:
        f.write(str(p))
    np.testing.assert_array_equal(image.load_heightmap(p), h.astype(np.float64))
    # R of an RGB file written by write_exr
    p2 = tmp_path / "hr.exr"
    image.write_exr(p2, np.stack([h, h * 0, h * 0], axis=-1))
    np.testing.assert_array_equal(image.load_heightmap(p2), h.astype(np.float64))
    # Otherwise the first channel by name
    p3 = tmp_path / "hz.exr"
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"Z": h, "depth": h * 2}) as f:
        f.write(str(p3))
    np.testing.assert_array_equal(image.load_heightmap(p3), h.astype(np.float64))


def test_heightmap_errors_name_the_file(tmp_path):
    missing = tmp_path / "does_not_exist.png"
    with pytest.raises(ValueError, match="does_not_exist.png"):
        image.load_heightmap(missing)
    for name in ("garbage.png", "garbage.exr", "garbage.npy"):
        p = tmp_path / name
        p.write_bytes(b"this is not an image \x00\x01\x02" * 10)
        with pytest.raises(ValueError, match=name.replace(".", r"\.")):
            image.load_heightmap(p)
    p = tmp_path / "height.tiff"
    p.write_bytes(b"x")
    with pytest.raises(ValueError, match="height.tiff"):
        image.load_heightmap(p)
