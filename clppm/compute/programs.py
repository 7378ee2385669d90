"""clppm's OpenCL programs: one registry that builds, caches and checks every kernel source.

A program is named by its :class:`BuildSpec`: the ``.cl`` file under ``kernels/`` and its ``-D``
switches (:func:`clppm.compute.device.kernel_defines` assembles them, in one place).  The
:class:`Registry` builds each spec once per OpenCL context and keeps, per context, the program,
its :class:`~clppm.compute.kernelcall.Kernel` objects and the library kernels built on it
(pyopencl's scans and sorts).  Binaries persist across runs (:func:`binary_cache_dir`): in
pyopencl's program cache, in a folder clppm owns (:func:`program_cache_dir`), so that a broken
entry (a crashed compile's) is dropped by removing that folder, with no pyopencl internals
touched; on PoCL in its own kernel cache, also clppm's.
"""
from __future__ import annotations

import os
import re
import shutil
from dataclasses import dataclass, field

from importlib import resources


def kernel_dir() -> str:
    """Folder holding ``*.cl`` kernel sources (works for an installed package)."""
    return str(resources.files("clppm.kernels"))


#: pyopencl's one-line notice that a build log was not empty; it carries no log of its own
CHATTER = "Non-empty compiler output encountered"


def quiet_compiler_chatter() -> None:
    """Drop pyopencl's notice that a build log was not empty (:data:`CHATTER`).  Intel's runtime
    logs every build ("Compilation started", vectoriser remarks) and the notice cannot tell those
    from a warning; clppm's kernels build with no compiler warning on the CPU implementations
    (tests/test_quiet.py reads the logs), and ``PYOPENCL_COMPILER_OUTPUT=1`` still prints every
    log in full (pyopencl then warns with another message, which passes)."""
    import warnings
    warnings.filterwarnings("ignore", message=CHATTER)


def is_pocl(device) -> bool:
    return device.platform.name == "Portable Computing Language"


def device_defines(device) -> list[str]:
    """The ``-D`` switches a device's builds get whatever the program (the program's own:
    :func:`clppm.compute.device.kernel_defines`): INLINE_MATH on PoCL, whose kernel library
    calls fmin, fmax, clamp, floor and sqrt out of line even on scalars (kernels/scalar.h)."""
    return ["INLINE_MATH"] if is_pocl(device) else []


class BuildError(RuntimeError):
    """A kernel program failed to build or lacks a kernel its source declares."""


@dataclass(frozen=True)
class BuildSpec:
    """A program: ``filename`` (under ``kernels/``) and its sorted ``-D`` switches."""

    filename: str
    defines: tuple = ()

    @classmethod
    def of(cls, filename: str, defines: dict | None = None) -> "BuildSpec":
        return cls(filename, tuple(sorted((defines or {}).items())))

    def options(self) -> list[str]:
        """The compiler options of the switches: ``-DK=V`` (booleans: present when true, floats
        as C float literals); FAST_MATH is the compiler's relaxed math, not only a macro."""
        opts = []
        for k, v in self.defines:
            if k == "FAST_MATH":
                if v:
                    opts += ["-cl-fast-relaxed-math", "-DFAST_MATH=1"]
                continue
            if isinstance(v, bool):
                if v:
                    opts.append(f"-D{k}={int(v)}")
            elif isinstance(v, float):
                opts.append(f"-D{k}={v!r}f")
            else:
                opts.append(f"-D{k}={v}")
        return opts

    def defined(self) -> set[str]:
        """The macro names the options define."""
        return {o[2:].split("=")[0] for o in self.options() if o.startswith("-D")}

    def read(self) -> str:
        """The file's text."""
        path = os.path.join(kernel_dir(), self.filename)
        try:
            with open(path, encoding="utf-8") as f:
                return f.read()
        except (OSError, UnicodeDecodeError) as e:
            raise BuildError(f"kernel source {self.filename} cannot be read from {kernel_dir()} ({e}); "
                             "the clppm installation is incomplete: reinstall it (pip install clppm)") from None


def compile_inputs(src: str, spec: BuildSpec) -> tuple[str, list[str]]:
    """The source and options that compile ``src`` under ``spec``: the kernels folder on the
    include path, or, when its path holds a blank, the headers inlined (OpenCL compilers split
    options at blanks and take no quotes: PoCL answers "Invalid build option")."""
    kdir = kernel_dir()
    if any(c.isspace() for c in kdir):
        return inline_includes(src, kdir), spec.options()
    return src, [f"-I{kdir}"] + spec.options()


def compile_source(ctx, src: str, spec: BuildSpec):
    """``src`` (a program that is not a kernels/ file, e.g. one header alone) built under
    ``spec``'s switches, uncached."""
    src, opts = compile_inputs(src, spec)
    return _compile(ctx, src, opts, spec.filename, False)


