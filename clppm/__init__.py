"""clppm: spectral progressive photon mapping of a layered voxel skin model in OpenCL."""
from .version import __version__  # noqa: F401

# Before anything queries OpenCL platforms: let the ICD loader see pip-installed drivers.
from .compute import icd as _icd  # noqa: E402

_icd.register()
_icd.own_pocl_cache()


def render(config, integrator="ppm", **kwargs):
    """Render a skin scene; return a :class:`clppm.output.film.RenderResult` (the image and its
    report).

    ``config``: a TOML file, a shipped config's name (``"forearm"``, ``"cheek"``; see
    ``clppm config --example``) or a dict from :func:`clppm.config.load` (changed with
    :func:`clppm.config.set_item`).  ``integrator``: ``"ppm"`` (progressive photon mapping, the
    default) or ``"pt"`` (the unbiased path tracer).

    Keyword arguments, as the options of ``clppm render`` (None or absent: the config's value):

    * ``method``: ``"a"`` .. ``"f"``, how sample points are placed on eye rays;
    * ``passes``, ``photons`` (stored per pass), ``seed``: ints;
    * ``resolution``: ``(width, height)`` in pixels;
    * ``spacing``: an equal sample spacing along eye rays, um (overrides a-c's);
    * ``spp``: eye rays per pixel;
    * ``device``: a device as ``--device`` takes it (``"1:0"``, ``"intel"``, ``"pocl"``);
    * ``out``: a path ``NAME.exr`` (writes the EXR, PNG, JSON report and checkpoint, as the
      command does) or ``NAME.png``; None writes nothing;
    * ``progress``: print progress to stderr;
    * ``resume``: a checkpoint ``NAME.ckpt.npz`` to continue (``passes`` the new total);
    * ``devices`` (``"all"`` or ``"P:D,P:D"``) or ``scheduler`` (an address): render on a
      Dask cluster (:func:`clppm.run.entry.render_distributed`), the same bytes as in-process.

    With ``integrator="pt"``: ``passes``, ``seed``, ``resolution``, ``device``, ``out``,
    ``progress`` and ``resume`` (:func:`clppm.run.entry.render_pt`).

    Raises :class:`clppm.config.ConfigError` for a bad value (exit 2 on the command line) and
    :class:`clppm.compute.device.DeviceError` when no device can run it (exit 3).

    >>> res = clppm.render("forearm", resolution=(64, 48), passes=2, photons=100_000)
    >>> res.spectral.shape, res.rgb.shape        # ((48, 64, 81), (48, 64, 3))

    The call becomes one :class:`clppm.request.RenderRequest`
    (:meth:`~clppm.request.RenderRequest.of`), rendered by :func:`clppm.run.entry.render`.
    """
    from . import config as _config
    from .request import RenderRequest
    cfg = _config.load(_config.find(config)) if isinstance(config, str) else config
    from .run.entry import render as render_entry
    return render_entry(RenderRequest.of(cfg, integrator, **kwargs))


def __getattr__(name):
    """``clppm.config`` and ``clppm.image`` without importing them first (PEP 562)."""
    if name in ("config", "image"):
        import importlib
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'clppm' has no attribute {name!r}")
