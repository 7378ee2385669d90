"""clppm: spectral progressive photon mapping of a layered voxel skin model in OpenCL."""
__version__ = "0.1.0"


def render(config, **kwargs):
    """Render a config (a path or a validated dict); returns a RenderResult (image + report).

    Keyword arguments as ``clppm render``: method, passes, photons, resolution, seed,
    spacing, device, out, progress, resume.
    """
    from . import config as _config
    from . import progressive as _render
    cfg = _config.load(config) if isinstance(config, str) else config
    return _render.render(cfg, **kwargs)