def program_cache_dir() -> str:
    """The folder of clppm's program binaries (pyopencl's cache format, keyed by source, options
    and device): ``$XDG_CACHE_HOME/clppm/programs`` (default ``~/.cache``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "clppm", "programs")


def binary_cache_dir(device) -> str:
    """Where ``device``'s program binaries persist: PoCL keeps its own (``POCL_CACHE_DIR``,
    clppm's by default, :func:`clppm.compute.icd.own_pocl_cache`) and pyopencl then leaves the
    build to it, as it does on NVIDIA's (its compute cache); any other device's are in
    :func:`program_cache_dir`."""
    if is_pocl(device):
        from .icd import owned_pocl_cache
        return os.environ.get("POCL_CACHE_DIR") or owned_pocl_cache()
    return program_cache_dir()


def _caching() -> bool:
    """Binaries are kept unless ``PYOPENCL_NO_CACHE`` is set (as pyopencl itself reads it)."""
    return not os.environ.get("PYOPENCL_NO_CACHE")


def forget_binaries() -> None:
    """Drop every program binary clppm keeps (a rebuild then compiles from source)."""
    shutil.rmtree(program_cache_dir(), ignore_errors=True)


@dataclass
class BuildStats:
    """Per process: programs built (from source or from cached binaries) and their seconds."""

    programs: int = 0
    seconds: float = 0.0
    by_file: dict = field(default_factory=dict)

    def add(self, filename: str, seconds: float) -> None:
        self.programs += 1
        self.seconds += seconds
        n, s = self.by_file.get(filename, (0, 0.0))
        self.by_file[filename] = (n + 1, s + seconds)


class Registry:
    """Every program of a process, built once per (context, spec), and the Kernel objects and
    library kernels made on them, once per context."""

    def __init__(self):
        self._programs: dict = {}
        self._kernels: dict = {}
        self._library: dict = {}
        self.stats = BuildStats()

    def program(self, ctx, spec: BuildSpec, fault: str = ""):
        """The program of ``spec`` on ``ctx``, built now or found; checked to hold every kernel
        the source declares outside undecided conditions (a cached binary lacking one is
        rebuilt without the caches).  ``fault``: :func:`inject_fault`'s deliberate breakage."""
        key = (ctx, spec, fault)
        prg = self._programs.get(key)
        if prg is None:
            prg = self._programs[key] = self._build(ctx, spec, fault)
        return prg

    def made(self, ctx, spec: BuildSpec, name: str, make, fault: str = ""):
        """An object made once on the program of ``spec`` (``make(program)``: a kernel object
        named ``name``, :func:`clppm.compute.kernelcall.kernels`)."""
        key = (ctx, spec, fault, name)
        k = self._kernels.get(key)
        if k is None:
            k = self._kernels[key] = make(self.program(ctx, spec, fault))
        return k

    def library(self, ctx, name: str, make):
        """A library kernel (``make(ctx)``: a pyopencl scan or sort) made once per context."""
        k = self._library.get((ctx, name))
        if k is None:
            k = self._library[(ctx, name)] = make(ctx)
        return k

    def _build(self, ctx, spec: BuildSpec, fault: str):
        import time
        from .icd import prune_pocl_cache, owned_pocl_cache
        dev = ctx.devices[0]
        src, opts = compile_inputs(spec.read(), spec)
        want = expected_kernels(src, spec.defined())      # the source's, before any fault
        src, opts = inject_fault(fault, dev, spec.filename, src, opts)
        t0 = time.perf_counter()
        prg = _compile(ctx, src, opts, spec.filename, _caching())
        missing = want - set(kernel_names(prg))
        for whole in (False, True):   # a broken cache entry (a crashed compile's): drop, rebuild
            if not missing:
                break
            forget_binaries()
            d = os.environ.get("POCL_CACHE_DIR")
            if is_pocl(dev) and d and os.path.isdir(d):
                prune_pocl_cache(d)
                if whole and d == owned_pocl_cache():   # its entries: PoCL needs the folder
                    for n in os.listdir(d):
                        shutil.rmtree(os.path.join(d, n), ignore_errors=True)
            prg = _compile(ctx, src, opts, spec.filename, False)
            missing = want - set(kernel_names(prg))
        if missing:
            raise BuildError(f"kernel build of {spec.filename} on device '{dev.name.strip()}' "
                             f"({dev.platform.name.strip()}) holds no kernel {', '.join(sorted(missing))}, "
                             "even rebuilt without the kernel caches")
        self.stats.add(spec.filename, time.perf_counter() - t0)
        return prg


#: the process's programs
REGISTRY = Registry()


def _compile(ctx, src: str, opts: list, filename: str, cache: bool):
    import pyopencl as cl
    quiet_compiler_chatter()
    cache_dir = program_cache_dir() if cache else False
    opts = list(opts) + [f"-D{k}" for k in device_defines(ctx.devices[0])]
    try:
        return cl.Program(ctx, src).build(options=opts, cache_dir=cache_dir)
    except cl.Error as e:  # build failure (RuntimeError), bad options (LogicError): name + log
        dev = ctx.devices[0].name.strip()
        raise BuildError(f"kernel build of {filename} failed on device '{dev}' "
                         f"with options {' '.join(opts)}:\n{e}") from None


