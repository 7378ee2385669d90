"""OpenCL devices and kernel programs.

One place that picks a device (``--device`` or ``PYOPENCL_CTX``), finds the
kernel sources of an installed clppm, and builds them with ``-D`` options
through the process's program registry (:mod:`clppm.compute.programs`).  Errors here are :class:`DeviceError` with a
message a user can act on (no traceback).
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass

from . import devicecheck
from .programs import (implementation, kernel_dir,  # noqa: F401
                       quiet_compiler_chatter)



class DeviceError(RuntimeError):
    """No usable OpenCL platform/device, or a kernel failed to build."""


NO_PLATFORM_HELP = (
    "no OpenCL platform found. clppm needs an OpenCL driver; the CPU driver PoCL "
    "installs from pip:  pip install 'clppm[pocl]'  (or: pip install pocl-binary-distribution)"
)


def _cl():
    try:
        import pyopencl as cl
    except ImportError as e:  # pragma: no cover - dependency missing
        raise DeviceError(f"pyopencl is not installed ({e}); pip install clppm") from None
    quiet_compiler_chatter()
    return cl


def list_devices() -> list[tuple[int, int, "object", "object"]]:
    """All (platform index, device index, platform, device)."""
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    out = []
    for ip, p in enumerate(platforms):
        try:
            devs = p.get_devices()
        except cl.Error:
            devs = []
        for idev, d in enumerate(devs):
            out.append((ip, idev, p, d))
    return out


def describe(device) -> dict:
    cl = _cl()
    return {
        "name": device.name.strip(),
        "platform": device.platform.name.strip(),
        "version": device.version.strip(),
        "implementation": implementation(device),
        "platform_version": device.platform.version.strip(),
        "driver_version": device.driver_version.strip(),
        "type": cl.device_type.to_string(device.type),
        "compute_units": int(device.max_compute_units),
        "global_mem_bytes": int(device.global_mem_size),
        "max_alloc_bytes": int(device.max_mem_alloc_size),
        "fp64": "cl_khr_fp64" in device.extensions,
        "int64_atomics": "cl_khr_int64_base_atomics" in device.extensions,
    }


# Default choice among devices that pass their self-test: GPUs first, then CPU implementations in
# this order, the faster first by docs/devices.md's measured throughput (bench/devices.py).
CPU_PREFERENCE = ("intel", "pocl")


def short_version(device) -> str:
    """The platform's version up to its first comma ("OpenCL 3.0 PoCL 3.0-rc2  Linux")."""
    return " ".join(device.platform.version.split(",")[0].split())


def _rank(entry) -> tuple:
    cl = _cl()
    dev = entry[3]
    impl = implementation(dev)
    pref = CPU_PREFERENCE.index(impl) if impl in CPU_PREFERENCE else len(CPU_PREFERENCE)
    return (0 if dev.type & cl.device_type.GPU else 1, pref, entry[0], entry[1])


#: one line per device a default choice passed over, and why (a render prints them)
SELECTION_NOTES: list[str] = []


def device_problem(dev, spec: str | None = None) -> str | None:
    """Why ``dev`` is not usable (one line), or None: its compiler check (:func:`compiler_problem`)
    and then its known-answer self-test (:func:`self_test`, cached per user; off with
    ``CLPPM_SELF_TEST=0``)."""
    why = compiler_problem(dev)
    if why is not None or not devicecheck.enabled():
        return why
    res = self_test(dev, spec or device_spec(dev))
    return None if res.passed else f"its self-test failed: {res.reason}"


def self_test(dev, spec: str, rerun: bool = False) -> devicecheck.SelfTest:
    """``dev``'s known-answer self-test (reachable as ``spec``; :mod:`clppm.compute.devicecheck`):
    cached, else run now in a child; a child that crashed leaves no kernel cache entries behind."""
    return devicecheck.check(dev, spec, rerun,
                             on_crash=lambda: forget_kernel_cache(implementation(dev)))


