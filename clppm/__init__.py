"""clppm: spectral progressive photon mapping of a layered voxel skin model in OpenCL."""
__version__ = "0.1.0"

# Before anything queries OpenCL platforms: let the ICD loader see pip-installed drivers.
from . import icd as _icd  # noqa: E402

_icd.register()
_icd.own_pocl_cache()


def render(config, integrator="ppm", **kwargs):
    """Render a config (a path, a shipped config's name, or a validated dict); returns a
    RenderResult (image + report).

    Keyword arguments as ``clppm render``: method, passes, photons, resolution, seed,
    spacing, device, out, progress, resume; ``devices`` ("all" or "P:D,P:D") or ``scheduler``
    (an address) render on a Dask cluster (:func:`clppm.executor.render_distributed`).
    ``integrator="pt"``: the path tracer (``clppm.pathtracer.render_pt``: passes, seed,
    resolution, device, out, progress, resume).  The call becomes one
    :class:`clppm.request.RenderRequest` (:meth:`~clppm.request.RenderRequest.of`).
    """
    from . import config as _config
    from .request import RenderRequest
    cfg = _config.load(_config.find(config)) if isinstance(config, str) else config
    req = RenderRequest.of(cfg, integrator, **kwargs)
    if req.integrator == "pt":
        from .pathtracer import render_pt
        return render_pt(req)
    if req.cluster is not None and (req.cluster.devices or req.cluster.scheduler):
        from .executor import render_distributed
        return render_distributed(req)
    from . import progressive
    return progressive.render(req.replace(cluster=None))