def kernel_names(prg) -> list[str]:
    try:
        return [n for n in prg.kernel_names.split(";") if n]
    except Exception:                     # a program the driver cannot describe holds nothing
        return []


_KERNEL_DECL = re.compile(r"__kernel\s+void\s+(\w+)\s*\(")
_COND = re.compile(r"^[ \t]*#[ \t]*(if|ifdef|ifndef|elif|else|endif)\b[ \t]*(\w*)", re.M)


def expected_kernels(src: str, defined: set[str]) -> set[str]:
    """The kernels ``src`` declares outside preprocessor conditions it cannot decide: ``#ifdef``
    and ``#ifndef`` of ``defined`` names are followed, any other ``#if`` is left undecided (its
    kernels are not required)."""
    events = sorted([(m.start(), "k", m.group(1)) for m in _KERNEL_DECL.finditer(src)]
                    + [(m.start(), m.group(1), m.group(2)) for m in _COND.finditer(src)])
    stack: list = []                 # per open condition: True, False, or None (undecided)
    out = set()
    for _, what, arg in events:
        if what == "k":
            if all(c is True for c in stack):
                out.add(arg)
        elif what in ("ifdef", "ifndef"):
            stack.append((arg in defined) == (what == "ifdef"))
        elif what == "if":
            stack.append(None)
        elif what == "elif" and stack:
            stack[-1] = None
        elif what == "else" and stack:
            stack[-1] = None if stack[-1] is None else not stack[-1]
        elif what == "endif" and stack:
            stack.pop()
    return out


# Implementations by the short names ``--device`` takes: a (platform name, platform version)
# substring identifies each.  Users see these names in ``clppm devices``.
IMPLEMENTATIONS = (("pocl", ("portable computing language", "pocl")),
                   ("intel", ("intel(r) opencl", "intel")),
                   ("nvidia", ("nvidia",)), ("amd", ("amd accelerated", "amd")),
                   ("rusticl", ("rusticl",)), ("oclgrind", ("oclgrind",)))


def implementation(device) -> str:
    """Short name of ``device``'s OpenCL implementation ("pocl", "intel", ...), else its platform."""
    plat = f"{device.platform.name} {device.platform.version}".lower()
    for short, keys in IMPLEMENTATIONS:
        if any(k in plat for k in keys):
            return short
    return device.platform.name.strip().lower()


def inject_fault(fault: str, dev, filename: str, src: str, opts: list) -> tuple[str, list]:
    """Deliberately broken builds, for the tests of the self-test and of verified builds only:
    ``CLPPM_FAULT=[IMPL@]FILE:KIND[:KERNEL]`` (several, comma-separated; IMPL: on that
    implementation only), KIND ``crash`` (KERNEL's first
    work item writes to address 0 at its first launch), ``drop`` (KERNEL is not a kernel: the
    program lacks it) or ``wrong`` (``-DCLPPM_FAULT_WRONG``: photon.cl scatters less)."""
    for f in filter(None, (x.strip() for x in fault.split(","))):
        impl, _, f = f.rpartition("@")
        file_, kind, *rest = f.split(":") + [""]
        if file_ != filename or (impl and impl != implementation(dev)):
            continue
        name = rest[0] if rest and rest[0] else r"\w+"
        m = re.search(r"__kernel(\s+void\s+" + name + r"\s*\()", src)
        if kind == "wrong":
            opts = opts + ["-DCLPPM_FAULT_WRONG=1"]
        elif kind == "drop" and m:
            src = src[:m.start()] + m.group(1).lstrip() + src[m.end():]
        elif kind == "crash" and m:
            brace = src.index("{", m.end())
            src = (src[:brace + 1] + " if (get_global_id(0) == 0) *(volatile __global int*)0 = 1; "
                   + src[brace + 1:])
    return src, opts


_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]*"([^"]+)"[ \t]*$', re.M)


def inline_includes(src: str, kdir: str, seen: frozenset = frozenset()) -> str:
    """Replace ``#include "x.h"`` of files in ``kdir`` by their text (``#line`` keeps log lines)."""
    def sub(m):
        name = m.group(1)
        if name in seen:                              # a header that includes itself
            return ""
        try:
            with open(os.path.join(kdir, name), encoding="utf-8") as f:
                text = f.read()
        except OSError:
            return m.group(0)                         # not ours: leave it to the compiler
        line = src.count("\n", 0, m.start()) + 2
        return (f'#line 1 "{name}"\n' + inline_includes(text, kdir, seen | {name})
                + f"\n#line {line}\n")
    return _INCLUDE.sub(sub, src)