def device_spec(dev) -> str:
    """``dev``'s "P:D" (as ``clppm devices`` prints it)."""
    key = _device_key(dev)
    for ip, idev, _, d in list_devices():
        if _device_key(d) == key:
            return f"{ip}:{idev}"
    raise DeviceError(f"device '{dev.name.strip()}' is not among the OpenCL devices found")


def _first_usable(cands: list, what: str):
    """The first device of ``cands`` (in :func:`_rank` order) that passes :func:`device_problem`;
    a one-line note in :data:`SELECTION_NOTES` for each one passed over."""
    cands = sorted(cands, key=_rank)
    whys = []
    for ip, idev, _, dev in cands:
        why = device_problem(dev, f"{ip}:{idev}")
        if why is None:
            SELECTION_NOTES[:] = [f"device {ip}:{idev} '{d.name.strip()}' ({implementation(d)}) "
                                  f"passed over: {w}" for (ip, idev, d), w in whys]
            return dev
        whys.append(((ip, idev, dev), why))
    (ip, idev, dev), why = whys[0]
    raise DeviceError(f"no OpenCL device {what}is usable; device {ip}:{idev} '{dev.name.strip()}' "
                      f"({implementation(dev)}): {why}" + "".join(
                          f"; device {a}:{b} '{d.name.strip()}': {w}" for (a, b, d), w in whys[1:]))


def _by_name(devs: list, spec: str) -> list:
    """Devices of implementation/platform ``spec``, else those whose device name contains it."""
    s = spec.lower()
    impl = [d for d in devs if implementation(d[3]) == s or s in d[3].platform.name.lower()]
    return impl or [d for d in devs if s in d[3].name.lower()]


def select_device(spec: str | None = None):
    """Pick a device.

    ``spec`` is ``"P:D"`` (platform and device index, as ``clppm devices``
    prints), ``"P"``, an implementation or platform name (``pocl``, ``intel``,
    ``nvidia``: case-insensitive substring of the platform name), or a
    substring of the device name.  Without ``spec``, ``PYOPENCL_CTX`` (same
    forms) is honoured, else the first device that compiles kernels, GPUs first
    and then CPU implementations in :data:`CPU_PREFERENCE` order.  Among several
    devices a name matches, the same order decides.
    A device that fails its known-answer self-test (:mod:`clppm.checks.selftest`) is never chosen by
    default (:data:`SELECTION_NOTES` says which were passed over, and why); a named one that
    fails is refused (:class:`DeviceError`).
    """
    devs = list_devices()
    if not devs:
        raise DeviceError(NO_PLATFORM_HELP)
    source = "--device"
    if spec is None:
        spec = os.environ.get("PYOPENCL_CTX") or None
        source = "PYOPENCL_CTX"
    SELECTION_NOTES.clear()
    if spec is None:
        return _first_usable(devs, "")
    spec = str(spec).strip()
    parts = spec.split(":")
    if all(p.isdigit() for p in parts if p != "") and parts[0] != "":
        ip = int(parts[0])
        idev = int(parts[1]) if len(parts) > 1 and parts[1] != "" else 0
        for p_, d_, _, dev in devs:
            if p_ == ip and d_ == idev:
                return _named(dev, f"{p_}:{d_}", source, spec)
        raise DeviceError(f"{source} = '{spec}': no such device; `clppm devices` lists "
                          + ", ".join(f"{a}:{b}" for a, b, _, _ in devs))
    cands = _by_name(devs, spec)
    if not cands:
        raise DeviceError(f"{source} = '{spec}': no implementation, platform or device name "
                          "contains it; `clppm devices` lists them")
    ranked = sorted(cands, key=_rank)
    for ip, idev, _, dev in ranked:                  # the first one that compiles and passes
        if device_problem(dev, f"{ip}:{idev}") is None:
            return dev
    ip, idev, _, dev = ranked[0]
    return _named(dev, f"{ip}:{idev}", source, spec)


