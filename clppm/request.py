"""A render as one typed request: the scene's config and the run's own values.

The config (a validated dict, :mod:`clppm.config`) describes the scene and its defaults; the
command line or the API may ask for another method, pass count, photon count, resolution, seed
or sample count for this run.  Those values live in a :class:`RenderRequest`, built once by
``clppm render`` or :func:`clppm.render` and rendered by the one entry
(:func:`clppm.run.entry.render`, whatever the integrator or executor), which builds the
:class:`clppm.scene.scene.Scene` the passes see from it once; nothing writes them back into the
config.

The request answers what the run uses (:attr:`RenderRequest.settings`, the ``[render]`` table
with the run's values; :attr:`RenderRequest.camera`) and what a checkpoint or a report records
(:meth:`RenderRequest.resolved`: the config as this run renders it, each run value at its key;
:meth:`RenderRequest.checkpoint_identity`, the one definition of what a checkpoint must match).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from typing import Callable

from . import config as C
from .scene.camera import Camera, from_config as camera_from_config
from .config import RenderSettings, render_settings

#: the run's values: (flag, config section, config key); the flag names a refusal
RUN_KEYS = {"method": ("--method", "render", "method"),
            "spacing": ("--spacing", "render", "spacing_um"),
            "passes": ("--passes", "render", "passes"),
            "photons": ("--photons", "render", "photons"),
            "resolution": ("--resolution", "camera", "resolution"),
            "seed": ("--seed", "render", "seed"),
            "spp": ("--spp", "camera", "spp")}
INTEGRATORS = ("ppm", "pt")


def _flag(cfg: dict, flag: str, section: str, key: str, value) -> dict:
    """``config.override`` for a run value: a refusal names the flag as the user gave it, not
    the key it sets."""
    try:
        return C.override(cfg, section, key, value)
    except C.ConfigError as e:
        raise C.ConfigError("command line", flag, value, f"{e.why} ({section}.{key})") from None


def _typed(name: str, value):
    if name == "resolution":
        return [int(value[0]), int(value[1])]
    return float(value) if name == "spacing" else value if name == "method" else int(value)


def resolved_config(cfg: dict, **values) -> dict:
    """A new config: ``cfg`` with the run's values (keywords of :data:`RUN_KEYS`; None: the
    config's) at their keys, each checked as the file's value is.  ``photons`` below
    ``render.initial_photons`` lowers that to ``photons`` too (the first search cannot want more
    photons than a pass stores).  ``cfg`` itself is not changed."""
    for name in RUN_KEYS:                # this order: a refusal names the first bad flag
        v = values.pop(name, None)
        if v is None:
            continue
        flag, section, key = RUN_KEYS[name]
        v = _typed(name, v)
        if name == "photons" and 1 <= v < render_settings(cfg).initial_photons:
            cfg = _flag(cfg, flag, "render", "initial_photons", v)
        cfg = _flag(cfg, flag, section, key, v)
    if values:
        raise TypeError(f"not a run value: {', '.join(values)}")
    return cfg


@dataclass(frozen=True)
class Outputs:
    """Where the run writes: the image (its PNG, report and previews beside it), the checkpoint,
    progress lines on stderr."""

    out: str | None = None
    checkpoint: str | None = None    # None with ``out``: NAME.ckpt.npz beside it
    progress: bool = False

    @property
    def checkpoint_path(self) -> str | None:
        from .output.checkpoint import default_path
        return self.checkpoint or (default_path(self.out) if self.out else None)


@dataclass(frozen=True)
class Budget:
    """When the run stops short of its passes, and what it reports on the way."""

    stop_after: int | None = None    # stop once this many passes are done (a checkpoint is written)
    snapshot_every: int = 0
    on_snapshot: Callable | None = None   # (passes, wall s, RenderResult) -> True to stop
    on_pass: Callable | None = None       # in-process PPM: (p, point state) after every pass
    on_chunk: Callable | None = None      # Dask: (ChunkDone) as each chunk arrives


@dataclass(frozen=True)
class Cluster:
    """A Dask cluster to run on: a scheduler's address, local devices (``all`` or ``P:D,...``)
    or a client; ``flag`` names the scheduler in messages (--scheduler or CLPPM_SCHEDULER)."""

    scheduler: str | None = None
    devices: object = None
    client: object = None
    flag: str = "--scheduler"

    @property
    def how(self) -> str:
        """The option a refusal names."""
        return self.flag if self.scheduler else "--devices" if self.devices else "executor"


@dataclass(frozen=True)
class RenderRequest:
    """One render: the scene's config (validated, never rewritten) and the run's own values.

    ``method`` ... ``spp``: what the command line or the API asked for (None: the config's); the
    integrator reads the merged values from :attr:`settings` and :attr:`camera`."""

    scene: dict
    integrator: str = "ppm"
    method: str | None = None
    spacing: float | None = None
    passes: int | None = None
    photons: int | None = None
    resolution: tuple | None = None
    seed: int | None = None
    spp: int | None = None
    device: str | None = None        # a device spec (``PYOPENCL_CTX`` syntax; None: the default)
    dev: object = field(default=None, compare=False)   # an opened clppm.compute.device.Device, if any
    outputs: Outputs = Outputs()
    resume: str | None = None        # a checkpoint to continue
    budget: Budget = Budget()
    cluster: Cluster | None = None   # None: in this process
    source: str = "<config>"         # the config's name in messages
    _resolved: dict = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self):
        if self.integrator not in INTEGRATORS:
            raise C.ConfigError("clppm.render", "integrator", self.integrator, "must be 'ppm' or 'pt'")
        object.__setattr__(self, "_resolved", resolved_config(self.scene, **self.run_values()))

    @classmethod
    def of(cls, cfg: dict, integrator: str = "ppm", *, method=None, spacing=None, passes=None,
           photons=None, resolution=None, seed=None, spp=None, device: str | None = None,
           dev=None, out: str | None = None, checkpoint_path: str | None = None,
           progress: bool = False, resume: str | None = None, stop_after: int | None = None,
           snapshot_every: int = 0, on_snapshot=None, on_pass=None, on_chunk=None,
           scheduler: str | None = None, devices=None, client=None,
           scheduler_flag: str = "--scheduler", source: str = "<config>") -> "RenderRequest":
        """The request of :func:`clppm.render`'s keywords (those of ``clppm render``)."""
        cluster = (Cluster(scheduler, devices, client, scheduler_flag)
                   if scheduler or devices or client is not None else None)
        return cls(scene=cfg, integrator=integrator, method=method, spacing=spacing, passes=passes,
                   photons=photons, resolution=None if resolution is None else tuple(resolution),
                   seed=seed, spp=spp, device=device, dev=dev,
                   outputs=Outputs(out, checkpoint_path, progress), resume=resume,
                   budget=Budget(stop_after, snapshot_every, on_snapshot, on_pass, on_chunk),
                   cluster=cluster, source=source)

    def run_values(self) -> dict:
        """The run's values that were given (name -> value), as :data:`RUN_KEYS` names them."""
        return {k: getattr(self, k) for k in RUN_KEYS if getattr(self, k) is not None}

    def given(self, name: str) -> bool:
        return getattr(self, name) is not None

    def flag_or_key(self, name: str) -> str:
        """How a message names a run value: its flag when given, else its config key."""
        flag, section, key = RUN_KEYS[name]
        return flag if self.given(name) else f"{section}.{key}"

    def replace(self, **changes) -> "RenderRequest":
        return dataclasses.replace(self, **changes)

    def portable(self) -> "RenderRequest":
        """What travels to a Dask worker: the scene and the run's values, without the opened
        device, the callbacks, the cluster or the outputs (the client writes those)."""
        return self.replace(dev=None, outputs=Outputs(), budget=Budget(), cluster=None, resume=None)

    # what the run uses -------------------------------------------------------------------------
    @property
    def settings(self) -> RenderSettings:
        """The ``[render]`` table with the run's values (passes, photons, seed, method...)."""
        return render_settings(self._resolved)

    @property
    def camera_table(self) -> dict:
        """The ``[camera]`` table with the run's resolution and samples per pixel."""
        return self._resolved["camera"]

    @property
    def camera(self) -> Camera:
        return camera_from_config(self.camera_table)

    @property
    def checkpoint(self) -> str | None:
        return self.outputs.checkpoint_path

    # what is recorded ---------------------------------------------------------------------------
    def resolved(self) -> dict:
        """The config as this run renders it (each run value at its key): what the run report
        records and the scene checks examine.  A new dict each call."""
        return json.loads(json.dumps(self._resolved, default=str))

    def config_identity(self) -> dict:
        """The config as a checkpoint records it: every key that changes the picture."""
        keep = self.resolved()
        keep["render"] = {k: v for k, v in keep["render"].items() if k not in C.NOT_PICTURE}
        return keep

    def scene_key(self) -> str:
        """A short hash of :meth:`config_identity`: what a Dask worker's scene depends on (a
        longer or resumed render reuses the scenes its workers hold)."""
        text = json.dumps(self.config_identity(), sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def checkpoint_identity(self, device: str, **shape) -> dict:
        """What a checkpoint of this run must match to be resumed: the config's identity, the
        device, and the integrator's own counts (``shape``: sample points, pixels, bands...)."""
        head = {"integrator": self.integrator} if self.integrator != "ppm" else {}
        return {**head, "config": self.config_identity(), "device": device, **shape}