def _named(dev, pd: str, source: str, spec: str):
    """The device the user named, unless it failed its self-test: then exit 3 with the reason
    (a device that computes wrong answers or aborts is not used, named or not)."""
    if compiler_problem(dev) is not None:
        return dev                                  # its build error names the device later
    why = device_problem(dev, pd)
    if why is not None:
        raise DeviceError(f"device {pd} '{dev.name.strip()}' ({implementation(dev)}, {source} = "
                          f"'{spec}'): {why}; `clppm devices` lists the others "
                          "(CLPPM_SELF_TEST=0 skips the self-test)")
    return dev


_PROBE_SRC = "__kernel void clppm_probe(__global float* a) { a[get_global_id(0)] = 1.0f; }"
UNKNOWN_CPU_HELP = ("its compiler does not know this CPU (PoCL 3.0 from pip is built on LLVM 14, "
                    "which predates e.g. AMD Zen 5); install a newer PoCL, e.g. Debian's "
                    "'apt install pocl-opencl-icd', and clppm will use it")


_PROBED: dict = {}


def _probe(dev) -> str | None:
    cl = _cl()
    try:
        ctx = cl.Context([dev])
        cl.Program(ctx, _PROBE_SRC).build()
    except cl.Error as e:
        msg = " ".join(str(e).split())
        if "unknown target CPU" in msg:
            return UNKNOWN_CPU_HELP
        return f"a test kernel does not build ({msg[:200]})"
    return None


def _device_key(dev) -> tuple:
    return (dev.platform.name.strip(), dev.platform.version.strip(), dev.name.strip(),
            dev.version.strip())


def compiler_problem(dev) -> str | None:
    """Why ``dev`` cannot build kernels (a one-line reason), or None when it can.

    Checked once per device and process by building a one-line kernel: the pip PoCL (LLVM 14)
    rejects CPUs newer than its LLVM ("unknown target CPU 'generic'"), and a machine may then
    carry a second, working PoCL."""
    key = _device_key(dev)
    if key not in _PROBED:
        _PROBED[key] = _probe(dev)
    return _PROBED[key]


_WIDE_SRC = ("float16 clppm_twice16(float16 a) { return a + a; }\n"
             "__kernel void clppm_probe16(__global float16* a) "
             "{ a[get_global_id(0)] = clppm_twice16(a[get_global_id(0)]); }\n")
_WIDE: dict = {}


def wide_vectors(dev) -> bool:
    """Whether kernels may pass 16-lane vectors (float16, long16) between functions on ``dev``
    (a pyopencl device).  pip's PoCL 3.0 on AMD Zen 4 compiles a kernel's front end for a CPU
    without AVX-512 and its code for the host's AVX-512, and then aborts the process at a
    kernel's first launch ("Cannot emit physreg copy instruction"); its compiler says so while
    building ("... without 'avx512f' enabled changes the ABI").  Checked once per device and
    process by building a probe that passes a float16 (its compiler chatter on stderr dropped):
    no such warning and no failure, True.  Kernels then build without them (NO_VEC16)."""
    key = _device_key(dev)
    if key not in _WIDE:
        cl = _cl()
        import warnings
        try:
            with _stderr_dropped(), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                prg = cl.Program(cl.Context([dev]), _WIDE_SRC).build()
            log = prg.get_build_info(dev, cl.program_build_info.LOG) or ""
            _WIDE[key] = "changes the ABI" not in log
        except cl.Error:
            _WIDE[key] = False
    return _WIDE[key]


class _stderr_dropped:
    """File descriptor 2 to /dev/null for a probe's build (PoCL's clang prints "1 warning
    generated." there itself, past pyopencl)."""

    def __enter__(self):
        import sys
        sys.stderr.flush()
        self.saved = os.dup(2)
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 2)
        os.close(null)

    def __exit__(self, *exc):
        os.dup2(self.saved, 2)
        os.close(self.saved)
        return False


# Launches record here, per (device, kernel), what clppm asked of the device: the local size it
# used and the kernel's limits (clppm devices --kernels prints them).
LAUNCHED: dict[tuple, dict] = {}


def kernel_limits(kernel, device) -> dict:
    """The kernel's work-group size limit, preferred multiple and private bytes per work item."""
    cl = _cl()
    kwi = cl.kernel_work_group_info

    def q(what):
        try:
            return int(kernel.get_work_group_info(what, device))
        except cl.Error:                       # not reported (e.g. an OpenCL 1.0 driver)
            return None
    return {"work_group_size": q(kwi.WORK_GROUP_SIZE),
            "preferred_multiple": q(kwi.PREFERRED_WORK_GROUP_SIZE_MULTIPLE),
            "private_mem_bytes": q(kwi.PRIVATE_MEM_SIZE),
            "local_mem_bytes": q(kwi.LOCAL_MEM_SIZE)}


def local_size(kernel, device, want: int = 64) -> int:
    """The local size to launch ``kernel`` with: ``want`` (a power of two; global sizes are
    rounded up to it), halved until the kernel's queried work-group limit and the device's first
    work-item dimension admit it.  Cached per kernel object."""
    key = (_device_key(device), kernel.function_name, kernel.int_ptr)
    hit = LAUNCHED.get(key)
    if hit is not None and hit["asked"] == want:
        return hit["local_size"]
    lim = kernel_limits(kernel, device)
    cap = min(lim["work_group_size"] or want, int(device.max_work_item_sizes[0]),
              int(device.max_work_group_size))
    ls = int(want)
    while ls > max(1, cap):
        ls //= 2
    LAUNCHED[key] = {**lim, "asked": int(want), "local_size": ls}
    return ls


def global_size(n: int, want: int = 64) -> int:
    """``n`` work items rounded up to a multiple of ``want`` (at least ``want``): one global
    size rule for every launch, so PoCL compiles a kernel for one work-group size only."""
    return max(want, (int(n) + want - 1) // want * want)


def launch(kernel, queue, n: int, want: int = 64, rows: int | None = None) -> tuple[tuple, tuple]:
    """The (global, local) sizes to run ``kernel`` over ``n`` work items: ``kernel(queue,
    *launch(kernel, queue, n), *args)``; the local size from :func:`local_size`.  With ``rows``,
    a 2-D range of ``rows`` rows of ``n`` (a work group within one row)."""
    g, ls = global_size(n, want), local_size(kernel, queue.device, want)
    if _SELFTEST_CHILD:
        _first_launch(kernel, queue)
    return ((g,), (ls,)) if rows is None else ((g, int(rows)), (ls, 1))


_SELFTEST_CHILD = os.environ.get("CLPPM_SELF_TEST_CHILD") == "1"
_FIRST_LAUNCHED: set = set()


def _first_launch(kernel, queue) -> None:
    """In the self-test's child: before a kernel's first launch, finish what is queued and say
    which kernel comes next, so that a crash in its compile (PoCL compiles a kernel at its first
    launch) or its run is attributed to it."""
    name = kernel.function_name
    if name in _FIRST_LAUNCHED:
        return
    queue.finish()
    _FIRST_LAUNCHED.add(name)
    print(f"clppm-selftest-stage: {name}'s first launch", flush=True)


def launched(device) -> list[dict]:
    """What :func:`local_size` recorded on ``device``, one row per kernel name."""
    k = _device_key(device)
    rows = {}
    for (dk, name, _), v in LAUNCHED.items():
        if dk == k:
            rows[name] = {"kernel": name, **v}
    return [rows[n] for n in sorted(rows)]


@dataclass
class Device:
    """A context + queue on one device, and the program builder for it; ``chosen`` says why
    this device (the option that named it, or the default rule), ``passed_over`` the devices
    the default rule skipped and why."""

    ctx: object
    queue: object
    device: object
    chosen: str = ""
    passed_over: tuple = ()

    @property
    def name(self) -> str:
        return self.device.name.strip()

    def info(self) -> dict:
        return {**describe(self.device), "chosen": self.chosen, "passed_over": list(self.passed_over)}

    def build(self, filename: str, defines: dict | None = None) -> object:
        """The program of ``kernels/filename`` with ``-D`` ``defines``, from the process's
        registry (:mod:`clppm.compute.programs`: built once per context, binaries cached per
        device, checked to hold every kernel the source declares)."""
        from .programs import REGISTRY, BuildSpec, BuildError
        try:
            return REGISTRY.program(self.ctx, BuildSpec.of(filename, defines), fault())
        except BuildError as e:
            raise DeviceError(str(e)) from None

    def library(self, name: str, make):
        """A library kernel on this context (``make(ctx)``: a pyopencl scan or sort), made once."""
        from .programs import REGISTRY
        return REGISTRY.library(self.ctx, name, make)


def fault() -> str:
    """``CLPPM_FAULT``: deliberately broken builds for the self-test's tests (programs.inject_fault)."""
    return os.environ.get("CLPPM_FAULT", "")


#: the gather's density estimators (kernels/gather.cl ESTIMATOR)
ESTIMATORS = {"sphere": 0, "clip": 1, "layer": 2, "beam": 3}


def kernel_defines(vol=None, *, nb: int | None = None, hero: int = 1, estimator: str | None = None,
                   gclass: int | None = None, pt_fp64: bool | None = None,
                   count_candidates: bool = False, exact_rsqrt: bool = False,
                   photon_counters: bool = False, photon_plain_walk: bool = False,
                   depth_roulette: bool = False, vec16: bool = True, photon_lanes: int = 1) -> dict:
    """Every ``-D`` switch of clppm's kernels, assembled in this one place (as MCX-CL does).

    From the volume: NB bands, NL layers, NINC inclusions (when there are any: kernels/inclusion.h),
    MAPS (chromophore maps, when there are any: kernels/maps.h),
    FLAT (no relief or papillae: the flat code paths),
    SMOOTH_SURFACE and NVAR (model.surface = "smooth": the walk on the smooth surfaces, smoothwalk.h);
    ``nb`` alone (no volume): the photon grid's kernels (hashgrid.cl).  HERO_C: bands a photon
    path carries, when more than one (spectral.h).  FAST_MATH: the compiler's relaxed math,
    when CLPPM_FAST_MATH=1.  A pass's own: ESTIMATOR (gather.cl: sphere, clip, layer, beam),
    GCLASS (the beam gather's band classes), PT_FP64 (pt.cl: double-precision sums; relief
    builds of every pass: the smooth surfaces in double, kernels/surface.h: ``surface_fp64``),
    COUNT_CANDIDATES (gather.cl: count the photons a query visits, for bench/gather.py),
    EXACT_RSQRT (gather.cl: rsqrt for native_rsqrt, to compare layouts off PoCL to float rounding),
    PHOTON_COUNTERS (photon.cl: count events, crossings and loop steps, for bench/photons.py),
    PHOTON_PLAIN_WALK (photon.cl: the smooth walk of the other passes, tile by tile, for tests),
    DEPTH_ROULETTE (photon.cl: render.depth_roulette_um's roulette below the storage depth),
    LANES (photon.cl: photon_pass_lanes, the photon pass in explicit SIMD lanes of this width),
    NO_VEC16 (gather.cl: the beam's band math lane by lane, where :func:`wide_vectors` is false).
    One switch depends on the device alone and every build gets it there:
    :func:`clppm.compute.programs.device_defines` (INLINE_MATH on PoCL)."""
    if vol is None:
        return {"NB": int(nb)} if nb is not None else {}
    d = {"NB": vol.nb, "NL": vol.nl, "FLAT": vol.flat, "FAST_MATH": os.environ.get("CLPPM_FAST_MATH") == "1"}
    if not vol.flat and vol.surface == "smooth":
        d["SMOOTH_SURFACE"] = 1                  # kernels/smoothwalk.h
        d["NVAR"] = int(vol.heights.shape[0])
        d["SMOOTH_CELL"] = int(vol.cell)
    if getattr(vol, "ninc", 0):
        d["NINC"] = int(vol.ninc)                 # kernels/inclusion.h; 0 (absent): compiled out
    if getattr(vol, "maps", None) is not None:
        d["MAPS"] = 1                             # kernels/maps.h; absent: compiled out
    if hero > 1:
        d["HERO_C"] = int(hero)
    if estimator is not None:
        d["ESTIMATOR"] = ESTIMATORS[estimator]
    if gclass is not None:
        d["GCLASS"] = int(gclass)
    if pt_fp64 is not None:
        d["PT_FP64"] = bool(pt_fp64)
    if count_candidates:
        d["COUNT_CANDIDATES"] = 1
    if exact_rsqrt:
        d["EXACT_RSQRT"] = 1
    if photon_counters:
        d["PHOTON_COUNTERS"] = 1
    if photon_plain_walk:
        d["PHOTON_PLAIN_WALK"] = 1
    if depth_roulette:
        d["DEPTH_ROULETTE"] = 1
    if photon_lanes > 1:
        d["LANES"] = int(photon_lanes)
    if not vec16:
        d["NO_VEC16"] = 1
    return d


def surface_fp64(dev, vol) -> bool | None:
    """PT_FP64 for a pass's build: a relief build evaluates the smooth surfaces (kernels/surface.h)
    in double where the device has it, as the path tracer does, so that all passes refract alike;
    None (no switch) for a flat one."""
    return None if vol.flat else bool(dev.info()["fp64"])


def forget_kernel_cache(impl: str) -> None:
    """Drop what the kernel caches may hold of a crashed or broken build: clppm's program
    binaries (:func:`clppm.compute.programs.forget_binaries`), PoCL's broken entries
    (:func:`clppm.compute.icd.prune_pocl_cache`) and every entry of the PoCL cache clppm owns
    (``POCL_CACHE_DIR`` set by :func:`clppm.compute.icd.own_pocl_cache`; a cache the user
    chose is only pruned)."""
    import shutil
    from .icd import owned_pocl_cache, prune_pocl_cache
    from .programs import forget_binaries
    forget_binaries()
    d = os.environ.get("POCL_CACHE_DIR")
    if impl == "pocl" and d and os.path.isdir(d):
        prune_pocl_cache(d)
        if d == owned_pocl_cache():  # its entries: PoCL needs the folder itself
            for n in os.listdir(d):
                shutil.rmtree(os.path.join(d, n), ignore_errors=True)


DEFAULT_RULE = ("the default: GPUs first, then " + ", ".join(CPU_PREFERENCE)
                + ", the first that passes its self-test")


@functools.lru_cache(maxsize=None)
def _open(spec: str | None, source: str) -> Device:
    cl = _cl()
    dev = select_device(spec)
    ctx = cl.Context([dev])
    queue = cl.CommandQueue(ctx)
    chosen = DEFAULT_RULE if spec is None else f"{source} {spec}"
    return Device(ctx=ctx, queue=queue, device=dev, chosen=chosen,
                  passed_over=tuple(SELECTION_NOTES) if spec is None else ())


def open_device(spec: str | None = None) -> Device:
    """Context and queue on the selected device (one per process and spec)."""
    source = "--device"
    if spec is None:
        spec = os.environ.get("PYOPENCL_CTX") or None
        source = "PYOPENCL_CTX ="
    return _open(spec, source)


def check_alloc(dev: Device, needs: dict[str, int]) -> None:
    """Raise :class:`DeviceError` if buffers in ``needs`` (name -> bytes) do not fit."""
    info = dev.info()
    total = sum(needs.values())
    big = max(needs.items(), key=lambda kv: kv[1]) if needs else ("", 0)
    if big[1] > info["max_alloc_bytes"] or total > info["global_mem_bytes"]:
        lines = "\n".join(f"  {k}: {v / 2**20:.1f} MiB" for k, v in sorted(needs.items()))
        raise DeviceError(
            f"this render needs {total / 2**20:.1f} MiB of device memory "
            f"(largest buffer '{big[0]}' {big[1] / 2**20:.1f} MiB) but device '{dev.name}' "
            f"has {info['global_mem_bytes'] / 2**20:.0f} MiB global memory and a "
            f"{info['max_alloc_bytes'] / 2**20:.0f} MiB largest single allocation:\n{lines}\n"
            "options: fewer stored photons per pass (--photons), a lower resolution "
            "(--resolution), or a sparser sampling method (--method c/f)")
